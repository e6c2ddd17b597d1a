"""Gaps between obstacle ellipses (the paper's eq. 3, corrected) and the groups they form.

Eq. (3) as printed constrains x and y by polyhedra (A₁ x ≤ b₁); for the ellipses of eq. (1) the
closest-point problem is the second-order cone programme

    minimise    ‖x − y‖₂
    subject to  ‖A₁ x + b₁‖₂ ≤ 1,   ‖A₂ y + b₂‖₂ ≤ 1,

whose optimum is 0 exactly when the ellipses intersect. It is built once with Parameters (DPP:
`A₁ @ x` is parameter × variable) and re-solved for every pair.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import cvxpy as cp
import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from cvxnav.geometry import Ellipse, EllipseStack, FloatArray

__all__ = ["Gap", "GapError", "ellipse_gap", "group_ellipses"]


class GapError(RuntimeError):
    """The closest-point SOCP did not reach an optimum."""


@dataclass(frozen=True)
class Gap:
    """Closest points `point_1` ∈ e1, `point_2` ∈ e2 and their distance (0 when the ellipses meet)."""

    distance_m: float
    point_1: FloatArray
    point_2: FloatArray


@functools.lru_cache(maxsize=1)
def _gap_problem() -> tuple[cp.Problem, tuple[cp.Parameter, ...], cp.Variable, cp.Variable]:
    A1, A2 = cp.Parameter((2, 2), name="A1"), cp.Parameter((2, 2), name="A2")
    b1, b2 = cp.Parameter(2, name="b1"), cp.Parameter(2, name="b2")
    x, y = cp.Variable(2, name="x"), cp.Variable(2, name="y")
    problem = cp.Problem(
        cp.Minimize(cp.norm(x - y, 2)),
        [cp.norm(A1 @ x + b1, 2) <= 1.0, cp.norm(A2 @ y + b2, 2) <= 1.0],
    )
    return problem, (A1, b1, A2, b2), x, y


def ellipse_gap(e1: Ellipse, e2: Ellipse, *, solver: str = "CLARABEL") -> Gap:
    """Eq. (3) with ellipsoid constraints: the closest points of two ellipses and their distance.

    Solved in coordinates shifted to the midpoint of the two centres (translation leaves the gap
    unchanged and keeps the problem data well scaled). Not thread-safe: the problem is shared.
    """
    shift = 0.5 * (e1.center + e2.center)
    problem, (A1, b1, A2, b2), x, y = _gap_problem()
    A1.value, b1.value = e1.A, e1.b + e1.A @ shift
    A2.value, b2.value = e2.A, e2.b + e2.A @ shift
    try:
        problem.solve(solver=solver)
    except cp.error.SolverError as exc:
        raise GapError(f"ellipse gap solve failed with {solver}: {exc}") from exc
    if problem.status not in (cp.OPTIMAL, cp.OPTIMAL_INACCURATE) or x.value is None:
        raise GapError(f"ellipse gap solve with {solver} ended with status {problem.status!r}")
    p1, p2 = x.value + shift, y.value + shift
    return Gap(distance_m=max(0.0, float(np.linalg.norm(p1 - p2))), point_1=p1, point_2=p2)


_BOUNDARY_SAMPLES = 32  # closest sampled points bound the gap from above


def group_ellipses(
    ellipses: list[Ellipse],
    *,
    min_gap_m: float,
    connected: np.ndarray | None = None,
    solver: str = "CLARABEL",
) -> np.ndarray:
    """Group labels: ellipses closer than `min_gap_m` (= 2 r, the robot cannot pass) share a group.

    Groups are the connected components of the "gap < min_gap_m" graph. `connected` optionally labels
    ellipses already known to be joined (the pieces of one obstacle's cover); only pairs across labels
    are examined. Certain bounds settle almost every pair without a solve: the bounding circles'
    distance (centre, largest semi-axis) is a lower bound on the gap, the closest pair of sampled
    boundary points an upper bound. Only the pairs the bounds leave open get the SOCP of eq. (3), and
    a pair of components already joined is not examined again.
    """
    m = len(ellipses)
    if m == 0:
        return np.zeros(0, dtype=int)
    connected = np.arange(m) if connected is None else np.asarray(connected)
    centres = np.array([e.center for e in ellipses])
    radii = np.array([e.semi_axes[0] for e in ellipses])
    i, j = np.triu_indices(m, k=1)
    lower = np.linalg.norm(centres[i] - centres[j], axis=1) - radii[i] - radii[j]
    open_pair = (lower < min_gap_m) & (connected[i] != connected[j])
    i, j = i[open_pair], j[open_pair]
    boundary = np.stack([e.boundary(_BOUNDARY_SAMPLES) for e in ellipses])
    upper = np.array(
        [np.min(np.linalg.norm(boundary[a][:, None, :] - boundary[b][None, :, :], axis=2)) for a, b in zip(i, j)]
    ).reshape(-1)
    certain = upper < min_gap_m
    links = [(i[certain], j[certain])]
    labels = _components(m, connected, links)
    for a, b in zip(i[~certain], j[~certain]):
        if labels[a] != labels[b] and ellipse_gap(ellipses[a], ellipses[b], solver=solver).distance_m < min_gap_m:
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
