"""Minimum-volume enclosing ellipses (Löwner–John), the paper's eq. (1) corrected.

The paper's eq. (1) reads "maximise log det(A⁻¹)"; with the ellipse written {z : ‖A z + b‖₂ ≤ 1} the
area is π / det A, so the minimum-area ellipse MAXIMISES log det A:

    maximise    log det A
    subject to  ‖A xᵢ + b‖₂ ≤ 1,   i = 1 … m,      A ≻ 0.

Two routes solve it:

* `mvee` — the convex programme above in cvxpy (Boyd & Vandenberghe, Convex Optimization §8.4.1),
  built once per padded point count with a `cp.Parameter` for the points and re-solved.
* `mvee_fast` — the dual problem, maximise log det(Q diag(u) Qᵀ) over the simplex with qᵢ = (xᵢ, 1),
  solved by Newton steps on the support from the Kumar–Yildirim start (the extreme points along each
  axis), the support kept right by Khachiyan's algorithm with Todd–Yildirim away steps (Todd & Yildirim
  2007, "On Khachiyan's algorithm for the computation of minimum-volume enclosing ellipsoids"); pure
  numpy.

Both work on the convex-hull vertices (the MVEE of a set is the MVEE of its hull), in whitened
coordinates (centred, unit spread along both principal axes: the MVEE commutes with affine maps),
and both end with the same containment guarantee: the fitted ellipse is scaled about its centre by
the largest level ‖A xᵢ + b‖ if that exceeds 1, so every input point has level ≤ 1 up to rounding.

Degenerate inputs (one point, duplicates, collinear points, or a hull thinner than `eps_m`) have no
finite-area MVEE; they are fattened to P ⊕ {±eps e₁, ±eps e₂}, giving a thin ellipse that still
contains the points.
"""

from __future__ import annotations

import functools

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial import ConvexHull

from cvxnav.geometry import Ellipse, FloatArray

IntArray = NDArray[np.intp]

__all__ = ["FitError", "mvee", "mvee_fast", "mvee_fast_support"]

_ACCEPTED_STATUSES = ("optimal", "optimal_inaccurate")  # cvxpy's status strings
# A solver answer whose worst point sits further out than this is a failed solve, not rounding.
_MAX_SOLVER_VIOLATION = 1e-4


class FitError(RuntimeError):
    """An ellipse could not be fitted (bad input or a solver that did not reach an optimum)."""


# --------------------------------------------------------------------------- shared preprocessing


def _as_points(points: ArrayLike) -> FloatArray:
    z = np.asarray(points, dtype=float)
    if z.ndim == 1 and z.size == 2:
        z = z.reshape(1, 2)
    if z.ndim != 2 or z.shape[1] != 2 or z.shape[0] == 0:
        raise FitError(f"points must be a non-empty (n, 2) array, got shape {z.shape}")
    if not np.all(np.isfinite(z)):
        raise FitError("points must be finite")
    return z


def _support_points(z: FloatArray, *, eps_m: float) -> tuple[FloatArray, FloatArray, FloatArray, IntArray | None]:
    """Hull vertices of the (possibly fattened) set, in whitened coordinates.

    Returns (vertices_normalised, shift, transform, index) with x = shift + transform · x_normalised
    and `index` the vertices' rows of `z` (None when the set was fattened: its vertices are not in `z`).
    The set is degenerate when its spread across its principal axis is below `eps_m` (collinear,
    duplicate or single points); it is then replaced by its two extreme points along the principal
    axis ⊕ {±eps v₁, ±eps v₂}, v the principal axes, a set that contains the original points (a cross
    along x and y instead would leave a band only eps/√2 wide about a diagonal line). The MVEE is affine-equivariant
    (MVEE(T P) = T MVEE(P)), so fitting in coordinates where the set has unit spread along both
    principal axes gives the same ellipse, and a 10 m × 2 mm set is as well conditioned as a disc.
    """
    shift = z.mean(axis=0)
    centred = z - shift
    _, sv, vt = np.linalg.svd(centred, full_matrices=False) if len(z) > 1 else (None, np.zeros(1), np.eye(2))
    across = centred @ vt[-1]
    degenerate = len(sv) < 2 or np.ptp(across) < eps_m
    if degenerate:
        along = centred @ vt[0]
        ends = centred[[int(np.argmin(along)), int(np.argmax(along))]]
        cross = eps_m * np.array([vt[0], -vt[0], vt[1], -vt[1]])
        centred = (ends[:, None, :] + cross[None, :, :]).reshape(-1, 2)
        shift = shift + centred.mean(axis=0)
        centred = centred - centred.mean(axis=0)
        _, sv, vt = np.linalg.svd(centred, full_matrices=False)
    spread = sv / np.sqrt(len(centred))
    transform = vt.T * spread  # columns: principal axes scaled by their spread
    unit = (centred @ vt.T) / spread
    hull = ConvexHull(unit)
    return unit[hull.vertices], shift, transform, None if degenerate else hull.vertices


