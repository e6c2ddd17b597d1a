"""Each stage core bounds what a well-formed message may hold (services/limits.py) and rejects the rest
with a one-line StageInputError, keeping what it held before; degenerate but real clusters are fitted."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from schemas.messages import (ClusterMsg, Clusters, EllipsoidMsg, Ellipsoids, Goals, Header, Pose2D, RawPath, RobotState,
                              Scan)
from schemas.scenario import bundled_scenario
from services.contract import StageInputError
from services.ellipsoids.stage import EllipsoidsStage
from services.limits import MAX_ELLIPSES, MAX_PATH_POINTS, MAX_SENSED_POINTS
from services.planner.stage import PlannerStage
from services.sensing.stage import SensingStage
from services.smoother.stage import SmootherStage

SCENARIO = bundled_scenario()
HEADER = Header(stamp_s=0.1, seq=1)
POSE = Pose2D(x_m=0.0, y_m=0.0, theta_rad=float(SCENARIO.start.theta))
FAR = float(SCENARIO.bounds.max[0]) + 2.0 * float(SCENARIO.sensor.range)


def scan(points, *, pose: Pose2D = POSE) -> Scan:
    return Scan(header=HEADER, pose=pose, points=points)


def state(*, x_m: float = 0.0, goals_reached: int = 0, goal_index: int = 0) -> RobotState:
    return RobotState(header=HEADER, pose=Pose2D(x_m=x_m, y_m=0.0, theta_rad=0.0), speed_mps=0.0,
                      steering_rad=0.0, goal_index=goal_index, goals_reached=goals_reached, done=False)


def one_line_rejection(core, topic: str, message, match: str) -> None:
    with pytest.raises(StageInputError, match=match) as error:
        core.process(topic=topic, message=message, now_s=0.0)
    assert "\n" not in str(error.value)


WALL = [(3.0 + 0.05 * k, 1.0 - 0.05 * k) for k in range(21)]


@pytest.mark.parametrize(
    ("message", "match"),
    [
        (scan([(1.0, 1.0)] * (SCENARIO.sensor.rays + 1)), "scan points: 182 exceeds the limit of 181"),
        (scan([(1.0, 1.0)], pose=Pose2D(x_m=FAR, y_m=0.0, theta_rad=0.0)), "outside the map bounds"),
        (scan([(1.0, 1.0), (40.0, 0.0)]), "point 1 lies 40 m from the pose, beyond the sensor's range"),
    ],
    ids=["more-points-than-rays", "pose-off-map", "hit-beyond-range"],
)
def test_sensing_rejects_impossible_scans_and_forgets_nothing(message, match):
    core = SensingStage.from_scenario(SCENARIO)
    core.process(topic="scan", message=scan(WALL), now_s=0.0)
    remembered = core.memory.points().copy()
    one_line_rejection(core, "scan", message, match)
    np.testing.assert_array_equal(core.memory.points(), remembered)


def clusters(points) -> Clusters:
    return Clusters(header=HEADER, scan_seq=1, clusters=[ClusterMsg(cluster_id=0, points=points)])


@pytest.mark.parametrize(
    "points",
    [[(4.0, 4.0)], [(4.0, 4.0)] * 30, [(4.0 + 0.1 * k, 4.0 + 0.1 * k) for k in range(30)],
     [(4.0, 4.0), (4.0, 4.0 + 1e-9)]],
    ids=["one-point", "all-equal", "collinear", "nearly-equal"],
)
def test_degenerate_clusters_are_fitted_as_obstacles(points):
    (_, out), = EllipsoidsStage.from_scenario(SCENARIO).process(topic="clusters", message=clusters(points), now_s=0.0)
    z = np.asarray(points)
    levels = [np.linalg.norm(z @ np.array(e.A).T + np.array(e.b), axis=1) for e in out.ellipsoids]
    assert np.all(np.min(levels, axis=0) < 1.0)  # every point lies inside a grown ellipse


def test_ellipsoids_rejects_too_many_points_and_points_off_the_map():
    core = EllipsoidsStage.from_scenario(SCENARIO)
    many = [(4.0 + 1e-4 * k, 4.0) for k in range(MAX_SENSED_POINTS + 1)]
    one_line_rejection(core, "clusters", clusters(many), f"exceeds the limit of {MAX_SENSED_POINTS}")
    one_line_rejection(core, "clusters", clusters([(4.0, 4.0), (1e300, 4.0)]), "cluster 0: point 1")


def ellipse(*, A=((1.0, 0.0), (0.0, 1.0)), center=(4.0, 4.0)) -> EllipsoidMsg:
    A = np.array(A)
    return EllipsoidMsg(A=tuple(map(tuple, A.tolist())), b=tuple((-A @ np.array(center)).tolist()), group=0,
                        cluster_id=0)


BAD_ELLIPSES = {
    "too-many": ([ellipse()] * (MAX_ELLIPSES + 1), f"exceeds the limit of {MAX_ELLIPSES}"),
    "needle": ([ellipse(A=((1e9, 0.0), (0.0, 1.0)))], "ellipse 0 has semi-axes 1e-09 m"),
    "whole-world": ([ellipse(A=((1e-6, 0.0), (0.0, 1e-6)))], "must lie in"),
    "off-map": ([ellipse(center=(1e6, 0.0))], "ellipse centres: point 0"),
}


@pytest.mark.parametrize(("ellipses", "match"), BAD_ELLIPSES.values(), ids=BAD_ELLIPSES.keys())
def test_planner_and_smoother_reject_absurd_ellipse_sets(ellipses, match):
    planner = PlannerStage.from_scenario(SCENARIO)
    one_line_rejection(planner, "ellipsoids",
                       Ellipsoids(header=HEADER, scan_seq=1, inflation_m=0.65, ellipsoids=ellipses), match)
    assert planner.pending is None
    path = RawPath(header=HEADER, scan_seq=1, status="ok", goal_index=0, points=[(0.0, 0.0), (1.0, 1.0)],
                   ellipsoids=ellipses)
    one_line_rejection(SmootherStage.from_scenario(SCENARIO), "raw_path", path, match)


@pytest.mark.parametrize(
    ("message", "match"),
    [(state(x_m=FAR), "state: pose"), (state(goals_reached=3), "goals_reached 3"),
     (state(goal_index=2), "goal_index 2")],
    ids=["off-map", "more-goals-reached-than-exist", "goal-index-beyond"],
)
def test_planner_keeps_its_state_when_a_state_is_absurd(message, match):
    planner = PlannerStage.from_scenario(SCENARIO)
    planner.process(topic="state", message=state(), now_s=0.0)
    held = planner.robot_state
    one_line_rejection(planner, "state", message, match)
    assert planner.robot_state is held


@pytest.mark.parametrize(("stage", "goals_of"), [(PlannerStage, lambda core: core.config.goals),
                                                  (EllipsoidsStage, lambda core: core.goals)], ids=["planner", "ellipsoids"])
def test_goals_outside_the_map_are_refused_and_the_old_ones_stay(stage, goals_of):
    core = stage.from_scenario(SCENARIO)
    far = Goals(header=HEADER, goals=[(4.0, 1.0), (FAR, 0.0)])
    one_line_rejection(core, "goals", far, r"goals: goal 1: pose \(.*\) is outside the map bounds")
    assert np.array_equal(goals_of(core), SCENARIO.goals_array)


def test_smoother_rejects_oversized_and_off_map_paths():
    smoother = SmootherStage.from_scenario(SCENARIO)
    long = [(0.0, 1e-3 * k) for k in range(MAX_PATH_POINTS + 1)]
    path = dict(header=HEADER, scan_seq=1, status="ok", goal_index=0, ellipsoids=[])
    one_line_rejection(smoother, "raw_path", RawPath(points=long, **path), f"exceeds the limit of {MAX_PATH_POINTS}")
    one_line_rejection(smoother, "raw_path", RawPath(points=[(0.0, 0.0), (0.0, -1e9)], **path), "raw path: point 1")


finite = st.floats(allow_nan=False, allow_infinity=False, width=64)


@settings(max_examples=60, deadline=None)
@given(points=st.lists(st.tuples(finite, finite), max_size=40),
       pose=st.builds(Pose2D, x_m=finite, y_m=finite, theta_rad=finite))
def test_sensing_never_fails_otherwise_on_any_finite_scan(points, pose):
    """Any well-formed scan is either clustered or rejected with StageInputError; nothing else escapes."""
    core = SensingStage.from_scenario(SCENARIO)
    try:
        (_, out), = core.process(topic="scan", message=scan(points, pose=pose), now_s=0.0)
    except StageInputError:
        assert len(core.memory) == 0
        return
    assert sum(len(c.points) for c in out.clusters) == len(core.memory)


@settings(max_examples=40, deadline=None)
@given(points=st.lists(st.tuples(finite, finite), min_size=1, max_size=30))
def test_ellipsoids_never_fails_otherwise_on_any_finite_cluster(points):
    core = EllipsoidsStage.from_scenario(SCENARIO)
    try:
        (_, out), = core.process(topic="clusters", message=clusters(points), now_s=0.0)
    except StageInputError:
        return
    assert len(out.ellipsoids) >= 1
