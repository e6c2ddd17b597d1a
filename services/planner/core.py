"""The planner stage's pure core: check the straight reference (eq. 2), choose the way round globally,
refine by convex optimisation, and check the refined path exactly before anyone smooths it."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np

from cvxnav.geometry import Ellipse, EllipseStack, FloatArray
from services.planner.refine import RefineSettings, SolverFailure, refine
from services.planner.route import tangent_route


@dataclass(frozen=True)
class PathPlan:
    status: Literal["ok", "no_path"]
    points: FloatArray  # the optimised points (empty when there is no path)
    goal_indices: tuple[int, ...] = ()
    reason: str = ""
    iterations: int = 0


def intersected(points: FloatArray, ellipses: list[Ellipse], *, level: float = 1.0) -> FloatArray:
    """Indices of the ellipses a polyline enters: the paper's eq. (2), exact on every segment."""
    if not ellipses or len(points) < 2:
        return np.zeros(0, dtype=int)
    levels = EllipseStack.of(ellipses).segment_levels(points[:-1], points[1:])
    return np.flatnonzero(np.min(levels, axis=0) < level)


def plan_path(
    *,
    start: FloatArray,
    heading_rad: float | None,
    goals: FloatArray,
    ellipses: list[Ellipse],
    bounds_min: FloatArray,
    bounds_max: FloatArray,
    max_curvature: float,
    settings: RefineSettings = RefineSettings(),
) -> PathPlan:
    """Shortest drivable path start → goals (in order) outside every (grown) ellipse, or `no_path`."""
    start = np.asarray(start, dtype=float)
    goals = np.atleast_2d(np.asarray(goals, dtype=float))
    stack = EllipseStack.of(ellipses)
    if len(stack) and np.min(stack.levels(np.vstack([start, goals]))) < 1.0:
        inside = "start" if np.min(stack.levels(start)) < 1.0 else "a goal"
        return PathPlan("no_path", np.zeros((0, 2)), reason=f"{inside} lies inside an obstacle's grown ellipse")
    reference = np.vstack([start, goals])
    if len(intersected(reference, ellipses, level=settings.level)) == 0:
        legs = [reference[k : k + 2] for k in range(len(goals))]
    else:
        legs = tangent_route(
            start=start,
            goals=goals,
            ellipses=ellipses,
            bounds_min=bounds_min,
            bounds_max=bounds_max,
            level=settings.level,
        )
    if legs is None:
        return PathPlan("no_path", np.zeros((0, 2)), reason="every route to the goals is blocked")
    try:
        refined = refine(
            legs=legs,
            ellipses=ellipses,
            bounds_min=bounds_min,
            bounds_max=bounds_max,
            max_curvature=max_curvature,
            heading_rad=heading_rad,
            settings=settings,
        )
    except SolverFailure as failure:
        return PathPlan("no_path", np.zeros((0, 2)), reason=str(failure))
    if len(intersected(refined.points, ellipses)):
        return PathPlan("no_path", np.zeros((0, 2)), reason="refined path enters an ellipse")
    return PathPlan("ok", refined.points, refined.goal_indices, iterations=refined.iterations)
