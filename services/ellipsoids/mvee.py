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

Both work in whitened coordinates (centred, unit spread along both principal axes: the MVEE commutes
with affine maps), and both end with the same containment guarantee: the fitted ellipse is scaled
about its centre by the largest level ‖A xᵢ + b‖ if that exceeds 1, so every input point has level
≤ 1 up to rounding. The cvxpy route is handed the convex-hull vertices alone (the MVEE of a set is
the MVEE of its hull), one cone per vertex. The numpy route takes every point: an interior point
never enters its support, and checking it costs the Todd–Yildirim test less than Qhull's call costs
(about 64 µs at these sizes: the numpy fit was no slower without it anywhere from 8 to 10 000 points,
measured; at 100 000 points it was 30 % slower).

Degenerate inputs (one point, duplicates, collinear points, or a hull thinner than `eps_m`) have no
finite-area MVEE; they are fattened to P ⊕ {±eps e₁, ±eps e₂}, giving a thin ellipse that still
contains the points.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.linalg import lapack
from scipy.spatial import ConvexHull

from services.geometry import Ellipse, FloatArray

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


@dataclass(frozen=True)
class _Whitened:
    """The (possibly fattened) set in whitened coordinates: x = shift + (u · spread) @ axes.

    `index` holds the rows of `z` the points `u` come from (None when the set was fattened: its
    points are not in `z`).
    """

    u: FloatArray
    shift: FloatArray
    axes: FloatArray  # rows: the principal directions
    spread: FloatArray
    index: IntArray | None

    def ellipse(self, center: FloatArray, shape: FloatArray, *, z: FloatArray, max_violation: float) -> Ellipse:
        """{u : (u − c)ᵀ P (u − c) ≤ 1} as {x : ‖A x + b‖ ≤ 1}, scaled about its centre to contain `z`.

        With W = diag(1/spread) · axes (x − shift ↦ u), the world form is S = Wᵀ P W, and A = S^{1/2}
        in closed form for 2 × 2 (√S = (S + √det S · I) / √(tr S + 2√det S)). A point of `z` further
        out than level 1 + `max_violation` is a failed fit.
        """
        W = self.axes / self.spread[:, None]
        S = W.T @ shape @ W
        (s11, s12), (_, s22) = S.tolist()
        root_det = math.sqrt(max(s11 * s22 - s12 * s12, 0.0))
        scale = math.sqrt(s11 + s22 + 2.0 * root_det)
        A = np.array([[s11 + root_det, s12], [s12, s22 + root_det]]) / scale
        x = self.shift + (center * self.spread) @ self.axes
        worst = float(np.sqrt(np.max(np.sum(((z - x) @ A) ** 2, axis=1))))
        if worst > 1.0 + max_violation:
            raise FitError(f"fitted ellipse misses a point by level {worst:.3g} (> 1 + {max_violation:g})")
        if worst > 1.0:
            A = A / (worst * (1.0 + 4.0 * np.finfo(float).eps))
        return Ellipse(A=A, b=-A @ x)


