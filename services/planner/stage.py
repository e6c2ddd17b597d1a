"""The planner stage core: Ellipsoids + RobotState → RawPath.

It keeps the current plan and replans only when it must: when there is none, when a goal has been
reached (the remaining goals changed), when the robot has drifted off it, or when the newest ellipsoids
invalidate it (the paper's eq. 2 intersection check, `intersected`) and a local repair of it, which
keeps its way round every obstacle, does not verify (`_repair`). Otherwise it re-publishes the current
plan trimmed to start where the robot is, under the same `plan_id`.

A replan starts at the robot's pose and heading and runs through the remaining goals. When the smoothed
curve of a new plan would fail verification, the plan is re-optimised with wider margins (the same
repairs as `cvxnav plan`), so the smoother downstream is handed a path it can accept. A car that
newly grown covers have boxed in, with no turn left inside the full margin, plans with the margin
within a turning radius of it given up down to the run's hard floor (`relieved_scales`), never past it;
boxed in even there, it gets `no_path` with that reason, and the sim backs the car out along its
tracks (`sim.core`): the planner plans forward motion only.

With a budget (`PlannerConfig.budget_s`: in a live run 15 % of the sensor period, or `--budget-ms`) every scan is
answered within it, and repairs and replans go on in the background. The foreground only checks what
the stage has: the current plan trimmed to the robot and re-verified against the scan's ellipses. A
repair or replan runs on a worker thread (`_Replan`: one at a time, from a snapshot of the scan's
inputs, `_Scan`), and the scan waits for it while the budget lasts: one done by then answers it, as
without a budget. Otherwise the scan is answered with the current plan, trimmed and re-verified, if it
still holds (it was made before a goal was reached and runs through the goals ahead), else with
`no_path` — never an unverified plan — marked `replanning` with the reason "replanning: ..." (no
verdict yet: the sim goes on as if the answer were still to come), or, when the last replan that ended
found no verified path, with its reason (a verdict, as without a budget). The status key says so too (a ``Notice``). A later
scan adopts the worker's plan only after the same trim and re-verification against its own ellipses as
any kept plan, and starts a new replan from its own inputs when that fails. New goals and `restore()`
call a running replan off (it stops before its next attempt, and what it made is dropped); `stop()`
waits for it too (`_STOP_WAIT_S` at most: a solve is not interrupted). A lockstep run has no budget: it
repairs and replans in the foreground, the sim waits for the answer, and its trajectories repeat.

Inputs are checked on arrival (``services.limits``): a state must put the robot inside the map with
a goal count the scenario has, and an ellipse set is bounded in size and reach; a rejected one never
replaces the state or ellipsoids the planner holds. New ``Goals`` (a robot's /goal_pose, from the ROS
2 bridge) replace the scenario's and drop the current plan: the next scan is planned to them.

The current plan and the plan counter are the core's `state()`: the shell checkpoints them on every
replan, and hands them to a restarted stage's `restore()`. Nothing unsafe rides on this: a reloaded plan is only
re-published after the same check against the newest ellipsoids as any kept plan (`_still_valid`),
else the stage replans. What it keeps is continuity: the car resumes the route it was committed to
(a fresh plan from a standstill may go round the other side of an obstacle) and plan ids stay unique,
so a consumer counting replans by id does not count the old ids twice.
"""

from __future__ import annotations

import json
import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from functools import partial

import numpy as np
import shapely
from pydantic import BaseModel

from schemas.messages import Ellipsoids, Goals, RawPath, RobotState
from schemas.scenario import Scenario
from services.contract import Notice, Outputs, StageInputError, StateError
from services.convert import answer_header, ellipse_to_msg, ellipses_from_msgs
from services.geometry import Ellipse, EllipseStack, FloatArray, arc_lengths, keep_out_scales, polyline_length
from services.limits import Reach
from services.planner.core import PathPlan, goals_ahead, intersected, margin_ladder, plan_within
from services.planner.refine import RefineSettings, SolverFailure, refine
from services.smoother.core import Smoothed, smooth

logger = logging.getLogger(__name__)

# Keep the start this far outside an ellipse when it has to be shrunk (level ≥ 1 + margin).
_START_LEVEL_MARGIN = 0.02
# A plan that passes deeper into an ellipse than this level has no side of it to keep: a warm repair
# would straddle it, and fail, before the replan.
_REPAIR_MIN_LEVEL = 0.5
# A repair that has not met the curvature bound in this many solves gives way to the next margin or
# to a replan: repairs that took more went on to fail verification.
_REPAIR_ITERATIONS_UNMET = 4
_REPLANNING = ("replanning: no verified path for this scan within the budget; the replan goes on in the "
               "background")
