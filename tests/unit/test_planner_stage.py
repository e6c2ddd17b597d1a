"""The planner stage pairs each scan's ellipsoids with the robot state of that same scan, and turns a
boxed-in car out inside its margin but never past the hard floor."""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np
import pytest

from depot_car import depot_car_scenario
from schemas.messages import Ellipsoids, Goals, Header, Pose2D, RawPath, RobotState
from schemas.scenario import bundled_scenario, load_scenario, parse_scenario
from services.contract import Notice, StageInputError
from services.convert import ellipse_to_msg, ellipses_from_msgs
from services.drive.guard import PathGuard
from services.geometry import Ellipse, EllipseStack, keep_out_scales
from services.planner.core import plan_until_verified
from services.planner.stage import PlannerStage, boxed_in, crosses_closed_gap, trim_to_robot
from services.smoother.core import smooth
from services.smoother.stage import SmootherStage

SCENARIO = bundled_scenario()


def state(seq: int) -> RobotState:
    return RobotState(header=Header(stamp_s=0.1 * seq, seq=seq), pose=Pose2D(x_m=0.0, y_m=0.0, theta_rad=0.785),
                      speed_mps=0.0, steering_rad=0.0, goal_index=0, goals_reached=0, done=False)


def ellipsoids(seq: int) -> Ellipsoids:
    return Ellipsoids(header=Header(stamp_s=0.1 * seq, seq=seq), scan_seq=seq, inflation_m=SCENARIO.inflation_m,
                      ellipsoids=[])


def test_ellipsoids_arriving_before_their_state_wait_for_it():
    planner = PlannerStage.from_scenario(SCENARIO)
    planner.process(topic="state", message=state(2), now_s=0.0)
    assert planner.process(topic="ellipsoids", message=ellipsoids(3), now_s=0.0) == []  # state 3 not here yet
    (topic, out), = planner.process(topic="state", message=state(3), now_s=0.0)
    assert topic == "raw_path" and isinstance(out, RawPath)
    assert out.scan_seq == 3 and out.status == "ok"


def test_state_first_answers_at_once():
    planner = PlannerStage.from_scenario(SCENARIO)
    planner.process(topic="state", message=state(5), now_s=0.0)
    (_, out), = planner.process(topic="ellipsoids", message=ellipsoids(5), now_s=0.0)
    assert out.scan_seq == 5


def test_a_car_boxed_in_by_a_grown_cover_turns_out_inside_the_margin_but_not_past_the_hard_floor(scenarios_dir):
    """field-60 at t = 23.5 s (closed loop): a cover grew round the car as more of its obstacle came into
    view, and from the car's pose every forward turn crosses the full margin. The planner gives the margin
    up near the car, down to the floor that keeps the footprint half the safety distance clear, and the
    curve it publishes verifies and passes the sim's guard."""
    scenario = load_scenario(scenarios_dir / "field-60.json")
    doc = json.loads((Path(__file__).parents[1] / "data" / "field60-boxed-in.json").read_text())
    robot, sensed = RobotState.model_validate(doc["state"]), Ellipsoids.model_validate(doc["ellipsoids"])
    start = np.array([robot.pose.x_m, robot.pose.y_m])
    planner = PlannerStage.from_scenario(scenario)
    config = planner.config

    full = EllipseStack.of(ellipses_from_msgs(sensed.ellipsoids))
    assert full.levels(start).min() > 1.0  # the car is outside every grown ellipse ...
    heading = robot.pose.theta_rad
    assert boxed_in(full, start=start, heading_rad=heading, max_curvature=config.max_curvature)
    assert not boxed_in(full, start=start, heading_rad=heading + np.pi, max_curvature=config.max_curvature)
    plan, smoothed = plan_until_verified(  # ... yet no turn from here verifies with the full margin
        start=start, heading_rad=robot.pose.theta_rad, goals=config.goals, ellipses=ellipses_from_msgs(sensed.ellipsoids),
        bounds_min=config.bounds_min, bounds_max=config.bounds_max, max_curvature=config.max_curvature,
        settings=config.refine, repairs=config.repairs,
        smooth_fn=lambda points: smooth(points, ellipses=ellipses_from_msgs(sensed.ellipsoids),
                                        max_curvature=config.max_curvature, heading_rad=None, goals=config.goals,
                                        goal_tolerance_m=config.goal_tolerance_m, bounds_min=config.bounds_min,
                                        bounds_max=config.bounds_max))
    assert smoothed is None or not smoothed.verification.ok

    planner.process(topic="state", message=robot, now_s=0.0)
    (_, raw), = planner.process(topic="ellipsoids", message=sensed, now_s=0.0)
    assert raw.status == "ok" and planner.plan_relieved
    (_, curve), = SmootherStage.from_scenario(scenario).process(topic="raw_path", message=raw, now_s=0.0)
    assert curve.status == "ok" and curve.max_curvature <= config.max_curvature

    guard = PathGuard(inflation_m=scenario.inflation_m, keep_out_m=scenario.keep_out_m)
    guard.know(sensed)
    assert guard.check(curve.points, start=start) is None
    used = EllipseStack.of(ellipses_from_msgs(raw.ellipsoids))
    scale = used.reach / full.reach
    hard = keep_out_scales(full.semi_axes, inflation_m=scenario.inflation_m, keep_m=scenario.keep_out_m)
    assert np.all(scale >= hard - 1e-9)
    shrunk = scale < 1.0 - 1e-9
    assert shrunk.any()
    near = np.linalg.norm(full.centers - start, axis=1) - full.reach < 1.0 / config.max_curvature
    assert np.all(near[shrunk])  # only near the car


