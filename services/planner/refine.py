"""Shortest smooth path outside the ellipses by sequential convex programming (paper eq. 4).

The paper's problem

    minimise   Σᵢ ‖zᵢ₊₁ − zᵢ‖²
    subject to ‖Aⱼ zᵢ + bⱼ‖ ≥ 1      (outside every ellipse)
               ‖zᵢ₊₁ − zᵢ‖ ≤ 0.1     (step bound; the paper writes a one-sided per-axis bound, a slip)
               z₀ = current position, goals at fixed indices

is not convex: the outside constraint is the complement of a convex set. The convex feasible set method
(Liu, Lin & Tomizuka, the paper's ref. [6]) replaces it at the current iterate z̄ by a half-plane: with
n = (A z̄ + b)/‖A z̄ + b‖, ‖A z + b‖ ≥ nᵀ(A z + b), so nᵀ(A z + b) ≥ 1 implies the true constraint. The
half-plane is an inner approximation, so every iterate stays outside every ellipse and the length never
increases. Which side of each obstacle to pass is fixed by the initial route (`route.py`), chosen globally.

Two additions make the result drivable by a car: the start heading (z₁ − z₀ parallel to it) and a
curvature bound written as a second-order cone, ‖zᵢ₊₁ − 2zᵢ + zᵢ₋₁‖ ≤ κ s², which bounds the curvature
of points at least s apart (turning by φ over steps ≥ s gives ‖Δ²z‖ ≳ s φ and curvature ≈ φ / s). So
that the optimiser cannot earn a sharper turn by shortening steps, each step keeps a length of at
least lᵢ (a fixed fraction of its previous length) through the linearised dᵢᵀ(zᵢ₊₁ − zᵢ) ≥ lᵢ (dᵢ the
step's previous direction: again an inner approximation of ‖zᵢ₊₁ − zᵢ‖ ≥ lᵢ); the curvature budget at a
point uses the shorter of its two previous steps, and iterations continue until the curvature measured
with the actual spacing meets the bound. The curvature cone carries a penalised slack so every subproblem
is feasible and an unattainable bound shows up as slack rather than as a solver failure.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import cvxpy as cp
import numpy as np

from cvxnav.geometry import Ellipse, EllipseStack, FloatArray, polyline_length

_OK = (cp.OPTIMAL, cp.OPTIMAL_INACCURATE)


class SolverFailure(RuntimeError):
    """A convex subproblem did not solve to optimality."""


@dataclass(frozen=True)
class RefineSettings:
    step_m: float = 0.1  # the paper's step bound
    spacing_m: float = 0.08  # target point spacing: leaves the step bound room for the path to lengthen
    level: float = 1.02  # ‖A z + b‖ the refined points keep: margin for the smoothed curve
    curvature_factor: float = 0.9  # plan to this fraction of the car's curvature bound
    step_shrink: float = 0.8  # a step may shrink to this fraction of its length per iteration
    curvature_met_factor: float = 0.97  # converged once the actual curvature is within this of the bound
    min_iterations_unmet: int = 8  # iterations to spend on an unmet curvature bound before giving up
    slots: int = 8  # nearest ellipses linearised at each point
    trust_region_m: float = 0.5  # per-iteration move bound: keeps far ellipses out of reach
    max_iterations: int = 25
    rel_tolerance: float = 1e-5
    slack_weight: float = 1e3
    solver: str = "CLARABEL"


@dataclass(frozen=True)
class Refined:
    points: FloatArray
    goal_indices: tuple[int, ...]
    iterations: int
    curvature_slack: float


class _PathProblem:
    """The convex subproblem for n points and k linearised ellipses per point, built once (DPP).

    Every piece of data that changes between solves (fixed points, heading, half-planes, trust region,
    curvature budget, bounds) is a `cp.Parameter`, so cvxpy canonicalises once and each re-solve only
    rewrites numbers into Clarabel's matrices.
    """

    def __init__(self, n: int, slots: int, step_m: float, slack_weight: float) -> None:
        self.n, self.slots = n, slots
        self.z = cp.Variable((n, 2))
        self.slack = cp.Variable(n - 2, nonneg=True)
        self.fix_mask = cp.Parameter(n, nonneg=True)  # 1 where the point is pinned (start, goals)
        self.fix_x = cp.Parameter(n)  # mask · pinned x
        self.fix_y = cp.Parameter(n)
        self.heading = cp.Parameter(2)
        self.heading_normal = cp.Parameter(2)
        self.gx = [cp.Parameter(n) for _ in range(slots)]
        self.gy = [cp.Parameter(n) for _ in range(slots)]
        self.h = [cp.Parameter(n) for _ in range(slots)]
        self.center = cp.Parameter((n, 2))
        self.trust = cp.Parameter(nonneg=True)
        self.curvature_budget = cp.Parameter(n - 2, nonneg=True)
        self.step_direction = cp.Parameter((n - 1, 2))
        self.step_floor = cp.Parameter(n - 1)
        self.lo = cp.Parameter(2)
        self.hi = cp.Parameter(2)
        z = self.z
        first_step = z[1] - z[0]
        diff = z[1:] - z[:-1]
        second = z[2:] - 2 * z[1:-1] + z[:-2]
        constraints = [
            cp.multiply(self.fix_mask, z[:, 0]) == self.fix_x,
            cp.multiply(self.fix_mask, z[:, 1]) == self.fix_y,
            self.heading_normal @ first_step == 0,
            self.heading @ first_step >= 0,
            *(
                cp.multiply(gx, z[:, 0]) + cp.multiply(gy, z[:, 1]) >= h
                for gx, gy, h in zip(self.gx, self.gy, self.h)
            ),
            cp.norm(diff, 2, axis=1) <= step_m,
            cp.sum(cp.multiply(self.step_direction, diff), axis=1) >= self.step_floor,
            cp.norm(second, 2, axis=1) <= self.curvature_budget + self.slack,
            cp.abs(z - self.center) <= self.trust,
            *(z[:, axis] >= self.lo[axis] for axis in range(2)),
            *(z[:, axis] <= self.hi[axis] for axis in range(2)),
        ]
        objective = cp.sum_squares(diff) + slack_weight * cp.sum(self.slack)
        self.problem = cp.Problem(cp.Minimize(objective), constraints)


@lru_cache(maxsize=16)
def _problem(n: int, slots: int, step_m: float, slack_weight: float) -> _PathProblem:
    return _PathProblem(n, slots, step_m, slack_weight)


def _bucket(n: int) -> int:
    """Round the point count up so that problems of similar length share one compiled problem."""
    return int(32 * np.ceil(n / 32))


def resample_legs(legs: list[FloatArray], *, n: int) -> tuple[FloatArray, tuple[int, ...]]:
    """Resample consecutive legs (each a polyline) to `n` points in all, in proportion to leg length."""
    lengths = np.array([max(polyline_length(leg), 1e-9) for leg in legs])
    counts = np.maximum(1, np.round((n - 1) * lengths / lengths.sum()).astype(int))
    counts[-1] = (n - 1) - counts[:-1].sum()
    if counts[-1] < 1:
        raise ValueError("too few points for the number of legs")
    out = [legs[0][:1]]
    goal_indices = []
    for leg, count in zip(legs, counts):
        seg = np.linalg.norm(np.diff(leg, axis=0), axis=1)
        s = np.concatenate([[0.0], np.cumsum(seg)])
        targets = np.linspace(0.0, s[-1], count + 1)[1:]
        out.append(np.column_stack([np.interp(targets, s, leg[:, 0]), np.interp(targets, s, leg[:, 1])]))
        goal_indices.append(sum(len(o) for o in out) - 1)
    return np.vstack(out), tuple(goal_indices)


def _linearise(
    z: FloatArray, stack: EllipseStack, centers: FloatArray, reach: FloatArray, *, slots: int, level: float, trust_m: float
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Half-planes nᵀ(A z + b) ≥ level at each point for its nearest ellipses (unused slots: 0 ≥ −1)."""
    n = len(z)
    gx = np.zeros((n, slots))
    gy = np.zeros((n, slots))
    h = np.full((n, slots), -1.0)
    if len(stack) == 0:
        return gx, gy, h
    # Lower bound on the Euclidean distance to each ellipse: centre distance minus largest semi-axis.
    near = np.linalg.norm(z[:, None, :] - centers[None, :, :], axis=2) - reach[None, :]
    k = min(slots, len(stack))
    order = np.argsort(near, axis=1)[:, :k]
    within = np.zeros((n, slots), dtype=bool)
    within[:, :k] = near[np.arange(n)[:, None], order] <= 2.0 * trust_m + 0.5
    A = stack.A[order]  # (n, k, 2, 2)
    b = stack.b[order]  # (n, k, 2)
    u = np.einsum("nkij,nj->nki", A, z) + b
    normal = u / np.linalg.norm(u, axis=2, keepdims=True)
    g = np.einsum("nkij,nki->nkj", A, normal)  # Aᵀ n
    gx[:, :k], gy[:, :k] = g[..., 0], g[..., 1]
    h[:, :k] = level - np.einsum("nki,nki->nk", normal, b)
    gx[~within], gy[~within], h[~within] = 0.0, 0.0, -1.0
    return gx, gy, h


