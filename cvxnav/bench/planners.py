"""Every planner the benchmark compares, each behind the same small call: problem in, `Attempt` out.

cvxnav and the optimum run on this package alone. OMPL and Drake come from the optional extra
`bench` (`pip install -e ".[bench]"`) and are imported inside their functions, so `cvxnav` itself
never needs them; `peer_status()` says which are importable and why not.

All planners get the same grown ellipses (`BenchProblem.grown`). Only cvxnav also honours the start
heading and the car's curvature bound; the others plan for a point that may turn on the spot, so
their lengths are lower bounds on what a car could drive — the table says so.
"""

from __future__ import annotations

import importlib
import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Literal

import numpy as np

from cvxnav.bench.problem import BenchProblem
from services.geometry import Ellipse, EllipseStack, FloatArray, joined_legs, polyline_length, resample_polyline


@dataclass(frozen=True)
class Attempt:
    """One call of one planner: its path (None on failure) and how long it took."""

    path: FloatArray | None
    time_s: float  # the planner's planning time (what each planner's time means: `PlannerSpec.time_meaning`)
    reason: str = ""
    first_solution_s: float | None = None  # sampling planners: time until some path existed
    target_s: float | None = None  # sampling planners: time until the path was within the target factor
    extra: dict[str, float] = field(default_factory=dict)


def peer_status() -> dict[str, str]:
    """'' for each importable peer package, else the one-line reason it is skipped."""
    status = {}
    for name, module in (("ompl", "ompl.geometric"), ("drake", "pydrake.planning")):
        try:
            importlib.import_module(module)
            status[name] = ""
        except Exception as error:  # ImportError, or a broken binary wheel
            status[name] = f"{name} not importable ({type(error).__name__}: {error}); install the extra: pip install -e \".[bench]\""
    return status


# --------------------------------------------------------------------------- cvxnav


def forget_kept() -> None:
    """Drop what cvxnav keeps between plans in a process (the ellipse stacks, the refinement's compiled
    subproblems), so that a timed call builds them as a new query does."""
    from services.planner.refine import forget_problems

    EllipseStack.forget()
    forget_problems()


def plan_cvxnav(problem: BenchProblem) -> Attempt:
    """cvxnav's planning on the model every planner is handed: optimise + smooth (`cvxnav.plan.plan_on_model`,
    the planning half of `cvxnav plan`), the smoothed curve verified or no path.

    Timed as the peers are, on `problem.grown` (the fit excluded), building the planner's arrays of the
    ellipses (`EllipseStack`) and its convex subproblems included: the stacks and compiled subproblems
    kept from the last call are dropped first (the peers set their planners up afresh on each call too).
    """
    from cvxnav.plan import plan_on_model
    from services.planner.core import why_no_path

    forget_kept()
    t0 = time.perf_counter()
    plan, smoothed = plan_on_model(problem.scenario, problem.grown)
    elapsed = time.perf_counter() - t0
    if smoothed is None or not smoothed.verification.ok:
        why = why_no_path(plan, smoothed, max_curvature=problem.scenario.max_curvature,
                          goals=problem.scenario.goals_array)
        return Attempt(path=None, time_s=elapsed, reason=f"cvxnav: no_path ({why})")
    return Attempt(path=smoothed.points, time_s=elapsed)


def plan_optimum(problem: BenchProblem) -> Attempt:
    """The exact shortest path outside the grown ellipses (point robot): cvxnav's own route search.

    `services.planner.route.shortest_route` at level 1: the exact tangent graph of the ellipses
    (common tangents, tangents from the terminals, free boundary arcs), so its length — tangents plus
    elliptic arcs, in `extra` per leg — is the model's optimum. The path returned draws each arc as
    a circumscribed polyline, a little longer than the arc (≤ 1/cos(π/32) − 1) and still outside.
    """
    from services.planner.route import shortest_route

    t0 = time.perf_counter()
    route = shortest_route(
        start=problem.start,
        goals=problem.goals,
        ellipses=problem.grown,
        bounds_min=problem.bounds_min,
        bounds_max=problem.bounds_max,
        level=1.0,
    )
    elapsed = time.perf_counter() - t0
    if route is None:
        return Attempt(path=None, time_s=elapsed, reason="tangent graph: no route")
    path = joined_legs(route.legs)
    return Attempt(path=path, time_s=elapsed, extra={f"leg{k}_m": length for k, length in enumerate(route.lengths_m)})


