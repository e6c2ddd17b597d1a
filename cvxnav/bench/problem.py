"""The one obstacle model every planner in the benchmark is given, and the checks every answer gets.

The model is cvxnav's own known-map fit (`cvxnav.plan.fit_known_obstacles`) grown by width/2 + safety
distance, so no planner is judged against a different world than the one it was handed. Answers are
judged twice: against that model (exact segment test, `EllipseStack.segment_levels`) and against the
TRUE obstacles (`Scenario.clearance` on the densely resampled path), which is what a robot would hit.
"""

from __future__ import annotations

import json
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from schemas.scenario import Scenario
from services.geometry import Ellipse, EllipseStack, FloatArray, polyline_length, resample_polyline

# The true-geometry check allows this much less than width/2 + safety: the grown ellipses are built
# from a 16-gon cover of each circle, so a path hugging one may sit a few mm inside the exact margin.
COLLISION_TOLERANCE_M = 0.02


class _NoClock:
    """Stands in for the pipeline's stage clock: the benchmark times whole calls itself."""

    @contextmanager
    def stage(self, name: str) -> Iterator[None]:
        yield


@dataclass(frozen=True)
class BenchProblem:
    """One scenario as every planner sees it: start, goals in order, bounds and the grown ellipses."""

    scenario: Scenario
    grown: list[Ellipse]

    @classmethod
    def of(cls, scenario: Scenario) -> BenchProblem:
        from cvxnav.plan import PlanSettings, fit_known_obstacles

        raw, _ = fit_known_obstacles(scenario, settings=PlanSettings(), clock=_NoClock())
        return cls(scenario=scenario, grown=[e.grown(scenario.inflation_m) for e in raw])

    @property
    def name(self) -> str:
        return self.scenario.name

    @property
    def start(self) -> FloatArray:
        return np.array(self.scenario.start.xy, dtype=float)

    @property
    def goals(self) -> FloatArray:
        return self.scenario.goals_array

    @property
    def bounds_min(self) -> FloatArray:
        return np.array(self.scenario.bounds.min, dtype=float)

    @property
    def bounds_max(self) -> FloatArray:
        return np.array(self.scenario.bounds.max, dtype=float)

    @property
    def stack(self) -> EllipseStack:
        return EllipseStack.of(self.grown)

    def legs(self) -> list[tuple[FloatArray, FloatArray]]:
        """(from, to) of each leg: start → goal₁ → goal₂ … (sampling planners plan each leg alone)."""
        waypoints = np.vstack([self.start, self.goals])
        return [(waypoints[k], waypoints[k + 1]) for k in range(len(self.goals))]


@dataclass(frozen=True)
class PathCheck:
    """What a returned path is worth: its length, its worst true clearance, whether it counts."""

    length_m: float
    min_clearance_m: float
    collides: bool  # closer than width/2 + safety − COLLISION_TOLERANCE_M to a true obstacle
    reaches_goals: bool
    min_model_level: float  # min ‖A z + b‖ over the path's segments and the grown ellipses (< 1: inside)


def check_path(problem: BenchProblem, path: FloatArray, *, spacing_m: float = 0.02) -> PathCheck:
    """Judge a polyline on the true geometry (dense samples) and on the grown-ellipse model (exact)."""
    path = np.asarray(path, dtype=float)
    scenario = problem.scenario
    dense = resample_polyline(path, max_spacing_m=spacing_m)
    clearance = float(np.min(scenario.clearance(dense))) if scenario.obstacles else float("inf")
    stack = problem.stack
    level = float(np.min(stack.segment_levels(path[:-1], path[1:]))) if len(stack) and len(path) > 1 else np.inf
    # Goals in order, each within the scenario's tolerance of some later point than the previous one.
    reached, cursor = True, 0
    for goal in problem.goals:
        hits = np.flatnonzero(np.linalg.norm(dense[cursor:] - goal, axis=1) <= scenario.goal_tolerance)
        if not len(hits):
            reached = False
            break
        cursor += int(hits[0])
    starts_right = bool(np.linalg.norm(path[0] - problem.start) <= 1e-6)
    return PathCheck(
        length_m=polyline_length(path),
        min_clearance_m=clearance,
        collides=clearance < scenario.inflation_m - COLLISION_TOLERANCE_M,
        reaches_goals=reached and starts_right,
        min_model_level=level,
    )


def reference_lengths(path: Path) -> dict[str, float]:
    """REFERENCE.json's true-geometry optima by scenario name (empty when the file is absent)."""
    if not path.is_file():
        return {}
    return {str(k): float(v) for k, v in json.loads(path.read_text(encoding="utf-8"))["optimal_length"].items()}