# With a deadline, the planner's default share of the sensor period: sensing, ellipsoids, smoother and the
# hops between them take the rest (docs/closed-loop.md: a quarter left live p99 past 50 ms on two scenes).
_PERIOD_SHARE = 0.15
# How long `stop()` waits for a replan it called off: within the shell's grace for the whole stop
# (services.shell.stage.STOP_GRACE_S), with room for closing the session.
_STOP_WAIT_S = 1.0
_BOXED_IN = ("boxed in: every forward turn the car can make from here crosses an obstacle, even with the margin "
             "near it given up to the hard floor")


@dataclass(frozen=True)
class PlannerConfig:
    goals: FloatArray
    goal_tolerance_m: float
    bounds_min: FloatArray
    bounds_max: FloatArray
    max_curvature: float  # the footprint centre's (Scenario.centre_max_curvature): the sim drives the centre
    inflation_m: float
    keep_out_m: float  # the hard floor (Scenario.keep_out_m): relieved plans keep this from the fits
    reach: Reach
    # A sensed obstacle's cover grows as more of its surface comes into view, so a plan that hugged
    # the old cover at the known-map margin (level 1.02) soon lies inside the new one, often where the
    # car can no longer steer away. Online, plans keep a wider margin; and they bend to 0.9 of the
    # curvature bound, so the tracker has steering in reserve to correct an error on the tightest arc.
    # A refinement whose curvature is still unmet after a dozen solves does not verify: in the eight
    # public closed loops every verified plan took 2-8, the unverified ones 9-25. The closed loops keep
    # the tight convergence tolerance they were measured with: which way round a newly seen obstacle
    # the car goes can turn on a hair (docs/closed-loop.md).
    refine: RefineSettings = field(
        default_factory=lambda: RefineSettings(level=1.1, curvature_factor=0.9, max_iterations=12, rel_tolerance=1e-5))
    # (level, curvature_factor): wider margins first, for a smoothed curve that clips an ellipse; last
    # the known-map margin, for a car boxed in near obstacles that the wide margin leaves no turn from.
    repairs: tuple[tuple[float, float], ...] = ((1.15, 0.8), (1.2, 0.65), (1.02, 0.97))
    max_cross_track_m: float = 0.5  # farther than this from the plan: replan from where the robot is
    repair_slack_m: float = 0.5  # a warm repair of the plan may lengthen it by this much (`_repair`)
    repair_rejoin_m: float = 3.0  # ... and re-optimises it this far past the last stretch it must move
    # Seconds an answer may take (None: no deadline): a repair or replan runs in the background, and the
    # scan waits for it this long at most. Lockstep runs keep none: the sim waits for the answer, and
    # their trajectories repeat.
    budget_s: float | None = None

    @classmethod
    def from_scenario(cls, scenario: Scenario) -> PlannerConfig:
        return cls(
            goals=scenario.goals_array,
            goal_tolerance_m=float(scenario.goal_tolerance),
            bounds_min=np.array(scenario.bounds.min, dtype=float),
            bounds_max=np.array(scenario.bounds.max, dtype=float),
            max_curvature=scenario.centre_max_curvature,
            inflation_m=scenario.inflation_m,
            keep_out_m=scenario.keep_out_m,
            reach=Reach.of(scenario),
        )


def trim_to_robot(points: FloatArray, *, position: FloatArray, heading_rad: float) -> tuple[FloatArray, float]:
    """The plan from the vertex that starts the segment nearest the robot, among the segments that run
    within 90° of its heading; and the robot's distance to it (inf when none does).

    Trimming at a vertex (not at the foot of the perpendicular) keeps the control polygon a suffix of
    the planned one: a foot just short of the next vertex would leave a tiny first control segment and
    a clamped spline with a large curvature at its start. A segment against the heading is never the
    robot's place on the plan: a plan that comes back past where the car is (it backed out along its
    tracks) would otherwise be trimmed to its way back, which the car cannot turn onto (a closed loop
    in a dense field steered into an obstacle doing so).
    """
    if len(points) < 2:
        return points, float(np.linalg.norm(points[0] - position)) if len(points) else np.inf
    a, b = points[:-1], points[1:]
    e = b - a
    ee = np.maximum(np.einsum("ij,ij->i", e, e), 1e-18)
    u = np.clip(np.einsum("ij,ij->i", position - a, e) / ee, 0.0, 1.0)
    dist = np.linalg.norm(a + u[:, None] * e - position, axis=1)
    dist[e @ np.array([np.cos(heading_rad), np.sin(heading_rad)]) <= 0.0] = np.inf
    k = int(np.argmin(dist))
    return points[k:], float(dist[k])


