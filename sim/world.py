"""The simulator's ground truth: the true obstacles and the questions the run report asks of them.

The planner never sees these; it only gets what the range sensor returns. The sim uses them to cast
rays, to detect collisions (run.json status "collision") and to measure `min_clearance`.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
import shapely
from numpy.typing import ArrayLike, NDArray

from schemas.occupancy import FREE, OccupancyGrid
from services.drive.vehicle import VehicleState, footprint
from sim.sensor import Circle, Obstacle, RayTargets

FloatArray = NDArray[np.float64]


@dataclass(frozen=True, eq=False)
class World:
    """True obstacles (shapely geometries or exact `Circle`s) and the robot's footprint size."""

    obstacles: Sequence[Obstacle]
    robot_width_m: float
    robot_length_m: float
    bounds_min: tuple[float, float] | None = None
    bounds_max: tuple[float, float] | None = None
    ray_targets: RayTargets = field(init=False, repr=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "obstacles", tuple(self.obstacles))
        object.__setattr__(self, "ray_targets", RayTargets.of(self.obstacles))
        object.__setattr__(self, "_shapes", [o for o in self.obstacles if not isinstance(o, (Circle, OccupancyGrid))])
        object.__setattr__(self, "_circles", [o for o in self.obstacles if isinstance(o, Circle)])
        object.__setattr__(self, "_grids", [o for o in self.obstacles if isinstance(o, OccupancyGrid)])

    @classmethod
    def from_scenario(cls, scenario) -> World:
        """Obstacles from `scenario.obstacles[i]`: circles kept exact, occupancy grids as their cells,
        everything else via `.solid()`."""
        obstacles: list[Obstacle] = []
        for obstacle in scenario.obstacles:
            if getattr(obstacle, "type", None) == "circle":
                obstacles.append(Circle(center=tuple(obstacle.center), radius_m=float(obstacle.radius)))
            elif getattr(obstacle, "type", None) == "occupancy_grid":
                obstacles.append(obstacle.grid)
            else:
                obstacles.append(obstacle.solid())
        bounds = getattr(scenario, "bounds", None)
        return cls(
            obstacles=obstacles,
            robot_width_m=float(scenario.robot.width),
            robot_length_m=float(scenario.robot.length),
            bounds_min=tuple(map(float, bounds.min)) if bounds is not None else None,
            bounds_max=tuple(map(float, bounds.max)) if bounds is not None else None,
        )

    def clearance(self, points: ArrayLike) -> FloatArray:
        """Euclidean distance from each point to the nearest obstacle (0 inside one, inf with none)."""
        z = np.atleast_2d(np.asarray(points, dtype=float)).reshape(-1, 2)
        best = np.full(len(z), np.inf)
        if self._shapes and len(z):
            pts = shapely.points(z)
            d = shapely.distance(np.asarray(self._shapes, dtype=object)[:, None], pts[None, :])
            best = np.minimum(best, d.min(axis=0))
        for circle in self._circles:
            best = np.minimum(best, circle.distance(z))
        for grid in self._grids:
            best = np.minimum(best, grid.clearance(z))
        return best

    def footprint_clearance(self, state: VehicleState) -> float:
        """Distance from the robot's rectangle to the nearest obstacle (0 when touching or overlapping)."""
        shape = footprint(state, width_m=self.robot_width_m, length_m=self.robot_length_m)
        best = np.inf
        if self._shapes:
            best = float(np.min(shapely.distance(shape, np.asarray(self._shapes, dtype=object))))
        for circle in self._circles:
            best = min(best, max(float(shape.distance(shapely.Point(circle.center))) - circle.radius_m, 0.0))
        for grid in self._grids:
            best = min(best, _grid_footprint_clearance(grid, shape, centre=(state.x_m, state.y_m)))
        return float(best)

    def footprint_collides(self, state: VehicleState) -> bool:
        """True when the rectangle touches or overlaps any obstacle."""
        return self.footprint_clearance(state) <= 0.0

    def footprint_in_bounds(self, state: VehicleState) -> bool:
        """True when the whole rectangle lies inside the scenario's bounds (always, without bounds)."""
        if self.bounds_min is None or self.bounds_max is None:
            return True
        minx, miny, maxx, maxy = footprint(state, width_m=self.robot_width_m, length_m=self.robot_length_m).bounds
        return (minx >= self.bounds_min[0] and miny >= self.bounds_min[1]
                and maxx <= self.bounds_max[0] and maxy <= self.bounds_max[1])


def _grid_footprint_clearance(grid: OccupancyGrid, shape: shapely.Polygon, *, centre: tuple[float, float]) -> float:
    """Exact distance from the footprint to the grid's blocked squares (0 on or in one, or beyond the map).

    Candidates are the border cells (a free footprint's nearest blocked square is one, as for a point):
    a square whose centre is d from the footprint's centre is at least d − h − s√2/2 away (h the
    footprint's half-diagonal, s the cell), so only those within the nearest centre's distance plus
    2h + s√2 are measured, with shapely.
    """
    corners = np.asarray(shape.exterior.coords)[:-1]
    if np.any(grid.state_at(corners) != FREE) or np.any(grid.state_at(np.asarray(centre)[None, :]) != FREE):
        return 0.0
    tree, cells = grid._border_tree
    if tree is None:
        return float("inf")
    g = grid.to_grid(np.asarray(centre)[None, :])[0]
    half = float(np.max(np.linalg.norm(corners - np.asarray(centre), axis=1)))
    nearest = float(tree.query(g)[0])
    ball = tree.query_ball_point(g, r=nearest + 2.0 * half + grid.resolution_m * np.sqrt(2.0))
    lo = grid.to_world(cells[ball] - 0.5 * grid.resolution_m)
    hi = grid.to_world(cells[ball] + 0.5 * grid.resolution_m)
    if grid.origin_yaw_rad == 0.0:
        boxes = shapely.box(lo[:, 0], lo[:, 1], hi[:, 0], hi[:, 1])
    else:
        half_cell = 0.5 * grid.resolution_m
        offsets = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]]) * half_cell
        boxes = shapely.polygons(np.stack([grid.to_world(cells[ball] + o) for o in offsets], axis=1))
    return float(np.min(shapely.distance(shape, boxes)))
