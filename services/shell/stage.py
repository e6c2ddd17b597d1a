"""The one Zenoh shell every process runs in: a pure core inside, the same thin shell around each.

A core is plain code (``services.contract``): ``process(topic=, message=, now_s=)`` returns the
messages to publish, by topic. ``run_stage`` does all the I/O for any process of the wiring table
(``schemas.wiring.PROCESSES``): the session, the liveliness token, the status key, the input bounds,
the checkpoint file; which keys a process reads and writes comes from the table, never from the core.
The same shell runs a stage, the ticking source (the sim: it asks the core when it next wants to tick,
tells it of the watched stages' liveliness and hands it every status) and the sink (the monitor).

A stage receives each input into a small ring (``Ring``, ``INPUT_RING`` samples): a stage that falls
behind works on the newest sample that decodes, and the stale ones are dropped, so nothing queues
without bound. A source or sink handles every input, in arrival order, from one bounded queue
(``QUEUE_CAPACITY``; when it is full the oldest are dropped and counted). The worker sleeps until a
sample arrives (``Inbox``) or a tick is due, rather than polling. Samples newer than the one a stage
handles which do not decode are reported, never processed: garbage on a key cannot push a real
message out unless it outnumbers the ring. After every input a stage publishes a ``StageStatus`` on
``<prefix>/status/<stage>``: ``error`` with a one-line reason for an input it could not use (oversize,
bad JSON, wrong schema, non-finite number, validation failure, ``StageInputError``, solver failure),
``ok`` otherwise (with the reason a core gives in a ``Notice``: an answer a deadline cut short); a
source or sink reports only the errors, and a ``Refusal`` its core returns. A
rejected input publishes nothing else, so the last good outputs stand. The status carries the rejected
input's stamp (``input_stamp_s``) only when the input decoded; garbage on a key is reported, but never
as the verdict on a real scan.

Frames: the keys carry world coordinates; a core computes in a local frame near the scenario
(``services.convert.LocalFrame``), and the shell moves every message between the two as it hands it
to the core and publishes what the core returns, so no core sees a coordinate of 10⁶ m.

Bounds: a payload larger than ``max_payload_bytes`` (``cvxnav service --max-payload-bytes``, default
1 MiB) is rejected before it is decoded; each core bounds what a decoded message may hold (points
per scan, per cluster set, per path; ellipses per set; coordinates within the scenario's extent).

Every key the shell declares under the prefix is a wiring-table topic carrying a JSON model. A process
that is also a ROS 2 node (``StageSpec.ros2``, the bridge) speaks rmw_zenoh's keys outside that space
from the same session, without a second shell (``services.shell.ros2``): the node and its topics with
their liveliness tokens, each input sample handed to the core undecoded (``Bridging.receive``, after
the topic's own payload cap) in arrival order with the process's other inputs, and the core's ``Raw``
outputs published with the rmw attachment. Its rejected inputs are reported on its status key too.
"""

from __future__ import annotations

import gc
import logging
import os
import signal
import threading
import time
from collections import deque
from collections.abc import Callable
from contextlib import ExitStack
from pathlib import Path
from typing import TYPE_CHECKING, TypeVar

import zenoh
from pydantic import BaseModel

from schemas.messages import DecodeError, Header, M, StageStatus, decode
from schemas.wiring import (
    PROCESSES,
    TOPICS,
    StageSpec,
    alive_key,
    key,
    model_for,
    stage_of_alive_key,
    stage_of_status_key,
    status_key,
)
from services.contract import (
    Bridging,
    Listening,
    Notice,
    Outputs,
    Raw,
    Refusal,
    Scheduled,
    StageCore,
    StageInputError,
    Stateful,
    Stopping,
    TickingCore,
    Watching,
)
from services.convert import LocalFrame
from services.limits import DEFAULT_MAX_PAYLOAD_BYTES
from services.shell.checkpoint import Checkpoint
from services.shell.watchdog import Progress

if TYPE_CHECKING:
    from services.shell.ros2 import BridgePorts

logger = logging.getLogger(__name__)

MAX_REASON_CHARS = 300
# The longest a worker sleeps with no input: how long it may take to notice a stop.
STOP_CHECK_S = 0.05
# Samples held per input key: the newest decodable one among them is processed, older ones dropped.
INPUT_RING = 8
# Samples a source or sink holds between drains (every one is handled; past this the oldest go).
QUEUE_CAPACITY = 20_000


