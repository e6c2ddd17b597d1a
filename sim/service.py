"""The sim stage: the kinematic car, its range sensor and its controller, closing the loop over Zenoh.

`SimCore` is the pure part (no I/O, clock and seed are arguments): it senses, accepts the pipeline's
answers and integrates the car. `run_sim` is the Zenoh shell around it, in one of two modes:

- lockstep (default): at each sensor tick the sim publishes the state and the scan, then waits (up to
  `answer_timeout_s` of wall time) for the pipeline's answer to that scan before integrating the next
  sensor period. The answer is the SmoothPath carrying the scan's `scan_seq` (status ok or no_path), or
  an error status of any stage for that scan: then no path could be verified against what the car now
  knows, and the car brakes rather than drive on a path checked only against older obstacles.
  Sim time then depends only on the scenario and the seed, so two runs give the same trajectory, and a
  run goes as fast as the pipeline answers.
- realtime: sim time follows the wall clock; scans go out at the sensor rate and the newest path is
  used whenever it arrives, as on a real robot.

Either way the car never drives on a stale plan or without one: it brakes within its limits and waits.
When the pipeline answers a scan without a path it can drive (no_path, or a stage's error for that
scan) and the car is at rest, the car backs out along its own tracks, its length plus one turning
radius at a time and at most `max_backouts` times per goal, scanning again after each. A car can drive
into a dead end before it has seen that it is one: in a dense field it then has no forward turn left
inside the margins (a closed loop in a 60-obstacle field stood still there for good; 4 m back along its
tracks a plan verified). It backs out only over ground it has driven: the world is static, and the
rear axle retraces the tracks within a few cm. Not against the newest covers: they over-approximate,
and grow over tracks the car drove clear of the obstacle (60-obstacle field: level 0.982 against the
guard's floor of 0.99). It does not scan meanwhile (the sensor faces the dead end it is leaving), so
lockstep runs stay deterministic. With no tracks or back-outs left, such answers for
`no_path_patience_s` with the car at rest end the run as no_path.
A smooth_path it cannot use (oversize, undecodable, or answering a scan it never sent) is ignored and
reported on ``<prefix>/status/sim`` with a one-line reason, like any stage's rejected input.
Two watchdogs add to that:

- liveliness: the sim follows the pipeline stages' tokens (`<prefix>/alive/*`). When one disappears
  (its process died) the car brakes at once, and it drives again only on an answer to a scan sent after
  the loss, once every stage is back. In lockstep the sim then stops waiting for the answer to the
  current scan (none will come) and runs on the wall clock, braking and standing, until the stage is
  back; so a restart costs the car the restart time, never the answer timeout. Scan hits taken while
  the sensing stage was down ride along with every scan until the pipeline answers one, so the
  restarted stage's memory misses nothing the car saw (its point memory dedupes them).
- the path check (`sim.guard`): every path, and the path being driven whenever newer ellipses arrive,
  is checked against the newest grown ellipses from the ellipsoid stage; a path that enters one is not
  driven. For a received path the sim says why on `<prefix>/status/sim`; a driven path that newer
  ellipses cross is routine (the planner replans on the same ellipses), so it is only logged.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import zenoh

from cvxnav.runtime import (
    DEFAULT_MAX_PAYLOAD_BYTES,
    STOP_CHECK_S,
    Inbox,
    Ring,
    StageInputError,
    decode_sample,
    freeze_startup_objects,
    one_line,
)
from schemas.files import LatencyStats, RunFile
from schemas.messages import (
    DecodeError,
    Ellipsoids,
    Header,
    M,
    Pose2D,
    RobotState,
    Scan,
    SmoothPath,
    StageStatus,
    decode,
)
from schemas.messages import World as WorldMessage
from schemas.scenario import Scenario
from schemas.wiring import STAGES, alive_key, key, status_key
from services.limits import Reach
from sim.controller import GoalTracker, PurePursuit
from sim.guard import PathGuard, ahead
from sim.sensor import RangeSensor
from sim.truth import world_message
from sim.vehicle import VehicleLimits, VehicleState, step
from sim.world import World

logger = logging.getLogger(__name__)

Outcome = str  # "reached" | "no_path" | "timeout" | "collision"
PIPELINE_STAGES = tuple(name for name in STAGES if name != "sim")
_UNHEARD_CELL_M = 0.01  # hits kept for a restarted sensing stage: one per cell of this size
_UNHEARD_MAX = 10_000  # and at most this many (the newest), so a scan stays well under the payload cap
_SCAN_POSES_KEPT = 256  # where the recent scans were taken (a path is checked from its scan's pose)
_TRACK_STEP_M = 0.05  # the tracks the car can back out along: one pose per this much forward travel


def default_time_limit_s(scenario: Scenario) -> float:
    """Sim-time budget: three times the straight-line tour at full speed, plus a minute for detours."""
    tour = np.vstack([scenario.start.xy, scenario.goals_array])
    length_m = float(np.sum(np.linalg.norm(np.diff(tour, axis=0), axis=1)))
    return 3.0 * length_m / float(scenario.robot.max_speed) + 60.0


@dataclass(frozen=True)
class SimConfig:
    dt_s: float = 0.05  # integration step (one trajectory row each)
    time_limit_s: float | None = None  # sim time; None: default_time_limit_s(scenario)
    stale_after_s: float = 1.5  # a path older than this (sim time) is not driven on
    no_path_patience_s: float = 2.0  # no drivable path this long, at rest with no back-out left: the run ends
    # How far the car backs out along its tracks at a time (None: its length plus one minimum turning
    # radius, room to turn), and how often per goal.
    backout_m: float | None = None
    max_backouts: int = 4
    noise_std_m: float = 0.0  # range noise, drawn from a generator seeded with `seed`
    seed: int = 0
    answer_timeout_s: float = 10.0  # lockstep: wall time to wait for the answer to a scan
    realtime: bool = False
    max_payload_bytes: int = DEFAULT_MAX_PAYLOAD_BYTES  # a larger smooth_path is rejected undecoded


@dataclass
class SimCore:
    """The car, its sensor and controller, and the record of the run; advanced by its caller."""

    scenario: Scenario
    config: SimConfig = field(default_factory=SimConfig)

    def __post_init__(self) -> None:
        scenario = self.scenario
        self.world = World.from_scenario(scenario)
        self.limits = VehicleLimits.from_scenario(scenario)
        self.sensor = RangeSensor.from_scenario(scenario, noise_std_m=self.config.noise_std_m)
        self.rng = np.random.default_rng(self.config.seed) if self.config.noise_std_m > 0.0 else None
        self.controller = PurePursuit.from_limits(self.limits)
        self.goals = GoalTracker.from_scenario(scenario)
        self.state = VehicleState.at_start(scenario)
        self.time_limit_s = self.config.time_limit_s or default_time_limit_s(scenario)
        period_s = 1.0 / float(scenario.sensor.rate_hz)
        self.steps_per_scan = max(1, round(period_s / self.config.dt_s))
        self.step_index = 0
        self.scan_seq = 0
        self.path: np.ndarray | None = None
        self.path_time_s = -math.inf
        self.progress_m: float | None = None
        self.no_path_since_s: float | None = None  # answers without a drivable path since then
        self.no_path_reason = ""
        self.tracks: list[tuple[float, float, float]] = [self._pose()]  # forward poses, ≥ _TRACK_STEP_M apart
        self.backout: np.ndarray | None = None  # rear-axle points to back along, while backing out
        self.backout_progress_m: float | None = None
        self.backout_keep = 0  # how many of `tracks` remain once the back-out ends
        self.backouts = 0  # started for the current goal
        self.backout_m = self.config.backout_m or float(scenario.robot.length) + self.limits.min_turn_radius_m
        self.plan_ids: list[int] = []
        self.guard = PathGuard(inflation_m=scenario.inflation_m, keep_out_m=scenario.keep_out_m)
        self.missing: set[str] = set()  # pipeline stages whose liveliness token is gone
        self.resume_seq = 0  # answers to earlier scans are not taken: they predate a stage's loss or a back-out
        self.scan_xy: dict[int, tuple[float, float]] = {}  # recent scans' positions, by seq
        self.unheard: dict[tuple[int, int], tuple[float, float]] = {}  # hits the sensing stage missed
        self.unheard_seq: int | None = None  # the first scan that carried them to a live sensing stage
        self.trajectory: list[tuple[float, float, float, float]] = [self._row()]
        self.min_clearance_m = self.world.footprint_clearance(self.state)
        self.outcome: Outcome | None = None

    @property
    def t_s(self) -> float:
        return self.step_index * self.config.dt_s

    @property
    def scan_due(self) -> bool:
        """A sensor tick: every sensor period, except while the car backs out."""
        return self.step_index % self.steps_per_scan == 0 and self.backout is None

    @property
    def backing_out(self) -> bool:
        return self.backout is not None

    def _row(self) -> tuple[float, float, float, float]:
        return (self.t_s, self.state.x_m, self.state.y_m, self.state.theta_rad)

    def _heading(self) -> np.ndarray:
        return np.array([math.cos(self.state.theta_rad), math.sin(self.state.theta_rad)])

    def _pose(self) -> tuple[float, float, float]:
        return (self.state.x_m, self.state.y_m, self.state.theta_rad)

    def robot_state(self) -> RobotState:
        s = self.state
        return RobotState(
            header=Header(stamp_s=self.t_s, seq=self.scan_seq),
            pose=Pose2D(x_m=s.x_m, y_m=s.y_m, theta_rad=s.theta_rad),
            speed_mps=s.speed_mps, steering_rad=s.steering_rad,
            goal_index=min(self.goals.reached_count, len(self.goals.goals) - 1),
            goals_reached=self.goals.reached_count, done=self.outcome is not None,
        )

    def sense(self) -> tuple[RobotState, Scan]:
        """The state and the scan of this sensor tick; both carry the tick's seq and sim time.

        While the sensing stage is down its hits are kept (one per 1 cm cell); once it is back they are
        sent with every scan until the pipeline answers one of those scans.
        """
        s = self.state
        hits = self.sensor.scan(x_m=s.x_m, y_m=s.y_m, theta_rad=s.theta_rad,
                                obstacles=self.world.ray_targets, rng=self.rng)
        points = [(float(x), float(y)) for x, y in hits]
        if "sensing" in self.missing:
            self._keep_unheard(points)
        elif self.unheard:
            if self.unheard_seq is None:
                self.unheard_seq = self.scan_seq
            points = list(self.unheard.values()) + points
        self.scan_xy[self.scan_seq] = (s.x_m, s.y_m)
        while len(self.scan_xy) > _SCAN_POSES_KEPT:
            del self.scan_xy[next(iter(self.scan_xy))]
        scan = Scan(header=Header(stamp_s=self.t_s, seq=self.scan_seq),
                    pose=Pose2D(x_m=s.x_m, y_m=s.y_m, theta_rad=s.theta_rad), points=points)
        return self.robot_state(), scan

    def _keep_unheard(self, points: list[tuple[float, float]]) -> None:
        for x, y in points:
            cell = (math.floor(x / _UNHEARD_CELL_M), math.floor(y / _UNHEARD_CELL_M))
            self.unheard.pop(cell, None)
            self.unheard[cell] = (x, y)
        while len(self.unheard) > _UNHEARD_MAX:
            del self.unheard[next(iter(self.unheard))]

    def stage_lost(self, stage: str) -> None:
        """A pipeline stage's token is gone: brake, and drive only on answers to scans sent from now on."""
        if stage in self.missing:
            return
        self.missing.add(stage)
        self.reject(f"stage {stage} is down")
        self.resume_seq = self.scan_seq + 1

    def stage_back(self, stage: str) -> None:
        """A stage's token is back; the car still waits for an answer to a scan sent after the loss."""
        self.missing.discard(stage)

    def know(self, ellipsoids: Ellipsoids) -> str | None:
        """Take newer grown ellipses and re-check the rest of the path being driven against them.

        Returns why the path was dropped (the car brakes), None when it is still clear or there is none.
        """
        self.guard.know(ellipsoids)
        if self.path is None:
            return None
        position = (self.state.x_m, self.state.y_m)
        reason = self.guard.check(ahead(self.path, position=position), start=position)
        if reason is not None:
            self.reject(f"newer obstacles: {reason}")
        return reason

    def accept(self, answer: SmoothPath) -> str | None:
        """Take the pipeline's newest answer: a path to follow, or its verdict that there is none.

        An answer is ignored while a stage is down or when it answers a scan sent before the loss. A
        path that enters a known ellipse, or starts against the car's heading, is not driven (the car
        brakes); the reason is returned.
        """
        if self.missing or answer.scan_seq < self.resume_seq or self.backout is not None:
            return None
        if self.unheard_seq is not None and answer.scan_seq >= self.unheard_seq:
            self.unheard.clear()  # the restarted sensing stage has had them
            self.unheard_seq = None
        if not self.plan_ids or self.plan_ids[-1] != answer.plan_id:
            self.plan_ids.append(answer.plan_id)
        if answer.status == "no_path":
            self.no_plan(answer.reason)
            return None
        if answer.goal_index != self.goals.reached_count or len(answer.points) < 2:
            return None  # planned for a goal already passed: keep the current path until the replan
        start = self.scan_xy.get(answer.scan_seq, (self.state.x_m, self.state.y_m))
        points = np.asarray(answer.points, dtype=float)
        reason = self.guard.check(points, start=start)
        if reason is None and np.dot(points[1] - points[0], self._heading()) <= 0.0:
            reason = "the path starts against the car's heading"  # a way the car cannot turn onto
        if reason is not None:
            self.no_plan(f"plan {answer.plan_id}: {reason}")
            return reason
        self.path = points
        self.path_time_s = self.t_s
        self.progress_m = None
        self.no_path_since_s = None
        return None

    def reject(self, reason: str) -> None:
        """Brake rather than drive on the path: a stage is down, or newer obstacles cross the path."""
        self.path = None
        self.no_path_reason = reason

    def no_plan(self, reason: str) -> None:
        """The pipeline answered the newest scan without a path the car can drive: brake, and count
        the time towards backing out or giving up.

        The previous path was verified against older obstacles; a replan that fails verification
        usually means the newest ones invalidate it, so it is never driven on after such an answer.
        """
        if self.backout is not None:
            return  # it answers a scan from before the back-out
        self.reject(reason)
        if self.no_path_since_s is None:
            self.no_path_since_s = self.t_s

    @property
    def replans(self) -> int:
        return max(0, len(self.plan_ids) - 1)

    def advance(self) -> Outcome | None:
        """Integrate one step: back out, or follow a fresh path, else brake and hold the wheels; judge
        the outcome."""
        if self.outcome is not None:
            return self.outcome
        fresh = self.path is not None and self.t_s - self.path_time_s <= self.config.stale_after_s
        if self.backout is not None:
            command = self.controller.reverse_command(self.state, path=self.backout,
                                                      progress_m=self.backout_progress_m)
            self.backout_progress_m = command.progress_m
            target_speed, target_steering = command.target_speed_mps, command.target_steering_rad
        elif fresh:
            command = self.controller.command(self.state, path=self.path, progress_m=self.progress_m)
            self.progress_m = command.progress_m
            target_speed, target_steering = command.target_speed_mps, command.target_steering_rad
        else:
            target_speed, target_steering = 0.0, self.state.steering_rad
        self.state = step(self.state, limits=self.limits, target_speed_mps=target_speed,
                          target_steering_rad=target_steering, dt_s=self.config.dt_s)
        self.step_index += 1
        if self.backout is not None:
            if target_speed == 0.0 and self.state.speed_mps == 0.0:  # backed out, at rest
                del self.tracks[self.backout_keep:]
                self.backout = None
        elif math.dist(self.tracks[-1][:2], (self.state.x_m, self.state.y_m)) >= _TRACK_STEP_M:
            self.tracks.append(self._pose())
        if self.step_index % self.steps_per_scan == 0:
            self.scan_seq += 1
        self.trajectory.append(self._row())
        clearance = self.world.footprint_clearance(self.state)
        self.min_clearance_m = min(self.min_clearance_m, clearance)
        if self.goals.update(x_m=self.state.x_m, y_m=self.state.y_m):
            self.backouts = 0
        if clearance <= 0.0 or not self.world.footprint_in_bounds(self.state):
            self.outcome = "collision"
        elif self.goals.done:
            self.outcome = "reached"
        elif (self.no_path_since_s is not None and self.state.speed_mps == 0.0 and self.backout is None
              and not self._back_out()
              and self.t_s - self.no_path_since_s >= self.config.no_path_patience_s):
            self.outcome = "no_path"
        elif self.t_s >= self.time_limit_s:
            self.outcome = "timeout"
        return self.outcome

    def _back_out(self) -> bool:
        """Start backing out along the tracks, `backout_m` or as far as they go; whether it started (not
        without tracks to back along, at least `_TRACK_STEP_M`, nor past `max_backouts` for this goal)."""
        if self.backouts >= self.config.max_backouts or len(self.tracks) < 2:
            return False
        poses = np.array([self._pose(), *self.tracks[::-1]])
        along = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(poses[:, :2], axis=0), axis=1))])
        end = min(int(np.searchsorted(along, self.backout_m)), len(poses) - 1)
        half = 0.5 * self.limits.wheelbase_m
        theta = poses[: end + 1, 2]
        self.backout = poses[: end + 1, :2] - half * np.column_stack([np.cos(theta), np.sin(theta)])
        self.backout_progress_m = None
        self.backout_keep = len(self.tracks) - end + 1  # the pose backed out to stays, the rest goes
        self.backouts += 1
        self.no_path_since_s = None
        self.resume_seq = self.scan_seq + 1  # a late answer (realtime) is for where the car was
        logger.info("backing out %.2f m along its tracks (%d of %d for this goal): %s", along[end],
                    self.backouts, self.config.max_backouts, self.no_path_reason)
        return True

    def result(self, *, latencies_ms: list[float]) -> RunFile:
        lat = np.asarray(latencies_ms, dtype=float)
        stats = (LatencyStats(p50=float(np.percentile(lat, 50)), p99=float(np.percentile(lat, 99)),
                              max=float(lat.max())) if lat.size else LatencyStats(p50=0.0, p99=0.0, max=0.0))
        return RunFile(
            scenario=self.scenario.name,
            status=self.outcome or "timeout",
            goals_reached=self.goals.reached_count,
            trajectory=self.trajectory,
            replans=self.replans,
            latency_ms=stats,
            min_clearance=float(self.min_clearance_m),
        )


# --------------------------------------------------------------------------- the Zenoh shell


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
