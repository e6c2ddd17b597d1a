"""The one Zenoh shell every stage runs in: pure core inside, the same thin shell around each.

A stage's core is plain code: ``process(topic=, message=, now_s=)`` returns the messages to publish,
by topic. ``run_stage`` does all the I/O. Which keys a stage reads and writes comes from the wiring
table (``schemas.wiring.STAGES``), never from the core.

Each input is received into a small ring (``Ring``, ``INPUT_RING`` samples): a stage that falls
behind works on the newest sample that decodes, and the stale ones are dropped, so nothing queues
without bound. The worker sleeps until a sample arrives (``Inbox``) rather than polling. Samples
newer than that one which do not decode are reported, never processed: garbage on a key cannot push
a real message out unless it outnumbers the ring. After every input the stage publishes a
``StageStatus`` on ``<prefix>/status/<stage>``: ``error`` with a one-line reason for an input it
could not use (oversize, bad JSON, wrong schema, non-finite number, validation failure,
``StageInputError``, solver failure), ``ok`` otherwise. A rejected input publishes nothing else, so
the last good outputs stand. The status carries the rejected input's stamp (``input_stamp_s``) only
when the input decoded; garbage on a key is reported, but never as the verdict on a real scan.

Bounds: a payload larger than ``max_payload_bytes`` (``cvxnav service --max-payload-bytes``, default
1 MiB) is rejected before it is decoded; each core bounds what a decoded message may hold (points
per scan, per cluster set, per path; ellipses per set; coordinates within the scenario's extent).
"""

from __future__ import annotations

import gc
import logging
import signal
import threading
import time
from collections import deque
from collections.abc import Callable
from contextlib import ExitStack
from pathlib import Path

import zenoh
from pydantic import BaseModel

from schemas.messages import DecodeError, Header, M, StageStatus, decode
from schemas.wiring import STAGES, StageSpec, alive_key, key, model_for, status_key
from services.contract import Outputs, StageCore, StageInputError, Stateful, TickingCore
from services.limits import DEFAULT_MAX_PAYLOAD_BYTES
from services.shell.checkpoint import Checkpoint

logger = logging.getLogger(__name__)

MAX_REASON_CHARS = 300
# The longest a worker sleeps with no input: how long it may take to notice a stop.
STOP_CHECK_S = 0.05
# Samples held per input key: the newest decodable one among them is processed, older ones dropped.
INPUT_RING = 8


def one_line(text: str) -> str:
    """The first line of ``text``, at most ``MAX_REASON_CHARS`` long: a status reason."""
    first = (text.splitlines() or [""])[0]
    return first if len(first) <= MAX_REASON_CHARS else first[: MAX_REASON_CHARS - 1] + "…"


class Ring:
    """A Zenoh subscriber callback that keeps the newest `capacity` samples (the oldest are dropped, as
    in zenoh's RingChannel) and wakes its inbox; read with `try_recv`, like a channel."""

    def __init__(self, capacity: int, wake: threading.Event) -> None:
        self._samples: deque[zenoh.Sample] = deque(maxlen=capacity)
        self._wake = wake

    def __call__(self, sample: zenoh.Sample) -> None:
        self._samples.append(sample)
        self._wake.set()

    def try_recv(self) -> zenoh.Sample | None:
        try:
            return self._samples.popleft()
        except IndexError:
            return None


class Inbox:
    """The rings of one worker's subscriptions, and the one event that wakes it when any receives.

    Waiting on it instead of polling the subscriptions takes the poll period off every hop: on
    field-25, `cvxnav run` went from scan→path p50 41–46 to 33–34 ms and 21–23 to 18–19 s wall.
    """

    def __init__(self) -> None:
        self._wake = threading.Event()

    def ring(self, capacity: int) -> Ring:
        return Ring(capacity, self._wake)

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


def install_signal_handlers(stop_event: threading.Event) -> None:
    """Set ``stop_event`` on SIGINT and SIGTERM (compose stops containers with SIGTERM).

    Must be called from the main thread (a Python restriction on ``signal.signal``).
    """

    def _stop(signum: int, _frame: object) -> None:
        logger.info("received %s, stopping", signal.Signals(signum).name)
        stop_event.set()

    signal.signal(signal.SIGINT, _stop)
    signal.signal(signal.SIGTERM, _stop)


