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
step's previous direction: again an inner approximation of ‖zᵢ₊₁ − zᵢ‖ ≥ lᵢ), and the curvature budget
at a point is κ lᵢ² for the smaller of its two floors: since the actual steps are no shorter, the
actual curvature ‖Δ²z‖ / s² stays within κ whatever the optimiser does with the spacing. Iterations
continue until the curvature measured with the actual spacing meets the bound.

The curvature cone and each point's half-planes carry penalised slacks (elastic mode, an exact ℓ₁
penalty): every subproblem is feasible — a robot that has just sensed an obstacle close ahead, or a
goal inside a newly grown cover, would otherwise make it infeasible — and an unattainable constraint
shows up as slack rather than as a solver failure. The exact checks downstream (the refined path
outside every ellipse, the smoother's proof on the continuous curve) decide what is published.

The first iterate is the route, except where it leaves the robot further off its heading than one
iteration can turn a step (the step floor lets a step turn by at most acos 0.95 ≈ 18°): there it is a
car's drive onto the route, which leaves along the heading and turns within the bound (`_driven_onto`).

A long route that is mostly straight (a corridor on a building's map) can be refined in windows: only
round the points where it breaks the curvature bound and round its start, the rest kept as the route has
it (`refine_in_windows`), so that the solves cost what the turns hold rather than what the route's
length does.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, replace
from functools import lru_cache

import clarabel
import numpy as np
import shapely
from scipy import sparse

from services.geometry import Ellipse, EllipseStack, FloatArray, arc_lengths, polyline_length

_OK = ("optimal", "optimal_inaccurate")  # cvxpy's status strings


class SolverFailure(RuntimeError):
    """A convex subproblem did not solve to optimality."""


@dataclass(frozen=True)
class RefineSettings:
    step_m: float = 0.1  # the paper's step bound
    spacing_m: float = 0.09  # target point spacing: leaves the step bound room for the path to lengthen
    level: float = 1.01  # ‖A z + b‖ the refined points keep: margin for the smoothed curve
    start_level: float = 1.003  # ... within one turning radius of the start, where the car cannot yet steer away
    curvature_factor: float = 0.97  # plan to this fraction of the car's curvature bound ...
    step_shrink: float = 0.95  # ... at steps no shorter than this fraction of the previous ones
    curvature_met_factor: float = 0.97  # converged once the actual curvature is within this of the bound
    min_iterations_unmet: int = 8  # iterations to spend on an unmet curvature bound before giving up
    slots: int = 8  # nearest ellipses linearised at each point
    trust_region_m: float = 0.5  # per-iteration move bound: keeps far ellipses out of reach
    # Iterations at most. Past 10 an iteration has not shortened a plan measured: every public scenario,
    # the bench's maps and the random ACES queries of docs/maps.md plan to the same length as under 25.
    max_iterations: int = 10
    # Converged once an iteration changes Σ‖Δz‖² by less than this fraction. For evenly spaced points it
    # is about L² / (n − 1), so 2 % on it is about 1 % on the length: the first solve's answer is taken
    # when bending the route to the curvature bound lengthened it by less than that, which on the public
    # maps saves a second solve for well under 1 % of length. (The planner stage keeps 1e-5: `PlannerConfig`.)
    rel_tolerance: float = 2e-2
    slack_weight: float = 1e3
    backend: str = "clarabel"  # "clarabel": Clarabel called directly; "cvxpy": the reference model
    solver: str = "CLARABEL"  # the cvxpy backend's solver
    # Refine only the stretches within this many turning radii of where the route breaks the curvature
    # bound or leaves the start off its heading, each on its own with its ends pinned to the route
    # (`refine_in_windows`); None: the whole route at once.
    window_radii: float | None = None


@dataclass(frozen=True)
class Refined:
    points: FloatArray
    goal_indices: tuple[int, ...]
    iterations: int
    curvature_slack: float


@dataclass(frozen=True)
class _Subproblem:
    """The data of one convex subproblem: everything that changes between iterations."""

    pinned: FloatArray  # (n,) 1 where the point is fixed (start, goals)
    pinned_points: FloatArray  # (n, 2) where (rows with pinned = 0 are ignored)
    heading: FloatArray  # (2,) unit start heading, or zeros for none
    gx: FloatArray  # (n, slots) half-planes gx·x + gy·y ≥ h
    gy: FloatArray
    h: FloatArray
    within: np.ndarray  # (n, slots) bool: the slots holding an ellipse in reach (the others are 0 ≥ −1)
    center: FloatArray  # (n, 2) trust-region centre (the current iterate)
    trust_m: float
    curvature_budget: FloatArray  # (n − 2,)
    step_direction: FloatArray  # (n − 1, 2)
    step_floor: FloatArray  # (n − 1,)
    lo: FloatArray  # (2,) bounds
    hi: FloatArray


class _CvxpyPathProblem:
    """The subproblem written in cvxpy: the readable specification, and the reference in tests.

    Every datum is a `cp.Parameter`, so the problem is built once per size. Solving canonicalises
    afresh each time: cvxpy's DPP compile of this problem grows quadratically with n (1.7 s at
    n = 416, measured), against 45–80 ms for a fresh canonicalisation. cvxpy is imported on first
    use (the import alone costs about 0.6 s; the default route does not need it).
    """

    def __init__(self, n: int, slots: int, step_m: float, slack_weight: float, solver: str) -> None:
        import cvxpy as cp

        self.solver = solver
        self.z = cp.Variable((n, 2))
        self.slack = cp.Variable(n - 2, nonneg=True)
        self.elastic = cp.Variable(n, nonneg=True)
        self.pinned = cp.Parameter(n, nonneg=True)
        self.pinned_x = cp.Parameter(n)  # pinned · x
        self.pinned_y = cp.Parameter(n)
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
            cp.multiply(self.pinned, z[:, 0]) == self.pinned_x,
            cp.multiply(self.pinned, z[:, 1]) == self.pinned_y,
            self.heading_normal @ first_step == 0,
            self.heading @ first_step >= 0,
            *(
                cp.multiply(gx, z[:, 0]) + cp.multiply(gy, z[:, 1]) + self.elastic >= h
                for gx, gy, h in zip(self.gx, self.gy, self.h)
            ),
            cp.norm(diff, 2, axis=1) <= step_m,
            cp.sum(cp.multiply(self.step_direction, diff), axis=1) >= self.step_floor,
            cp.norm(second, 2, axis=1) <= self.curvature_budget + self.slack,
            cp.abs(z - self.center) <= self.trust,
            *(z[:, axis] >= self.lo[axis] for axis in range(2)),
            *(z[:, axis] <= self.hi[axis] for axis in range(2)),
        ]
        objective = cp.sum_squares(diff) + slack_weight * (cp.sum(self.slack) + cp.sum(self.elastic))
        self.problem = cp.Problem(cp.Minimize(objective), constraints)

    def solve(self, data: _Subproblem) -> tuple[FloatArray, FloatArray, FloatArray]:
        self.pinned.value = data.pinned
        self.pinned_x.value = data.pinned * data.pinned_points[:, 0]
        self.pinned_y.value = data.pinned * data.pinned_points[:, 1]
        self.heading.value = data.heading
        self.heading_normal.value = np.array([-data.heading[1], data.heading[0]])
        for slot, (gx, gy, h) in enumerate(zip(self.gx, self.gy, self.h)):
            gx.value, gy.value, h.value = data.gx[:, slot], data.gy[:, slot], data.h[:, slot]
        self.center.value = data.center
        self.trust.value = data.trust_m
        self.curvature_budget.value = data.curvature_budget
        self.step_direction.value = data.step_direction
        self.step_floor.value = data.step_floor
        self.lo.value, self.hi.value = data.lo, data.hi
        self.problem.solve(solver=self.solver, ignore_dpp=True)
        if self.problem.status not in _OK:
            raise SolverFailure(f"path subproblem: solver status {self.problem.status}")
        return self.z.value, self.slack.value, self.elastic.value


class _ClarabelPathProblem:
    """The same subproblem handed to Clarabel directly, with a sparsity pattern fixed per size and slots.

    Variables x = (x₀, y₀, x₁, y₁, …, slack₁ … slackₙ₋₂, elasticᵢ for each point i with a half-plane);
    Clarabel solves
    min ½xᵀPx + qᵀx subject to
    b − A x ∈ K. The matrix is assembled once per pattern of half-planes, with explicit zeros wherever
    a coefficient can change (half-planes, heading, step directions); each iteration with the same
    pattern only overwrites A's and b's values in place (`DefaultSolver.update`), so the symbolic
    factorisation is reused and no modelling layer runs per solve. Only the slots that hold an ellipse
    in reach get a row (`pattern`, in point order): an empty slot is 0 ≥ −1, true
    whatever the point does, and on a map most slots are empty (on the MovingAI arena, whose walls
    are metres apart, 80–100 % of them), so leaving them out leaves the optimum as it is and the
    factorisation smaller. Row blocks, in cone order:
      zero      pinned points (2 per point), heading normal · (z₁ − z₀) = 0
      nonneg    −heading · (z₁ − z₀) ≤ 0; −g·zᵢ − elasticᵢ ≤ −h per plane; −dᵢ·(zᵢ₊₁ − zᵢ) ≤ −lᵢ;
                z ≤ min(c + τ, hi); −z ≤ −max(c − τ, lo); −slack ≤ 0; −elastic ≤ 0
      SOC(3)    (step_m, zᵢ₊₁ − zᵢ) for each step
      SOC(3)    (budgetᵢ + slackᵢ, zᵢ₊₁ − 2zᵢ + zᵢ₋₁) for each interior point
    With `bounded` = k < n the box rows (z ≤ …, −z ≤ …) and the step cones are kept for the first k
    points only: the relaxation that `_ClarabelOnDemand` solves first.
    `pattern`: the (n, slots) slots given a row; a subproblem whose slots in reach are exactly these
    solves here (`holds`).
    """

    def __init__(
        self, n: int, pattern: np.ndarray, pinned_count: int, step_m: float, slack_weight: float, *,
        bounded: int | None = None,
    ) -> None:
        self.n, self.pinned_count, self.pattern = n, pinned_count, pattern
        planes = np.nonzero(pattern)[0]
        self.elastic_points = np.unique(planes)  # a point without a half-plane needs no elastic slack
        e = len(self.elastic_points)
        self.bounded = kb = n if bounded is None else max(1, min(bounded, n))  # points with box rows, step cones
        nz = 2 * n
        self.size = nz + (n - 2) + e
        rows: list[np.ndarray] = []
        cols: list[np.ndarray] = []
        vals: list[np.ndarray] = []
        self._row = 0

        def block(count: int, entries: list[tuple[np.ndarray, np.ndarray, np.ndarray]]) -> slice:
            for r, c, v in entries:
                rows.append(self._row + np.asarray(r))
                cols.append(np.asarray(c))
                vals.append(np.asarray(v, dtype=float))
            out = slice(self._row, self._row + count)
            self._row += count
            return out

        def xs(i):  # column of x_i
            return 2 * np.asarray(i)

        def ys(i):
            return 2 * np.asarray(i) + 1

        slack = nz + np.arange(n - 2)
        elastic = nz + (n - 2) + np.arange(e)
        step = np.arange(n - 1)
        mid = np.arange(1, n - 1)
        k = np.arange(pinned_count)
        # Zero cone. The pinned rows' columns are filled in per solve (which points are pinned).
        self.pin_rows = block(2 * pinned_count, [(2 * k, np.zeros_like(k), np.zeros(pinned_count)),
                                                 (2 * k + 1, np.ones_like(k), np.zeros(pinned_count))])
        self.heading_normal_row = block(1, [(np.zeros(4, int), np.array([0, 1, 2, 3]), np.zeros(4))])
        zero_rows = self._row
        # Nonnegative cone.
        self.heading_row = block(1, [(np.zeros(4, int), np.array([0, 1, 2, 3]), np.zeros(4))])
        m = self.planes = len(planes)
        plane_elastic = elastic[np.searchsorted(self.elastic_points, planes)]
        self.obstacle_rows = block(m, [(np.arange(m), xs(planes), np.zeros(m)), (np.arange(m), ys(planes), np.zeros(m)),
                                       (np.arange(m), plane_elastic, -np.ones(m))])
        self.floor_rows = block(n - 1, [(step, xs(step), np.zeros(n - 1)), (step, ys(step), np.zeros(n - 1)),
                                        (step, xs(step + 1), np.zeros(n - 1)), (step, ys(step + 1), np.zeros(n - 1))])
        self.upper_rows = block(2 * kb, [(np.arange(2 * kb), np.arange(2 * kb), np.ones(2 * kb))])
        self.lower_rows = block(2 * kb, [(np.arange(2 * kb), np.arange(2 * kb), -np.ones(2 * kb))])
        self.slack_rows = block(n - 2, [(np.arange(n - 2), slack, -np.ones(n - 2))])
        self.elastic_rows = block(e, [(np.arange(e), elastic, -np.ones(e))])
        nonneg_rows = self._row - zero_rows
        # Second-order cones: step bound, then curvature.
        bounded_step = step[: kb - 1]
        t, ones = 3 * bounded_step, np.ones(kb - 1)
        self.step_cones = block(3 * (kb - 1), [(t + 1, xs(bounded_step + 1), -ones), (t + 1, xs(bounded_step), ones),
                                              (t + 2, ys(bounded_step + 1), -ones), (t + 2, ys(bounded_step), ones)])
        t = 3 * (mid - 1)
        entries = [(t, slack, -np.ones(n - 2))]
        for offset, weight in ((1, -1.0), (0, 2.0), (-1, -1.0)):
            entries += [(t + 1, xs(mid + offset), np.full(n - 2, weight)),
                        (t + 2, ys(mid + offset), np.full(n - 2, weight))]
        self.curvature_cones = block(3 * (n - 2), entries)

        # The entries; the matrix is assembled when the pinned points' columns are known (`_rebuild_pins`).
        self._entries = (np.concatenate(rows), np.concatenate(cols))
        self._values = np.concatenate(vals)
        self._A: sparse.csc_matrix | None = None
        self._order = np.zeros(0, dtype=np.intp)  # entry k of the matrix's data is value _order[k]
        self._b = np.zeros(self._row)
        self._b[self.step_cones.start : self.step_cones.stop : 3] = step_m
        self._P = _path_hessian(n, self.size)
        self._q = np.concatenate([np.zeros(nz), np.full(n - 2 + e, slack_weight)])
        self._cones = [
            clarabel.ZeroConeT(zero_rows),
            clarabel.NonnegativeConeT(nonneg_rows),
            *[clarabel.SecondOrderConeT(3)] * ((kb - 1) + (n - 2)),
        ]
        settings = clarabel.DefaultSettings()
        settings.verbose = False
        settings.presolve_enable = False
        settings.input_sparse_dropzeros = False
        settings.iterative_refinement_enable = False
        self._settings = settings
        self._solver: clarabel.DefaultSolver | None = None
        self._pinned_columns: tuple[int, ...] | None = None

    def holds(self, within: np.ndarray) -> bool:
        """Whether this is the set-up of exactly these slots in reach (a solve's rows are its own data's
        alone, so its result does not depend on which subproblems came before)."""
        return bool(np.array_equal(self.pattern, within))

    def _entry_slice(self, rows: slice) -> np.ndarray:
        """Indices (in entry order) of the entries in a block of rows."""
        r = self._entries[0]
        return np.flatnonzero((r >= rows.start) & (r < rows.stop))

    def solve(self, data: _Subproblem) -> tuple[FloatArray, FloatArray, FloatArray]:
        n, m = self.n, self.planes
        v = self._values
        b = self._b
        pinned = np.flatnonzero(data.pinned > 0)
        if len(pinned) != self.pinned_count:
            raise ValueError("pinned point count differs from the compiled problem")
        # Pinned rows: which columns they touch changes with the goal indices, so the matrix is rebuilt
        # (same shape and count) when the pinned set changes; the solver is then set up afresh.
        if self._pinned_columns != tuple(pinned):
            self._rebuild_pins(pinned)
        b[self.pin_rows] = data.pinned_points[pinned].reshape(-1)
        hx, hy = data.heading
        v[self._entry_slice(self.heading_normal_row)] = [hy, -hx, -hy, hx]  # normal (−hy, hx) · (z₁ − z₀)
        v[self._entry_slice(self.heading_row)] = [hx, hy, -hx, -hy]
        obstacle = self._entry_slice(self.obstacle_rows)
        v[obstacle[:m]] = -data.gx[self.pattern]
        v[obstacle[m : 2 * m]] = -data.gy[self.pattern]
        b[self.obstacle_rows] = -data.h[self.pattern]
        floor = self._entry_slice(self.floor_rows)
        d = data.step_direction
        v[floor] = np.concatenate([d[:, 0], d[:, 1], -d[:, 0], -d[:, 1]])
        b[self.floor_rows] = -data.step_floor
        k = self.bounded
        lo = np.tile(data.lo, k)
        hi = np.tile(data.hi, k)
        center = data.center[:k].reshape(-1)
        b[self.upper_rows] = np.minimum(center + data.trust_m, hi)
        b[self.lower_rows] = -np.maximum(center - data.trust_m, lo)
        b[self.curvature_cones.start : self.curvature_cones.stop : 3] = data.curvature_budget
        values = v[self._order]
        if self._solver is None:
            self._A.data = values
            self._solver = clarabel.DefaultSolver(self._P, self._q, self._A, b, self._cones, self._settings)
        else:
            # As lists: the binding reads a numpy array one element at a time, a list of floats about
            # three times faster, the conversion included.
            self._solver.update(A=values.tolist(), b=b.tolist())
        solution = self._solver.solve()
        if solution.status not in (clarabel.SolverStatus.Solved, clarabel.SolverStatus.AlmostSolved):
            raise SolverFailure(f"path subproblem: Clarabel status {solution.status}")
        x = np.asarray(solution.x)
        elastic = np.zeros(n)
        elastic[self.elastic_points] = x[3 * n - 2 :]
        return x[: 2 * n].reshape(n, 2), x[2 * n : 3 * n - 2], elastic

    def _rebuild_pins(self, pinned: np.ndarray) -> None:
        """Point the pinned rows at the pinned points' columns, assemble the matrix (the first solve always
        does: no column is pinned before it) and set the solver up afresh."""
        r, c = self._entries
        idx = self._entry_slice(self.pin_rows)
        local = r[idx] - self.pin_rows.start  # 2k for x of the k-th pinned point, 2k + 1 for y
        c[idx] = 2 * pinned[local // 2] + local % 2
        self._values[idx] = 1.0
        # CSC order: by column, then row (the entries are distinct, explicit zeros kept).
        self._order = np.lexsort((r, c))
        indptr = np.concatenate([[0], np.cumsum(np.bincount(c, minlength=self.size))])
        self._A = sparse.csc_matrix((self._values[self._order], r[self._order], indptr), shape=(self._row, self.size))
        self._solver = None
        self._pinned_columns = tuple(pinned)


def _path_hessian(n: int, size: int) -> sparse.csc_matrix:
    """The upper triangle of P = 2 DᵀD, D the steps zᵢ₊₁ − zᵢ of n points (x and y interleaved), so that
    ½ xᵀPx = Σ‖Δz‖², padded with zero columns to `size` (the slacks), in CSC form: column j ≥ 2 holds
    −2 in row j − 2 (the step from point j/2 − 1) and 2 × the number of steps at its point in row j."""
    nz = 2 * n
    steps = np.full(nz, 2.0)
    steps[[0, 1, nz - 2, nz - 1]] = 1.0  # the first and the last point have one step each
    j = np.arange(2, nz)
    indices = np.concatenate([[0, 1], np.column_stack([j - 2, j]).ravel()])
    data = np.concatenate([2.0 * steps[:2], np.column_stack([np.full(nz - 2, -2.0), 2.0 * steps[2:]]).ravel()])
    indptr = np.concatenate([[0, 1], 2 + 2 * np.arange(nz - 1), np.full(size - nz, 2 * nz - 2)])
    return sparse.csc_matrix((data, indices, indptr), shape=(size, size))


class _ClarabelOnDemand:
    """The Clarabel subproblem solved first without its box rows (trust region and map bounds) and step
    cones past the first `lead` points, and again whole only when its answer breaks one of them.

    Those constraints seldom bind: the points are spaced for the step bound to leave the path room to
    lengthen, and one solve rarely moves a point by the trust region, except where the car swings from
    its heading onto the route, so the first turning radius keeps them (without that, four of five
    200-obstacle fields broke them there in their first solve and were solved twice), as do a drive onto
    the route (`_driven_onto`) and a turning radius past it. An optimum of the
    relaxation that meets them is an optimum of the whole subproblem (it is feasible there, and nothing
    feasible there costs less), so the answer is the same up to the solver's tolerance. Past the lead
    they are a quarter of the rows (with every slot in reach) and the step cones half of the cones
    (docs/benchmarks.md has the figure).

    Each is set up for the slots in reach of the subproblem at hand and kept while later subproblems
    have the same ones. Never for a superset of them: extra empty rows leave the optimum as it is but
    move the solver's iterates (a closed loop's clearance by 1e-5 m), and a result must not depend on
    the solves that came before it in the process.
    """

    def __init__(self, n: int, pinned_count: int, step_m: float, slack_weight: float, lead: int) -> None:
        self._args = (n, pinned_count, step_m, slack_weight)
        self.step_m = step_m
        self.lead = lead
        self.relaxed: _ClarabelPathProblem | None = None  # set up when first needed
        self.full: _ClarabelPathProblem | None = None

    def solve(self, data: _Subproblem) -> tuple[FloatArray, FloatArray, FloatArray]:
        # An iterate with a step at the bound (a path the curvature bound keeps lengthening) meets it again:
        # solved whole at once. (Eight closed loops: 76 of 539 relaxed solves broke a bound without this;
        # with it 22 of 477, and 67 solved whole at once.)
        if _longest_step(data.center) < 0.99 * self.step_m:
            if self.relaxed is None or not self.relaxed.holds(data.within):
                self.relaxed = self._set_up(data.within, bounded=self.lead)
            z, slack, elastic = self.relaxed.solve(data)
            if _within_bounds(z, data, step_m=self.step_m):
                return z, slack, elastic
        if self.full is None or not self.full.holds(data.within):
            self.full = self._set_up(data.within, bounded=None)
        return self.full.solve(data)

    def _set_up(self, within: np.ndarray, *, bounded: int | None) -> _ClarabelPathProblem:
        n, pinned_count, step_m, slack_weight = self._args
        return _ClarabelPathProblem(n, within, pinned_count, step_m, slack_weight, bounded=bounded)


def _longest_step(z: FloatArray) -> float:
    steps = np.diff(z, axis=0)
    return float(np.sqrt(np.max(np.einsum("ij,ij->i", steps, steps))))


def _within_bounds(z: FloatArray, data: _Subproblem, *, step_m: float, tolerance: float = 1e-9) -> bool:
    """Whether points meet the step bound, the trust region and the map bounds (as the whole subproblem
    states them), to `tolerance`."""
    return bool(
        _longest_step(z) <= step_m + tolerance
        and np.max(np.abs(z - data.center)) <= data.trust_m + tolerance
        and np.min(z - data.lo) >= -tolerance
        and np.min(data.hi - z) >= -tolerance
    )


@lru_cache(maxsize=16)
def _problem(
    backend: str, n: int, slots: int, pinned_count: int, step_m: float, slack_weight: float, solver: str, lead: int
) -> _CvxpyPathProblem | _ClarabelOnDemand:
    if backend == "cvxpy":
        return _CvxpyPathProblem(n, slots, step_m, slack_weight, solver)
    return _ClarabelOnDemand(n, pinned_count, step_m, slack_weight, lead)


def forget_problems() -> None:
    """Drop the subproblems `refine` keeps compiled (with their solvers' set-ups), so the next refinement
    builds its own afresh, as a process's first does: a benchmark that repeats one query would otherwise
    time set-ups only its first call paid."""
    _problem.cache_clear()


def _bucket(n: int) -> int:
    """Round the point count up so that problems of similar length share one compiled problem."""
    return int(32 * np.ceil(n / 32))


def leg_counts(lengths: Sequence[float], *, n: int) -> list[int]:
    """How many of `n` points (the first one aside) each leg gets: in proportion to its length, at least one.

    The last leg gets what the others leave. When rounding up the others leaves it none (a short last
    leg), the points it lacks come from the legs with the most. (A handful of legs: plain floats, with
    numpy's rounding, half to even.)
    """
    if n - 1 < len(lengths):
        raise ValueError("too few points for the number of legs")
    lengths = [max(length, 1e-9) for length in lengths]
    total = sum(lengths)
    counts = [max(1, round((n - 1) * length / total)) for length in lengths[:-1]]
    counts.append((n - 1) - sum(counts))
    while counts[-1] < 1:
        counts[counts.index(max(counts[:-1]))] -= 1
        counts[-1] += 1
    return counts


def resample_legs(legs: list[FloatArray], *, n: int) -> tuple[FloatArray, tuple[int, ...]]:
    """Resample consecutive legs (each a polyline) to `n` points in all, in proportion to leg length."""
    counts = leg_counts([polyline_length(leg) for leg in legs], n=n)
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
    z: FloatArray, stack: EllipseStack, *, slots: int, level: FloatArray, trust_m: float
) -> tuple[FloatArray, FloatArray, FloatArray, np.ndarray]:
    """Half-planes nᵀ(A z + b) ≥ levelᵢ at each point for its nearest ellipses in reach of the trust
    region, and which slots hold one (the others: 0 ≥ −1)."""
    n = len(z)
    gx = np.zeros((n, slots))
    gy = np.zeros((n, slots))
    h = np.full((n, slots), -1.0)
    within = np.zeros((n, slots), dtype=bool)
    if len(stack) == 0:
        return gx, gy, h, within
    # Lower bound on the Euclidean distance to each ellipse: centre distance minus largest semi-axis
    # (formed as np.linalg.norm forms it, without its (n, m, 2) differences).
    dx = z[:, 0, None] - stack.centers[None, :, 0]
    dy = z[:, 1, None] - stack.centers[None, :, 1]
    near = np.sqrt(dx * dx + dy * dy) - stack.reach[None, :]
    k = min(slots, len(stack))
    if k < len(stack):  # the k nearest of each row, then sorted: no sort of the whole row
        order = np.argpartition(near, k - 1, axis=1)[:, :k]
        order = np.take_along_axis(order, np.argsort(np.take_along_axis(near, order, axis=1), axis=1), axis=1)
    else:
        order = np.argsort(near, axis=1)
    within[:, :k] = near[np.arange(n)[:, None], order] <= 2.0 * trust_m + 0.5
    A = stack.A[order]  # (n, k, 2, 2)
    b = stack.b[order]  # (n, k, 2)
    u = np.einsum("nkij,nj->nki", A, z) + b
    normal = u / np.linalg.norm(u, axis=2, keepdims=True)
    g = np.einsum("nkij,nki->nkj", A, normal)  # Aᵀ n
    gx[:, :k], gy[:, :k] = g[..., 0], g[..., 1]
    h[:, :k] = level[:, None] - np.einsum("nki,nki->nk", normal, b)
    gx[~within], gy[~within], h[~within] = 0.0, 0.0, -1.0
    return gx, gy, h, within


def _curvature_met(z: FloatArray, kappa: float) -> bool:
    """Whether the discrete curvature of the points, measured with their actual spacing, is within kappa."""
    return not np.any(curvature_broken(z, kappa))


def curvature_broken(z: FloatArray, kappa: float) -> np.ndarray:
    """For each interior point, whether its discrete curvature (measured with the actual spacing) exceeds kappa."""
    step = np.linalg.norm(np.diff(z, axis=0), axis=1)
    second = np.linalg.norm(z[2:] - 2 * z[1:-1] + z[:-2], axis=1)
    return ~(second <= kappa * np.minimum(step[:-1], step[1:]) ** 2 * (1 + 1e-3) + 1e-9)


def refine(
    *,
    legs: list[FloatArray],
    ellipses: list[Ellipse],
    bounds_min: FloatArray,
    bounds_max: FloatArray,
    max_curvature: float,
    heading_rad: float | None = None,
    settings: RefineSettings = RefineSettings(),
    at_robot: bool = True,
) -> Refined:
    """Refine a route (one polyline per leg, start → goal₁ → …) into the shortest drivable path.

    `at_robot`: the start is the robot's pose (see `start_level`); a window of the route
    (`refine_in_windows`) starts on the route instead. Raises `SolverFailure` if a subproblem fails; the
    caller verifies the result either way.
    """
    if settings.window_radii is not None:
        return refine_in_windows(legs=legs, ellipses=ellipses, bounds_min=bounds_min, bounds_max=bounds_max,
                                 max_curvature=max_curvature, heading_rad=heading_rad, settings=settings)
    stack = EllipseStack.of(ellipses)
    kappa = settings.curvature_factor * max_curvature
    drive_m = 0.0
    if at_robot and heading_rad is not None:
        first, drive_m = _driven_onto(legs[0], heading_rad, stack=stack, max_curvature=kappa, settings=settings)
        legs = [first, *legs[1:]]
    total = sum(polyline_length(leg) for leg in legs)
    n = _bucket(int(np.ceil(total / settings.spacing_m)) + 1)
    z, goal_indices = resample_legs(legs, n=n)
    # The margin above level 1 gives the smoothed curve room; a robot that has just sensed an obstacle
    # close ahead cannot give that room within its first turning radius, so there the plan only has to
    # stay outside (the smoother still proves the continuous curve clear).
    along = arc_lengths(z)
    first_turn = (along < 1.0 / max_curvature) & at_robot
    level = np.where(first_turn, min(settings.start_level, settings.level), settings.level)
    # Clarabel's first solve keeps the step and trust-region bounds over that stretch, and over a drive onto
    # the route and a turning radius past it, where the solves move the points most (`_ClarabelOnDemand`),
    # its point count rounded up to a multiple of 8 so that similar plans share one compiled problem.
    kept = (along < drive_m + 1.0 / max_curvature) & at_robot
    lead = 8 * -(-(int(np.count_nonzero(kept)) + 1) // 8) if settings.backend == "clarabel" else 0
    problem = _problem(
        settings.backend, n, settings.slots, 1 + len(goal_indices), settings.step_m, settings.slack_weight,
        settings.solver, lead,
    )
    pinned = np.zeros(n)
    pinned[[0, *goal_indices]] = 1.0
    pinned_points = z.copy()
    heading = np.zeros(2) if heading_rad is None else np.array([np.cos(heading_rad), np.sin(heading_rad)])

    # The route itself is the first iterate (or, from a robot facing off it, the drive onto it): when it is
    # already optimal (the exact tangent route often is, up to the curvature bound) one solve confirms it.
    previous = previous_path = float(np.sum(np.diff(z, axis=0) ** 2))
    previous_penalty = 0.0
    iterations = 0
    slack = np.zeros(n - 2)
    for iterations in range(1, settings.max_iterations + 1):
        gx, gy, h, within = _linearise(
            z, stack, slots=settings.slots, level=level, trust_m=settings.trust_region_m
        )
        delta = np.diff(z, axis=0)
        step = np.linalg.norm(delta, axis=1)
        floor = settings.step_shrink * step
        direction = delta / np.maximum(step, 1e-12)[:, None]
        if heading_rad is not None:
            direction[0] = heading  # the first step is pinned to the heading: its floor must be along it
        data = _Subproblem(
            pinned=pinned,
            pinned_points=pinned_points,
            heading=heading,
            gx=gx,
            gy=gy,
            h=h,
            within=within,
            center=z,
            trust_m=settings.trust_region_m,
            curvature_budget=kappa * np.minimum(floor[:-1], floor[1:]) ** 2,
            step_direction=direction,
            step_floor=floor,
            lo=np.asarray(bounds_min, dtype=float),
            hi=np.asarray(bounds_max, dtype=float),
        )
        z, slack, elastic = problem.solve(data)
        penalty = float(np.sum(np.maximum(slack, 0.0)) + np.sum(np.maximum(elastic, 0.0)))
        path = float(np.sum(np.diff(z, axis=0) ** 2))
        cost = path + settings.slack_weight * penalty
        tolerance = settings.rel_tolerance * max(abs(cost), 1e-9)
        # Later iterates cannot get longer (each is feasible for the next subproblem); the first can,
        # when the route breaks the curvature bound: that is progress, not a stall.
        stalled = -tolerance <= previous - cost <= tolerance if iterations == 1 else previous - cost <= tolerance
        # A solve that clears the previous one's slack drops its cost by the whole penalty; if its path
        # moved no more than the tolerance, that drop was all there was to gain.
        cleared = previous_penalty > 0.0 and penalty <= 1e-9 and abs(previous_path - path) <= tolerance
        met = _curvature_met(z, settings.curvature_met_factor * max_curvature)
        if (stalled or cleared) and (met or iterations >= settings.min_iterations_unmet):
            break
        previous, previous_path, previous_penalty = cost, path, penalty
    return Refined(
        points=z,
        goal_indices=goal_indices,
        iterations=iterations,
        curvature_slack=float(np.max(slack, initial=0.0)),
    )


def _off_heading(step: FloatArray, heading_rad: float) -> float:
    """The angle (0 … π) between a step and the heading."""
    along = (step[0] * math.cos(heading_rad) + step[1] * math.sin(heading_rad)) / math.hypot(step[0], step[1])
    return math.acos(min(1.0, max(-1.0, along)))


_JOINED_M, _JOINED_RAD = 0.01, 0.01  # a drive this close to the route and its direction has joined it


def _driven_onto(route: FloatArray, heading_rad: float, *, stack: EllipseStack, max_curvature: float,
                 settings: RefineSettings) -> tuple[FloatArray, float]:
    """The route's start as a car would drive onto it, where the route leaves the start further off the
    heading than one iteration can turn a step (`_driven_path`); the route itself where it leaves along
    the heading, or where that drive comes within the refined points' level of an ellipse or does not
    come back onto the route. With it, how long the drive is before it is on the route (0 for the route).

    The refinement turns a step's direction by at most acos(`step_shrink`) an iteration (its length
    along its previous direction keeps that fraction of it): from a route that leaves the start at a
    right angle to the heading its first solves only swing the start round, a few degrees each. Started
    from a path that already leaves along the heading and turns within the curvature bound, it only
    has to shorten it.
    """
    distinct = route[np.concatenate([[True], np.any(route[1:] != route[:-1], axis=1)])]
    if len(distinct) < 2:
        return route, 0.0
    if _off_heading(distinct[1] - distinct[0], heading_rad) <= math.acos(settings.step_shrink):
        return route, 0.0
    found = _driven_path(distinct, heading_rad, radius_m=1.0 / max_curvature, step_m=settings.spacing_m)
    level = min(settings.start_level, settings.level)
    if found is None or (len(stack) and np.min(stack.min_levels(found[0])) < level):
        return route, 0.0
    driven, car = found
    return driven, polyline_length(driven[:car])


def _driven_path(route: FloatArray, heading_rad: float, *, radius_m: float,
                 step_m: float) -> tuple[FloatArray, int] | None:
    """A car's path from the route's first point, leaving along the heading, onto the route (a polyline
    of distinct consecutive points): pure pursuit of the point one turning radius further along the route
    than the car's projection, steering within the turning radius (at full lock while that point lies
    behind), steps of `step_m` along exact arcs; once it crosses the route, or is within `_JOINED_M` of
    it and `_JOINED_RAD` of its direction, the route from there on (an overshoot could take it into an
    ellipse the route runs along). With it, how many of its first points are the car's (the last of them
    on the route). None if it has not come back onto it within the route's length twice over."""
    seg = np.diff(route, axis=0)
    seg_len = np.linalg.norm(seg, axis=1)
    starts, unit = route[:-1], seg / seg_len[:, None]
    along = np.concatenate([[0.0], np.cumsum(seg_len)])
    x, y, theta = float(route[0, 0]), float(route[0, 1]), heading_rad
    points = [(x, y)]
    side = 0.0
    for _ in range(int(2.0 * along[-1] / step_m) + 1):
        # The projection onto the route (the nearest point of its segments), and which side of it the car is.
        t = np.clip(np.einsum("ij,ij->i", np.array([x, y]) - starts, unit), 0.0, seg_len)
        gap = np.hypot(starts[:, 0] + t * unit[:, 0] - x, starts[:, 1] + t * unit[:, 1] - y)
        k = int(np.argmin(gap))
        here = unit[k, 0] * (y - starts[k, 1]) - unit[k, 1] * (x - starts[k, 0])
        if len(points) > 1 and (here * side < 0.0 or gap[k] <= _JOINED_M and abs(
                math.remainder(math.atan2(unit[k, 1], unit[k, 0]) - theta, 2.0 * math.pi)) <= _JOINED_RAD):
            return np.vstack([np.array(points), route[k + 1 :]]), len(points)
        side = here
        s = min(float(along[k] + t[k]) + radius_m, float(along[-1]))
        gx, gy = np.interp(s, along, route[:, 0]), np.interp(s, along, route[:, 1])
        bearing = math.remainder(math.atan2(gy - y, gx - x) - theta, 2.0 * math.pi)
        reach = math.hypot(gx - x, gy - y)
        if math.cos(bearing) <= 0.0 or reach <= 1e-9:
            curvature = math.copysign(1.0 / radius_m, bearing)
        else:
            curvature = max(-1.0 / radius_m, min(1.0 / radius_m, 2.0 * math.sin(bearing) / reach))
        turn = curvature * step_m
        chord = step_m if turn == 0.0 else 2.0 * math.sin(0.5 * turn) / curvature
        x, y = x + chord * math.cos(theta + 0.5 * turn), y + chord * math.sin(theta + 0.5 * turn)
        theta += turn
        points.append((x, y))
    return None


_MET_SLACK = 1e-6  # a curvature slack at most this is a met bound (as `plan_path` takes it)
_STUCK_FACTOR = 0.9  # a widened window's unmet slack at least this × its narrower ones' is not widened again
_ALONG_COS = math.cos(1e-6)  # a first step within 1e-6 rad of the heading is along it
_PIN_TOLERANCE_M = 0.02  # a window's path this close to the route near a pinned end has come back onto it


def refine_in_windows(
    *,
    legs: list[FloatArray],
    ellipses: list[Ellipse],
    bounds_min: FloatArray,
    bounds_max: FloatArray,
    max_curvature: float,
    heading_rad: float | None,
    settings: RefineSettings,
) -> Refined:
    """The route refined only where it needs it: each stretch within `window_radii` turning radii (arc
    length) of a point that breaks the curvature bound, or of the start when the route does not leave it
    along the heading, on its own; the rest of the route is kept as it is.

    The route (`route.tangent_route`) is the model's exact shortest path without the curvature bound:
    tangent segments and arcs round the ellipses, at the planning level. Where its points, sampled as the
    refinement samples them, meet the curvature bound and leave the start along the heading, it is what
    the refinement's first solve would confirm (as `plan_path` returns a clear straight reference
    unrefined); only its sharp turns and its start need the curvature and heading work, and a solve then
    costs what its window holds, not what the route's length does. Each window's ends are pinned to the
    route — its first point, with the route's direction there as its heading, and its last two points, as
    the planner stage's repair pins the plan it keeps — so each kept neighbour is collinear with the
    pinned ends and the curvature bound holds across every join. A window whose curvature bound is not
    met, or whose path still moves off the route near a pinned end (the pins, not the turn, decided it
    there), is widened, by twice as much each time, and merged with the windows it reaches; one that
    reaches the whole route is the whole refinement (`refine` without windows). A widened window that
    meets its bound no better than the narrower ones it grew from is not widened again (`_stuck`): the
    result keeps its slack, and the caller tries another route. Nor is one that breaks the bound only
    where its path turns back at a goal before the last (`_broken_at_goals`): the caller loops through the
    goals there. The caller verifies the path whole, as any refined path.
    """
    whole = replace(settings, window_radii=None)
    total = sum(polyline_length(leg) for leg in legs)
    z, goal_indices = resample_legs(legs, n=int(np.ceil(total / settings.spacing_m)) + 1)
    n = len(z)
    length = np.linalg.norm(np.diff(z, axis=0), axis=1)
    along = np.concatenate([[0.0], np.cumsum(length)])
    radius = 1.0 / (settings.curvature_factor * max_curvature)
    reach = settings.window_radii * radius
    sharp = 1 + np.flatnonzero(curvature_broken(z, settings.curvature_met_factor * max_curvature))
    intervals = [(along[k] - reach, along[k] + reach) for k in sharp.tolist()]
    if heading_rad is not None:
        off = _off_heading(z[1] - z[0], heading_rad)
        if math.cos(off) < _ALONG_COS:
            # Swinging onto the route takes about a turning radius per radian, and as much again to come
            # back onto its line: the start's window is that much longer.
            intervals.append((-reach, reach + 4.0 * off * radius))
    if not intervals:
        return Refined(points=z, goal_indices=goal_indices, iterations=0, curvature_slack=0.0)
    gap = 2.0 * float(length.max())  # windows closer than two steps are one: their points would meet
    intervals = _merged(intervals, gap=gap)
    solved: dict[tuple[int, int], Refined] = {}
    widen = reach
    while True:
        spans = _spans(along, intervals)
        intervals = [(along[a], along[b]) for a, b in spans]
        if spans == [(0, n - 1)]:
            return refine(legs=legs, ellipses=ellipses, bounds_min=bounds_min, bounds_max=bounds_max,
                          max_curvature=max_curvature, heading_rad=heading_rad, settings=whole)
        for a, b in spans:
            if (a, b) not in solved:
                solved[a, b] = _refine_window(z, a, b, goal_indices=goal_indices, ellipses=ellipses,
                                              bounds_min=bounds_min, bounds_max=bounds_max,
                                              max_curvature=max_curvature, heading_rad=heading_rad, settings=whole)
        unmet = [(solved[a, b].curvature_slack > _MET_SLACK and not _stuck(solved, a, b)
                  and not _broken_at_goals(solved[a, b], _cuts(a, b, n=n, goal_indices=goal_indices), goal_indices,
                                           kappa=settings.curvature_met_factor * max_curvature, radius_m=radius))
                 or _held_by_its_ends(z, a, b, solved[a, b].points, reach) for a, b in spans]
        if not any(unmet):
            break
        widen *= 2.0
        intervals = _merged([(lo - widen, hi + widen) if bad else (lo, hi)
                             for (lo, hi), bad in zip(intervals, unmet)], gap=gap)
    # The kept stretches and the windows' points, in order; where each goal ends up.
    parts, index = [], np.full(n, -1)
    count = cursor = 0
    for a, b in spans:
        parts.append(z[cursor:a])
        index[cursor:a] = count + np.arange(a - cursor)
        count += a - cursor
        window = solved[a, b]
        index[[a, *_cuts(a, b, n=n, goal_indices=goal_indices)]] = count + np.array([0, *window.goal_indices])
        parts.append(window.points)
        count += len(window.points)
        cursor = b + 1
    parts.append(z[cursor:])
    index[cursor:] = count + np.arange(n - cursor)
    return Refined(
        points=np.vstack(parts),
        goal_indices=tuple(int(index[g]) for g in goal_indices),
        iterations=sum(solved[span].iterations for span in spans),
        curvature_slack=max(solved[span].curvature_slack for span in spans),
    )


def _stuck(solved: dict[tuple[int, int], Refined], a: int, b: int) -> bool:
    """Whether window a … b, widened from the windows it grew from (the widest of the narrower ones within
    it whose curvature bound was unmet), met it no better: its slack is not down by a tenth on the largest
    of theirs. Its turn is not one the pins made (a car facing away from every route, with no room to turn
    round), and widening it further only refines more of the route to the same slack, the whole route at
    last."""
    inner = {(lo, hi): r.curvature_slack for (lo, hi), r in solved.items()
             if a <= lo and hi <= b and (lo, hi) != (a, b) and r.curvature_slack > _MET_SLACK}
    grew_from = [slack for (lo, hi), slack in inner.items()
                 if not any(c <= lo and hi <= d and (c, d) != (lo, hi) for c, d in inner)]
    return bool(grew_from) and solved[a, b].curvature_slack >= _STUCK_FACTOR * max(grew_from)


def _broken_at_goals(window: Refined, cuts: list[int], goal_indices: tuple[int, ...], *, kappa: float,
                     radius_m: float) -> bool:
    """Whether every point where a window's path breaks the curvature bound `kappa` lies within two turning
    radii (along it) of a goal before the route's last where the path turns back: its directions a turning
    radius before and after the goal more than a right angle apart (`cuts`: the route's points the
    window's legs end at, `_cuts`). The curve must loop through such a goal, which no wider refinement of
    a route that goes there and back bends into: the window is not widened, and its slack tells the caller
    to loop through the goals (`services.planner.core`)."""
    last = goal_indices[-1]
    goals = np.array([window.goal_indices[k] for k, cut in enumerate(cuts) if cut in goal_indices and cut != last],
                     dtype=np.intp)
    broken = 1 + np.flatnonzero(curvature_broken(window.points, kappa))
    if not len(goals) or not len(broken):
        return False
    z, along = window.points, arc_lengths(window.points)
    before = z[np.searchsorted(along, along[goals] - radius_m)]
    after = z[np.minimum(np.searchsorted(along, along[goals] + radius_m), len(z) - 1)]
    back = goals[np.einsum("ij,ij->i", z[goals] - before, after - z[goals]) < 0.0]
    return bool(len(back)) and bool(
        np.all(np.min(np.abs(along[broken, None] - along[back][None, :]), axis=1) <= 2.0 * radius_m))


def _merged(intervals: list[tuple[float, float]], *, gap: float) -> list[tuple[float, float]]:
    """Intervals less than `gap` apart joined, in order."""
    out: list[tuple[float, float]] = []
    for lo, hi in sorted(intervals):
        if out and lo <= out[-1][1] + gap:
            out[-1] = (out[-1][0], max(out[-1][1], hi))
        else:
            out.append((lo, hi))
    return out


def _span(along: FloatArray, lo: float, hi: float) -> tuple[int, int]:
    """The points (first, last) of a window covering the arc lengths lo … hi: from the last point at or
    before lo to the first at or after hi, widened to a multiple of 32 points (`_bucket`: the refinement
    then samples the window as the route does, and windows share compiled problems)."""
    n = len(along)
    a = max(int(np.searchsorted(along, lo, side="right")) - 1, 0)
    b = min(int(np.searchsorted(along, hi, side="left")), n - 1)
    size = _bucket(b - a + 1)
    b = min(a + size - 1, n - 1)
    return max(b - size + 1, 0), b


def _held_by_its_ends(z: FloatArray, a: int, b: int, points: FloatArray, reach_m: float) -> bool:
    """Whether a window's refined path has not come back most of the way onto the route within half a
    reach of a pinned end (not the robot's start nor the route's end): some point there lies more than
    `_PIN_TOLERANCE_M` and a quarter of the window's largest move off the route's points a … b, so the pin
    rather than the turn shaped the path there. (Distances to the route's polyline: a window that starts
    at the robot may begin from a drive onto the route, `_driven_onto`, whose points are not the route's.)"""
    off = shapely.distance(shapely.points(points), shapely.LineString(z[a : b + 1]))
    along = arc_lengths(points)
    ends = np.zeros(len(points), dtype=bool)
    if a > 0:
        ends |= along <= 0.5 * reach_m
    if b < len(z) - 1:
        ends |= along >= along[-1] - 0.5 * reach_m
    return bool(np.any(off[ends] > max(_PIN_TOLERANCE_M, 0.25 * float(off.max()))))


def _spans(along: FloatArray, intervals: list[tuple[float, float]]) -> list[tuple[int, int]]:
    """The windows' points (`_span`), those that overlap or touch once widened joined into one."""
    spans: list[tuple[int, int]] = []
    for lo, hi in intervals:
        a, b = _span(along, lo, hi)
        while spans and a <= spans[-1][1] + 1:
            first, last = spans.pop()
            a, b = _span(along, along[min(a, first)], along[max(b, last)])
        spans.append((a, b))
    return spans


def _cuts(a: int, b: int, *, n: int, goal_indices: tuple[int, ...]) -> list[int]:
    """A window's leg ends after its first point: the goals inside it, then its last two points (pinned,
    unless the last is the route's end, the final goal)."""
    ends = {g for g in goal_indices if a < g <= b} | {b}
    if b < n - 1:
        ends.add(b - 1)
    return sorted(ends)


def _refine_window(z: FloatArray, a: int, b: int, *, goal_indices: tuple[int, ...], ellipses: list[Ellipse],
                   bounds_min: FloatArray, bounds_max: FloatArray, max_curvature: float,
                   heading_rad: float | None, settings: RefineSettings) -> Refined:
    """Points a … b of the route refined on their own, ends pinned (see `refine_in_windows`)."""
    cuts = [a, *_cuts(a, b, n=len(z), goal_indices=goal_indices)]
    legs = [z[c0 : c1 + 1] for c0, c1 in zip(cuts, cuts[1:])]
    if a > 0:
        heading_rad = math.atan2(z[a + 1, 1] - z[a, 1], z[a + 1, 0] - z[a, 0])
    return refine(legs=legs, ellipses=ellipses, bounds_min=bounds_min, bounds_max=bounds_max,
                  max_curvature=max_curvature, heading_rad=heading_rad, settings=settings, at_robot=a == 0)