def free_start_scales(stack: EllipseStack, *, start: FloatArray, inflation_m: float) -> FloatArray:
    """Per ellipse, the scale about its centre that frees the robot from a grown ellipse it is inside (1: none).

    A fit may stick out of a newly seen obstacle by up to its tolerance, and the robot may already be
    closer than the full inflation to it; planning from inside an ellipse is impossible. Scaling the
    ellipse by s about its centre divides every level by s, so s = level(start) / 1.02 puts the start at
    level 1.02. An ellipse scaled by no less than `keep_out_scales(..., keep_m=0)` still contains the
    un-grown fit: the robot keeps a reduced margin but never plans into the obstacle itself. An ellipse
    that would need more shrinking is left alone (no path).
    """
    if len(stack) == 0:
        return np.ones(0)
    level = stack.levels(start)[0]
    floor = keep_out_scales(stack.semi_axes, inflation_m=inflation_m, keep_m=0.0)
    scale = level / (1.0 + _START_LEVEL_MARGIN)
    return np.where((level < 1.0 + _START_LEVEL_MARGIN) & (scale >= floor) & (scale > 0.0), scale, 1.0)


def inset_bounds(bounds_min: FloatArray, bounds_max: FloatArray, *, keep_m: float, start: FloatArray,
                 goals: FloatArray) -> tuple[FloatArray, FloatArray]:
    """The map's bounds moved in by the run's hard floor `keep_m`: the sim's path guard keeps every path's
    centre line that far inside them, as from a wall (`services.drive.guard`), so a plan that ran nearer
    an edge would be refused scan after scan.

    Like the guard, less near a robot already closer to an edge than that: the bounds then keep the
    start `_START_LEVEL_MARGIN` of its own depth inside them, as `free_start_scales` keeps it outside an
    ellipse (the guard allows the start's depth over 1 + `guard.START_SLACK`, more). Never past a goal
    (one nearer an edge than the floor cannot be driven to in any case: the guard says why).
    """
    def depth(points: FloatArray) -> float:
        points = np.atleast_2d(points)
        return float(np.minimum(points - bounds_min, bounds_max - points).min())

    inset = max(0.0, min(keep_m, depth(start) / (1.0 + _START_LEVEL_MARGIN), depth(goals) if len(goals) else keep_m))
    return bounds_min + inset, bounds_max - inset


def relieved_scales(
    stack: EllipseStack, *, start: FloatArray, within_m: float, inflation_m: float, keep_out_m: float
) -> FloatArray:
    """Per ellipse, the scale that trades its margin down to the run's hard floor, for those within
    `within_m` of the start (1 for the rest).

    A car that new covers have boxed in — an obstacle's cover grew as more of it came into view, and
    the car, close to it already, cannot turn inside the full margin — may still turn out safely inside
    part of it. Near the start only, an ellipse shrinks to the least scale that still keeps `keep_out_m`
    from its fit (`keep_out_scales`): the footprint stays half the safety distance clear.
    """
    if len(stack) == 0:
        return np.ones(0)
    near = np.linalg.norm(stack.centers - start, axis=1) - stack.reach < within_m
    keep = keep_out_scales(stack.semi_axes, inflation_m=inflation_m, keep_m=keep_out_m)
    return np.where(near, keep, 1.0)


def boxed_in(stack: EllipseStack, *, start: FloatArray, heading_rad: float, max_curvature: float) -> bool:
    """Whether every arc the car can start on — constant curvature from −κ to κ, over a quarter turn at
    full lock — enters an ellipse: then no curve from here clears them (a fan of nine arcs; a curve that
    bends one way and then the other stays between the extreme ones over so short a stretch).
    """
    if len(stack) == 0:
        return False
    s = np.arange(1, 32) * (0.5 * np.pi / max_curvature / 31)  # arc length along each arc
    half = 0.5 * np.linspace(-max_curvature, max_curvature, 9)[:, None] * s  # half the turn so far
    # The chord of an arc of length s and curvature k: 2 sin(ks/2)/k = s sinc, along heading + ks/2.
    chord = s * np.sinc(half / np.pi)
    arcs = start + chord[..., None] * np.stack([np.cos(heading_rad + half), np.sin(heading_rad + half)], axis=-1)
    levels = stack.levels(arcs.reshape(-1, 2)).min(axis=1).reshape(arcs.shape[:2])
    return bool(np.all(levels.min(axis=1) < 1.0))


def crosses_closed_gap(
    path: FloatArray, ellipses: list[Ellipse], *, entered: FloatArray, groups: FloatArray, clusters: FloatArray
) -> bool:
    """Whether `path` passes between an ellipse in `entered` and another of its group from another
    cluster: through a gap the ellipsoid stage found narrower than the robot's passage (eq. 3), which
    no change of margin opens. Tested cheaply, as the path crossing the segment between their centres.
    """
    pairs = [(i, j) for i in entered for j in np.flatnonzero((groups == groups[i]) & (clusters != clusters[i]))]
    if not pairs:
        return False
    centers = np.array([e.center for e in ellipses])
    return bool(np.any(shapely.intersects(shapely.LineString(path), shapely.linestrings(centers[np.array(pairs)]))))


def scaled(ellipses: list[Ellipse], scales: FloatArray) -> list[Ellipse]:
    """Each ellipse scaled about its centre by its factor (level ÷ scale)."""
    out = []
    for ellipse, scale in zip(ellipses, scales):
        if scale >= 1.0:
            out.append(ellipse)
            continue
        A = ellipse.A / scale
        out.append(Ellipse(A=A, b=-A @ ellipse.center))
    return out