class _Shell:
    """The per-input step of ``run_stage``: size check, decode, process, publish, report."""

    def __init__(
        self,
        *,
        spec: StageSpec,
        core: StageCore,
        publishers: dict[str, zenoh.Publisher],
        status_publisher: zenoh.Publisher,
        max_payload_bytes: int,
        clock: Callable[[], float],
        checkpoint: Checkpoint | None,
    ) -> None:
        self._spec = spec
        self._checkpoint = checkpoint
        self._core = core
        self._publishers = publishers
        self._status_publisher = status_publisher
        self._max_payload_bytes = max_payload_bytes
        self._clock = clock
        self._status_seq = 0
        self._last_stamp_s = 0.0  # of the last input the core accepted: the status's sim time
        self._input_stamp_s: float | None = None  # of the input being handled, once decoded

    def handle_newest(self, *, topic: str, samples: list[zenoh.Sample]) -> None:
        """Of samples in arrival order, process the newest that decodes; report each newer one that does not.

        Older samples are superseded and dropped undecoded, as the ring drops them.
        """
        for sample in reversed(samples):
            input_key = str(sample.key_expr)
            started = time.perf_counter()
            self._input_stamp_s = None
            try:
                message = self._decoded(topic=topic, sample=sample)
            except DecodeError as error:
                self._report(input_key=input_key, started=started, reason=one_line(f"{input_key}: {error}"))
                continue
            self._step(lambda: self._process(topic=topic, message=message), input_key=input_key)
            return

    def tick(self) -> None:
        """One timer step; reports a status only when it fails (a tick has no input to judge)."""
        core: TickingCore = self._core  # type: ignore[assignment]  # run_stage's contract
        self._input_stamp_s = None
        self._step(lambda: core.tick(now_s=self._clock()), input_key=None, report_ok=False)

    def _step(self, step: Callable[[], Outputs], *, input_key: str | None, report_ok: bool = True) -> None:
        started = time.perf_counter()
        where = input_key or "tick"
        try:
            outputs = self._checked(step())
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
        for out_topic, message in outputs:
            self._publishers[out_topic].put(message.model_dump_json())
        if self._input_stamp_s is not None:
            self._last_stamp_s = self._input_stamp_s
        if report_ok:
            self._report(input_key=input_key, started=started, reason=None)

    def _decoded(self, *, topic: str, sample: zenoh.Sample) -> BaseModel:
        return decode_sample(model_for(topic), sample, max_payload_bytes=self._max_payload_bytes)

    def _process(self, *, topic: str, message: BaseModel) -> Outputs:
        header = getattr(message, "header", None)
        if isinstance(header, Header):
            self._input_stamp_s = header.stamp_s
        return self._core.process(topic=topic, message=message, now_s=self._clock())

    def _checked(self, outputs: Outputs) -> Outputs:
        """Reject a core's output batch that breaks the wiring table, before any of it is published."""
        for out_topic, message in outputs:
            if out_topic not in self._publishers:
                raise TypeError(f"stage {self._spec.name} does not publish {out_topic!r}")
            if type(message) is not model_for(out_topic):
                expected = model_for(out_topic).__name__
                raise TypeError(f"{out_topic} carries {expected}, not {type(message).__name__}")
        return outputs

    def _report(self, *, input_key: str | None, started: float, reason: str | None) -> None:
        stamp_s = self._last_stamp_s if self._input_stamp_s is None else self._input_stamp_s
        status = StageStatus(
            header=Header(stamp_s=stamp_s, seq=self._status_seq),
            stage=self._spec.name,
            state="ok" if reason is None else "error",
            reason=reason or "",
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
    hold hundreds of thousands of them: on field-25 each pass stalled the stage it hit by up to 33 ms
    (the smoother's p99 went 38 → 8 ms once they were frozen). What a stage allocates per message is
    freed by reference counting, so the passes that remain are short. Called once, by the process's
    main loop, when start-up is done.
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
) -> None:
    """Run ``stage`` (a name in the wiring table) with ``core`` until ``stop_event`` is set.

    The session owns every declaration; all are undeclared, and the liveliness token withdrawn,
    before this returns. With ``tick_period_s``, ``core`` must be a ``TickingCore`` and its
    ``tick`` runs at that period between inputs. ``ready_event`` is set once the stage is declared.
    With ``state_dir``, a ``Stateful`` core gets back the state saved there and saves it there.
    """
    checkpoint = None
    if state_dir is not None and isinstance(core, Stateful):
        checkpoint = Checkpoint(state_dir=state_dir)
        checkpoint.restore(core)
    spec = STAGES[stage]
    with zenoh.open(session_config) as session, ExitStack() as declarations:
        declare = declarations.enter_context
        publishers = {
            topic: declare(
                session.declare_publisher(key(prefix, topic), encoding=zenoh.Encoding(model_for(topic).encoding()))
            )
            for topic in spec.publishes
        }
        status_publisher = declare(
            session.declare_publisher(status_key(prefix, stage), encoding=zenoh.Encoding(StageStatus.encoding()))
        )
        inbox = Inbox()
        rings = {topic: inbox.ring(INPUT_RING) for topic in spec.subscribes}
        for topic, ring in rings.items():
            declare(session.declare_subscriber(key(prefix, topic), ring))
        declare(session.liveliness().declare_token(alive_key(prefix, stage)))
        shell = _Shell(
            spec=spec,
            core=core,
            publishers=publishers,
            status_publisher=status_publisher,
            max_payload_bytes=max_payload_bytes,
            clock=clock,
            checkpoint=checkpoint,
        )
        logger.info("stage %s running under %s", stage, prefix)
        freeze_startup_objects()
        if ready_event is not None:
            ready_event.set()
        next_tick_s = time.monotonic()
        while not stop_event.is_set():
            if tick_period_s is not None and time.monotonic() >= next_tick_s:
                shell.tick()
                next_tick_s = max(next_tick_s + tick_period_s, time.monotonic())
            idle = True
            for topic, ring in rings.items():
                samples = [s for s in iter(ring.try_recv, None) if s.kind == zenoh.SampleKind.PUT]
                if samples:
                    idle = False
                    shell.handle_newest(topic=topic, samples=samples)
            if idle:
                until_tick_s = STOP_CHECK_S if tick_period_s is None else next_tick_s - time.monotonic()
                inbox.wait(min(STOP_CHECK_S, until_tick_s))
    logger.info("stage %s stopped", stage)