def _ellipse(
    A_unit: FloatArray, b_unit: FloatArray, *, shift: FloatArray, transform: FloatArray, z: FloatArray, max_violation: float
) -> Ellipse:
    """‖A' T⁻¹(x − shift) + b'‖ ≤ 1 as {x : ‖A x + b‖ ≤ 1}, scaled about its centre to contain `z`.

    A symmetric: A = (MᵀM)^{1/2} with M = A' T⁻¹, in closed form for 2 × 2 (√S = (S + √det S · I) /
    √(tr S + 2√det S)). A point of `z` further out than level 1 + `max_violation` is a failed fit.
    """
    M = A_unit @ np.linalg.inv(transform)
    center = shift + transform @ np.linalg.solve(A_unit, -b_unit)
    S = M.T @ M
    root_det = np.sqrt(max(S[0, 0] * S[1, 1] - S[0, 1] * S[1, 0], 0.0))
    A = (S + root_det * np.eye(2)) / np.sqrt(S[0, 0] + S[1, 1] + 2.0 * root_det)
    worst = float(np.sqrt(np.max(np.sum(((z - center) @ A) ** 2, axis=1))))
    if worst > 1.0 + max_violation:
        raise FitError(f"fitted ellipse misses a point by level {worst:.3g} (> 1 + {max_violation:g})")
    if worst > 1.0:
        A = A / (worst * (1.0 + 4.0 * np.finfo(float).eps))
    return Ellipse(A=A, b=-A @ center)


# --------------------------------------------------------------------------- cvxpy route


def _bucket(count: int) -> int:
    """The padded size: the smallest power of two ≥ count, at least 8."""
    return max(8, 1 << (count - 1).bit_length())


@functools.lru_cache(maxsize=None)
def _mvee_problem(size: int):
    """Eq. (1) for `size` points, built once; the points are a (2, size) Parameter (DPP: A @ P).

    cvxpy is imported here, on first use: the import alone costs about 0.6 s, and the covers the
    planner builds use the numpy route below.
    """
    import cvxpy as cp

    points = cp.Parameter((2, size), name="points")
    A = cp.Variable((2, 2), PSD=True, name="A")
    b = cp.Variable(2, name="b")
    constraints = [cp.norm(A @ points + b[:, None], 2, axis=0) <= 1.0]
    problem = cp.Problem(cp.Maximize(cp.log_det(A)), constraints)
    return problem, points, A, b


def mvee(points: ArrayLike, *, solver: str = "CLARABEL", eps_m: float = 1e-3) -> Ellipse:
    """Löwner–John ellipse of `points` by the convex programme of eq. (1) (maximise log det A).

    The hull vertices are padded to a bucket size by repeating one vertex (a duplicate does not
    change the MVEE) so that one compiled problem per bucket serves every call. Not thread-safe:
    the cached problems are shared.
    """
    z = _as_points(points)
    vertices, shift, transform, _ = _support_points(z, eps_m=eps_m)
    size = _bucket(len(vertices))
    padded = np.vstack([vertices, np.repeat(vertices[:1], size - len(vertices), axis=0)])
    problem, param, A, b = _mvee_problem(size)
    param.value = padded.T
    from cvxpy.error import SolverError

    try:
        problem.solve(solver=solver)
    except SolverError as exc:
        raise FitError(f"MVEE solve failed with {solver}: {exc}") from exc
    if problem.status not in _ACCEPTED_STATUSES or A.value is None:
        raise FitError(f"MVEE solve with {solver} ended with status {problem.status!r}")
    A_unit = 0.5 * (A.value + A.value.T)
    if np.linalg.eigvalsh(A_unit)[0] <= 0.0:
        raise FitError(f"MVEE solve with {solver} returned a shape matrix that is not positive definite")
    return _ellipse(
        A_unit, np.asarray(b.value, dtype=float), shift=shift, transform=transform, z=z, max_violation=_MAX_SOLVER_VIOLATION
    )