def _whiten(z: FloatArray, *, eps_m: float, hull: bool) -> _Whitened:
    """The set in whitened coordinates (centred, unit spread along both principal axes); only its hull
    vertices when `hull`.

    The set is degenerate when its spread across its principal axis is below `eps_m` (collinear,
    duplicate or single points); it is then replaced by its two extreme points along the principal
    axis ⊕ {±eps v₁, ±eps v₂}, v the principal axes, a set that contains the original points (a cross
    along x and y instead would leave a band only eps/√2 wide about a diagonal line). The MVEE is
    affine-equivariant (MVEE(T P) = T MVEE(P)), so fitting in coordinates where the set has unit
    spread along both principal axes gives the same ellipse, and a 10 m × 2 mm set is as well
    conditioned as a disc; and it is the MVEE of the hull vertices alone.
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
    unit = (centred @ vt.T) / spread
    index = ConvexHull(unit).vertices if hull else np.arange(len(unit))
    return _Whitened(unit[index], shift, vt, spread, None if degenerate else index)


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
    whitened = _whiten(z, eps_m=eps_m, hull=True)
    vertices = whitened.u
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
    center = np.linalg.solve(A_unit, -np.asarray(b.value, dtype=float))
    return whitened.ellipse(center, A_unit @ A_unit, z=z, max_violation=_MAX_SOLVER_VIOLATION)


# --------------------------------------------------------------------------- numpy route

_ACTIVE_SET_ROUNDS = 8
# Todd–Yildirim steps before the first Newton round: they bring the start's worst violators in, so that
# round usually works on the right support (docs/benchmarks.md, measurement history).
_WARM_UP_STEPS = 3
_LIFT = 3.0  # d + 1 for d = 2: at the optimum Mᵢ = qᵢᵀ X⁻¹ qᵢ equals 3 on the support and ≤ 3 elsewhere.


def _solve(a: FloatArray, b: FloatArray) -> FloatArray:
    """a⁻¹ b by LAPACK's gesv, called directly: on the 3 × 3 and at most 6 × 6 systems here numpy.linalg's
    wrapper costs several times the solve (numpy.linalg.solve 6.1 µs, gesv 1.3 µs; the same routine,
    the same result). Raises LinAlgError, as numpy.linalg.solve does, when a is singular."""
    _, _, x, info = lapack.dgesv(a, b)
    if info != 0:
        raise np.linalg.LinAlgError(f"singular matrix (gesv info {info})")
    return x


def _todd_yildirim(Q: FloatArray, u: FloatArray, *, tol: float, max_iter: int) -> tuple[FloatArray, bool]:
    """Khachiyan's coordinate ascent with Todd–Yildirim away/drop steps on the dual of eq. (1).

    X(u) = Q diag(u) Qᵀ, Mᵢ = qᵢᵀ X⁻¹ qᵢ. A toward step moves weight λ = (Mⱼ − 3)/(3 (Mⱼ − 1)) onto the
    worst point j; an away step takes weight off the support point k with the smallest Mₖ (dropping
    it when the step reaches uₖ = 0). X⁻¹ and M are updated by Sherman–Morrison. Stops when
    max M ≤ 3 (1 + tol) and min over the support ≥ 3 (1 − tol); returns (u, whether it stopped so).
    """
    u = u.copy()
    Xi = _solve((Q * u) @ Q.T, np.eye(3))
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

    Gradient Mᵢ = qᵢᵀ X⁻¹ qᵢ, Hessian −(qᵢᵀ X⁻¹ qⱼ)² = −(K∘K)ᵢⱼ. The Newton system
    [[K∘K, 1], [1ᵀ, 0]] [d; ν] = [M; 0] has a closed form: K diag(u) K = K on the support, so
    (K∘K) u = M, and the step is d = u − w / Σw with (K∘K) w = 1 (least squares when K∘K is
    singular, which happens when more than five points lie on the optimal ellipse, e.g. a regular
    polygon). The step is truncated to keep u ≥ 0, dropping the point that blocks. On the right
    support this converges quadratically; whatever it leaves unfinished the final Todd–Yildirim pass
    completes.
    """
    u = u.copy()
    support = np.flatnonzero(u)
    for _ in range(max_iter):
        Qs, us = Q[:, support], u[support]
        K = Qs.T @ _solve((Qs * us) @ Qs.T, Qs)
        if float(np.abs(K.diagonal() - _LIFT).max()) <= _LIFT * tol * 0.1:
            break
        H, ones = K * K, np.ones(len(support))
        try:
            w = _solve(H, ones)
        except np.linalg.LinAlgError:
            w = np.linalg.lstsq(H, ones, rcond=None)[0]
        total = float(w.sum())
        if not total > 0.0:
            break
        d = us - w / total
        blocking = d < 0.0
        alpha = min(1.0, float((-us[blocking] / d[blocking]).min(initial=np.inf)))
        us = us + alpha * d
        us[us < 1e-14] = 0.0
        u[support] = us / us.sum()
        support = support[us > 0.0]
    return u