def _ellipsoids_with(seq: int, *circles: tuple[tuple[float, float], float]) -> Ellipsoids:
    wire = [ellipse_to_msg(Ellipse.circle(center=c, radius=r), group=k, cluster_id=k) for k, (c, r) in enumerate(circles)]
    return Ellipsoids(header=Header(stamp_s=0.1 * seq, seq=seq), scan_seq=seq, inflation_m=SCENARIO.inflation_m,
                      ellipsoids=wire)


def test_a_car_boxed_in_even_at_the_hard_floor_gets_no_path_with_the_reason():
    """An unseen field of field-60's kind, closed loop at t = 13 s: the car stands in a pocket that a
    grown cover closed. No curve verifies, and every turn crosses even the hard floor: the planner says
    so (no_path, whereupon the sim ends the run) rather than publish a curve the smoother rejects."""
    doc = json.loads((Path(__file__).parents[1] / "data" / "unseen60-boxed-in.json").read_text())
    scenario = parse_scenario(json.dumps(doc["scenario"]), source="unseen60-boxed-in")
    robot, sensed = RobotState.model_validate(doc["state"]), Ellipsoids.model_validate(doc["ellipsoids"])
    start = np.array([robot.pose.x_m, robot.pose.y_m])
    assert EllipseStack.of(ellipses_from_msgs(sensed.ellipsoids)).levels(start).min() > 1.0  # not in collision
    planner = PlannerStage.from_scenario(scenario)
    planner.process(topic="state", message=robot, now_s=0.0)
    (_, raw), = planner.process(topic="ellipsoids", message=sensed, now_s=0.0)
    assert raw.status == "no_path" and raw.reason.startswith("boxed in") and raw.points == []
    assert planner.plan is None


def test_a_plan_that_a_grown_cover_invalidates_is_repaired_on_the_same_side_of_it():
    planner = PlannerStage.from_scenario(SCENARIO)
    centre = np.array([4.0, 5.2])  # just left of the diagonal to the first goal: the plan passes right of it
    planner.process(topic="state", message=state(0), now_s=0.0)
    (_, first), = planner.process(topic="ellipsoids", message=_ellipsoids_with(0, (tuple(centre), 1.0)), now_s=0.0)
    before = np.array(first.points)
    goal = SCENARIO.goals_array[0]

    def side(point):  # which side of the line start → first goal
        return np.sign(goal[0] * point[1] - goal[1] * point[0])

    def passes(path):  # the side of the obstacle's centre the path passes on
        return side(path[np.argmin(np.linalg.norm(path - centre, axis=1))] - centre)

    assert passes(before) == -side(centre)  # round the far side of it
    grown = 1.25  # the cover grows: the kept plan now runs through it
    assert np.min(np.linalg.norm(before - centre, axis=1)) < grown
    planner.process(topic="state", message=state(1), now_s=0.0)
    (_, second), = planner.process(topic="ellipsoids", message=_ellipsoids_with(1, (tuple(centre), grown)), now_s=0.0)
    after = np.array(second.points)
    assert second.status == "ok" and second.plan_id == first.plan_id + 1
    assert np.min(np.linalg.norm(after - centre, axis=1)) >= grown
    assert passes(after) == passes(before)
    # Only the stretch near the cover, and a rejoin distance past it, moved: from the first goal on
    # the repaired plan is the kept one, point for point.
    kept = before[np.argmin(np.linalg.norm(before - goal, axis=1)):]
    np.testing.assert_array_equal(after[-len(kept):], kept)
    (_, curve), = SmootherStage.from_scenario(SCENARIO).process(topic="raw_path", message=second, now_s=0.0)
    assert curve.status == "ok"