@dataclass(frozen=True)
class _Scan:
    """One scan's inputs, made ready to plan from: a background replan's snapshot."""

    message: Ellipsoids
    goal_base: int  # goals reached
    position: FloatArray
    heading_rad: float
    goals: FloatArray  # those ahead
    ellipses: list[Ellipse]  # the sensed ones, any the robot is inside shrunk off it (`free_start_scales`)
    relieved: list[Ellipse] | None  # ... and the margin near the robot given up to the hard floor, if it was
    bounds: tuple[FloatArray, FloatArray]  # where plans may go: the map's less the guard's floor (`inset_bounds`)


@dataclass(frozen=True)
class _Made:
    """A plan a repair or replan made (None: no path), and the ellipses it was checked against; `reason`:
    why there is none, or why the plan made does not verify (only a lockstep run publishes it then)."""

    points: FloatArray | None
    goal_base: int
    relieved: bool
    margin: int
    used: list[Ellipse]
    reason: str = ""


class _Replan:
    """A repair or replan (`work(late=)`, `late` saying whether it was called off) on a daemon thread of its own."""

    def __init__(self, scan: _Scan, work: Callable[..., _Made]) -> None:
        self.scan = scan
        self.called_off = threading.Event()
        self.done = threading.Event()
        self.made: _Made | None = None
        self.error: Exception | None = None  # raised in the foreground when the replan is collected
        self._thread = threading.Thread(target=self._run, args=(work,), name="planner-replan", daemon=True)
        self._thread.start()

    def _run(self, work: Callable[..., _Made]) -> None:
        try:
            self.made = work(late=self.called_off.is_set)
        except Exception as error:
            self.error = error
        finally:
            self.done.set()

    def join(self, timeout_s: float) -> bool:
        self._thread.join(timeout_s)
        return not self._thread.is_alive()


