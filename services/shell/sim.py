"""The sim's Zenoh shell: `SimCore` (``sim.core``) closing the loop with the pipeline over Zenoh.

See ``sim.core`` for the two modes (lockstep, realtime) and the watchdogs this loop drives.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import zenoh

from schemas.files import RunFile
from schemas.messages import DecodeError, Ellipsoids, Header, M, RobotState, Scan, SmoothPath, StageStatus, decode
from schemas.messages import World as WorldMessage
from schemas.scenario import Scenario
from schemas.wiring import STAGES, alive_key, key, status_key
from services.contract import StageInputError
from services.limits import Reach
from services.shell.stage import STOP_CHECK_S, Inbox, Ring, decode_sample, freeze_startup_objects, one_line
from sim.core import SimConfig, SimCore
from sim.truth import world_message

logger = logging.getLogger(__name__)

PIPELINE_STAGES = tuple(name for name in STAGES if name != "sim")


@dataclass
class _Answers:
    """What the sim hears back: paths by scan_seq, stage errors by the scan stamp they concern, the
    ellipsoid stage's newest grown ellipses and the pipeline stages' liveliness changes; and where it
    says why it would not drive on a path."""

    inbox: Inbox  # wakes the sim when any of the rings below receives
    paths_key: str
    paths: Ring
    statuses: Ring
    status_pub: zenoh.Publisher  # the sim's own status
    max_payload_bytes: int
    reach: Reach
    ellipsoids: Ring
    alive: Ring
    published_at: dict[int, float] = field(default_factory=dict)  # scan seq -> perf_counter
    stamps: dict[int, float] = field(default_factory=dict)  # scan seq -> sim stamp
    latencies_ms: list[float] = field(default_factory=list)
    rejected: dict[float, str] = field(default_factory=dict)  # scan stamp -> reason
    back_at: float = -math.inf  # monotonic time a stage last came back
    status_seq: int = 0

    def newest_path(self) -> SmoothPath | None:
        """Drain the path queue; record latencies; the newest usable path (None if none came)."""
        newest = None
        while (sample := self.paths.try_recv()) is not None:
            try:
                answer = self._answer(SmoothPath, sample)
            except DecodeError as error:
                self._report(str(sample.key_expr), one_line(f"{sample.key_expr}: {error}"))
                continue
            sent = self.published_at.pop(answer.scan_seq, None)
            if sent is not None:
                self.latencies_ms.append((time.perf_counter() - sent) * 1e3)
            if newest is None or answer.scan_seq >= newest.scan_seq:
                newest = answer
        return newest

    def _answer(self, model: type[M], sample: zenoh.Sample) -> M:
        """A received SmoothPath or Ellipsoids, bounded in size and answering a scan the sim sent."""
        answer = decode_sample(model, sample, max_payload_bytes=self.max_payload_bytes)
        if answer.scan_seq not in self.stamps:
            raise DecodeError(f"answers scan {answer.scan_seq}, which the sim never sent")
        return answer

    def _report(self, input_key: str, reason: str) -> None:
        logger.warning("ignoring %s", reason)
        stamp_s = max(self.stamps.values(), default=0.0)
        status = StageStatus(header=Header(stamp_s=stamp_s, seq=self.status_seq), stage="sim", state="error",
                             reason=reason, input_key=input_key, processing_ms=0.0)
        self.status_seq += 1
        self.status_pub.put(status.model_dump_json())

    def drain_statuses(self) -> None:
        while (sample := self.statuses.try_recv()) is not None:
            try:
                status = decode(StageStatus, sample.payload.to_bytes(), encoding=str(sample.encoding))
            except DecodeError:
                continue
            if status.state == "error" and status.stage != "sim" and status.input_stamp_s is not None:
                self.rejected[status.input_stamp_s] = f"{status.stage}: {status.reason}"

    def watch(self, core: SimCore) -> None:
        """Pass liveliness changes and the newest ellipses to the core; log a path the ellipses dropped."""
        while (sample := self.alive.try_recv()) is not None:
            stage = str(sample.key_expr).rsplit("/", 1)[-1]
            if stage not in PIPELINE_STAGES:
                continue
            if sample.kind == zenoh.SampleKind.DELETE:
                if stage not in core.missing:
                    logger.warning("stage %s is down: braking until it is back and a fresh plan arrives", stage)
                core.stage_lost(stage)
            elif stage in core.missing:
                logger.warning("stage %s is back", stage)
                core.stage_back(stage)
                self.back_at = time.monotonic()
        newest = None
        while (sample := self.ellipsoids.try_recv()) is not None:
            try:
                message = self._decoded_ellipsoids(sample)
            except (DecodeError, StageInputError) as error:
                self._report(str(sample.key_expr), one_line(f"{sample.key_expr}: {error}"))
                continue
            if newest is None or message.scan_seq >= newest.scan_seq:
                newest = message
        if newest is not None:
            dropped = core.know(newest)
            if dropped is not None:  # the planner replans on the same ellipses: routine, not an error
                logger.info("newer obstacles cross the path being driven; braking until the replan: %s", dropped)

    def _decoded_ellipsoids(self, sample: zenoh.Sample) -> Ellipsoids:
        """Ellipses the guard may trust as far as checks go: bounded, and answering a scan the sim sent.

        The guard keeps the newest set by scan; a forged one numbered past every real scan would
        otherwise blind it to the real obstacles for the rest of the run.
        """
        message = self._answer(Ellipsoids, sample)
        self.reach.check_ellipses(message.ellipsoids, what="ellipsoids")
        return message

    def take(self, core: SimCore, answer: SmoothPath) -> None:
        """Hand the core an answer; if it will not drive on it, say why on the sim's status key."""
        reason = core.accept(answer)
        if reason is None:
            return
        self._report(self.paths_key, f"plan {answer.plan_id} for scan {answer.scan_seq} not driven: {reason}")