# --------------------------------------------------------------------------- the paper, as written


def _detour(p: FloatArray, q: FloatArray, ellipse: Ellipse, *, arc_step_rad: float) -> FloatArray | None:
    """Points p, (arc round the ellipse on the shorter side), q — or None when p→q misses it or p is inside.

    In the unit-disc frame u = A z + b the segment is u₀ + t v; it crosses the circle at the roots
    t₁ < t₂ of ‖u₀ + t v‖² = 1. The detour follows the circle from the entry angle to the exit angle the
    short way round, at radius 1/cos(step/2) so that every chord of it stays outside the ellipse.
    """
    A, b = ellipse.A, ellipse.b
    u0, v = A @ p + b, A @ (q - p)
    a, half_b, c = v @ v, u0 @ v, u0 @ u0 - 1.0
    disc = half_b * half_b - a * c
    if a <= 0.0 or disc <= 0.0 or c <= 0.0:
        return None
    t1, t2 = (-half_b - np.sqrt(disc)) / a, (-half_b + np.sqrt(disc)) / a
    if t1 >= 1.0 or t2 <= 0.0:
        return None
    theta1 = np.arctan2(*(u0 + t1 * v)[::-1])
    theta2 = np.arctan2(*(u0 + t2 * v)[::-1])
    delta = (theta2 - theta1 + np.pi) % (2.0 * np.pi) - np.pi  # the shorter way round
    steps = max(1, int(np.ceil(abs(delta) / arc_step_rad)))
    angles = theta1 + delta * np.linspace(0.0, 1.0, steps + 1)
    rho = 1.0 / np.cos(abs(delta) / steps / 2.0)
    u = rho * np.column_stack([np.cos(angles), np.sin(angles)])
    arc = np.linalg.solve(A, (u - b).T).T
    return np.vstack([p, arc, q])


def plan_paper(problem: BenchProblem, *, arc_step_rad: float = np.pi / 16, max_passes: int = 64) -> Attempt:
    """The seed paper's method as written: straight reference, local detours, then an unverified Bézier.

    Check the straight line start → goals against every ellipse (eq. 2); replace the first crossing by
    a detour round that ellipse on its shorter side; repeat. No global choice of side and no check of
    the smoothed curve: the piecewise-Bézier (eq. 5, `services.smoother.core.bspline`) over the
    detoured points is returned as it is — the true-geometry check decides whether it counts.
    """
    from services.smoother.core import bspline, sample

    t0 = time.perf_counter()
    stack = problem.stack
    path = np.vstack([problem.start, problem.goals])
    reason = ""
    for _ in range(max_passes):
        if not len(stack):
            break
        levels = stack.segment_levels(path[:-1], path[1:])
        crossings = np.argwhere(levels < 1.0)
        if not len(crossings):
            break
        seg, j = crossings[0]
        # The first ellipse along that segment: the one whose closest point comes earliest is close
        # enough to the paper's left-to-right treatment.
        detour = _detour(path[seg], path[seg + 1], problem.grown[j], arc_step_rad=arc_step_rad)
        if detour is None:
            reason = "a detour starts inside another obstacle's ellipse"
            break
        path = np.vstack([path[:seg], detour, path[seg + 2 :]])
    else:
        reason = f"still crossing an ellipse after {max_passes} detours"
    control = resample_polyline(path, max_spacing_m=0.1)
    curve = sample(bspline(control), spacing_m=0.05)
    return Attempt(path=curve, time_s=time.perf_counter() - t0, reason=reason)


# --------------------------------------------------------------------------- OMPL


SamplingPlanner = Literal["BITstar", "InformedRRTstar"]