def mvee_fast(points: ArrayLike, *, tol: float = 1e-9, eps_m: float = 1e-3, max_iter: int = 100_000) -> Ellipse:
    """Löwner–John ellipse of `points` by the dual of eq. (1), in numpy (`mvee_fast_support` without the support)."""
    return mvee_fast_support(points, tol=tol, eps_m=eps_m, max_iter=max_iter)[0]


def mvee_fast_support(
    points: ArrayLike, *, tol: float = 1e-9, eps_m: float = 1e-3, max_iter: int = 100_000
) -> tuple[Ellipse, IntArray | None]:
    """Löwner–John ellipse of `points` by the dual of eq. (1), in numpy, and its support.

    From the Kumar–Yildirim start (Kumar & Yildirim 2005: the extreme points along each axis, in
    whitened coordinates most of the support), a few Todd–Yildirim steps bring in the worst
    violators; then rounds of Newton on the support, each followed by one Todd–Yildirim step that
    brings in a violator or drops a point, until its check passes: on return max Mᵢ ≤ 3 (1 + tol),
    which bounds the area above the optimum by a factor (1 + tol) (Khachiyan's bound), and the
    ellipse is scaled to contain every point. From the optimal weights u: centre c = Σ uᵢ xᵢ, shape
    E = (Σ uᵢ xᵢ xᵢᵀ − c cᵀ)⁻¹ / 2, A = E^{1/2}, b = −A c.

    The support is the rows of `points` that carry weight (uᵢ > 0); None for a degenerate set, whose
    ellipse is fitted to fattened points. The weights depend on the support alone, so they are the
    same answer for any set that holds the support and lies in the ellipse (what the covers reuse).
    """
    z = _as_points(points)
    whitened = _whiten(z, eps_m=eps_m, hull=False)
    unit = whitened.u
    Q = np.vstack([unit.T, np.ones(len(unit))])
    # Kumar–Yildirim start: the extreme points along both (whitened) axes, usually most of the support.
    u = np.zeros(len(unit))
    u[np.concatenate([np.argmin(unit, axis=0), np.argmax(unit, axis=0)])] = 1.0
    if np.count_nonzero(u) < 3:  # a point extreme along both axes twice: no ellipse through two points
        u[:] = 1.0
    u /= u.sum()
    u, done = _todd_yildirim(Q, u, tol=tol, max_iter=_WARM_UP_STEPS)
    for _ in range(_ACTIVE_SET_ROUNDS):
        if done:
            break
        # Newton on the support; one Todd–Yildirim step then brings in a violator or drops a point.
        u = _newton_polish(Q, u, tol=tol)
        u, done = _todd_yildirim(Q, u, tol=tol, max_iter=1)
    if not done:
        u, done = _todd_yildirim(Q, u, tol=tol, max_iter=max_iter)
    if not done:
        raise FitError(f"Todd–Yildirim iterations did not reach tolerance {tol:g} in {max_iter} steps")
    c = unit.T @ u
    (s11, s12), (_, s22) = ((unit.T * u) @ unit - np.outer(c, c)).tolist()
    det = s11 * s22 - s12 * s12
    if not (s11 > 0.0 and det > 0.0):  # Sylvester's criterion
        raise FitError("MVEE weights collapsed onto a degenerate support")
    shape = np.array([[s22, -s12], [-s12, s11]]) / (2.0 * det)  # (2 Σ)⁻¹
    ellipse = whitened.ellipse(c, shape, z=z, max_violation=max(1e-3, 10.0 * tol))
    index = whitened.index
    return ellipse, None if index is None else index[u > 0.0]