def wait_for_stages(session: zenoh.Session, *, prefix: str, stages: tuple[str, ...], timeout_s: float,
                    stop_event: threading.Event | None = None) -> set[str]:
    """Poll the liveliness tokens until every stage is up; the ones still missing after the timeout."""
    deadline = time.monotonic() + timeout_s
    missing = set(stages)
    while missing and time.monotonic() < deadline and not (stop_event and stop_event.is_set()):
        for reply in session.liveliness().get(f"{prefix}/alive/*", timeout=1.0):
            if reply.ok is not None:
                missing.discard(str(reply.ok.key_expr).rsplit("/", 1)[-1])
        if missing:
            time.sleep(0.05)
    return missing


def _publish_world(session: zenoh.Session, *, scenario: Scenario, prefix: str) -> zenoh.Queryable:
    """Put the true map once, and answer gets on its key, so a monitor that joins later still has it."""
    world = world_message(scenario)
    payload, encoding = world.model_dump_json(), zenoh.Encoding(WorldMessage.encoding())
    world_key = key(prefix, "world")
    session.put(world_key, payload, encoding=encoding)
    return session.declare_queryable(world_key, lambda query: query.reply(world_key, payload, encoding=encoding))


def run_sim(
    *,
    scenario: Scenario,
    config: SimConfig,
    session_config: zenoh.Config,
    prefix: str,
    stop_event: threading.Event,
    out_path: Path | None = None,
    stage_wait_s: float = 30.0,
) -> RunFile:
    """Run the car until it reaches every goal, gives up (no_path), collides, or runs out of time."""
    core = SimCore(scenario=scenario, config=config)
    with zenoh.open(session_config) as session:
        block = zenoh.CongestionControl.BLOCK
        scan_pub = session.declare_publisher(key(prefix, "scan"), encoding=zenoh.Encoding(Scan.encoding()),
                                             congestion_control=block)
        state_pub = session.declare_publisher(key(prefix, "state"),
                                              encoding=zenoh.Encoding(RobotState.encoding()),
                                              congestion_control=block)
        inbox = Inbox()
        rings = {name: inbox.ring(_ANSWER_RING) for name in ("paths", "statuses", "ellipsoids", "alive")}
        session.declare_subscriber(key(prefix, "smooth_path"), rings["paths"])
        session.declare_subscriber(status_key(prefix, "*"), rings["statuses"])
        session.declare_subscriber(key(prefix, "ellipsoids"), rings["ellipsoids"])
        session.liveliness().declare_subscriber(alive_key(prefix, "*"), rings["alive"], history=True)
        answers = _Answers(
            inbox=inbox,
            paths_key=key(prefix, "smooth_path"),
            status_pub=session.declare_publisher(status_key(prefix, "sim"),
                                                 encoding=zenoh.Encoding(StageStatus.encoding())),
            max_payload_bytes=config.max_payload_bytes,
            reach=Reach.of(scenario),
            **rings,
        )
        token = session.liveliness().declare_token(alive_key(prefix, "sim"))
        world_queryable = _publish_world(session, scenario=scenario, prefix=prefix)
        missing = wait_for_stages(session, prefix=prefix, stages=PIPELINE_STAGES, timeout_s=stage_wait_s,
                                  stop_event=stop_event)
        if missing:
            logger.warning("stages not alive after %.0f s: %s", stage_wait_s, ", ".join(sorted(missing)))
        for stage in missing:
            core.stage_lost(stage)
        freeze_startup_objects()

        def publish_tick() -> None:
            state, scan = core.sense()
            state_pub.put(state.model_dump_json())
            answers.published_at[scan.header.seq] = time.perf_counter()
            answers.stamps[scan.header.seq] = scan.header.stamp_s
            scan_pub.put(scan.model_dump_json())

        try:
            if config.realtime:
                _realtime_loop(core=core, answers=answers, publish_tick=publish_tick, stop_event=stop_event)
            else:
                _lockstep_loop(core=core, answers=answers, publish_tick=publish_tick, stop_event=stop_event,
                               timeout_s=config.answer_timeout_s)
            state_pub.put(core.robot_state().model_dump_json())  # done=True: the run is over
        finally:
            token.undeclare()
            world_queryable.undeclare()
    result = core.result(latencies_ms=answers.latencies_ms)
    if out_path is not None:
        result.write(out_path)
    return result