class PlannerStage:
    def __init__(self, *, config: PlannerConfig, clock: Callable[[], float] = time.perf_counter) -> None:
        self.config = config
        self.robot_state: RobotState | None = None  # the newest robot state
        self.pending: Ellipsoids | None = None  # ellipsoids waiting for the state of their scan
        self.plan: FloatArray | None = None  # the current plan (points), None when there is none
        self.plan_goal_base = 0  # goals reached when the current plan was made
        self.plan_relieved = False  # the current plan was made with the margin near the robot relieved
        self.plan_margin = 0  # the `_repair_margins` entry the current plan was last repaired at
        self.plan_id = 0
        self._seq = 0
        self._state: tuple[tuple[int, int], bytes] | None = None  # `state()` as of (plan_id, goal base)
        self._clock = clock
        self._replan_job: _Replan | None = None  # the background replan (with a budget), until collected
        self._verdict = ""  # why the last background replan collected made no verified plan ("" when it did)

    @property
    def replanning(self) -> bool:
        """Whether a background replan is running."""
        return self._replan_job is not None and not self._replan_job.done.is_set()

    def stop(self, *, now_s: float) -> Outputs:
        """Call a running replan off and wait for it, `_STOP_WAIT_S` at most (a solve is not interrupted)."""
        job, self._replan_job = self._replan_job, None
        if job is not None:
            job.called_off.set()
            if not job.join(_STOP_WAIT_S):
                logger.warning("a replan called off was still running %.1f s after the stop", _STOP_WAIT_S)
        return []

    def _call_off(self) -> None:
        """Drop what a running replan makes (it stops before its next attempt); one at a time still holds."""
        if self._replan_job is not None:
            self._replan_job.called_off.set()
        self._verdict = ""

    @classmethod
    def from_scenario(cls, scenario: Scenario, *, deadline: bool = False,
                      budget_ms: float | None = None) -> PlannerStage:
        """The planner of `scenario`; with `deadline`, each answer's budget is `budget_ms`, by default its
        share of the sensor's period (a live run: `_PERIOD_SHARE`)."""
        config = PlannerConfig.from_scenario(scenario)
        if deadline:
            budget_s = _PERIOD_SHARE / float(scenario.sensor.rate_hz) if budget_ms is None else budget_ms * 1e-3
            config = replace(config, budget_s=budget_s)
        return cls(config=config)

    def state(self) -> bytes:
        """The current plan, the goals reached when it was made and the plan counter, as JSON.

        Every new plan takes a new id, so the JSON is made again only when the id (or the goal base) moved.
        """
        made_for = (self.plan_id, self.plan_goal_base)
        if self._state is None or self._state[0] != made_for:
            plan = None if self.plan is None else self.plan.tolist()
            doc = {"plan": plan, "goal_base": self.plan_goal_base, "plan_id": self.plan_id}
            self._state = (made_for, json.dumps(doc).encode())
        return self._state[1]

    def restore(self, data: bytes) -> None:
        try:
            doc = json.loads(data)
            plan = None if doc["plan"] is None else np.asarray(doc["plan"], dtype=float).reshape(-1, 2)
            goal_base, plan_id = int(doc["goal_base"]), int(doc["plan_id"])
        except (ValueError, TypeError, KeyError) as error:
            raise StateError(f"not a plan checkpoint: {error!r}") from None
        if plan is not None and not np.all(np.isfinite(plan)):
            raise StateError("the plan has non-finite points")
        self._call_off()
        self.plan, self.plan_goal_base, self.plan_id = plan, goal_base, plan_id

    def process(self, *, topic: str, message: BaseModel, now_s: float) -> Outputs:
        """Plan for a scan once both its ellipsoids and the robot state of that scan are here.

        The state comes straight from the sim while the ellipsoids come through two stages, so either
        may arrive first; pairing them by scan (RobotState.header.seq == Ellipsoids.scan_seq) makes
        the answer independent of arrival order, and a lockstep run deterministic.
        """
        if isinstance(message, Goals):
            goals = np.asarray(message.goals, dtype=float).reshape(-1, 2)
            self.config.reach.check_goals(goals, what="goals")
            self.config = replace(self.config, goals=goals)
            self._call_off()
            self.plan, self.plan_goal_base = None, 0
            return []
        if isinstance(message, RobotState):
            self._check_state(message)
            self.robot_state = message
            pending, self.pending = self.pending, None
            if pending is not None and pending.scan_seq == message.header.seq:
                return self._plan(pending, message)
            return []
        if not isinstance(message, Ellipsoids):
            raise StageInputError(f"planner does not handle {topic!r}")
        self.config.reach.check_ellipses(message.ellipsoids, what="ellipsoids")
        if self.robot_state is None or self.robot_state.header.seq < message.scan_seq:
            self.pending = message  # the state of this scan is still on its way
            return []
        return self._plan(message, self.robot_state)

    def _check_state(self, state: RobotState) -> None:
        goals = len(self.config.goals)
        if state.goals_reached > goals or state.goal_index >= goals:
            raise StageInputError(f"state: goal_index {state.goal_index}, goals_reached {state.goals_reached}, "
                                  f"but the scenario has {goals} goals")
        self.config.reach.check_pose(state.pose, what="state")

    def _plan(self, message: Ellipsoids, state: RobotState) -> Outputs:
        started_s = self._clock()
        budget_s = self.config.budget_s
        if budget_s is None:
            return self._answer(self._scan(message, state))
        outputs = self._answer_by(self._scan(message, state), until_s=started_s + budget_s)
        if self._clock() - started_s > budget_s:
            outputs.append(("raw_path", Notice(f"deadline: answered in {(self._clock() - started_s) * 1e3:.0f} ms, "
                                               f"over the {budget_s * 1e3:.0f} ms budget")))
        return outputs

    def _scan(self, message: Ellipsoids, state: RobotState) -> _Scan:
        goal_base = state.goals_reached
        if goal_base >= len(self.config.goals):
            raise StageInputError("every goal is already reached")
        config = self.config
        position = np.array([state.pose.x_m, state.pose.y_m])
        goals = goals_ahead(position, config.goals[goal_base:], tolerance_m=config.goal_tolerance_m)
        if not len(goals):  # the sim counts them reached before it sends the state
            raise StageInputError(f"every goal from {goal_base} on is within tolerance of the robot: reached")
        sensed = ellipses_from_msgs(message.ellipsoids)
        stack = EllipseStack.of(sensed)
        free = free_start_scales(stack, start=position, inflation_m=config.inflation_m)
        relief = np.minimum(free, relieved_scales(stack, start=position, within_m=1.0 / config.max_curvature,
                                                  inflation_m=config.inflation_m, keep_out_m=config.keep_out_m))
        return _Scan(message=message, goal_base=goal_base, position=position, heading_rad=state.pose.theta_rad,
                     goals=goals, ellipses=scaled(sensed, free),
                     relieved=scaled(sensed, relief) if np.any(relief < free) else None,
                     bounds=inset_bounds(config.bounds_min, config.bounds_max, keep_m=config.keep_out_m,
                                         start=position, goals=goals))

    def _answer(self, scan: _Scan) -> Outputs:
        """The scan's answer, planned in the foreground: the current plan if it holds, else its repair or a replan."""
        kept = self._kept(scan)
        if kept is not None:
            return self._publish(scan, *kept)
        made = self._make(scan, self._held(scan.goal_base), late=lambda: False)
        self._adopt(made, scan)
        return self._publish(scan, made.points, made.used, reason=made.reason)

    def _answer_by(self, scan: _Scan, *, until_s: float) -> Outputs:
        """The scan's answer by clock time `until_s`: the current plan if it holds (a replan that finished
        adopted first); else a repair or replan in the background, waited for until then; else the
        current plan if it holds for the goals before one was reached, else no_path while replanning."""
        collected = self._collect()
        kept = self._kept(scan, earlier_goals=True)
        while kept is None or self.plan_goal_base != scan.goal_base:
            if self._replan_job is None:
                if collected is not None and collected.scan is scan:  # made from this scan, and it does not hold
                    return self._publish(scan, None, collected.made.used,
                                         reason=collected.made.reason or "no replan verified")
                self._replan_job = _Replan(scan, partial(self._make, scan, self._held(scan.goal_base)))
            if not self._replan_job.done.wait(max(0.0, until_s - self._clock())):
                if kept is not None:
                    return self._publish(scan, *kept)
                if self._verdict:  # the last replan's verdict stands while the next one runs
                    return [*self._publish(scan, None, scan.ellipses, reason=self._verdict),
                            ("raw_path", Notice(f"{self._verdict}; {_REPLANNING}"))]
                return [*self._publish(scan, None, scan.ellipses, reason=_REPLANNING, replanning=True),
                        ("raw_path", Notice(_REPLANNING))]
            collected = self._collect()
            kept = self._kept(scan, earlier_goals=True)
        return self._publish(scan, *kept)

    def _collect(self) -> _Replan | None:
        """The background replan, if it finished (not called off), its plan adopted; its error raised."""
        job = self._replan_job
        if job is None or not job.done.is_set():
            return None
        self._replan_job = None
        if job.error is not None:
            raise job.error
        if job.called_off.is_set():
            return None
        self._adopt(job.made, job.scan)
        self._verdict = job.made.reason
        return job

    def _held(self, goal_base: int) -> tuple[FloatArray, int, bool] | None:
        """The current plan, the margin it was repaired at and whether it is relieved, if made for `goal_base`."""
        if self.plan is None or self.plan_goal_base != goal_base:
            return None
        return self.plan, self.plan_margin, self.plan_relieved

    def _kept(self, scan: _Scan, *, earlier_goals: bool = False) -> tuple[FloatArray, list[Ellipse]] | None:
        """The current plan trimmed to the robot and verified against the scan's ellipses (`_still_valid`),
        and those ellipses; None when it does not hold, or was made for other goals — with `earlier_goals`,
        for fewer reached than the scan's (it runs through the goals ahead too)."""
        if self.plan is None or not (self.plan_goal_base == scan.goal_base
                                     or earlier_goals and self.plan_goal_base < scan.goal_base):
            return None
        used = scan.relieved if self.plan_relieved and scan.relieved is not None else scan.ellipses
        points = self._still_valid(self.plan, position=scan.position, heading_rad=scan.heading_rad, goals=scan.goals,
                                   ellipses=used, bounds=scan.bounds)
        return None if points is None else (points, used)

    def _make(self, scan: _Scan, held: tuple[FloatArray, int, bool] | None, *, late: Callable[[], bool]) -> _Made:
        """A plan from `scan` when the current one (`held`, if made for its goals) does not hold: its local
        repair (`_repair`), else a replan (`_replan`), which `late()` calls off. Reads `scan`, `held` and
        the config's settings only, so it runs as well on a worker thread."""
        if held is not None:
            plan, margin, relieved = held
            used = scan.relieved if relieved and scan.relieved is not None else scan.ellipses
            repaired = self._repair(plan, margin=margin, position=scan.position, heading_rad=scan.heading_rad,
                                    goals=scan.goals, ellipses=used, bounds=scan.bounds,
                                    groups=np.array([e.group for e in scan.message.ellipsoids]),
                                    clusters=np.array([e.cluster_id for e in scan.message.ellipsoids]))
            if repaired is not None:
                return _Made(repaired[0], scan.goal_base, relieved, repaired[1], used)
        plan, used, relieved = self._replan(position=scan.position, heading_rad=scan.heading_rad, goals=scan.goals,
                                            ellipses=scan.ellipses, relieved=scan.relieved, bounds=scan.bounds,
                                            late=late)
        return _Made(plan.points if plan.status == "ok" else None, scan.goal_base, relieved, 0, used,
                     reason=plan.reason)

    def _adopt(self, made: _Made, scan: _Scan) -> None:
        """`made` becomes the current plan, under a new id (no path: none)."""
        self.plan_id += 1
        if made.points is None:
            logger.info("no path from (%.2f, %.2f): %s", *scan.position, made.reason)
            self.plan = None
        else:
            self.plan, self.plan_goal_base = made.points, made.goal_base
            self.plan_relieved, self.plan_margin = made.relieved, made.margin

    def _publish(self, scan: _Scan, points: FloatArray | None, used: list[Ellipse], *, reason: str = "",
                 replanning: bool = False) -> Outputs:
        """The scan's RawPath: `points` (None: no_path, with `reason`, and whether it is `replanning`), and
        the ellipses they were checked against."""
        message = scan.message
        wire = [
            ellipse_to_msg(ellipse, group=msg.group, cluster_id=msg.cluster_id)
            for ellipse, msg in zip(used, message.ellipsoids)
        ]
        out = RawPath(
            header=answer_header(scan_header=message.header, seq=self._seq),
            scan_seq=message.scan_seq,
            status="ok" if points is not None else "no_path",
            goal_index=scan.goal_base,
            points=[] if points is None else [(float(x), float(y)) for x, y in points],
            ellipsoids=wire,
            plan_id=self.plan_id,
            reason="" if points is not None else reason,
            replanning=replanning,
        )
        self._seq += 1
        return [("raw_path", out)]

    def _smooth(self, points: FloatArray, *, goals: FloatArray, ellipses: list[Ellipse],
                bounds: tuple[FloatArray, FloatArray]) -> Smoothed:
        """The curve the smoother downstream will make of `points`, verified as it will verify it (within
        `bounds`, which lie within the map's bounds the smoother keeps to)."""
        config = self.config
        return smooth(points, ellipses=ellipses, max_curvature=config.max_curvature, heading_rad=None, goals=goals,
                      goal_tolerance_m=config.goal_tolerance_m, bounds_min=bounds[0], bounds_max=bounds[1])

    def _repair_margins(self) -> tuple[tuple[float, float], ...]:
        """(level, curvature factor) a repair tries in turn: the base margin, then the known-map one."""
        config = self.config
        return (config.refine.level, config.refine.curvature_factor), config.repairs[-1]

    def _repair(
        self, plan: FloatArray, *, margin: int, position: FloatArray, heading_rad: float, goals: FloatArray,
        ellipses: list[Ellipse], bounds: tuple[FloatArray, FloatArray], groups: FloatArray, clusters: FloatArray,
    ) -> tuple[FloatArray, int] | None:
        """`plan`, the current plan (last repaired at `_repair_margins()[margin]`), no longer valid,
        re-optimised from the robot's pose as the first iterate of the refinement, and the margin it was
        made at; None unless that is a local change whose smoothed curve verifies.

        New obstacles (or a grown cover) usually only nudge the plan, and a warm start from it needs a
        couple of convex solves where a fresh plan searches routes and tries every margin of the repair
        ladder (seconds, when the car is in a tight spot). The warm start keeps the plan's way round
        every obstacle, which the route search chose globally; that choice is only kept while the
        repair lengthens the rest of the path by at most `repair_slack_m` — a longer detour re-opens
        it, and the stage replans from scratch. So does a plan that runs deep into an ellipse (it has
        no side of it to keep), or between two ellipses that are grouped (`crosses_closed_gap`), and a
        repair that still enters one (the way round is blocked).

        Only the plan up to `repair_rejoin_m` past the last stretch the new ellipses invalidate is
        re-optimised; the rest is kept point for point (a solve costs about 0.08 ms per point). The
        base margin is tried first, then the known-map one; a plan already repaired at the known-map
        margin is repaired at that margin alone (a car hugging a growing cover at it would otherwise
        spend every scan's budget on base-margin attempts whose turns it can no longer make: 8–9
        solves each on field-25, about 90 ms).
        """
        config = self.config
        trimmed, off_m = trim_to_robot(plan, position=position, heading_rad=heading_rad)
        if off_m > config.max_cross_track_m or len(trimmed) < 3:
            return None
        ahead = np.vstack([position, trimmed[1:]])
        # One eq. (2) test of the plan's segments against the ellipses near them serves every check below.
        rows, cols, levels = EllipseStack.of(ellipses).segment_pairs(ahead[:-1], ahead[1:])
        entering = levels < 1.0
        if np.min(levels, initial=np.inf) < _REPAIR_MIN_LEVEL or crosses_closed_gap(
                ahead, ellipses, entered=np.unique(cols[entering]), groups=groups, clusters=clusters):
            return None
        ends, cut = [], 0
        for goal in goals:  # the plan's vertex at each goal, so that refine pins every goal it passes through
            hits = np.flatnonzero(np.linalg.norm(ahead[cut:] - goal, axis=1) < 1e-6)
            if len(hits) == 0 or hits[0] == 0:
                return None
            cut += int(hits[0])
            ends.append(cut)
        # Only the stretch up to the last segment the new ellipses invalidate, and a rejoin distance
        # past it, is re-optimised; the rest of the plan is kept. The kept rest's first step is pinned
        # too (a second leg), so the curvature bound holds across the join.
        along = arc_lengths(ahead)
        bad = rows[entering]  # segments the new ellipses invalidate
        join = int(np.searchsorted(along, along[bad.max() + 1] + config.repair_rejoin_m)) if len(bad) else len(ahead)
        if join + 1 < ends[0]:
            legs, rest = [ahead[: join + 1], ahead[join : join + 2]], ahead[join + 2 :]
        else:
            legs = [ahead[start : end + 1] for start, end in zip([0, *ends[:-1]], ends)]
            rest = ahead[:0]
        longest_m = polyline_length(ahead) + config.repair_slack_m
        margins = self._repair_margins()
        for margin in range(margin, len(margins)):
            level, factor = margins[margin]
            try:
                refined = refine(legs=legs, ellipses=ellipses, bounds_min=bounds[0],
                                 bounds_max=bounds[1], max_curvature=config.max_curvature,
                                 heading_rad=heading_rad,
                                 settings=replace(config.refine, level=level, curvature_factor=factor,
                                                  min_iterations_unmet=_REPAIR_ITERATIONS_UNMET))
            except SolverFailure:
                continue
            points = np.vstack([refined.points, rest])
            if len(intersected(points, ellipses)):
                return None  # the way round is blocked by the obstacles themselves: no margin opens it
            if polyline_length(points) > longest_m:
                continue
            if self._smooth(points, goals=goals, ellipses=ellipses, bounds=bounds).verification.ok:
                return points, margin
        return None

    def _still_valid(self, plan: FloatArray, *, position: FloatArray, heading_rad: float, goals: FloatArray,
                     ellipses: list[Ellipse], bounds: tuple[FloatArray, FloatArray]) -> FloatArray | None:
        """`plan` (the current one) trimmed to the robot, if it is still clear and still smooths; else None.

        A suffix's clamped spline starts with a different curvature from the full plan's curve at the
        same place, so the cut moves back (2, 4, 8, … vertices, down to the whole plan, which verified
        when it was made) until the smoothed curve verifies. Every candidate is checked against the
        newest ellipses, so a plan that a new obstacle invalidates is never re-published.
        """
        config = self.config
        trimmed, off_m = trim_to_robot(plan, position=position, heading_rad=heading_rad)
        if off_m > config.max_cross_track_m or len(intersected(np.vstack([position, trimmed]), ellipses)):
            return None
        cut = len(plan) - len(trimmed)
        back = 0
        while True:
            candidate = plan[max(0, cut - back):]
            if len(candidate) >= 4:
                if self._smooth(candidate, goals=goals, ellipses=ellipses, bounds=bounds).verification.ok:
                    return candidate
            if cut - back <= 0:
                return None
            back = 2 if back == 0 else 2 * back

    def _replan(
        self, *, position: FloatArray, heading_rad: float, goals: FloatArray, ellipses: list[Ellipse],
        relieved: list[Ellipse] | None, bounds: tuple[FloatArray, FloatArray], late: Callable[[], bool],
    ) -> tuple[PathPlan, list[Ellipse], bool]:
        """A new plan from the robot; the ellipses it was made against; whether they are the `relieved` ones.

        The full margin first, re-optimised with the repairs' wider margins while the smoothed curve
        fails. A car that grown covers have boxed in (`boxed_in`) gets no curve verified at any of
        those margins, and trying them all costs seconds: it plans against the `relieved` ellipses
        (the margin near it given up down to the hard floor) first. Whichever comes first, the other
        is tried when it does not verify; with neither verified, the full-margin plan is returned —
        or `no_path`, when the car is boxed in even with the margin near it at the hard floor. Once
        `late()` (the replan was called off), it stops before its next attempt, with `no_path`.
        """
        config = self.config
        options = [(ellipses, config.repairs, False)]
        if relieved is not None:
            relief_first = boxed_in(EllipseStack.of(ellipses), start=position, heading_rad=heading_rad,
                                    max_curvature=config.max_curvature)
            option = (relieved, config.repairs[-1:], True)
            options = [option, *options] if relief_first else [*options, option]
        fallback: tuple[PathPlan, list[Ellipse], bool] | None = None
        for used, repairs, relief in options:
            attempted = plan_within(
                start=position, heading_rad=heading_rad, goals=goals, ellipses=used,
                bounds_min=bounds[0], bounds_max=bounds[1], max_curvature=config.max_curvature,
                ladder=margin_ladder(config.refine, repairs), late=late,
                smooth_fn=lambda points, used=used: self._smooth(points, goals=goals, ellipses=used, bounds=bounds),
            )
            if attempted.smoothed is not None and attempted.smoothed.verification.ok:
                if relief:
                    logger.info("boxed in at (%.2f, %.2f): planned with the margin near the robot relieved "
                                "to the hard floor", *position)
                return attempted.plan, used, relief
            if late():
                return PathPlan("no_path", np.zeros((0, 2)), reason="replan called off"), used, relief
            if not relief:
                plan = attempted.plan
                fallback = (replace(plan, reason="no replan verified") if plan.status == "ok" else plan, used, relief)
        floor = relieved if relieved is not None else ellipses
        if boxed_in(EllipseStack.of(floor), start=position, heading_rad=heading_rad,
                    max_curvature=config.max_curvature):
            # Nothing verified, and every turn crosses even the hard floor: the car, which only drives
            # forwards, cannot leave. Say so, rather than publish a curve the smoother must reject.
            return PathPlan("no_path", np.zeros((0, 2)), reason=_BOXED_IN), floor, relieved is not None
        assert fallback is not None  # the full-margin option always runs
        return fallback
