"""A known map (a robot's /map as the pipeline's `Map`) in the ellipsoid stage: its walls near the robot
go out with the sensed obstacles, so the planner and the smoother, unchanged, keep the margin from them."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from depot_car import depot_car_scenario
from schemas.messages import ClusterMsg, Clusters, Header, Pose2D, RobotState
from schemas.occupancy import FREE, OccupancyGrid, load_map
from schemas.scenario import load_scenario
from services.contract import StageInputError
from services.convert import ellipses_from_msgs, grid_to_msg
from services.ellipsoids.stage import MAP_CLUSTER_ID, EllipsoidsStage
from services.geometry import EllipseStack
from services.planner.stage import PlannerStage
from services.smoother.stage import SmootherStage

START = Pose2D(x_m=9.675, y_m=5.875, theta_rad=0.1573)  # depot-1's start
GOAL = (16.89, 2.57)  # 8 m on: the straight line runs through the depot's shelves


@pytest.fixture(scope="module")
def depot(shared_dir) -> OccupancyGrid:
    return load_map(shared_dir / "maps" / "depot.yaml")


@pytest.fixture(scope="module")
def scenario(shared_dir):
    """depot-1's robot with a 10 m laser and the goal 8 m on, the map not in the scenario: it comes as a message."""
    base = load_scenario(shared_dir / "map-scenarios" / "depot-1.json")
    return base.model_copy(update={"obstacles": [], "goals": [GOAL],
                                   "sensor": base.sensor.model_copy(update={"range": 10.0})})


def stage_of(scenario) -> EllipsoidsStage:
    """The ellipsoid stage, sending the map's walls within 10 m: the whole way to the goal 8 m on."""
    stage = EllipsoidsStage.from_scenario(scenario)
    stage.config = dataclasses.replace(stage.config, map_window_m=10.0)
    return stage


def header(seq: int) -> Header:
    return Header(stamp_s=0.1 * seq, seq=seq)


def state(seq: int, pose: Pose2D = START) -> RobotState:
    return RobotState(header=header(seq), pose=pose, speed_mps=0.0, steering_rad=0.0, goal_index=0, goals_reached=0,
                      done=False)


def ellipsoids_with_map(stage: EllipsoidsStage, grid: OccupancyGrid, *, seq: int = 0, clusters=(),
                        pose: Pose2D = START) -> object:
    stage.process(topic="map", message=grid_to_msg(grid, header=header(0)), now_s=0.0)
    stage.process(topic="state", message=state(seq, pose), now_s=0.0)
    (_, out), = stage.process(topic="clusters", message=Clusters(header=header(seq), scan_seq=seq,
                                                                  clusters=list(clusters)), now_s=0.0)
    return out


def test_every_point_of_the_window_within_the_margin_of_a_wall_is_inside_a_map_ellipse(scenario, depot) -> None:
    stage = stage_of(scenario)
    window, r = stage.config.map_window_m, scenario.inflation_m
    sensed = ClusterMsg(cluster_id=0, points=[(12.0, 7.0), (12.1, 7.05)])
    out = ellipsoids_with_map(stage, depot, clusters=[sensed])
    walls = [e for e in out.ellipsoids if e.cluster_id == MAP_CLUSTER_ID]
    assert [e.cluster_id for e in out.ellipsoids if e.cluster_id != MAP_CLUSTER_ID] == [0]
    assert 50 < len(walls) < 400
    # A lattice of free points over the window: those nearer a wall than the margin are inside one.
    robot = np.array([START.x_m, START.y_m])
    x, y = np.meshgrid(np.arange(-window, window, 0.07), np.arange(-window, window, 0.07))
    z = robot + np.column_stack([x.ravel(), y.ravel()])
    z = z[(np.linalg.norm(z - robot, axis=1) <= window) & (depot.state_at(z) == FREE)]
    close = z[depot.clearance(z) < r - 1e-9]
    assert len(close) > 1000
    stack = EllipseStack.of(ellipses_from_msgs(walls))
    assert stack.levels(close).min(axis=1).max() < 1.0
    # ... and none of the map's walls farther off is sent.
    assert np.all(np.linalg.norm(stack.centers - robot, axis=1) - stack.semi_axes[:, 0] <= window)