def plan_ompl(
    problem: BenchProblem,
    *,
    planner: SamplingPlanner,
    budget_s: float,
    leg_optima_m: list[float],
    target_factor: float = 1.01,
) -> Attempt:
    """OMPL's asymptotically optimal planner on R², valid = outside every grown ellipse, leg by leg.

    Each leg gets the budget and the objective's cost threshold target_factor × that leg's optimum, so
    the planner stops as soon as it is within 1 % (OMPL's `isSatisfied`), or when the budget runs out.
    States are checked by ‖A z + b‖ ≥ 1 and motions exactly by the segment test (a Python
    `MotionValidator`, not OMPL's sampled one), both by `EllipseStack` as cvxnav checks its straight
    line: numpy calls from C++, so OMPL's times include that callback overhead. The time is the time
    to the target (the budget when it was not reached); `first_solution_s` is the time to the first
    path. Both sum over legs, which run one after another, and both include building the checkers'
    arrays of the ellipses, as cvxnav's time includes its own.
    """
    from ompl import base as ob
    from ompl import geometric as og
    from ompl import util as ou

    ou.setLogLevel(ou.LOG_NONE)
    EllipseStack.forget()  # the checkers' arrays are built from the model inside the time, as cvxnav's are
    t0 = time.perf_counter()
    stack = problem.stack
    arrays_s = time.perf_counter() - t0

    def valid(state) -> bool:
        return bool(stack.levels((state[0], state[1])).min() >= 1.0)

    class ExactMotion(ob.MotionValidator):
        """p→q is valid when min over t of ‖A (p + t (q − p)) + b‖ ≥ 1 for every ellipse (eq. 2, exact)."""

        def checkMotion(self, s1, s2, *rest) -> bool:  # noqa: N802 (OMPL's name)
            return stack.polyline_level(((s1[0], s1[1]), (s2[0], s2[1]))) >= 1.0

    legs = problem.legs()
    total_s = first_s = target_s = arrays_s
    reached = True
    path: list[FloatArray] = []
    for (p, q), leg_optimum in zip(legs, leg_optima_m):
        t0 = time.perf_counter()
        space = ob.RealVectorStateSpace(2)
        box = ob.RealVectorBounds(2)
        for axis in range(2):
            box.setLow(axis, float(problem.bounds_min[axis]))
            box.setHigh(axis, float(problem.bounds_max[axis]))
        space.setBounds(box)
        si = ob.SpaceInformation(space)
        si.setStateValidityChecker(valid)
        si.setMotionValidator(ExactMotion(si))
        si.setup()
        start, goal = si.allocState(), si.allocState()
        start[0], start[1] = float(p[0]), float(p[1])
        goal[0], goal[1] = float(q[0]), float(q[1])
        pdef = ob.ProblemDefinition(si)
        pdef.setStartAndGoalStates(start, goal)
        objective = ob.PathLengthOptimizationObjective(si)
        objective.setCostThreshold(ob.Cost(target_factor * leg_optimum))
        pdef.setOptimizationObjective(objective)
        algorithm = getattr(og, planner)(si)
        algorithm.setProblemDefinition(pdef)
        algorithm.setup()
        first: list[float] = []

        def stop() -> bool:
            # Polled by the planner between iterations: notes when the first path appears, and ends the
            # run at the budget. The planner itself stops once the objective's threshold is met.
            now = time.perf_counter() - t0
            if not first and np.isfinite(algorithm.bestCost().value()):
                first.append(now)
            return now >= budget_s

        algorithm.solve(ob.PlannerTerminationCondition(stop))
        solved = pdef.hasExactSolution()
        # Timed until the path is read out into an array, as cvxnav's time includes producing its points.
        leg = np.array([[s[0], s[1]] for s in pdef.getSolutionPath().getStates()]) if solved else None
        elapsed = time.perf_counter() - t0
        if leg is None:
            return Attempt(path=None, time_s=total_s + elapsed, reason=f"{planner}: no path in {budget_s:g} s")
        path.append(leg)
        first_s += first[0] if first else elapsed
        hit = elapsed if polyline_length(leg) <= target_factor * leg_optimum else None
        reached &= hit is not None
        target_s += hit if hit is not None else elapsed
        total_s += elapsed
    return Attempt(
        path=joined_legs(path),
        time_s=target_s,
        first_solution_s=first_s,
        target_s=target_s if reached else None,
        reason="" if reached else f"{planner}: not within {100 * (target_factor - 1):g} % of the optimum in {budget_s:g} s",
    )


# --------------------------------------------------------------------------- Drake


