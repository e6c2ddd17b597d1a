"""`services.maps.seed.drivable_path`: a path the car can drive to its goal, searched on the grid itself."""

from __future__ import annotations

import math

import numpy as np

from schemas.occupancy import OccupancyGrid
from services.drive.controller import menger_curvature
from services.geometry import resample_polyline
from services.maps.seed import drivable_path

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


def _path(grid: OccupancyGrid, start, heading_rad: float, goal):
    lo, hi = grid.bounds()
    return drivable_path(grid, start=np.array(start), heading_rad=heading_rad, goal=np.array(goal), radius_m=1.0,
                         margin_m=_MARGIN, spacing_m=0.09, bounds_min=lo, bounds_max=hi)


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