# --------------------------------------------------------------------------- numpy route

_ACTIVE_SET_ROUNDS = 8
_LIFT = 3.0  # d + 1 for d = 2: at the optimum Mᵢ = qᵢᵀ X⁻¹ qᵢ equals 3 on the support and ≤ 3 elsewhere.


def _todd_yildirim(Q: FloatArray, u: FloatArray, *, tol: float, max_iter: int) -> tuple[FloatArray, bool]:
    """Khachiyan's coordinate ascent with Todd–Yildirim away/drop steps on the dual of eq. (1).

    X(u) = Q diag(u) Qᵀ, Mᵢ = qᵢᵀ X⁻¹ qᵢ. A toward step moves weight λ = (Mⱼ − 3)/(3 (Mⱼ − 1)) onto the
    worst point j; an away step takes weight off the support point k with the smallest Mₖ (dropping
    it when the step reaches uₖ = 0). X⁻¹ and M are updated by Sherman–Morrison. Stops when
    max M ≤ 3 (1 + tol) and min over the support ≥ 3 (1 − tol); returns (u, whether it stopped so).
    """
    u = u.copy()
    Xi = np.linalg.inv((Q * u) @ Q.T)
    M = np.einsum("ij,ij->j", Q, Xi @ Q)
    for _ in range(max_iter):
        j = int(np.argmax(M))
        k = int(np.argmin(np.where(u > 0.0, M, np.inf)))
        up, down = M[j] / _LIFT - 1.0, 1.0 - M[k] / _LIFT
        if max(up, down) <= tol:
            return u, True
        if up >= down:
            idx, lam = j, (M[j] - _LIFT) / (_LIFT * (M[j] - 1.0))
        else:
            idx, lam = k, -min((_LIFT - M[k]) / (_LIFT * (M[k] - 1.0)), u[k] / (1.0 - u[k]))
        w = Xi @ Q[:, idx]
        c = lam / (1.0 - lam + lam * M[idx])
        Xi = (Xi - c * np.outer(w, w)) / (1.0 - lam)
        M = (M - c * (Q.T @ w) ** 2) / (1.0 - lam)
        u *= 1.0 - lam
        u[idx] += lam
        if u[idx] < 1e-15:
            u[idx] = 0.0
    return u, False


def _newton_polish(Q: FloatArray, u: FloatArray, *, tol: float, max_iter: int = 12) -> FloatArray:
    """Newton's method for max log det(Q diag(u) Qᵀ) s.t. Σu = 1 on the current support.

    Gradient Mᵢ = qᵢᵀ X⁻¹ qᵢ, Hessian −(qᵢᵀ X⁻¹ qⱼ)²; each step solves the equality-constrained Newton
    system [[(K∘K), 1], [1ᵀ, 0]] [d; ν] = [M; 0] (least squares when it is singular, which happens when
    more than five points lie on the optimal ellipse, e.g. a regular polygon) and is truncated to keep
    u ≥ 0, dropping the point that blocks. On the right support this converges quadratically; whatever
    it leaves unfinished the final Todd–Yildirim pass completes.
    """
    u = u.copy()
    for _ in range(max_iter):
        S = np.flatnonzero(u)
        Qs, us = Q[:, S], u[S]
        K = Qs.T @ np.linalg.solve((Qs * us) @ Qs.T, Qs)
        g = K.diagonal()
        if np.abs(g - _LIFT).max() <= _LIFT * tol * 0.1:
            break
        n = len(S)
        kkt = np.zeros((n + 1, n + 1))
        kkt[:n, :n] = K * K
        kkt[n, :n] = kkt[:n, n] = 1.0
        rhs = np.zeros(n + 1)
        rhs[:n] = g
        try:
            d = np.linalg.solve(kkt, rhs)[:n]
        except np.linalg.LinAlgError:
            d = np.linalg.lstsq(kkt, rhs, rcond=None)[0][:n]
        blocking = d < 0.0
        alpha = min(1.0, float((-us[blocking] / d[blocking]).min(initial=np.inf)))
        us = us + alpha * d
        us[us < 1e-14] = 0.0
        total = us.sum()
        if total <= 0.0:
            break
        u[S] = us / total
    return u


