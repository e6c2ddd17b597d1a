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
        object.__setattr__(self, "_shapes", [o for o in self.obstacles if not isinstance(o, Circle)])
        object.__setattr__(self, "_circles", [o for o in self.obstacles if isinstance(o, Circle)])

    @classmethod
    def from_scenario(cls, scenario) -> World:
        """Obstacles from `scenario.obstacles[i]`: circles kept exact, everything else via `.solid()`."""
        obstacles: list[Obstacle] = []
        for obstacle in scenario.obstacles:
            if getattr(obstacle, "type", None) == "circle":
                obstacles.append(Circle(center=tuple(obstacle.center), radius_m=float(obstacle.radius)))
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
        return best

    def footprint_clearance(self, state: VehicleState) -> float:
        """Distance from the robot's rectangle to the nearest obstacle (0 when touching or overlapping)."""
        shape = footprint(state, width_m=self.robot_width_m, length_m=self.robot_length_m)
        best = np.inf
        if self._shapes:
            best = float(np.min(shapely.distance(shape, np.asarray(self._shapes, dtype=object))))
        for circle in self._circles:
            best = min(best, max(float(shape.distance(shapely.Point(circle.center))) - circle.radius_m, 0.0))
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