def one_line(text: str) -> str:
    """The first line of ``text``, at most ``MAX_REASON_CHARS`` long: a status reason."""
    first = (text.splitlines() or [""])[0]
    return first if len(first) <= MAX_REASON_CHARS else first[: MAX_REASON_CHARS - 1] + "…"


class Ring:
    """A Zenoh subscriber callback that keeps the newest `capacity` samples (the oldest are dropped, as
    in zenoh's RingChannel) and wakes its inbox; read with `try_recv`, like a channel."""

    def __init__(self, capacity: int, wake: threading.Event) -> None:
        self._samples: deque = deque(maxlen=capacity)
        self._wake = wake
        self.dropped = 0

    def __call__(self, sample) -> None:
        if len(self._samples) == self._samples.maxlen:
            self.dropped += 1
        self._samples.append(sample)
        self._wake.set()

    def try_recv(self):
        try:
            return self._samples.popleft()
        except IndexError:
            return None


class Inbox:
    """The rings of one worker's subscriptions, and the one event that wakes it when any receives.

    Waiting on it instead of polling the subscriptions takes the poll period off every hop.
    """

    def __init__(self) -> None:
        self._wake = threading.Event()

    def ring(self, capacity: int) -> Ring:
        return Ring(capacity, self._wake)

    def tagged(self, ring: Ring, tag: str) -> Callable[[zenoh.Sample], None]:
        """A subscriber callback putting (tag, sample) into `ring`: one queue for several subscriptions."""
        return lambda sample: ring((tag, sample))

    def wait(self, timeout_s: float) -> None:
        """Sleep until a sample arrives (or one arrived since the last wait), at most `timeout_s`.

        Clearing the event before the caller drains its rings loses nothing: a sample that lands
        after the clear is either drained now or sets the event for the next wait.
        """
        self._wake.wait(max(0.0, timeout_s))
        self._wake.clear()


def decode_sample(model: type[M], sample: zenoh.Sample, *, max_payload_bytes: int) -> M:
    """One received sample as `model`; a payload over `max_payload_bytes` is refused before decoding."""
    size = len(sample.payload)
    if size > max_payload_bytes:
        raise DecodeError(f"payload of {size} bytes exceeds max_payload_bytes={max_payload_bytes}")
    return decode(model, sample.payload.to_bytes(), encoding=str(sample.encoding))


STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)  # compose, systemd and a dying parent stop a stage with SIGTERM


def install_signal_handlers(stop_event: threading.Event) -> None:
    """Set ``stop_event`` on SIGINT and SIGTERM, from a thread of its own.

    A Python signal handler runs in the main thread between two of its bytecodes, possibly inside
    ``stop_event.set()`` or ``wait()`` themselves, whose lock is not reentrant: a handler that set the
    event deadlocked a planner hit by two signals at once. So the C handler only writes the signal's
    number to a pipe (``signal.set_wakeup_fd``), and a relay thread reading it sets the event.
    Must be called once per process, from the main thread (a Python restriction on ``signal.signal``).
    """
    read_fd, write_fd = os.pipe()
    os.set_blocking(write_fd, False)
    signal.set_wakeup_fd(write_fd, warn_on_full_buffer=False)

    def relay() -> None:
        while (signum := os.read(read_fd, 1)[0]) not in STOP_SIGNALS:
            pass
        logger.info("received %s, stopping", signal.Signals(signum).name)
        stop_event.set()

    threading.Thread(target=relay, name="signal-relay", daemon=True).start()
    for signum in STOP_SIGNALS:
        signal.signal(signum, lambda _signum, _frame: None)  # a Python handler, so the C one writes the pipe


_STATUS = "\0status"  # queue tags of the inputs that are not topics
_ALIVE = "\0alive"
_ROS = "\0ros/"  # + the port: a ROS 2 topic's sample
DRAIN_S = 1.0  # a stopping source or sink handles what already arrived, until quiet or this long
# After a stop, how long the process waits for its worker (a solve in progress) before it exits without
# it: within the 2 s an operator, systemd or `docker stop` may expect, with room for the interpreter's exit.
STOP_GRACE_S = 1.5
T = TypeVar("T")


