"""The sim's core: the kinematic car, its range sensor and its controller, and the record of the run.

`SimCore` is pure (no I/O, clock and seed are arguments): it senses, accepts the pipeline's answers
and integrates the car; `sim.stage.SimStage` drives it from what the shell hears, in lockstep or in
real time.

The car never drives on a stale plan or without one: it brakes within its limits and waits.
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
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field

import numpy as np

from schemas.files import LatencyStats, RunFile
from schemas.messages import Ellipsoids, Header, Pose2D, RobotState, Scan, SmoothPath
from schemas.scenario import Scenario
from services.drive.controller import GoalTracker, PurePursuit
from services.drive.guard import PathGuard, ahead
from services.drive.vehicle import VehicleLimits, VehicleState, step
from services.geometry import arc_lengths
from sim.sensor import RangeSensor
from sim.world import World

logger = logging.getLogger(__name__)

Outcome = str  # "reached" | "no_path" | "timeout" | "collision"; a run stopped before one is "interrupted"
_UNHEARD_CELL_M = 0.01  # hits kept for a restarted sensing stage: one per cell of this size
_UNHEARD_MAX = 10_000  # and at most this many (the newest)
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
        self.goals.update(x_m=self.state.x_m, y_m=self.state.y_m)  # goals at the start are reached at once
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
        self.guard = PathGuard.from_scenario(scenario)
        self.missing: set[str] = set()  # pipeline stages whose liveliness token is gone
        self.resume_seq = 0  # answers to earlier scans are not taken: they predate a stage's loss or a back-out
        self.scan_xy: dict[int, tuple[float, float]] = {}  # recent scans' positions, by seq
        self.unheard: dict[tuple[int, int], tuple[float, float]] = {}  # hits the sensing stage missed
        self.carried: dict[int, list[tuple[int, int]]] = {}  # scan seq -> the unheard hits (cells) it carried
        self.trajectory: list[tuple[float, float, float, float]] = [self._row()]
        self.min_clearance_m = self.world.footprint_clearance(self.state)
        self.outcome: Outcome | None = "reached" if self.goals.done else None

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

        The guard remembers the hits, and the car brakes if the path it drives now passes too close to
        one. While the sensing stage is down its hits are kept (one per 1 cm cell); once it is back each
        scan carries those within the sensor's range of its pose, as many as leave it a scan the sensing
        stage accepts (one hit per ray at most, `services.limits`), until an answer to a scan that carried
        them arrives. Hits the car has driven out of range of wait until it is back in range.
        """
        s = self.state
        hits = self.sensor.scan(x_m=s.x_m, y_m=s.y_m, theta_rad=s.theta_rad,
                                obstacles=self.world.ray_targets, rng=self.rng)
        self.guard.sense(hits)
        self._recheck("its own scan")
        points = [(float(x), float(y)) for x, y in hits]
        if "sensing" in self.missing:
            self._keep_unheard(points)
        elif self.unheard:
            points = points + self._carry(points)
        self.scan_xy[self.scan_seq] = (s.x_m, s.y_m)
        while len(self.scan_xy) > _SCAN_POSES_KEPT:
            del self.scan_xy[next(iter(self.scan_xy))]
        scan = Scan(header=Header(stamp_s=self.t_s, seq=self.scan_seq),
                    pose=Pose2D(x_m=s.x_m, y_m=s.y_m, theta_rad=s.theta_rad), points=points)
        return self.robot_state(), scan

    def _carry(self, hits: list[tuple[float, float]]) -> list[tuple[float, float]]:
        """The unheard hits this scan carries (recorded under its seq, see `accept`)."""
        room = self.sensor.rays - len(hits)
        x_m, y_m = self.state.x_m, self.state.y_m
        cells = [cell for cell, (x, y) in self.unheard.items()
                 if math.hypot(x - x_m, y - y_m) <= self.sensor.range_m][:max(0, room)]
        self.carried[self.scan_seq] = cells
        while len(self.carried) > _SCAN_POSES_KEPT:
            del self.carried[next(iter(self.carried))]
        return [self.unheard[cell] for cell in cells]

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
        return self._recheck("newer obstacles")

    def _recheck(self, what: str) -> str | None:
        """Check the rest of the path being driven against what the guard now knows; brake if it fails."""
        if self.path is None:
            return None
        position = (self.state.x_m, self.state.y_m)
        reason = self.guard.check(ahead(self.path, position=position), start=position)
        if reason is not None:
            self.reject(f"{what}: {reason}")
        return reason

    def accept(self, answer: SmoothPath) -> str | None:
        """Take the pipeline's newest answer: a path to follow, or its verdict that there is none.

        An answer is ignored while a stage is down or when it answers a scan sent before the loss. A
        path the guard refuses (off the map, too close to a hit of the car's own scans, into a known
        ellipse), or that starts against the car's heading, is not driven (the car brakes); the reason
        is returned. An answer to a scan older than `stale_after_s` (realtime, after a link was cut) is
        no verdict on where the car is now: a path it rejects, or its no_path, only brakes the car, and
        never starts a back-out. Nor is the planner's no_path while it replans in the background
        (`replanning`): the car goes on as if the answer were still to come, on its path while that is
        fresh and clear of what the guard knows, as it does while a late answer is on its way.
        """
        verdict = self.no_plan if self.t_s - answer.header.stamp_s <= self.config.stale_after_s else self.reject
        for cell in self.carried.pop(answer.scan_seq, ()):  # the restarted sensing stage has had them
            self.unheard.pop(cell, None)
        if self.missing or answer.scan_seq < self.resume_seq or self.backout is not None:
            return None
        if not self.plan_ids or self.plan_ids[-1] != answer.plan_id:
            self.plan_ids.append(answer.plan_id)
        if answer.status == "no_path" and answer.replanning:
            return None  # no verdict yet: as if the answer were still to come
        if answer.status == "no_path":
            verdict(answer.reason)
            return None
        if answer.goal_index != self.goals.reached_count or len(answer.points) < 2:
            return None  # planned for a goal already passed: keep the current path until the replan
        start = self.scan_xy.get(answer.scan_seq, (self.state.x_m, self.state.y_m))
        points = np.asarray(answer.points, dtype=float)
        reason = self.guard.check(points, start=start)
        if reason is None and np.dot(points[1] - points[0], self._heading()) <= 0.0:
            reason = "the path starts against the car's heading"  # a way the car cannot turn onto
        if reason is not None:
            verdict(f"plan {answer.plan_id}: {reason}")
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
        along = arc_lengths(poses[:, :2])
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
            status=self.outcome or "interrupted",  # stopped before the run had an outcome
            goals_reached=self.goals.reached_count,
            trajectory=self.trajectory,
            replans=self.replans,
            latency_ms=stats,
            min_clearance=float(self.min_clearance_m) if math.isfinite(self.min_clearance_m) else None,  # no obstacle
        )