# A stage that came back this recently may have missed the scan: re-send it if no answer came in a second.
_REJOIN_RESEND_S = 5.0
# Samples the sim holds per subscription between drains (paths, statuses, ellipsoids, liveliness).
_ANSWER_RING = 256


def _lockstep_loop(*, core: SimCore, answers: _Answers, publish_tick, stop_event: threading.Event,
                   timeout_s: float) -> None:
    while core.outcome is None and not stop_event.is_set():
        if not core.scan_due:  # backing out, with no scan to wait for; or back in step with the sensor after it
            core.advance()
            continue
        seq = core.scan_seq
        publish_tick()
        stamp = core.t_s
        started = time.monotonic()
        deadline = started + timeout_s
        resend_at = started + 1.0
        answered = False
        while not answered and time.monotonic() < deadline and not stop_event.is_set():
            answers.watch(core)
            if core.missing:
                break  # no answer will come: brake on the wall clock until the stage is back
            answer = answers.newest_path()
            if answer is not None and answer.scan_seq == seq:
                _await_ellipsoids(core=core, answers=answers, seq=seq, deadline=min(deadline, time.monotonic() + 1.0))
                answers.take(core, answer)
                answered = True
                break
            answers.drain_statuses()
            reasons = [reason for s, reason in answers.rejected.items() if abs(s - stamp) <= 1e-9]
            if reasons:
                core.no_plan(reasons[0])  # no verified path for what the car now knows: brake
                answered = True
                break
            rejoined = time.monotonic() - answers.back_at < _REJOIN_RESEND_S
            if (seq == 0 or rejoined) and time.monotonic() >= resend_at:
                publish_tick()  # routes to fresh (or restarted) peers may not have been up for this scan
                resend_at = time.monotonic() + 1.0
            answers.inbox.wait(min(deadline, resend_at, time.monotonic() + STOP_CHECK_S) - time.monotonic())
        answers.rejected.clear()
        stalled = bool(core.missing)
        if not answered and not stalled and not stop_event.is_set():
            logger.warning("no answer to scan %d within %.1f s; driving on what the car has", seq, timeout_s)
        for _ in range(core.steps_per_scan):
            if core.advance() is not None:
                return
        if stalled:
            stop_event.wait(max(0.0, started + core.steps_per_scan * core.config.dt_s - time.monotonic()))


def _await_ellipsoids(*, core: SimCore, answers: _Answers, seq: int, deadline: float) -> None:
    """Lockstep: the ellipses of scan `seq` come straight from their stage, the path two stages later;
    wait (briefly) for them so the path is checked against the same obstacles in every run."""
    while core.guard.scan_seq < seq and time.monotonic() < deadline:
        answers.inbox.wait(min(deadline - time.monotonic(), STOP_CHECK_S))
        answers.watch(core)


def _realtime_loop(*, core: SimCore, answers: _Answers, publish_tick, stop_event: threading.Event) -> None:
    started = time.monotonic()
    while core.outcome is None and not stop_event.is_set():
        if core.scan_due:
            publish_tick()
        answers.watch(core)
        answer = answers.newest_path()
        if answer is not None:
            answers.take(core, answer)
        answers.drain_statuses()
        published = {stamp for seq, stamp in answers.stamps.items() if seq >= core.resume_seq}
        concerning = [reason for stamp, reason in answers.rejected.items() if stamp in published]
        if concerning:
            # A stage could not verify a path for a scan the car sent (since a stage's loss or its last
            # back-out): brake until a verified one arrives. Errors about anything else (a malformed
            # message on a key) leave the plan in force.
            core.no_plan(concerning[0])
        answers.rejected.clear()
        wake = started + (core.step_index + 1) * core.config.dt_s
        stop_event.wait(max(0.0, wake - time.monotonic()))
        core.advance()
