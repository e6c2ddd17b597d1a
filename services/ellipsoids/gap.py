"""Gaps between obstacle ellipses (the paper's eq. 3, corrected) and the groups they form.

Eq. (3) as printed constrains x and y by polyhedra (A₁ x ≤ b₁); for the ellipses of eq. (1) the
closest-point problem is the second-order cone programme

    minimise    ‖x − y‖₂
    subject to  ‖A₁ x + b₁‖₂ ≤ 1,   ‖A₂ y + b₂‖₂ ≤ 1,

whose optimum is 0 exactly when the ellipses intersect. Two routes solve it: Clarabel called directly
(the default: a three-cone problem of five variables, no modelling layer) and the same programme in
cvxpy, built once with Parameters (DPP: `A₁ @ x` is parameter × variable), which the tests hold the
direct route to. cvxpy is imported on first use of its route: the import alone costs about 0.6 s, more
than a whole plan on a small map.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import clarabel
import numpy as np
from scipy import sparse
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from services.geometry import Ellipse, FloatArray

__all__ = ["Gap", "GapError", "ellipse_gap", "gap_samples", "group_ellipses"]


class GapError(RuntimeError):
    """The closest-point SOCP did not reach an optimum."""


@dataclass(frozen=True)
class Gap:
    """Closest points `point_1` ∈ e1, `point_2` ∈ e2 and their distance (0 when the ellipses meet)."""

    distance_m: float
    point_1: FloatArray
    point_2: FloatArray


@functools.lru_cache(maxsize=1)
def _gap_problem():
    import cvxpy as cp

    A1, A2 = cp.Parameter((2, 2), name="A1"), cp.Parameter((2, 2), name="A2")
    b1, b2 = cp.Parameter(2, name="b1"), cp.Parameter(2, name="b2")
    x, y = cp.Variable(2, name="x"), cp.Variable(2, name="y")
    problem = cp.Problem(
        cp.Minimize(cp.norm(x - y, 2)),
        [cp.norm(A1 @ x + b1, 2) <= 1.0, cp.norm(A2 @ y + b2, 2) <= 1.0],
    )
    return problem, (A1, b1, A2, b2), x, y


def _gap_cvxpy(A1, b1, A2, b2, *, solver: str) -> tuple[FloatArray, FloatArray]:
    import cvxpy as cp

    problem, (pA1, pb1, pA2, pb2), x, y = _gap_problem()
    pA1.value, pb1.value, pA2.value, pb2.value = A1, b1, A2, b2
    try:
        problem.solve(solver=solver)
    except cp.error.SolverError as exc:
        raise GapError(f"ellipse gap solve failed with {solver}: {exc}") from exc
    if problem.status not in (cp.OPTIMAL, cp.OPTIMAL_INACCURATE) or x.value is None:
        raise GapError(f"ellipse gap solve with {solver} ended with status {problem.status!r}")
    return x.value, y.value


_CLARABEL_SETTINGS = clarabel.DefaultSettings()
_CLARABEL_SETTINGS.verbose = False


def _gap_pattern() -> tuple[sparse.csc_matrix, np.ndarray, np.ndarray]:
    """`_gap_clarabel`'s constraint matrix with zeros where A₁ and A₂ go, and the positions of their
    entries (row-major) in its data."""
    A = np.zeros((9, 5))
    A[0, 4] = -1.0  # t
    A[1:3, 0:2] = -np.eye(2)  # x − y
    A[1:3, 2:4] = np.eye(2)
    entry = np.zeros((9, 5), dtype=int)  # 1-4: A₁'s entries, 5-8: A₂'s, 9: the constants above
    entry[A != 0.0] = 9
    entry[4:6, 0:2] = [[1, 2], [3, 4]]
    entry[7:9, 2:4] = [[5, 6], [7, 8]]
    marked = sparse.csc_matrix(entry)
    positions = np.argsort(marked.data, kind="stable")
    pattern = sparse.csc_matrix((A.T[entry.T > 0], marked.indices, marked.indptr), shape=A.shape)
    return pattern, positions[:4], positions[4:8]


_GAP_P = sparse.csc_matrix((5, 5))
_GAP_A, _GAP_A1, _GAP_A2 = _gap_pattern()
_GAP_Q = np.array([0.0, 0.0, 0.0, 0.0, 1.0])
_GAP_CONES = [clarabel.SecondOrderConeT(3)] * 3


def _gap_clarabel(A1, b1, A2, b2) -> tuple[FloatArray, FloatArray]:
    """Variables v = (x, y, t): minimise t s.t. (t, x − y), (1, A₁x + b₁), (1, A₂y + b₂) ∈ SOC(3).

    Clarabel's form is b − A v ∈ K, so each cone's rows hold minus the coefficients. The matrix is
    made from its fixed sparsity pattern (building it from a dense array took most of a solve's time).
    """
    data = _GAP_A.data.copy()
    data[_GAP_A1], data[_GAP_A2] = -np.ravel(A1), -np.ravel(A2)
    A = sparse.csc_matrix((data, _GAP_A.indices, _GAP_A.indptr), shape=_GAP_A.shape)
    b = np.zeros(9)
    b[3], b[4:6] = 1.0, b1
    b[6], b[7:9] = 1.0, b2
    solution = clarabel.DefaultSolver(_GAP_P, _GAP_Q, A, b, _GAP_CONES, _CLARABEL_SETTINGS).solve()
    if solution.status not in (clarabel.SolverStatus.Solved, clarabel.SolverStatus.AlmostSolved):
        raise GapError(f"ellipse gap solve with Clarabel ended with status {solution.status}")
    v = np.asarray(solution.x)
    return v[0:2], v[2:4]


def ellipse_gap(e1: Ellipse, e2: Ellipse, *, method: str = "clarabel", solver: str = "CLARABEL") -> Gap:
    """Eq. (3) with ellipsoid constraints: the closest points of two ellipses and their distance.

    Solved in coordinates shifted to the midpoint of the two centres (translation leaves the gap
    unchanged and keeps the problem data well scaled). `method` "cvxpy" solves the cvxpy model with
    `solver` (not thread-safe: the problem is shared).
    """
    shift = 0.5 * (e1.center + e2.center)
    data = (e1.A, e1.b + e1.A @ shift, e2.A, e2.b + e2.A @ shift)
    x, y = _gap_cvxpy(*data, solver=solver) if method == "cvxpy" else _gap_clarabel(*data)
    p1, p2 = x + shift, y + shift
    return Gap(distance_m=max(0.0, float(np.linalg.norm(p1 - p2))), point_1=p1, point_2=p2)


_BOUNDARY_SAMPLES = 32  # closest sampled points bound the gap from above
_PAIRS_AT_ONCE = 64  # pairs whose sample distances are computed in one array: 64 × 32 × 32 × 2 doubles, 1 MiB


def gap_samples(ellipse: Ellipse) -> FloatArray:
    """The boundary points `group_ellipses` bounds gaps with (a caller may keep them per ellipse)."""
    return ellipse.boundary(_BOUNDARY_SAMPLES)


def group_ellipses(
    ellipses: list[Ellipse],
    *,
    min_gap_m: float,
    connected: np.ndarray | None = None,
    samples: list[FloatArray] | None = None,
    method: str = "clarabel",
) -> np.ndarray:
    """Group labels: ellipses closer than `min_gap_m` (= 2 r, the robot cannot pass) share a group.

    Groups are the connected components of the "gap < min_gap_m" graph. `connected` optionally labels
    ellipses already known to be joined (the pieces of one obstacle's cover); only pairs across labels
    are examined. Certain bounds settle almost every pair without a solve: the bounding circles'
    distance (centre, largest semi-axis) is a lower bound on the gap, the closest pair of sampled
    boundary points an upper bound. Only the pairs the bounds leave open get the SOCP of eq. (3), and
    a pair of components already joined is not examined again. `samples` are the ellipses'
    `gap_samples` if the caller keeps them (computed here otherwise).
    """
    m = len(ellipses)
    if m == 0:
        return np.zeros(0, dtype=int)
    connected = np.arange(m) if connected is None else np.asarray(connected)
    centres = np.array([e.center for e in ellipses])
    radii = np.array([e.semi_axes[0] for e in ellipses])
    # Candidate pairs (i < j, in row order): centres within min_gap_m + 2 max radius, from a KD-tree
    # rather than all m (m − 1) / 2 pairs (a map of 2000 pieces: 2 million).
    i, j = cKDTree(centres).query_pairs(min_gap_m + 2.0 * float(radii.max()), output_type="ndarray").T
    order = np.lexsort((j, i))
    i, j = i[order], j[order]
    lower = np.linalg.norm(centres[i] - centres[j], axis=1) - radii[i] - radii[j]
    open_pair = (lower < min_gap_m) & (connected[i] != connected[j])
    i, j = i[open_pair], j[open_pair]
    boundary = np.stack(samples if samples is not None else [gap_samples(e) for e in ellipses])
    upper = np.concatenate([np.zeros(0)] + [
        np.min(np.linalg.norm(boundary[i[k : k + _PAIRS_AT_ONCE], :, None] - boundary[j[k : k + _PAIRS_AT_ONCE], None],
                              axis=3), axis=(1, 2))
        for k in range(0, len(i), _PAIRS_AT_ONCE)
    ])
    certain = upper < min_gap_m
    links = [(i[certain], j[certain])]
    labels = _components(m, connected, links)
    for a, b in zip(i[~certain], j[~certain]):
        if labels[a] != labels[b] and ellipse_gap(ellipses[a], ellipses[b], method=method).distance_m < min_gap_m:
            links.append((np.array([a]), np.array([b])))
    return _components(m, connected, links)


def _components(m: int, connected: np.ndarray, links: list[tuple[np.ndarray, np.ndarray]]) -> np.ndarray:
    """Connected components of `m` nodes joined by `links` and by equal `connected` labels."""
    rows = np.concatenate([np.arange(m), *(a for a, _ in links)])
    # Join every node to the first node carrying its label.
    first = np.unique(connected, return_index=True)[1][np.unique(connected, return_inverse=True)[1]]
    cols = np.concatenate([first, *(b for _, b in links)])
    graph = coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(m, m))
    return connected_components(graph, directed=False)[1].astype(int)