def mvee_fast(points: ArrayLike, *, tol: float = 1e-9, eps_m: float = 1e-3, max_iter: int = 100_000) -> Ellipse:
    """Löwner–John ellipse of `points` by the dual of eq. (1), in numpy (`mvee_fast_support` without the support)."""
    return mvee_fast_support(points, tol=tol, eps_m=eps_m, max_iter=max_iter)[0]


def mvee_fast_support(
    points: ArrayLike, *, tol: float = 1e-9, eps_m: float = 1e-3, max_iter: int = 100_000
) -> tuple[Ellipse, IntArray | None]:
    """Löwner–John ellipse of `points` by the dual of eq. (1), in numpy, and its support.

    Newton on the support from the Kumar–Yildirim start (Kumar & Yildirim 2005: the extreme points
    along each axis; in whitened coordinates most of the support, so no Todd–Yildirim warm-up is
    needed), Todd–Yildirim steps to bring in violators, then the full Todd–Yildirim check: on return max Mᵢ ≤ 3 (1 + tol), which bounds the area above the optimum by a
    factor (1 + tol) (Khachiyan's bound), and the ellipse is scaled to contain every point. From the
    optimal weights u: centre c = Σ uᵢ xᵢ, shape E = (Σ uᵢ xᵢ xᵢᵀ − c cᵀ)⁻¹ / 2, A = E^{1/2}, b = −A c.

    The support is the rows of `points` that carry weight (uᵢ > 0); None for a degenerate set, whose
    ellipse is fitted to fattened points. The weights depend on the support alone, so they are the
    same answer for any set that holds the support and lies in the ellipse (what the covers reuse).
    """
    z = _as_points(points)
    vertices, shift, transform, index = _support_points(z, eps_m=eps_m)
    Q = np.vstack([vertices.T, np.ones(len(vertices))])
    # Kumar–Yildirim start: the extreme points along both (whitened) axes, usually most of the support.
    u = np.zeros(len(vertices))
    u[np.concatenate([np.argmin(vertices, axis=0), np.argmax(vertices, axis=0)])] = 1.0
    if np.count_nonzero(u) < 3:  # a point extreme along both axes twice: no ellipse through two points
        u[:] = 1.0
    u /= u.sum()
    done = False
    for _ in range(_ACTIVE_SET_ROUNDS):
        # Newton on the support; one Todd–Yildirim step then brings in a violator or drops a point.
        u = _newton_polish(Q, u, tol=tol)
        u, done = _todd_yildirim(Q, u, tol=tol, max_iter=1)
        if done:
            break
    if not done:
        u, done = _todd_yildirim(Q, u, tol=tol, max_iter=max_iter)
    if not done:
        raise FitError(f"Todd–Yildirim iterations did not reach tolerance {tol:g} in {max_iter} steps")
    c = vertices.T @ u
    sigma = (vertices.T * u) @ vertices - np.outer(c, c)
    w, R = np.linalg.eigh(sigma)
    if w[0] <= 0.0:
        raise FitError("MVEE weights collapsed onto a degenerate support")
    A_unit = R @ np.diag(1.0 / np.sqrt(2.0 * w)) @ R.T
    ellipse = _ellipse(A_unit, -A_unit @ c, shift=shift, transform=transform, z=z, max_violation=max(1e-3, 10.0 * tol))
    return ellipse, None if index is None else index[u > 0.0]