def run_in_worker(work: Callable[[], T], *, stop_event: threading.Event,
                  grace_s: float = STOP_GRACE_S) -> tuple[bool, T | None]:
    """Run `work` in a worker thread while the calling (main) thread stays free for signals.

    Returns (True, its result) once it ends, or (False, None) when it is still busy `grace_s` after
    `stop_event` was set: a core in a long solve (native code, which a signal handler cannot
    interrupt) must not hold the process, so the caller exits without it. An exception in `work` is
    raised here.
    """
    outcome: dict[str, object] = {}

    def target() -> None:
        try:
            outcome["result"] = work()
        except BaseException as error:  # handed to the main thread, which raises it
            outcome["error"] = error

    worker = threading.Thread(target=target, name="stage-worker", daemon=True)
    worker.start()
    while worker.is_alive() and not stop_event.wait(0.1):
        pass
    worker.join(grace_s)
    if worker.is_alive():
        return False, None
    if "error" in outcome:
        raise outcome["error"]  # type: ignore[misc]
    return True, outcome.get("result")  # type: ignore[return-value]


class _Shell:
    """The steps of ``run_stage``: size check, decode, process, checkpoint, publish, report."""

    def __init__(
        self,
        *,
        spec: StageSpec,
        core: StageCore,
        prefix: str,
        publishers: dict[str, zenoh.Publisher],
        status_publisher: zenoh.Publisher,
        max_payload_bytes: int,
        clock: Callable[[], float],
        checkpoint: Checkpoint | None,
        frame: LocalFrame = LocalFrame(),
    ) -> None:
        self._spec = spec
        self._frame = frame
        self._core = core
        self._prefix = prefix
        self._publishers = publishers
        self._status_publisher = status_publisher
        self._max_payload_bytes = max_payload_bytes
        self._clock = clock
        self._checkpoint = checkpoint
        # What the core asks of the shell, looked up once (a protocol check is slow in a busy loop).
        self.scheduled = isinstance(core, Scheduled)
        self._watching, self._listening = isinstance(core, Watching), isinstance(core, Listening)
        self._latched: dict[str, str] = {}  # topic -> the last payload published on it
        self.ros: BridgePorts | None = None  # a ROS 2 node's topics (StageSpec.ros2)
        self._raw: tuple[str, str] | None = None  # (port, key) of the ROS sample being handled
        self._status_seq = 0
        self._last_stamp_s = 0.0  # of the last input the core accepted: the status's sim time
        self._input_stamp_s: float | None = None  # of the input being handled, once decoded

    @property
    def done(self) -> bool:
        return self.scheduled and self._core.done

    def next_tick_s(self) -> float | None:
        return self._core.next_tick_s(now_s=self._clock()) if self.scheduled else None

    def handle_newest(self, *, topic: str, samples: list[zenoh.Sample]) -> None:
        """Of samples in arrival order, process the newest that decodes; report each newer one that does not.

        Older samples are superseded and dropped undecoded, as the ring drops them.
        """
        for sample in reversed(samples):
            if self._handle(topic=topic, sample=sample):
                return

    def handle(self, *, tag: str, sample: zenoh.Sample) -> None:
        """One input of a source or sink: a topic's sample, a status, or a liveliness change."""
        if tag == _ALIVE:
            stage = stage_of_alive_key(self._prefix, str(sample.key_expr))
            if stage in self._spec.watches and self._watching:
                alive = sample.kind == zenoh.SampleKind.PUT
                self._step(lambda: self._core.stage_alive(stage=stage, alive=alive, now_s=self._clock()),
                           input_key=None, report_ok=False)
        elif sample.kind != zenoh.SampleKind.PUT:
            return
        elif tag.startswith(_ROS):
            self._handle_raw(port=tag[len(_ROS):], sample=sample)
        elif tag == _STATUS:
            stage = stage_of_status_key(self._prefix, str(sample.key_expr))
            if stage is None or not self._listening:
                return
            try:
                status = decode_sample(StageStatus, sample, max_payload_bytes=self._max_payload_bytes)
            except DecodeError as error:
                logger.debug("ignoring the status on %s: %s", sample.key_expr, error)
                return
            self._step(lambda: self._core.hear_status(stage=stage, status=status, now_s=self._clock()),
                       input_key=None, report_ok=False)
        else:
            self._handle(topic=tag, sample=sample)

    def _handle(self, *, topic: str, sample: zenoh.Sample) -> bool:
        """Decode and process one sample of `topic`; False when it did not decode (reported)."""
        input_key = str(sample.key_expr)
        started = time.perf_counter()
        self._input_stamp_s = None
        try:
            message = decode_sample(model_for(topic), sample, max_payload_bytes=self._max_payload_bytes)
        except DecodeError as error:
            self._report(input_key=input_key, started=started, reason=one_line(f"{input_key}: {error}"))
            return False
        self._step(lambda: self._process(topic=topic, message=message), input_key=input_key,
                   report_ok=self._spec.reports_ok)
        return True

    def _handle_raw(self, *, port: str, sample: zenoh.Sample) -> None:
        """One sample of a ROS 2 input topic, handed to the core as bytes once within the topic's cap."""
        input_key = str(sample.key_expr)
        started = time.perf_counter()
        self._input_stamp_s = None
        size, cap = len(sample.payload), self.ros.max_payload_bytes(port)
        if size > cap:
            self._report(input_key=input_key, started=started,
                         reason=one_line(f"{input_key}: payload of {size} bytes exceeds max_payload_bytes={cap}"))
            return
        core: Bridging = self._core  # type: ignore[assignment]  # run_stage's contract
        self._raw = (port, input_key)
        try:
            self._step(lambda: core.receive(port=port, key_expr=input_key, payload=sample.payload.to_bytes(),
                                            now_s=self._clock()), input_key=input_key, report_ok=False)
        finally:
            self._raw = None

    def tick(self) -> None:
        """One timer step; reports a status only when it fails (a tick has no input to judge)."""
        core: TickingCore = self._core  # type: ignore[assignment]  # run_stage's contract
        self._input_stamp_s = None
        self._step(lambda: core.tick(now_s=self._clock()), input_key=None, report_ok=False)

    def stop(self) -> None:
        """The core's last outputs, if it has any, before the session closes."""
        if isinstance(self._core, Stopping):
            self._input_stamp_s = None
            self._step(lambda: self._core.stop(now_s=self._clock()), input_key=None, report_ok=False)

    def answer(self, topic: str) -> Callable[[zenoh.Query], None]:
        """A queryable's callback: the last message published on the latched `topic`, if any."""
        encoding = zenoh.Encoding(model_for(topic).encoding())

        def reply(query: zenoh.Query) -> None:
            payload = self._latched.get(topic)
            if payload is not None:
                query.reply(key(self._prefix, topic), payload, encoding=encoding)

        return reply

    def _step(self, step: Callable[[], Outputs], *, input_key: str | None, report_ok: bool) -> None:
        started = time.perf_counter()
        where = input_key or "tick"
        try:
            messages, raws, refusals, notices = self._checked(step())
            if self._checkpoint is not None:  # before the outputs that depend on the state
                self._checkpoint.save(self._core)  # type: ignore[arg-type]  # run_stage's contract
        except (DecodeError, StageInputError) as error:
            self._report(input_key=input_key, started=started, reason=one_line(f"{where}: {error}"))
            return
        except Exception as error:  # a solver or core failure must not stop the stage
            logger.exception("stage %s failed on %s", self._spec.name, where)
            self._report(input_key=input_key, started=started,
                         reason=one_line(f"{where}: {type(error).__name__}: {error}"))
            return
        for out_topic, message in messages:
            payload = self._frame.to_world(message).model_dump_json()
            self._publishers[out_topic].put(payload)
            if TOPICS[out_topic].latched:
                self._latched[out_topic] = payload
        for port, raw in raws:
            self.ros.put(port, raw.payload)
        if self._input_stamp_s is not None:
            self._last_stamp_s = self._input_stamp_s
        if report_ok:
            self._report(input_key=input_key, started=started, reason=None,
                         note="; ".join(one_line(notice.reason) for notice in notices))
        self._input_stamp_s = None  # a refusal concerns an earlier input, not this one's stamp
        for in_topic, refusal in refusals:
            self._report(input_key=self._refused_key(in_topic), started=started, reason=one_line(refusal.reason))

    def _refused_key(self, topic: str) -> str:
        """The key of a refused input: a topic's under the prefix, a ROS sample's own (or its topic's)."""
        if topic in self._spec.subscribes:
            return key(self._prefix, topic)
        return self._raw[1] if self._raw is not None and self._raw[0] == topic else self.ros.key(topic)

    def _process(self, *, topic: str, message: BaseModel) -> Outputs:
        header = getattr(message, "header", None)
        if isinstance(header, Header):
            self._input_stamp_s = header.stamp_s
        return self._core.process(topic=topic, message=self._frame.to_local(message), now_s=self._clock())

    def _checked(self, outputs: Outputs) -> tuple[list[tuple[str, BaseModel]], list[tuple[str, Raw]],
                                                  list[tuple[str, Refusal]], list[Notice]]:
        """A core's output batch split into messages, raw bytes, refusals and notices; one that breaks the
        wiring table (or the ROS interface) is rejected before any of it is published."""
        messages, raws, refusals, notices = [], [], [], []
        for topic, item in outputs:
            if isinstance(item, Notice):
                if topic not in self._publishers:
                    raise TypeError(f"stage {self._spec.name} does not publish {topic!r}")
                notices.append(item)
                continue
            if isinstance(item, Refusal):
                if topic not in self._spec.subscribes and not (self.ros is not None and topic in self.ros.inputs):
                    raise TypeError(f"stage {self._spec.name} does not read {topic!r}")
                refusals.append((topic, item))
                continue
            if isinstance(item, Raw):
                if self.ros is None or not self.ros.publishes(topic):
                    raise TypeError(f"stage {self._spec.name} publishes no ROS topic {topic!r}")
                raws.append((topic, item))
                continue
            if topic not in self._publishers:
                raise TypeError(f"stage {self._spec.name} does not publish {topic!r}")
            if type(item) is not model_for(topic):
                raise TypeError(f"{topic} carries {model_for(topic).__name__}, not {type(item).__name__}")
            messages.append((topic, item))
        return messages, raws, refusals, notices

    def _report(self, *, input_key: str | None, started: float, reason: str | None, note: str = "") -> None:
        """The status of one input: ``error`` with `reason`, else ``ok`` with the core's notices, if any."""
        stamp_s = self._last_stamp_s if self._input_stamp_s is None else self._input_stamp_s
        status = StageStatus(
            header=Header(stamp_s=stamp_s, seq=self._status_seq),
            stage=self._spec.name,
            state="ok" if reason is None else "error",
            reason=one_line(note) if reason is None else reason,
            input_key=input_key,
            input_stamp_s=self._input_stamp_s,
            processing_ms=(time.perf_counter() - started) * 1e3,
        )
        self._status_seq += 1
        if reason is not None:
            logger.warning("stage %s rejected input: %s", self._spec.name, reason)
        self._status_publisher.put(status.model_dump_json())