def test_a_path_between_two_grouped_obstacles_crosses_a_closed_gap_but_one_round_them_does_not():
    ellipses = [Ellipse.circle(center=(0.0, 1.0), radius=0.6), Ellipse.circle(center=(0.0, -1.0), radius=0.6)]
    between = np.array([[-3.0, 0.0], [3.0, 0.0]])  # enters neither grown ellipse, but passes between them
    around = np.array([[-3.0, 0.0], [-1.0, 2.5], [1.0, 2.5], [3.0, 0.0]])
    entered = np.array([0])
    grouped = dict(groups=np.array([0, 0]), clusters=np.array([0, 1]))
    assert crosses_closed_gap(between, ellipses, entered=entered, **grouped)
    assert not crosses_closed_gap(around, ellipses, entered=entered, **grouped)
    # Not grouped (the gap is wide enough), or pieces of one cluster (a concave obstacle: its mouth may lie
    # between them).
    for groups, clusters in (([0, 1], [0, 1]), ([0, 0], [0, 0])):
        assert not crosses_closed_gap(between, ellipses, entered=entered, groups=np.array(groups),
                                      clusters=np.array(clusters))
    assert not crosses_closed_gap(between, ellipses, entered=np.array([], dtype=int), **grouped)


def test_the_robot_is_placed_on_the_stretch_of_the_plan_it_faces():
    """A plan out and back past the robot (it backed out along its tracks): the way back lies nearer, but
    runs against the heading, so the plan is trimmed to the way out; facing the other way, to the way back."""
    out = np.column_stack([np.linspace(0.0, 5.0, 51), np.zeros(51)])
    back = np.column_stack([np.linspace(5.0, 0.0, 51), np.full(51, 0.2)])
    plan = np.vstack([out, back])
    trimmed, off_m = trim_to_robot(plan, position=np.array([2.05, 0.15]), heading_rad=0.0)
    assert len(trimmed) == len(plan) - 20 and off_m == pytest.approx(0.15)
    trimmed, off_m = trim_to_robot(plan, position=np.array([2.05, 0.15]), heading_rad=np.pi)
    assert trimmed[0][1] == 0.2 and off_m == pytest.approx(0.05)
    _, off_m = trim_to_robot(out, position=np.array([2.05, 0.0]), heading_rad=np.pi)
    assert off_m == np.inf  # nothing of it runs the robot's way: off the plan, replan


def test_new_goals_replace_the_scenarios_in_the_planner_and_the_smoother():
    """A robot's /goal_pose reaches the pipeline as a Goals message: the planner drops its plan and plans to
    the new goal, and the smoother verifies the curve against the new goal, not the scenario's."""
    planner, smoother = PlannerStage.from_scenario(SCENARIO), SmootherStage.from_scenario(SCENARIO)
    planner.process(topic="state", message=state(0), now_s=0.0)
    (_, first), = planner.process(topic="ellipsoids", message=ellipsoids(0), now_s=0.0)
    assert np.allclose(first.points[-1], SCENARIO.goals[-1])

    goals = Goals(header=Header(stamp_s=0.2, seq=0), goals=[(4.0, 1.0)])
    assert planner.process(topic="goals", message=goals, now_s=0.0) == []
    assert smoother.process(topic="goals", message=goals, now_s=0.0) == []
    planner.process(topic="state", message=state(1), now_s=0.0)
    (_, raw), = planner.process(topic="ellipsoids", message=ellipsoids(1), now_s=0.0)
    assert raw.status == "ok" and raw.plan_id == first.plan_id + 1 and np.allclose(raw.points[-1], (4.0, 1.0))
    (_, curve), = smoother.process(topic="raw_path", message=raw, now_s=0.0)
    assert curve.status == "ok" and np.allclose(curve.points[-1], (4.0, 1.0))
    # A curve to the scenario's goals no longer verifies: it misses the robot's goal.
    with pytest.raises(StageInputError, match="misses goal 0"):
        smoother.process(topic="raw_path", message=first, now_s=0.0)


def _budget_planner(scenario, budget_s: float = 1e-9) -> PlannerStage:
    """A planner with a deadline; by default a nanosecond, which no replan meets."""
    from dataclasses import replace

    from services.planner.stage import PlannerConfig

    return PlannerStage(config=replace(PlannerConfig.from_scenario(scenario), budget_s=budget_s))


