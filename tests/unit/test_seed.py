"""`services.maps.seed.drivable_paths`: legs the car can drive through its goals, searched on the grid itself."""

from __future__ import annotations

import math

import numpy as np

from schemas.occupancy import OccupancyGrid
from services.drive.controller import menger_curvature
from services.geometry import resample_polyline
from services.maps.corridor import CoarseGrid
from services.maps.seed import drivable_paths

_RES = 0.05
_MARGIN = 0.3


def _room(width_m: float, height_m: float, *, walls: list[tuple[float, float, float, float]] = ()) -> OccupancyGrid:
    """A room of free cells with a one-cell wall round it, and wall boxes (x0, y0, x1, y1) in it."""
    rows, cols = round(height_m / _RES), round(width_m / _RES)
    blocked = np.zeros((rows, cols), dtype=bool)
    blocked[[0, -1], :] = blocked[:, [0, -1]] = True
    for x0, y0, x1, y1 in walls:
        blocked[round(y0 / _RES):round(y1 / _RES), round(x0 / _RES):round(x1 / _RES)] = True
    return OccupancyGrid.from_mask(blocked, resolution_m=_RES)


def _legs(grid: OccupancyGrid, start, heading_rad: float, goals, **options):
    """The last legs the search yields (through every goal, where found), None if it yields none."""
    lo, hi = grid.bounds()
    found = list(drivable_paths(grid, start=np.array(start), heading_rad=heading_rad, goals=np.array(goals),
                                radius_m=1.0, margin_m=_MARGIN, spacing_m=0.09, bounds_min=lo, bounds_max=hi,
                                **options))
    return found[-1] if found else None


def _path(grid: OccupancyGrid, start, heading_rad: float, goal):
    legs = _legs(grid, start, heading_rad, [goal])
    return None if legs is None else legs[0]


def test_a_goal_behind_the_car_is_reached_round_a_loop_clear_of_every_wall():
    grid = _room(8.0, 8.0)
    path = _path(grid, (4.0, 2.0), 0.0, (3.5, 2.0))
    assert path is not None
    assert np.allclose(path[0], [4.0, 2.0]) and np.allclose(path[-1], [3.5, 2.0])
    assert path[1, 0] > 4.0 and abs(path[1, 1] - 2.0) < 0.01  # off along the heading
    assert np.max(menger_curvature(path)) <= 1.0 + 1e-6  # the car's arcs and straight runs, to its end
    assert grid.clearance(resample_polyline(path, max_spacing_m=0.005)).min() >= _MARGIN


def test_a_goal_beyond_a_long_wall_is_reached_round_its_end():
    """A wall 1.2 m to the car's right spans most of the room: the goal 1.8 m beyond it is reached round
    its open end, and back down its other side."""
    grid = _room(8.0, 10.0, walls=[(5.2, 0.0, 5.4, 6.5)])
    path = _path(grid, (4.0, 2.0), 0.5 * math.pi, (7.0, 2.0))
    assert path is not None and np.allclose(path[-1], [7.0, 2.0])
    assert path[:, 1].max() > 6.5 + _MARGIN  # round the wall's open end
    assert grid.clearance(resample_polyline(path, max_spacing_m=0.005)).min() >= _MARGIN


def test_none_in_a_corridor_too_narrow_to_turn_round_in():
    """A dead-end corridor 1 m wide (0.4 m of it open to the car's centre) for a car turning at 1 m: the goal
    behind it is out of reach."""
    grid = _room(8.0, 1.1)
    assert _path(grid, (2.0, 0.55), 0.0, (1.0, 0.55)) is None


def test_goals_one_behind_the_other_are_reached_in_turn_round_a_loop():
    """The second goal lies 1.5 m behind the first, on the car's way: the car drives through the first and
    loops back to the second, leaving the first the way it arrived, the curvature bound kept across it."""
    grid = _room(8.0, 8.0)
    legs = _legs(grid, (4.0, 2.0), 0.0, [(6.0, 2.0), (4.5, 2.0)])
    assert legs is not None and len(legs) == 2
    assert np.allclose(legs[0][-1], [6.0, 2.0]) and np.allclose(legs[1][0], [6.0, 2.0])
    assert np.allclose(legs[1][-1], [4.5, 2.0])
    path = np.vstack([legs[0], legs[1][1:]])
    assert np.max(menger_curvature(path)) <= 1.0 + 1e-6
    assert grid.clearance(resample_polyline(path, max_spacing_m=0.005)).min() >= _MARGIN


def test_the_distance_left_round_the_walls_finds_a_way_the_straight_distance_does_not():
    """A wall from the floor to 2 m below the ceiling between the car and its goal: ordered by the straight
    distance, the search fills the room before the wall within its 3 000 poses; ordered by the coarse grid's
    distance left to the goal, which runs over the wall's end, it drives round it."""
    grid = _room(16.0, 10.0, walls=[(7.9, 0.0, 8.1, 8.0)])
    coarse = CoarseGrid(grid, _MARGIN, 0.2, start=np.array([2.0, 2.0]))
    assert _legs(grid, (2.0, 2.0), 0.0, [(14.0, 2.0)]) is None
    legs = _legs(grid, (2.0, 2.0), 0.0, [(14.0, 2.0)], to_go=coarse.distances_to)
    assert legs is not None and np.allclose(legs[0][-1], [14.0, 2.0])
    assert legs[0][:, 1].max() > 8.0 + _MARGIN
    assert grid.clearance(resample_polyline(legs[0], max_spacing_m=0.005)).min() >= _MARGIN


def test_the_distance_left_is_the_way_round_the_walls_and_infinite_where_none_joins():
    """From a goal beyond a wall to the car: within 3 % of the shortest way round the wall's end at the
    margin (between the polyline over its corners and the one a margin above them), and ∞ from a closed
    box and from inside the wall."""
    grid = _room(16.0, 10.0, walls=[(7.9, 0.0, 8.1, 8.0), (12.0, 6.0, 12.1, 9.9), (12.0, 6.0, 15.9, 6.1)])
    to_goal = CoarseGrid(grid, _MARGIN, 0.2, start=np.array([2.0, 2.0])).distances_to(np.array([14.0, 2.0]))
    d = to_goal(np.array([[2.0, 2.0], [14.0, 2.0], [14.0, 8.0], [8.0, 5.0]]))
    over_corners, above_them = 2.0 * math.hypot(5.9, 6.0) + 0.2, 2.0 * math.hypot(5.9, 6.0 + _MARGIN) + 0.2
    assert 0.97 * over_corners <= d[0] <= 1.03 * above_them
    assert d[1] == 0.0 and np.isinf(d[2:]).all()


def test_a_goal_before_a_wall_with_the_next_behind_is_arrived_at_facing_away_from_the_wall():
    """The first goal is 0.3 m short of the margin before a wall, the second back where the car came
    from: arrived at straight from the start, the car would face the wall with no room to turn; it comes
    round and arrives facing across the wall or away from it, and goes on to the second."""
    grid = _room(8.0, 8.0, walls=[(6.0, 2.5, 8.0, 5.5)])
    legs = _legs(grid, (2.0, 4.0), 0.0, [(5.4, 4.0), (2.0, 6.0)])
    assert legs is not None and len(legs) == 2 and np.allclose(legs[1][-1], [2.0, 6.0])
    arrival = legs[0][-1] - legs[0][-2]
    assert arrival[0] < 0.5 * np.linalg.norm(arrival)  # not within 60° of facing the wall
    path = np.vstack([legs[0], legs[1][1:]])
    assert grid.clearance(resample_polyline(path, max_spacing_m=0.005)).min() >= _MARGIN
