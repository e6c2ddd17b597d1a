"""The true map as a `World` message: what the sim tells the monitor, never the planning stages."""

from __future__ import annotations

from schemas.messages import CircleMsg, Header, Pose2D, World
from schemas.scenario import Scenario


def world_message(scenario: Scenario, *, stamp_s: float = 0.0) -> World:
    """Outlines of every true obstacle (circles exact, point sets as their convex hull, a map's occupied
    cells as rectangles)."""
    polygons: list[list[tuple[float, float]]] = []
    circles: list[CircleMsg] = []
    for obstacle in scenario.obstacles:
        if obstacle.type == "circle":
            circles.append(CircleMsg(center=tuple(obstacle.center), radius_m=float(obstacle.radius)))
        elif obstacle.type == "polygon":
            polygons.append([(float(x), float(y)) for x, y in obstacle.vertices])
        elif obstacle.type == "occupancy_grid":  # its occupied cells, as rectangles (unknown ones left out)
            polygons += [[(float(x), float(y)) for x, y in box] for box in obstacle.grid.rectangles()]
        else:
            polygons.append([(float(x), float(y)) for x, y in obstacle.cover_vertices()])
    return World(
        header=Header(stamp_s=stamp_s, seq=0),
        scenario=scenario.name,
        bounds_min=tuple(scenario.bounds.min),
        bounds_max=tuple(scenario.bounds.max),
        robot_width_m=scenario.robot.width,
        robot_length_m=scenario.robot.length,
        start=Pose2D(x_m=scenario.start.x, y_m=scenario.start.y, theta_rad=scenario.start.theta),
        goals=[(float(x), float(y)) for x, y in scenario.goals],
        goal_tolerance_m=scenario.goal_tolerance,
        polygons=polygons,
        circles=circles,
    )