def plan_drake_gcs(
    problem: BenchProblem,
    *,
    max_regions: int,
    seed: int,
    obstacle_shape: Literal["ellipses", "polygons"] = "ellipses",
    polygon_sides: int = 32,
    max_misses: int = 200,
) -> Attempt:
    """Drake: IRIS regions of the free space round the grown ellipses, then a GCS shortest path.

    Regions (Deits & Tedrake 2014, `pydrake.geometry.optimization.Iris`) are seeded at the start, each
    goal, then at seeded random free points not yet covered, until `max_regions` or `max_misses`
    samples in a row fall in covered space. Regions that intersect are joined; `GcsTrajectoryOptimization`
    (Marcucci et al. 2023) with first-order (straight) pieces and a path-length cost solves each leg by
    its convex relaxation and rounding. Time = IRIS + GCS; a leg that GCS does not solve is a failure.

    `obstacle_shape="ellipses"` hands IRIS the grown ellipses themselves (`Hyperellipsoid`); with the
    open solvers Drake has here (Clarabel; MOSEK is unlicensed) its "minimum uniform scaling to touch"
    SOCP often fails on them. `"polygons"` hands it `polygon_sides`-gons circumscribing each grown
    ellipse instead (at most 1/cos(π/sides) − 1 larger, 0.5 % for 32): a slightly bigger model, so its
    paths are still feasible in ours, and IRIS then needs only linear constraints.
    """
    from pydrake.geometry.optimization import (
        GraphOfConvexSetsOptions,
        HPolyhedron,
        Hyperellipsoid,
        Iris,
        IrisOptions,
        Point,
        VPolytope,
    )
    from pydrake.planning import GcsTrajectoryOptimization

    logging.getLogger("drake").setLevel(logging.WARNING)
    t0 = time.perf_counter()
    stack = problem.stack
    if obstacle_shape == "ellipses":
        obstacles = [Hyperellipsoid(e.A, e.center) for e in problem.grown]
    else:
        angles = 2.0 * np.pi * np.arange(polygon_sides) / polygon_sides
        unit = np.column_stack([np.cos(angles), np.sin(angles)]) / np.cos(np.pi / polygon_sides)
        obstacles = [HPolyhedron(VPolytope(np.linalg.solve(e.A, (unit - e.b).T))) for e in problem.grown]
    domain = HPolyhedron.MakeBox(problem.bounds_min, problem.bounds_max)
    options = IrisOptions()
    rng = np.random.default_rng(seed)
    regions = []
    seeds: list[FloatArray] = [problem.start, *problem.goals]
    misses = 0
    try:
        while len(regions) < max_regions and misses < max_misses:
            if seeds:
                sample = seeds.pop(0)
            else:
                sample = rng.uniform(problem.bounds_min, problem.bounds_max)
                free = not len(stack) or np.min(stack.levels(sample)) >= 1.0
                if not free or any(region.PointInSet(sample) for region in regions):
                    misses += 1
                    continue
                misses = 0
            regions.append(Iris(obstacles, sample, domain, options))
        iris_s = time.perf_counter() - t0
        edges = [
            (i, j) for i in range(len(regions)) for j in range(len(regions)) if i != j and regions[i].IntersectsWith(regions[j])
        ]
        path: list[FloatArray] = []
        for p, q in problem.legs():
            gcs = GcsTrajectoryOptimization(2)
            free = gcs.AddRegions(regions, edges, order=1, name="free")
            source = gcs.AddRegions([Point(p)], order=0, name="source")
            target = gcs.AddRegions([Point(q)], order=0, name="target")
            gcs.AddEdges(source, free)
            gcs.AddEdges(free, target)
            gcs.AddPathLengthCost()
            gcs_options = GraphOfConvexSetsOptions()
            gcs_options.max_rounded_paths = 10
            trajectory, result = gcs.SolvePath(source, target, gcs_options)
            if not result.is_success():
                return Attempt(
                    path=None,
                    time_s=time.perf_counter() - t0,
                    reason=f"GCS: {result.get_solution_result().name} with {len(regions)} IRIS regions",
                )
            corners = [trajectory.segment(k).control_points().T for k in range(trajectory.get_number_of_segments())]
            leg = np.vstack(corners)
            keep = np.concatenate([[True], np.linalg.norm(np.diff(leg, axis=0), axis=1) > 1e-9])
            leg = leg[keep]
            path.append(leg)
    except RuntimeError as error:  # Drake reports solver and IRIS failures as RuntimeError
        return Attempt(path=None, time_s=time.perf_counter() - t0, reason=" ".join(f"Drake: {error}".split())[:160])
    return Attempt(
        path=joined_legs(path),
        time_s=time.perf_counter() - t0,
        extra={"iris_ms": 1e3 * iris_s, "regions": float(len(regions))},
    )


PlannerFn = Callable[[BenchProblem, int], Attempt]