def _scan(planner: PlannerStage, robot: RobotState, sensed: Ellipsoids, seq: int) -> list:
    """The planner's outputs for scan `seq` of the robot at `robot`'s pose seeing `sensed`."""
    planner.process(topic="state", message=robot.model_copy(update={"header": robot.header.model_copy(update={"seq": seq})}),
                    now_s=0.0)
    return planner.process(topic="ellipsoids", message=sensed.model_copy(update={"scan_seq": seq}), now_s=0.0)


def _replan_done(planner: PlannerStage, *, timeout_s: float = 60.0) -> None:
    deadline = time.monotonic() + timeout_s
    while planner.replanning:
        assert time.monotonic() < deadline, "the background replan did not end"
        time.sleep(0.01)


def _boxed_in_field60(scenarios_dir):
    scenario = load_scenario(scenarios_dir / "field-60.json")
    doc = json.loads((Path(__file__).parents[1] / "data" / "field60-boxed-in.json").read_text())
    return scenario, RobotState.model_validate(doc["state"]), Ellipsoids.model_validate(doc["ellipsoids"])


def test_with_a_budget_a_replan_goes_on_in_the_background_and_a_later_scan_adopts_it_verified(scenarios_dir):
    """field-60's boxed-in pose, with a budget no replan meets: the scan is answered while the replan
    still runs, with no_path and the reason (never an unverified plan), which the status says too; the
    next scan, once the replan is done, publishes its plan under a new id, re-verified against that
    scan's ellipses, and the smoother and the sim's guard accept it."""
    scenario, robot, sensed = _boxed_in_field60(scenarios_dir)
    planner = _budget_planner(scenario)
    (topic, raw), *notices = _scan(planner, robot, sensed, 0)
    assert planner.replanning  # answered before the replan ended
    assert topic == "raw_path" and raw.status == "no_path" and raw.points == [] and raw.replanning
    assert raw.reason.startswith("replanning: no verified path for this scan within the budget")
    assert any(isinstance(notice, Notice) and notice.reason == raw.reason for _, notice in notices)
    _replan_done(planner)
    (_, raw2), *_ = _scan(planner, robot, sensed, 1)
    assert raw2.status == "ok" and not raw2.replanning and raw2.plan_id == raw.plan_id + 1 and not planner.replanning
    (_, curve), = SmootherStage.from_scenario(scenario).process(topic="raw_path", message=raw2, now_s=0.0)
    assert curve.status == "ok" and curve.max_curvature <= planner.config.max_curvature
    guard = PathGuard(inflation_m=scenario.inflation_m, keep_out_m=scenario.keep_out_m)
    guard.know(sensed)
    assert guard.check(curve.points, start=np.array([robot.pose.x_m, robot.pose.y_m])) is None
    (_, raw3), *_ = _scan(planner, robot, sensed, 2)  # kept: the same plan, no new replan
    assert raw3.points == raw2.points and raw3.plan_id == raw2.plan_id and not planner.replanning


def test_a_replan_within_the_budget_answers_its_own_scan_as_without_a_deadline(scenarios_dir):
    """With a budget the replan meets, the scan waits for it: the same plan as a lockstep planner's."""
    scenario, robot, sensed = _boxed_in_field60(scenarios_dir)
    (_, lockstep), = _scan(PlannerStage.from_scenario(scenario), robot, sensed, 0)
    (_, raw), = _scan(_budget_planner(scenario, budget_s=60.0), robot, sensed, 0)
    assert raw.status == lockstep.status == "ok" and raw.points == lockstep.points


def test_a_background_replan_that_finds_no_path_says_why_and_never_publishes_a_path():
    """The unseen field's pocket, where nothing verifies and every turn crosses even the hard floor:
    with a budget no replan meets, the first scan answers no_path while replanning (the car waits), and
    once that replan has ended, the next answers no_path with its verdict (the car may back out) and
    starts the next replan from its own inputs; with a budget it meets, the verdict at once, as
    without a deadline."""
    doc = json.loads((Path(__file__).parents[1] / "data" / "unseen60-boxed-in.json").read_text())
    scenario = parse_scenario(json.dumps(doc["scenario"]), source="unseen60-boxed-in")
    robot, sensed = RobotState.model_validate(doc["state"]), Ellipsoids.model_validate(doc["ellipsoids"])
    planner = _budget_planner(scenario)
    (_, raw), *_ = _scan(planner, robot, sensed, 0)
    assert raw.status == "no_path" and raw.reason.startswith("replanning:") and raw.replanning
    _replan_done(planner)
    (_, raw), (_, notice), *_ = _scan(planner, robot, sensed, 1)
    assert raw.status == "no_path" and raw.points == [] and planner.plan is None
    assert raw.reason.startswith("boxed in") and not raw.replanning and "; replanning:" in notice.reason
    assert planner.replanning  # the next one, from this scan
    planner.stop(now_s=0.0)
    (_, raw), = _scan(_budget_planner(scenario, budget_s=60.0), robot, sensed, 0)
    assert raw.status == "no_path" and raw.reason.startswith("boxed in")