def _curvature_met(z: FloatArray, kappa: float) -> bool:
    """Whether the discrete curvature of the points, measured with their actual spacing, is within kappa."""
    step = np.linalg.norm(np.diff(z, axis=0), axis=1)
    second = np.linalg.norm(z[2:] - 2 * z[1:-1] + z[:-2], axis=1)
    return bool(np.all(second <= kappa * np.minimum(step[:-1], step[1:]) ** 2 * (1 + 1e-3) + 1e-9))


def refine(
    *,
    legs: list[FloatArray],
    ellipses: list[Ellipse],
    bounds_min: FloatArray,
    bounds_max: FloatArray,
    max_curvature: float,
    heading_rad: float | None = None,
    settings: RefineSettings = RefineSettings(),
) -> Refined:
    """Refine a route (one polyline per leg, start → goal₁ → …) into the shortest drivable path.

    Raises `SolverFailure` if a subproblem fails; the caller verifies the result either way.
    """
    total = sum(polyline_length(leg) for leg in legs)
    n = _bucket(int(np.ceil(total / settings.spacing_m)) + 1)
    z, goal_indices = resample_legs(legs, n=n)
    stack = EllipseStack.of(ellipses)
    centers = np.array([e.center for e in ellipses]).reshape(-1, 2)
    reach = np.array([e.semi_axes[0] for e in ellipses])
    pb = _problem(n, settings.slots, settings.step_m, settings.slack_weight)

    mask = np.zeros(n)
    mask[0] = 1.0
    mask[list(goal_indices)] = 1.0
    pb.fix_mask.value = mask
    pb.fix_x.value = mask * z[:, 0]
    pb.fix_y.value = mask * z[:, 1]
    if heading_rad is None:
        pb.heading.value = np.zeros(2)
        pb.heading_normal.value = np.zeros(2)
    else:
        pb.heading.value = np.array([np.cos(heading_rad), np.sin(heading_rad)])
        pb.heading_normal.value = np.array([-np.sin(heading_rad), np.cos(heading_rad)])
    pb.trust.value = settings.trust_region_m
    pb.lo.value = np.asarray(bounds_min, dtype=float)
    pb.hi.value = np.asarray(bounds_max, dtype=float)
    kappa = settings.curvature_factor * max_curvature

    previous = np.inf
    iterations = 0
    for iterations in range(1, settings.max_iterations + 1):
        gx, gy, h = _linearise(
            z, stack, centers, reach, slots=settings.slots, level=settings.level, trust_m=settings.trust_region_m
        )
        for slot in range(settings.slots):
            pb.gx[slot].value, pb.gy[slot].value, pb.h[slot].value = gx[:, slot], gy[:, slot], h[:, slot]
        pb.center.value = z
        delta = np.diff(z, axis=0)
        step = np.linalg.norm(delta, axis=1)
        floor = settings.step_shrink * step
        pb.step_direction.value = delta / np.maximum(step, 1e-12)[:, None]
        pb.step_floor.value = floor
        pb.curvature_budget.value = kappa * np.minimum(step[:-1], step[1:]) ** 2
        # The problem is built once per size, but canonicalised afresh each solve: cvxpy's DPP compile
        # of this problem grows quadratically with n (1.7 s at n = 416, measured), while a fresh
        # canonicalisation plus Clarabel takes 45-80 ms, and a plan needs only a handful of iterations.
        pb.problem.solve(solver=settings.solver, ignore_dpp=True)
        if pb.problem.status not in _OK:
            raise SolverFailure(f"path subproblem {iterations}: solver status {pb.problem.status}")
        z = pb.z.value
        cost = float(pb.problem.value)
        stalled = previous - cost <= settings.rel_tolerance * max(abs(cost), 1e-9)
        met = _curvature_met(z, settings.curvature_met_factor * max_curvature)
        if stalled and (met or iterations >= settings.min_iterations_unmet):
            break
        previous = cost
    return Refined(
        points=z,
        goal_indices=goal_indices,
        iterations=iterations,
        curvature_slack=float(np.max(pb.slack.value, initial=0.0)),
    )