def freeze_startup_objects() -> None:
    """Exempt every object alive now (modules, compiled problems, caches) from garbage collection.

    The collector's full passes traverse every tracked object, and the libraries a stage imports
    hold hundreds of thousands of them: each pass stalls the stage it hits by tens of milliseconds.
    What a stage allocates per message is freed by reference counting, so the passes that remain are
    short. Called once, by the shell, when start-up is done.
    """
    gc.collect()
    gc.freeze()


def run_stage(
    *,
    stage: str,
    core: StageCore,
    session_config: zenoh.Config,
    prefix: str,
    stop_event: threading.Event,
    max_payload_bytes: int = DEFAULT_MAX_PAYLOAD_BYTES,
    clock: Callable[[], float] = time.monotonic,
    tick_period_s: float | None = None,
    ready_event: threading.Event | None = None,
    state_dir: Path | None = None,
    progress: Progress | None = None,
    frame: LocalFrame = LocalFrame(),
) -> None:
    """Run ``stage`` (a process of the wiring table) with ``core`` until ``stop_event`` is set, or the
    core is done (a ``Scheduled`` source whose run ended).

    The session owns every declaration; all are undeclared, and the liveliness token withdrawn,
    before this returns. A ``Scheduled`` core ticks when it asks to; another ``TickingCore`` every
    ``tick_period_s``, between inputs. ``ready_event`` is set once the process is declared. With
    ``state_dir``, a ``Stateful`` core gets back the state saved there and saves it there. The core
    works in ``frame`` (built from ``frame.scenario_to_local``): every message it is handed is moved
    into it, every one it publishes back into the world frame of the keys. ``progress`` is told when
    each pass of the loop begins (the heartbeat's evidence, ``services.shell.watchdog``).
    """
    progress = progress or Progress()
    spec = PROCESSES[stage]
    checkpoint = None
    if state_dir is not None and isinstance(core, Stateful):
        checkpoint = Checkpoint(state_dir=state_dir)
        checkpoint.restore(core)
    with zenoh.open(session_config) as session, ExitStack() as declarations:
        declare = declarations.enter_context
        # Every publisher drops on a congested link rather than wait: a reader that stops reading (a dead
        # monitor link) would otherwise stall this process, and behind it the whole loop, for Zenoh's
        # 5 s `wait_before_close`. The sim sends again the scan it waits for (``sim.stage``).
        publishers = {
            topic: declare(session.declare_publisher(
                key(prefix, topic), encoding=zenoh.Encoding(model_for(topic).encoding()),
                congestion_control=zenoh.CongestionControl.DROP))
            for topic in spec.publishes
        }
        status_publisher = declare(session.declare_publisher(
            status_key(prefix, stage), encoding=zenoh.Encoding(StageStatus.encoding()),
            congestion_control=zenoh.CongestionControl.DROP))
        shell = _Shell(spec=spec, core=core, prefix=prefix, publishers=publishers, status_publisher=status_publisher,
                       max_payload_bytes=max_payload_bytes, clock=clock, checkpoint=checkpoint, frame=frame)
        inbox = Inbox()
        queue = inbox.ring(QUEUE_CAPACITY)  # a source's or sink's inputs; a stage's statuses and liveliness
        rings = {} if spec.every_input else {topic: inbox.ring(INPUT_RING) for topic in spec.subscribes}
        deliver = {topic: rings[topic] if topic in rings else inbox.tagged(queue, topic) for topic in spec.subscribes}
        for topic in spec.subscribes:
            declare(session.declare_subscriber(key(prefix, topic), deliver[topic]))
        if spec.hears_statuses:
            declare(session.declare_subscriber(status_key(prefix), inbox.tagged(queue, _STATUS)))
        if spec.watches:
            declare(session.liveliness().declare_subscriber(alive_key(prefix), inbox.tagged(queue, _ALIVE),
                                                             history=True))
        if spec.ros2:  # a source: its ROS inputs join the one queue
            if not isinstance(core, Bridging):
                raise TypeError(f"stage {stage} is a ROS 2 node, but its core {type(core).__name__} does not bridge")
            from services.shell.ros2 import BridgePorts  # the bridge's alone: the other stages start without it

            shell.ros = BridgePorts(session, domain_id=core.domain_id, namespace=core.namespace,
                                    deliver=lambda port, sample: queue((_ROS + port, sample)))
            declarations.callback(shell.ros.close)
        for topic in spec.publishes:
            if TOPICS[topic].latched:
                declare(session.declare_queryable(key(prefix, topic), shell.answer(topic)))
        declare(session.liveliness().declare_token(alive_key(prefix, stage)))
        for topic in spec.subscribes:  # what a latched topic's publisher put before we came
            if TOPICS[topic].latched:
                for reply in session.get(key(prefix, topic), timeout=1.0):
                    if reply.ok is not None:
                        deliver[topic](reply.ok)
        logger.info("stage %s running under %s", stage, prefix)
        freeze_startup_objects()
        if ready_event is not None:
            ready_event.set()
        periodic_s = time.monotonic()
        while not stop_event.is_set() and not shell.done:
            progress.beat()
            until_tick_s = STOP_CHECK_S
            if shell.scheduled:
                due_s = shell.next_tick_s()
                if due_s is not None and clock() >= due_s:
                    shell.tick()
                    due_s = shell.next_tick_s()
                if due_s is not None:
                    until_tick_s = due_s - clock()
            elif tick_period_s is not None:
                if time.monotonic() >= periodic_s:
                    shell.tick()
                    periodic_s = max(periodic_s + tick_period_s, time.monotonic())
                until_tick_s = periodic_s - time.monotonic()
            idle = True
            while (item := queue.try_recv()) is not None:
                idle = False
                shell.handle(tag=item[0], sample=item[1])
            for topic, ring in rings.items():
                samples = [s for s in iter(ring.try_recv, None) if s.kind == zenoh.SampleKind.PUT]
                if samples:
                    idle = False
                    shell.handle_newest(topic=topic, samples=samples)
            if idle:
                inbox.wait(min(STOP_CHECK_S, until_tick_s))
        if spec.every_input and stop_event.is_set():  # what already arrived (the sim's last messages)
            deadline_s = time.monotonic() + DRAIN_S
            while time.monotonic() < deadline_s:
                inbox.wait(0.2)
                items = list(iter(queue.try_recv, None))
                if not items:
                    break
                for tag, sample in items:
                    shell.handle(tag=tag, sample=sample)
        shell.stop()
        if queue.dropped:
            logger.warning("stage %s dropped %d inputs: its queue was full", stage, queue.dropped)
    logger.info("stage %s stopped", stage)