def test_a_new_map_replaces_the_old_ones_walls(scenario, depot) -> None:
    stage = stage_of(scenario)
    ellipsoids_with_map(stage, depot)
    cover = stage.map
    ellipsoids_with_map(stage, depot, seq=1)  # the same map again (a stage that came back): the cover is kept
    assert stage.map is cover and cover.fitted
    open_floor = OccupancyGrid.from_mask(np.zeros((400, 600), dtype=bool), resolution_m=0.05)  # 30 x 20 m, no wall
    out = ellipsoids_with_map(stage, open_floor, seq=2)
    assert out.ellipsoids == ellipsoids_with_map(stage_of(scenario), open_floor, seq=2).ellipsoids
    robot = np.array([START.x_m, START.y_m])
    # Only the edge of the map is left (beyond it nothing is known): 5.6 m from the robot at the nearest.
    assert EllipseStack.of(ellipses_from_msgs(out.ellipsoids)).levels(robot[None] + [[0.0, -5.0]]).min() > 1.0


def test_the_plan_on_a_known_map_keeps_the_margin_from_its_walls(scenario, depot) -> None:
    out = ellipsoids_with_map(stage_of(scenario), depot)  # nothing sensed: only the map
    planner, smoother = PlannerStage.from_scenario(scenario), SmootherStage.from_scenario(scenario)
    planner.process(topic="state", message=state(0), now_s=0.0)
    (_, raw), = planner.process(topic="ellipsoids", message=out, now_s=0.0)
    (_, smooth), = smoother.process(topic="raw_path", message=raw, now_s=0.0)
    assert smooth.status == "ok", smooth.reason
    path = np.asarray(smooth.points)
    assert np.linalg.norm(path[-1] - GOAL) <= scenario.goal_tolerance
    straight = np.linspace((START.x_m, START.y_m), GOAL, 200)
    assert depot.clearance(straight).min() == 0.0  # the way straight there runs into the shelves
    assert depot.clearance(path).min() >= scenario.inflation_m


def test_a_map_off_the_scenarios_bounds_is_refused_and_the_one_held_stays(scenario, depot) -> None:
    stage = stage_of(scenario)
    ellipsoids_with_map(stage, depot)
    cover = stage.map
    far = OccupancyGrid.from_mask(np.ones((4, 4), dtype=bool), resolution_m=0.5, origin=(1e4, 0.0, 0.0))
    with pytest.raises(StageInputError, match=r"map: its extent \(10000, 0\) to \(10002, 2\) lies more than 10 m "
                                               r"outside the map bounds"):
        stage.process(topic="map", message=grid_to_msg(far, header=header(1)), now_s=0.0)
    assert stage.map is cover


def test_a_goal_just_beyond_the_margin_from_a_map_wall_is_let_out_and_one_within_it_held():
    """A map with a wall along its bottom row; goals 1.5 cm beyond the depot car's margin from it and 5 cm
    within. The map's cover may stray up to its tolerance (0.1 m) beyond the margin and held the first, so
    no plan could end there; the stage fits the pieces holding a goal ahead tighter, as `cvxnav plan` does
    (`GridCover.tighten`), and the second stays held."""
    mask = np.zeros((120, 240), dtype=bool)
    mask[0, :] = True  # y from 0 to 0.05 m
    grid = OccupancyGrid.from_mask(mask, resolution_m=0.05, source="wall")
    beyond, within = (5.5, 0.05 + 0.45 + 0.015), (6.0, 0.05 + 0.4)

    def levels(goals, point) -> float:
        scenario = depot_car_scenario(bounds=((0.0, 0.0), (12.0, 6.0)), start=(4.0, 3.0, 0.0), goals=goals)
        stage = EllipsoidsStage.from_scenario(scenario)
        out = ellipsoids_with_map(stage, grid, pose=Pose2D(x_m=4.0, y_m=3.0, theta_rad=0.0))
        walls = [e for e in out.ellipsoids if e.cluster_id == MAP_CLUSTER_ID]
        return float(EllipseStack.of(ellipses_from_msgs(walls)).levels(np.array([point])).min())

    assert levels([(9.0, 3.0)], beyond) <= 1.0  # held by the cover fitted to its tolerance
    assert levels([beyond], beyond) > 1.0
    assert levels([within], within) <= 1.0