def test_new_goals_call_a_background_replan_off_and_stop_leaves_no_replan_running():
    """What a replan for the old goals makes is never adopted; `stop` waits for the running replan."""
    planner = _budget_planner(SCENARIO)
    planner.process(topic="state", message=state(0), now_s=0.0)
    (_, raw), *_ = planner.process(topic="ellipsoids", message=_ellipsoids_with(0, ((4.0, 5.2), 1.0)), now_s=0.0)
    assert raw.status == "no_path" and raw.reason.startswith("replanning:")
    planner.process(topic="goals", message=Goals(header=Header(stamp_s=0.0, seq=0), goals=[(-4.0, 2.0)]), now_s=0.0)
    _replan_done(planner)
    planner.process(topic="state", message=state(1), now_s=0.0)
    (_, raw), *_ = planner.process(topic="ellipsoids", message=_ellipsoids_with(1, ((4.0, 5.2), 1.0)), now_s=0.0)
    assert raw.status == "no_path" and planner.plan is None and raw.plan_id == 0  # the old replan was dropped
    running = planner._replan_job  # the replan for the new goals
    planner.stop(now_s=0.0)
    assert not planner.replanning and not running._thread.is_alive()


def test_a_live_planners_budget_is_its_share_of_the_sensor_period_or_the_one_given():
    scenario = bundled_scenario()
    assert PlannerStage.from_scenario(scenario).config.budget_s is None  # lockstep: no deadline
    period_s = 1.0 / float(scenario.sensor.rate_hz)
    assert PlannerStage.from_scenario(scenario, deadline=True).config.budget_s == pytest.approx(0.15 * period_s)
    assert PlannerStage.from_scenario(scenario, deadline=True, budget_ms=40.0).config.budget_s == pytest.approx(0.04)


def test_a_plan_keeps_the_guards_floor_from_the_maps_bounds():
    """A room's dividing wall seen down to 0.6 m above the map's edge (its cover a grown disc there): the
    way round runs between it and the edge. The sim's path guard keeps every path the hard floor inside the
    bounds, as from a wall; the online margin (level 1.1) alone would push the plan to 0.33 m from the
    edge, a plan the guard refuses scan after scan while the car brakes. The plan keeps the floor, and the
    curve the smoother makes of it is one the guard drives."""
    scenario = depot_car_scenario(bounds=((0.0, 0.0), (12.0, 6.0)), start=(1.5, 3.0, 0.0), goals=[(11.0, 3.0)])
    planner = PlannerStage.from_scenario(scenario)
    robot = RobotState(header=Header(stamp_s=0.0, seq=0), pose=Pose2D(x_m=1.5, y_m=3.0, theta_rad=0.0), speed_mps=0.0,
                       steering_rad=0.0, goal_index=0, goals_reached=0, done=False)
    cover = Ellipse.circle(center=(6.0, 3.35), radius=2.75)
    wall = Ellipsoids(header=Header(stamp_s=0.0, seq=0), scan_seq=0, inflation_m=scenario.inflation_m,
                      ellipsoids=[ellipse_to_msg(cover, group=0, cluster_id=0)])
    planner.process(topic="state", message=robot, now_s=0.0)
    (_, raw), = planner.process(topic="ellipsoids", message=wall, now_s=0.0)
    assert raw.status == "ok"
    (_, curve), = SmootherStage.from_scenario(scenario).process(topic="raw_path", message=raw, now_s=0.0)
    assert curve.status == "ok"
    points = np.array(curve.points)
    assert points[:, 1].min() < 0.6  # it went round below the wall
    depth = np.minimum(points - [0.0, 0.0], [12.0, 6.0] - points).min()
    assert depth >= scenario.keep_out_m - 1e-6
    guard = PathGuard(inflation_m=scenario.inflation_m, keep_out_m=scenario.keep_out_m,
                      bounds_min=np.array([0.0, 0.0]), bounds_max=np.array([12.0, 6.0]))
    guard.know(wall)
    assert guard.check(curve.points, start=(1.5, 3.0)) is None
