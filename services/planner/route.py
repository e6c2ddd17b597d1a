"""Global choice of the way round every obstacle: the exact shortest route among the ellipses.

The outside constraint ‖A z + b‖ ≥ 1 is not convex, so a local method started from the straight line
settles on whichever side of an obstacle it happens to start on, and a U-shaped group of obstacles
traps it. Among convex obstacles a shortest path is made of segments tangent to the obstacles (or
ending at a terminal: the start or a goal) and arcs along their boundaries: the tangent graph (Liu &
Arimoto 1992; Latombe, Robot Motion Planning, ch. 4). It is built here exactly, on the ellipses
themselves scaled to the planning level ‖A z + b‖ = level (so the refinement starts on its own
feasible set), rather than on polygons round them: a polygon's corners close marginal passages and
move tangent points, and no polygon size is right for every map.

* Common tangents of ellipses i and j. In i's unit-disc frame the tangent line at angle θ,
  {x : nᵀx = 1} with n = (cos θ, sin θ), touches j (centre c, shape S there) exactly when
  nᵀc ± √(nᵀSn) = 1 (j's support function: + an outer tangent, both on one side; − an inner one).
  Squared, F(θ) = (1 − nᵀc)² − nᵀSn is a trigonometric polynomial of degree 2, a quartic in e^{iθ}:
  at most four tangents. When j's bounding disc is clear of the unit circle (|c| > 1 + ρ, ρ² the
  largest eigenvalue of S) there are exactly four, one of each sign in each of the windows
  |θ − ∠c| ∈ [acos((1 + ρ)/|c|), acos((1 − ρ)/|c|)], where the sign is known at both ends: found by
  safeguarded Newton — only where the window meets a free arc of i, and the window of j where that
  tangent touches j (the same construction from j's side) a free arc of j: the graph drops the rest.
  Close pairs (few: neighbours) bracket F's roots on a grid (`_trig_roots`).
* Tangents from a terminal: at angles ∠q ± acos(1/|q|) for q the terminal in the unit-disc frame.
* Arcs. Each ellipse's boundary is cut where another ellipse crosses it (‖M u(θ) + d‖² = 1, again a
  degree-2 trigonometric polynomial) or a map bound does (a cosine); between consecutive cuts an arc
  is wholly free or wholly blocked (how many obstacles cover it is counted round the boundary).
  Consecutive tangent points on a free arc are joined by it, at its exact length (Gauss–Legendre on
  the speed ‖A⁻¹ u′(θ)‖).

Tangent points inside another ellipse are dropped; every remaining tangent segment is checked exactly
against the other ellipses (eq. 2 on the continuous segment). In a dense field nearly all of them are
blocked, most through the depth of some ellipse: a point sampled on the segment in a grid cell wholly
inside an ellipse proves that at a fraction of the exact test's cost (`_DeepCells`, built once enough
segments wait for a test to pay for the grid), so only the rest get the exact one. Dijkstra then picks
every side globally. Only points x with ‖x − from‖ + ‖x − to‖ ≤ bound can lie on a leg no longer than
`bound`, so the graph is built within that informed ellipse, starting a little above the straight
distance and widening it (to the length of a route found beyond the bound, else by a factor) until the
leg found is within it — then it is the exact shortest. Tangents, cuts and segment tests are kept as it
widens.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.sparse import csr_array
from scipy.sparse.csgraph import dijkstra

from services.geometry import Ellipse, EllipseStack, FloatArray

_CHUNK = 20_000  # segments checked at once: bounds the memory of the broad phase
_ROOT_TOL = 1e-6  # a quartic root this close to the unit circle is a real angle
_BLOCK_TOL = 1e-9  # a segment touching a third ellipse (level 1 up to rounding) is clear
_ARC_PIECE_RAD = np.pi / 8  # Gauss–Legendre pieces for arc lengths
_ARC_VERTEX_RAD = np.pi / 16  # polyline vertices of an arc in the route returned
_DEEP_CELL = 0.5  # grid cells of the blocked-segment proof, × the median smallest semi-axis
# Segments to test at once for the grid to pay: below it the exact test alone is faster (corner-trap tests
# 29 then 50 segments, and its grid cost 0.65 ms to save 0.05; a 200-obstacle field tests thousands, and
# the grid takes its route search from 360 to 90 ms).
_DEEP_MIN_SEGMENTS = 256
_BOUND_FACTORS = (1.03, 1.1, 1.2, 1.35, 1.6, 2.2, np.inf)  # informed-ellipse bounds tried, × the straight distance
_GL_NODES, _GL_WEIGHTS = np.polynomial.legendre.leggauss(6)


@dataclass(frozen=True)
class Route:
    """The shortest route, one polyline per leg, and each leg's exact length.

    Arcs are polylines circumscribing the scaled ellipse (every chord tangent to it), so the whole
    polyline stays at level ≥ `level`; its length exceeds the exact one by at most 1/cos(π/32) − 1.
    """

    legs: list[FloatArray]
    lengths_m: list[float]


@dataclass(frozen=True)
class _Frames:
    """The scaled ellipses {z : ‖A z + b‖ ≤ 1} with their inverses, centres and reaches."""

    A: FloatArray
    b: FloatArray
    Ainv: FloatArray
    centers: FloatArray
    reach: FloatArray
    shape: FloatArray  # Q = A⁻¹A⁻ᵀ: the ellipse is {c + A⁻¹v : ‖v‖ ≤ 1}, support function √(nᵀQn)

    @classmethod
    def of(cls, stack: EllipseStack, scale: FloatArray) -> _Frames:
        A = stack.A / scale[:, None, None]
        b = stack.b / scale[:, None]
        Ainv = np.linalg.inv(A)
        return cls(A=A, b=b, Ainv=Ainv, centers=-np.einsum("mij,mj->mi", Ainv, b), reach=stack.reach * scale,
                   shape=np.einsum("kij,klj->kil", Ainv, Ainv))

    def relative(self, i: FloatArray, j: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Ellipse j's centre c = Aᵢcⱼ + bᵢ (k, 2) and shape S = Aᵢ Qⱼ Aᵢᵀ (k, 2, 2) in i's unit-disc frame.

        Written out entry by entry (a batch of 2 × 2 products is several times faster so than by einsum),
        summed in einsum's order: Sₗₘ = (Aₗ₀Q₀₀Aₘ₀ + Aₗ₀Q₀₁Aₘ₁) + (Aₗ₁Q₁₀Aₘ₀ + Aₗ₁Q₁₁Aₘ₁).
        """
        A, Q, z = self.A[i], self.shape[j], self.centers[j]
        b = self.b[i]
        c = np.empty((len(i), 2))
        S = np.empty((len(i), 2, 2))
        for l in range(2):
            c[:, l] = A[:, l, 0] * z[:, 0] + A[:, l, 1] * z[:, 1] + b[:, l]
            for m in range(2):
                S[:, l, m] = (A[:, l, 0] * Q[:, 0, 0] * A[:, m, 0] + A[:, l, 0] * Q[:, 0, 1] * A[:, m, 1]) + (
                    A[:, l, 1] * Q[:, 1, 0] * A[:, m, 0] + A[:, l, 1] * Q[:, 1, 1] * A[:, m, 1])
        return c, S

    def point(self, owner: FloatArray, u: FloatArray) -> FloatArray:
        """World points A⁻¹(u − b) of unit-frame points u on ellipses `owner`."""
        return np.einsum("kij,kj->ki", self.Ainv[owner], u - self.b[owner])

    def angle(self, owner: FloatArray, z: FloatArray) -> FloatArray:
        u = np.einsum("kij,kj->ki", self.A[owner], z) + self.b[owner]
        return np.mod(np.arctan2(u[:, 1], u[:, 0]), 2.0 * np.pi)


def _distance(x: FloatArray, y: FloatArray) -> FloatArray:
    """‖x − y‖ row by row (as np.linalg.norm sums it, without its (k, 2) temporaries)."""
    dx, dy = x[..., 0] - y[..., 0], x[..., 1] - y[..., 1]
    return np.sqrt(dx * dx + dy * dy)


def _unit(theta: FloatArray) -> FloatArray:
    return np.stack([np.cos(theta), np.sin(theta)], axis=-1)


def _trig(coef: FloatArray, theta: FloatArray) -> tuple[FloatArray, FloatArray]:
    """a₀ + a₁ cos θ + b₁ sin θ + a₂ cos 2θ + b₂ sin 2θ and its derivative; coef (..., 5) broadcast on θ."""
    a0, a1, b1, a2, b2 = (coef[..., k, None] for k in range(5))
    c, s, c2, s2 = np.cos(theta), np.sin(theta), np.cos(2 * theta), np.sin(2 * theta)
    return a0 + a1 * c + b1 * s + a2 * c2 + b2 * s2, -a1 * s + b1 * c - 2 * a2 * s2 + 2 * b2 * c2


def _quadratic_form_coef(K: FloatArray, e: FloatArray, const: FloatArray) -> FloatArray:
    """uᵀK u + 2 eᵀu + const with u = (cos θ, sin θ), as trigonometric coefficients (..., 5)."""
    return np.stack(
        [
            0.5 * (K[:, 0, 0] + K[:, 1, 1]) + const,
            2.0 * e[:, 0],
            2.0 * e[:, 1],
            0.5 * (K[:, 0, 0] - K[:, 1, 1]),
            K[:, 0, 1],
        ],
        axis=-1,
    )


def _bracketed_root(
    g, lo: FloatArray, hi: FloatArray, start: FloatArray | None = None, f_lo: FloatArray | None = None
) -> FloatArray:
    """Roots of g (value and derivative at (θ, indices)) in brackets [lo, hi] with a sign change.

    Newton steps from `start` (default: the middles) that leave the bracket become bisections
    (safeguarded Newton), element by element. `f_lo`: g's values at `lo`, when the caller has them.
    """
    lo, hi = lo.copy(), hi.copy()
    every = np.arange(len(lo))
    f_lo = g(lo, every)[0] if f_lo is None else f_lo.copy()
    x = 0.5 * (lo + hi) if start is None else np.clip(start, np.minimum(lo, hi), np.maximum(lo, hi))
    active = every
    for _ in range(60):
        xa, la, ha = x[active], lo[active], hi[active]
        f, df = g(xa, active)
        same = np.sign(f) == np.sign(f_lo[active])
        la, ha = np.where(same, xa, la), np.where(same, ha, xa)
        f_lo[active] = np.where(same, f, f_lo[active])
        step = xa - f / np.where(df != 0.0, df, 1.0)
        inside = (step >= np.minimum(la, ha)) & (step <= np.maximum(la, ha)) & (df != 0.0)
        new = np.where(inside, step, 0.5 * (la + ha))
        x[active], lo[active], hi[active] = new, la, ha
        active = active[np.abs(new - xa) >= 1e-13]
        if not len(active):
            break
    return x


_GRID = 2.0 * np.pi * np.arange(128) / 128
_GRID_BASIS = np.stack([np.ones(128), np.cos(_GRID), np.sin(_GRID), np.cos(2 * _GRID), np.sin(2 * _GRID)])


def _companion_roots(coef: FloatArray) -> tuple[FloatArray, FloatArray]:
    """All real roots by the quartic in z = e^{iθ}: z² times the polynomial is
    (a₂ − i b₂)/2 z⁴ + (a₁ − i b₁)/2 z³ + a₀ z² + (a₁ + i b₁)/2 z + (a₂ + i b₂)/2,
    whose roots on the unit circle are the real roots (then polished by Newton on the real function).
    """
    a0, a1, b1, a2, b2 = (coef[:, k] for k in range(5))
    poly = np.stack([(a2 - 1j * b2) / 2, (a1 - 1j * b1) / 2, a0 + 0j, (a1 + 1j * b1) / 2, (a2 + 1j * b2) / 2], axis=1)
    scale = np.max(np.abs(poly), axis=1)
    lead = poly[:, 0]
    lead = np.where(np.abs(lead) > 1e-13 * scale, lead, 1e-13 * scale + 0j)
    companion = np.zeros((len(coef), 4, 4), dtype=complex)
    companion[:, 0, :] = -poly[:, 1:] / lead[:, None]
    companion[:, 1, 0] = companion[:, 2, 1] = companion[:, 3, 2] = 1.0
    z = np.linalg.eigvals(companion) if len(coef) else np.zeros((0, 4), dtype=complex)
    real = np.abs(np.abs(z) - 1.0) < _ROOT_TOL
    theta = np.angle(z)
    for _ in range(3):
        f, df = _trig(coef, theta)
        theta = theta - np.where(np.abs(df) > 1e-12, f / np.where(np.abs(df) > 1e-12, df, 1.0), 0.0)
    return np.mod(theta, 2.0 * np.pi), real


def _trig_roots(coef: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Real roots θ (k, 4) of each degree-2 trigonometric polynomial, and which are real (k, 4).

    Sign changes on a 128-point grid bracket the roots, refined by safeguarded Newton. Two roots r₁, r₂
    in one grid step [t, t + h] make F(x) = (x − r₁)(x − r₂) F″(ξ)/2 there, so |F| ≤ max|F″| h²/2 at
    both ends of the step (F″ is bounded by |a₁| + |b₁| + 4(|a₂| + |b₂|)); the few polynomials with
    such a step (near-tangent crossings) take the companion-matrix route instead.
    """
    k = len(coef)
    h = _GRID[1]
    values = np.einsum("kc,cg->kg", coef, _GRID_BASIS)
    curvature = np.abs(coef[:, 1]) + np.abs(coef[:, 2]) + 4.0 * (np.abs(coef[:, 3]) + np.abs(coef[:, 4]))
    small = np.abs(values) <= 0.5 * curvature[:, None] * h * h
    hidden = np.any(small[:, :-1] & small[:, 1:], axis=1) | (small[:, -1] & small[:, 0])
    sign = np.sign(values)
    change = np.empty_like(small)  # step t → t + 1 (the last one wrapping round)
    np.not_equal(sign[:, :-1], sign[:, 1:], out=change[:, :-1])
    np.not_equal(sign[:, -1], sign[:, 0], out=change[:, -1])
    rows, cols = np.nonzero(change & ~hidden[:, None])
    slot = np.arange(len(rows)) - np.searchsorted(rows, rows)
    keep = slot < 4
    rows, cols, slot = rows[keep], cols[keep], slot[keep]
    theta = np.zeros((k, 4))
    real = np.zeros((k, 4), dtype=bool)

    def g(x, idx):
        f, df = _trig(coef[rows[idx]], x[:, None])
        return f[:, 0], df[:, 0]

    # Newton starts where the chord between the grid values crosses zero (regula falsi): a root on a grid
    # angle (an axis-aligned wall) is then found at once, where from the middle Newton overshot the end
    # and bisected towards it (corner-trap: 21 evaluations instead of 6).
    v_lo, v_hi = values[rows, cols], values[rows, (cols + 1) % len(_GRID)]
    start = _GRID[cols] + h * v_lo / (v_lo - v_hi)
    theta[rows, slot] = _bracketed_root(g, _GRID[cols], _GRID[cols] + h, start, f_lo=v_lo)
    real[rows, slot] = True
    fallback = np.flatnonzero(hidden)
    if len(fallback):
        theta[fallback], real[fallback] = _companion_roots(coef[fallback])
    return np.mod(theta, 2.0 * np.pi), real


def _window_roots(
    D: FloatArray, phi: FloatArray, S: FloatArray, sign: FloatArray, lo: FloatArray, hi: FloatArray
) -> FloatArray:
    """The root of g(θ) = D cos(θ − φ) − 1 + sign·√(nᵀSn) bracketed by [lo, hi] (sign ±1 each)."""
    s11, s12, s22 = S[:, 0, 0], S[:, 0, 1], S[:, 1, 1]

    def g(theta, k):
        c, s = np.cos(theta), np.sin(theta)
        h = np.sqrt(s11[k] * c * c + 2.0 * s12[k] * c * s + s22[k] * s * s)
        dh = ((s22[k] - s11[k]) * c * s + s12[k] * (c * c - s * s)) / h
        return D[k] * np.cos(theta - phi[k]) - 1.0 + sign[k] * h, -D[k] * np.sin(theta - phi[k]) + sign[k] * dh

    # Start from the root for a circle of j's radius √(nᵀSn) at the window's middle: Newton then
    # needs about three steps.
    mid = 0.5 * (lo + hi)
    radius = np.sqrt(s11 * np.cos(mid) ** 2 + 2.0 * s12 * np.cos(mid) * np.sin(mid) + s22 * np.sin(mid) ** 2)
    side = np.sign(np.sin(mid - phi))
    start = phi + side * np.arccos(np.clip((1.0 - sign * radius) / D, -1.0, 1.0))
    return _bracketed_root(g, lo, hi, start)


@dataclass
class _Segments:
    """Candidate tangent segments: end points, owning ellipses (−1 − k for terminal k), unit-frame angles."""

    p: FloatArray
    q: FloatArray
    owner_p: FloatArray
    owner_q: FloatArray
    theta_p: FloatArray
    theta_q: FloatArray

    @classmethod
    def concat(cls, parts: list[_Segments]) -> _Segments:
        return cls(*(np.concatenate([getattr(s, f) for s in parts]) for f in ("p", "q", "owner_p", "owner_q", "theta_p", "theta_q")))

    def take(self, keep: FloatArray) -> _Segments:
        return _Segments(self.p[keep], self.q[keep], self.owner_p[keep], self.owner_q[keep], self.theta_p[keep], self.theta_q[keep])


def _facing_windows(c: FloatArray, S: FloatArray):
    """For ellipse j (centre c, shape S in i's unit-disc frame): its distance D, whether its bounding
    disc is clear of the unit circle, the angle φ of its centre, and the windows' ends a₁ < a₂: the
    tangents touch the unit circle at angles φ ± [a₁, a₂], widened a little (for a circle, √(nᵀSn) = ρ
    everywhere, the roots sit exactly at the ends)."""
    D = np.linalg.norm(c, axis=1)
    rho = np.sqrt(0.5 * (S[:, 0, 0] + S[:, 1, 1] + np.hypot(S[:, 0, 0] - S[:, 1, 1], 2.0 * S[:, 0, 1])))
    far = D > (1.0 + rho) * (1.0 + 1e-9)
    phi = np.arctan2(c[:, 1], c[:, 0])
    a1 = np.arccos(np.clip((1.0 + rho) / D, -1.0, 1.0)) - 1e-7
    a2 = np.arccos(np.clip((1.0 - rho) / D, -1.0, 1.0)) + 1e-7
    return D, far, phi, a1, a2


def _pair_tangents(frames: _Frames, arcs: _Arcs, i: FloatArray, j: FloatArray) -> _Segments:
    """The common tangents of the ellipse pairs (i, j) whose tangent points both lie on free arcs (both
    ellipses' cuts are known: the graph would drop the others).

    A pair clear of each other (in i's frame) has one tangent of each sign in each of i's two windows,
    left and right of the centre line; a window holding no free arc of i is not solved. When the pair is
    also clear in j's frame, the tangent points on j lie in j's windows just as well, so a window of i is
    solved only if a window of j where its tangent could touch holds a free arc of j. An outer tangent
    touches both on one side of the centre line: it supports the hull of the two, and the line through
    both centres leaves the hull where only one ellipse's boundary is (the one clear of the other's
    bounding disc in its frame), with a tangent there that misses the other. Looking from j, the centre
    line runs the other way: its right window. Affine maps with det A > 0 keep sides. An inner tangent
    may touch j on either side.
    """
    c, S = frames.relative(i, j)
    D, far, phi, a1, a2 = _facing_windows(c, S)
    thetas, signs, rows = [], [], []
    f = np.flatnonzero(far)
    if len(f):
        lo = np.concatenate([phi[f] + a1[f], phi[f] - a2[f]])  # left window, then right
        hi = np.concatenate([phi[f] + a2[f], phi[f] - a1[f]])
        on_i = arcs.meets_free(i[np.tile(f, 2)], lo, hi)
        # j's windows, for the pairs with a window of i to solve (and clear of each other in j's frame).
        g = np.flatnonzero(on_i[: len(f)] | on_i[len(f) :])
        _, far_j, phi_j, a1_j, a2_j = _facing_windows(*frames.relative(j[f[g]], i[f[g]]))
        g, phi_j, a1_j, a2_j = g[far_j], phi_j[far_j], a1_j[far_j], a2_j[far_j]
        on_j = np.ones(2 * len(f), dtype=bool)
        on_j[np.concatenate([g, g + len(f)])] = arcs.meets_free(
            j[f[np.tile(g, 2)]], np.concatenate([phi_j + a1_j, phi_j - a2_j]), np.concatenate([phi_j + a2_j, phi_j - a1_j]))
        left_j, right_j = on_j[: len(f)], on_j[len(f) :]
        # The four windows (outer tangents, sign +1, then inner, −1; each left then right), one batch.
        solve = np.tile(on_i, 2) & np.concatenate([right_j, left_j, left_j | right_j, left_j | right_j])
        sign = np.repeat([1.0, 1.0, -1.0, -1.0], len(f))
        w = np.flatnonzero(solve)
        lo, hi = np.tile(lo, 2), np.tile(hi, 2)
        row = np.tile(f, 4)[w]
        thetas.append(_window_roots(D[row], phi[row], S[row], sign[w], lo[w], hi[w]))
        signs.append(sign[w])
        rows.append(row)
    n_ = np.flatnonzero(~far)
    if len(n_):
        cc = c[n_]
        P = cc[:, 0] ** 2 - S[n_, 0, 0]
        R = cc[:, 1] ** 2 - S[n_, 1, 1]
        Qx = cc[:, 0] * cc[:, 1] - S[n_, 0, 1]
        coef = np.stack([1.0 + 0.5 * (P + R), -2.0 * cc[:, 0], -2.0 * cc[:, 1], 0.5 * (P - R), Qx], axis=1)
        roots, real = _trig_roots(coef)
        k, slot = np.nonzero(real)
        th = roots[k, slot]
        side = 1.0 - np.einsum("ki,ki->k", _unit(th), cc[k])
        thetas.append(th)
        signs.append(np.where(side >= 0.0, 1.0, -1.0))
        rows.append(n_[k])
    if not thetas:
        return _Segments(*(np.zeros((0, 2)),) * 2, *(np.zeros(0, dtype=int),) * 2, *(np.zeros(0),) * 2)
    theta, sign, row = np.concatenate(thetas), np.concatenate(signs), np.concatenate(rows)
    n = _unit(theta)
    Sn = np.einsum("kij,kj->ki", S[row], n)
    h = np.sqrt(np.einsum("ki,ki->k", n, Sn))
    touch = c[row] + sign[:, None] * Sn / h[:, None]
    p = frames.point(i[row], n)
    q = frames.point(i[row], touch)
    theta_p, theta_q = np.mod(theta, 2.0 * np.pi), frames.angle(j[row], q)
    free = arcs.free[arcs.locate(i[row], theta_p)[0]] & arcs.free[arcs.locate(j[row], theta_q)[0]]
    return _Segments(p, q, i[row], j[row], theta_p, theta_q).take(free)


def _terminal_tangents(frames: _Frames, terminals: FloatArray, k: FloatArray, e: FloatArray) -> _Segments:
    """Both tangents from terminal k to ellipse e, for each pair (k, e) with the terminal outside."""
    q = np.einsum("kij,kj->ki", frames.A[e], terminals[k]) + frames.b[e]
    r = np.linalg.norm(q, axis=1)
    outside = r > 1.0
    k, e, q, r = k[outside], e[outside], q[outside], r[outside]
    phi = np.arctan2(q[:, 1], q[:, 0])
    half = np.arccos(1.0 / r)
    theta = np.concatenate([phi - half, phi + half])
    kk, ee = np.concatenate([k, k]), np.concatenate([e, e])
    z = frames.point(ee, _unit(theta))
    return _Segments(terminals[kk], z, -1 - kk, ee, np.zeros(len(kk)), np.mod(theta, 2.0 * np.pi))


_EDGE_RAD = 1e-9  # a cut's side is read this far either side of it
_FREE_BINS = 128  # angle bins of each ellipse's boundary, for a quick test of which windows meet a free arc


def _bin(theta: FloatArray) -> FloatArray:
    """The angle bin of θ ≥ 0 (not reduced: θ + 2π is in bin + _FREE_BINS, up to rounding)."""
    return np.floor(theta * (_FREE_BINS / (2.0 * np.pi))).astype(int)


def _bound_sources(frames: _Frames, owner: FloatArray, bounds_min: FloatArray, bounds_max: FloatArray):
    """Each bound as a cosine R cos(θ − ψ) + c − bound of ellipse `owner`'s boundary coordinate,
    covering where it is > 0 (past the bound): (R, ψ, offset, outward sign) per (owner, bound)."""
    out = []
    Ainv, centers = frames.Ainv[owner], frames.centers[owner]
    for axis in range(2):
        R = np.hypot(Ainv[:, axis, 0], Ainv[:, axis, 1])
        psi = np.arctan2(Ainv[:, axis, 1], Ainv[:, axis, 0])
        for bound, outward in ((bounds_min[axis], -1.0), (bounds_max[axis], 1.0)):
            out.append((R, psi, centers[:, axis] - bound, outward))
    return out


def _cuts(frames: _Frames, stack: EllipseStack, bounds_min: FloatArray, bounds_max: FloatArray, relevant: FloatArray):
    """Where each relevant ellipse's boundary is crossed by another ellipse or a bound.

    Returns (owner, θ, Δ) per cut, Δ = +1 where the boundary enters the other ellipse (or leaves the
    bounds), −1 where it leaves, 0 at a touch; and (i, coef) for each pair of ellipses that may
    overlap: ‖Aⱼ z(θ) + bⱼ‖² − 1 along i's boundary as trigonometric coefficients.
    """
    owners, thetas, deltas = [], [], []
    i, j = stack.near_pairs(frames.centers[relevant], frames.reach[relevant])
    i = relevant[i]
    keep = i != j
    i, j = i[keep], j[keep]
    # Separating axis along the centre line: projections that do not overlap mean no crossing.
    d = frames.centers[j] - frames.centers[i]
    Ai, Aj = frames.Ainv[i], frames.Ainv[j]
    support = np.linalg.norm(np.einsum("kij,ki->kj", Ai, d), axis=1) + np.linalg.norm(np.einsum("kij,ki->kj", Aj, d), axis=1)
    keep = np.einsum("ki,ki->k", d, d) <= support * (1.0 + 1e-9)
    i, j = i[keep], j[keep]
    M = np.einsum("kij,kjl->kil", frames.A[j], frames.Ainv[i])
    d = np.einsum("kij,kj->ki", frames.A[j], frames.centers[i]) + frames.b[j]
    coef = _quadratic_form_coef(
        np.einsum("kji,kjl->kil", M, M), np.einsum("kji,kj->ki", M, d), np.einsum("ki,ki->k", d, d) - 1.0
    )
    if len(i):
        roots, real = _trig_roots(coef)
        k, slot = np.nonzero(real)
        theta = roots[k, slot]
        after = _trig(coef[k], (theta + _EDGE_RAD)[:, None])[0][:, 0] < 0.0
        before = _trig(coef[k], (theta - _EDGE_RAD)[:, None])[0][:, 0] < 0.0
        owners.append(i[k])
        thetas.append(theta)
        deltas.append(after.astype(int) - before.astype(int))
    for R, psi, offset, outward in _bound_sources(frames, relevant, bounds_min, bounds_max):
        ratio = -offset / R
        hit = np.abs(ratio) < 1.0
        half = np.arccos(ratio[hit])
        for theta in (psi[hit] + half, psi[hit] - half):
            past = [outward * (R[hit] * np.cos(t - psi[hit]) + offset[hit]) > 0.0 for t in (theta + _EDGE_RAD, theta - _EDGE_RAD)]
            owners.append(relevant[hit])
            thetas.append(theta)
            deltas.append(past[0].astype(int) - past[1].astype(int))
    owner = np.concatenate(owners) if owners else np.zeros(0, dtype=int)
    theta = np.mod(np.concatenate(thetas), 2.0 * np.pi) if thetas else np.zeros(0)
    delta = np.concatenate(deltas) if deltas else np.zeros(0, dtype=int)
    return owner, theta, delta, i, coef


class _Arcs:
    """Free and blocked arcs of each ellipse's boundary between consecutive cuts.

    How many ellipses (and bounds) cover an arc is counted at one point of each boundary — the middle
    of its wrap-round arc, away from every cut — and carried round by the cuts' Δ: an arc is free where
    the count is 0.
    """

    def __init__(self, frames: _Frames, cuts, covered: FloatArray, bounds_min, bounds_max) -> None:
        """`cuts` from `_cuts` for the ellipses `covered` (a mask); the others get no free arc."""
        m = len(frames.A)
        owner, theta, delta, pair_i, pair_coef = cuts
        order = np.lexsort((theta, owner))
        self.owner, self.theta, delta = owner[order], theta[order], delta[order]
        self.count = np.bincount(self.owner, minlength=m)
        self.first = np.concatenate([[0], np.cumsum(self.count)[:-1]])
        # One arc per cut (from it to the next, the last wrapping round), or the whole boundary.
        arcs_of = np.maximum(self.count, 1)
        self.arc_first = np.concatenate([[0], np.cumsum(arcs_of)[:-1]])
        has = self.count > 0
        reference = np.zeros(m)
        last = self.first[has] + self.count[has] - 1
        reference[has] = 0.5 * (self.theta[last] + self.theta[self.first[has]] + 2.0 * np.pi)
        base = np.zeros(m, dtype=int)
        if len(pair_i):
            inside = _trig(pair_coef, reference[pair_i][:, None])[0][:, 0] < 0.0
            np.add.at(base, pair_i[inside], 1)
        every = np.arange(m)
        for R, psi, offset, outward in _bound_sources(frames, every, bounds_min, bounds_max):
            base += outward * (R * np.cos(reference - psi) + offset) > 0.0
        # Arc k of an ellipse starts at its cut k: count = base + Δ₀ + … + Δₖ (the last arc: base).
        running = np.cumsum(delta) - np.repeat(np.cumsum(delta)[self.first[has]] - delta[self.first[has]], self.count[has])
        coverage = np.repeat(base, arcs_of)
        cut_arcs = self.arc_first[self.owner] + np.arange(len(self.owner)) - self.first[self.owner]
        coverage[cut_arcs] += running
        self.free = (coverage == 0) & np.repeat(covered, arcs_of)
        # Ellipses with a free arc somewhere: only they can hold a tangent point of the graph.
        self.has_free = np.logical_or.reduceat(self.free, self.arc_first) if m else np.zeros(0, dtype=bool)
        self._keys = self.owner * 8.0 + self.theta
        # The angle bins each free arc touches, widened by 1e-9 rad either way (arc k of an ellipse runs
        # from its cut k to the next, the last one to the first + 2π), and their counts over two turns
        # of bins (bin b is bin b mod _FREE_BINS), for `meets_free`.
        cut = np.flatnonzero(self.free[cut_arcs])
        nxt = np.minimum(cut + 1, len(self.owner) - 1)
        following = (cut + 1 < len(self.owner)) & (self.owner[nxt] == self.owner[cut])
        end = np.where(following, self.theta[nxt], self.theta[self.first[self.owner[cut]]] + 2.0 * np.pi)
        start = np.mod(self.theta[cut] - 1e-9, 2.0 * np.pi)
        first_bin = _bin(start)
        bins = np.minimum(_bin(start + (end - self.theta[cut]) + 2e-9) - first_bin + 1, _FREE_BINS)
        local = np.arange(bins.sum()) - np.repeat(np.cumsum(bins) - bins, bins)
        near_free = np.zeros((m, _FREE_BINS), dtype=bool)
        near_free[np.repeat(self.owner[cut], bins), (np.repeat(first_bin, bins) + local) % _FREE_BINS] = True
        near_free[(self.count == 0) & self.has_free] = True  # a free loop
        twice = np.hstack([np.zeros((m, 1), dtype=bool), near_free, near_free, near_free[:, :1]])
        self._free_bins_before = np.cumsum(twice, axis=1, dtype=np.int32)

    def _cuts_upto(self, owner: FloatArray, theta: FloatArray) -> FloatArray:
        """How many of each ellipse's cuts lie at angles ≤ θ (θ ∈ [0, 2π))."""
        if not len(self.theta):
            return np.zeros(len(owner), dtype=int)
        return np.searchsorted(self._keys, owner * 8.0 + theta, side="right") - self.first[owner]

    def meets_free(self, owner: FloatArray, lo: FloatArray, hi: FloatArray) -> FloatArray:
        """Whether the angle window [lo, hi] (hi − lo < 2π) on each ellipse `owner` may hold a point
        that `locate` puts on a free arc: whether it meets an angle bin that a free arc touches. Both
        the window and the arcs are widened by 1e-9 rad either way, so a point of a free arc in the
        window lies in a bin counted for both, whichever turn rounding puts it in."""
        start = np.mod(lo - 1e-9, 2.0 * np.pi)
        first, last = _bin(start), _bin(start + (hi - lo) + 2e-9)  # last < first + 2 _FREE_BINS
        whole = last - first >= _FREE_BINS - 1
        last = np.minimum(last, first + _FREE_BINS - 2)
        met = self._free_bins_before[owner, last + 1] - self._free_bins_before[owner, first] > 0
        return np.where(whole, self.has_free[owner], met)

    def locate(self, owner: FloatArray, theta: FloatArray) -> tuple[FloatArray, FloatArray]:
        """The arc id of each boundary point, and its angle unwrapped past the arc's start cut."""
        count = self.count[owner]
        r = self._cuts_upto(owner, theta)
        wrap = (count > 0) & (r == 0)
        local = np.where(count > 0, (r - 1) % np.maximum(count, 1), 0)
        unwrapped = np.where(wrap, theta + 2.0 * np.pi, theta)
        return self.arc_first[owner] + local, unwrapped


def _arc_length(frames: _Frames, owner: FloatArray, start: FloatArray, span: FloatArray) -> FloatArray:
    """∫ ‖A⁻¹ u′(θ)‖ dθ from `start` over `span` (signed) on each scaled ellipse (Gauss–Legendre)."""
    pieces = np.maximum(1, np.ceil(np.abs(span) / _ARC_PIECE_RAD).astype(int))
    arc = np.repeat(np.arange(len(owner)), pieces)
    k = np.arange(len(arc)) - np.repeat(np.cumsum(pieces) - pieces, pieces)
    width = (span / pieces)[arc]
    theta = start[arc, None] + width[:, None] * (k[:, None] + 0.5 * (_GL_NODES[None, :] + 1.0))
    du = np.stack([-np.sin(theta), np.cos(theta)], axis=-1)
    speed = np.linalg.norm(np.einsum("kij,knj->kni", frames.Ainv[owner[arc]], du), axis=2)
    return np.bincount(arc, weights=0.5 * np.abs(width) * (speed @ _GL_WEIGHTS), minlength=len(owner))


def _arc_polyline(frames: _Frames, owner: int, start: float, span: float) -> FloatArray:
    """Points of the arc from `start` over `span` (signed), chords tangent to the ellipse, ends on it."""
    pieces = max(1, int(np.ceil(abs(span) / _ARC_VERTEX_RAD)))
    step = span / pieces
    angles = start + step * (np.arange(pieces) + 0.5)
    u = np.vstack([_unit(np.array([start])), _unit(angles) / np.cos(0.5 * step), _unit(np.array([start + span]))])
    return frames.point(np.full(len(u), owner), u)


class _DeepCells:
    """Square grid cells each wholly inside some ellipse: a cheap proof that a segment is blocked.

    A cell is marked when all four corners lie at level ≤ 1 − 1e-6 of one ellipse; the level is convex,
    so then the whole cell does. A segment with a point in a marked cell enters that ellipse deeper than
    the exact test's tolerance, and the ellipse is not one it is tangent to (it stays outside those), so
    the exact test would find it blocked. In a dense field almost every candidate segment is blocked,
    and most of them are found so by points sampled one cell apart.
    """

    def __init__(self, stack: EllipseStack) -> None:
        """Cells of `_DEEP_CELL` times the median smallest semi-axis (at most 1000 along the extent)."""
        low = np.min(stack.centers - stack.reach[:, None], axis=0)
        high = np.max(stack.centers + stack.reach[:, None], axis=0)
        cell = max(_DEEP_CELL * float(np.median(stack.semi_axes[:, 1])), float(np.max(high - low)) / 1000.0)
        low, high = low - cell, high + cell  # a border of unmarked cells, for the points off the grid
        self.origin, self.cell = low, cell
        self.deep = np.zeros(tuple(np.ceil((high - low) / cell).astype(int) + 1), dtype=bool)
        # The grid vertices in each ellipse's bounding box, box by box (rows of ny[e] vertices each).
        first = np.floor((stack.centers - stack.reach[:, None] - low) / cell).astype(int)
        last = np.ceil((stack.centers + stack.reach[:, None] - low) / cell).astype(int)
        nx, ny = (last - first + 1).T
        size = nx * ny
        owner = np.repeat(np.arange(len(stack)), size)
        local = np.arange(len(owner)) - np.repeat(np.cumsum(size) - size, size)
        step = ny[owner]
        ix, iy = first[owner, 0] + local // step, first[owner, 1] + local % step
        z = low + cell * np.column_stack([ix, iy])
        inside = np.linalg.norm(np.einsum("kij,kj->ki", stack.A[owner], z) + stack.b[owner], axis=1) <= 1.0 - 1e-6
        # Cell (ix, iy) has corners at vertex k, k + 1 (next iy) and k + step, k + step + 1 (next ix).
        k = np.flatnonzero((local // step < nx[owner] - 1) & (local % step < step - 1))
        k = k[inside[k] & inside[k + 1] & inside[k + step[k]] & inside[k + step[k] + 1]]
        self.deep[ix[k], iy[k]] = True

    def blocked(self, p: FloatArray, q: FloatArray) -> FloatArray:
        """Whether a point of segment p→q, sampled one cell apart, lies in a marked cell."""
        d = q - p
        count = np.ceil(_distance(q, p) / self.cell).astype(int) + 2
        skip = np.cumsum(count) - count
        t = np.arange(count.sum()) - np.repeat(skip, count)  # sample k of count, then scaled to [0, 1]
        t = t * np.repeat(1.0 / (count - 1), count)
        # Truncation and clipping put every point off the grid on its unmarked border; the grid is read
        # flat, cell (x, y) at x · rows + y.
        flat = np.zeros(len(t), dtype=int)
        for axis, size in enumerate(self.deep.shape):
            start, step = (p[:, axis] - self.origin[axis]) / self.cell, d[:, axis] / self.cell  # in cells
            index = (np.repeat(start, count) + t * np.repeat(step, count)).astype(int)
            flat = flat * size + np.clip(index, 0, size - 1)
        hit = self.deep.ravel()[flat]
        return np.logical_or.reduceat(hit, skip) if len(p) else np.zeros(0, dtype=bool)


class _TangentGraph:
    """The tangent graph, built within the legs' informed ellipses and grown as their bounds widen.

    Tangents, cuts, free arcs and segment tests do not depend on the bound, so each is computed once:
    a wider bound only adds the pairs, ellipses and segments it newly lets in. A pair is given tangents
    only when both ellipses have a free arc: a tangent point anywhere else is dropped (in a wall of
    overlapping ellipses, about half of them lie wholly inside the others).
    """

    def __init__(self, *, frames: _Frames, stack: EllipseStack, terminals: FloatArray, bounds_min, bounds_max) -> None:
        self.frames, self.stack, self.terminals = frames, stack, terminals
        self.bounds_min, self.bounds_max = bounds_min, bounds_max
        m, t = len(frames.A), len(terminals)
        self.covered = np.zeros(m, dtype=bool)  # ellipses whose cuts are known
        self.cuts = (np.zeros(0, dtype=int), np.zeros(0), np.zeros(0, dtype=int), np.zeros(0, dtype=int), np.zeros((0, 5)))
        self.arcs = _Arcs(frames, self.cuts, self.covered, bounds_min, bounds_max)
        self.pair_done = np.zeros((m, m), dtype=bool)  # pairs (i < j) with tangents
        kk, ee = np.meshgrid(np.arange(t), np.arange(m), indexing="ij")
        tk, tl = np.triu_indices(t, k=1)
        self.segments = _Segments.concat([
            _terminal_tangents(frames, terminals, kk.ravel(), ee.ravel()),
            _Segments(terminals[tk], terminals[tl], -1 - tk, -1 - tl, np.zeros(len(tk)), np.zeros(len(tk))),
        ])
        self.status = np.zeros(len(self.segments.p), dtype=np.int8)  # 0 untested, 1 clear, 2 blocked
        self.deep: _DeepCells | None = None  # built for the first batch of segments big enough to pay for it

    def _informed(self, bound: FloatArray, x: FloatArray, extra, y: FloatArray) -> FloatArray:
        """Whether a path through x (then `extra` further, then y) can fit some leg's bound."""
        a, z = self.terminals[:-1], self.terminals[1:]
        ok = np.zeros(len(x), dtype=bool)
        for leg in range(len(a)):
            if bound[leg] <= 0.0:
                continue
            if not np.isfinite(bound[leg]):
                return np.ones(len(x), dtype=bool)
            forward = _distance(x, a[leg]) + extra + _distance(y, z[leg])
            backward = _distance(y, a[leg]) + extra + _distance(x, z[leg])
            ok |= np.minimum(forward, backward) <= bound[leg] * (1.0 + 1e-12)
        return ok

    def _grow(self, bound: FloatArray) -> None:
        """Cuts of the ellipses and tangents of the pairs that the bound newly lets in."""
        frames = self.frames
        c, r = frames.centers, frames.reach
        # Ellipses that reach into some leg's informed ellipse (distance to a centre minus the reach).
        relevant = np.flatnonzero(self._informed(bound, c, -2.0 * r, c))
        new = relevant[~self.covered[relevant]]
        if len(new):
            parts = _cuts(frames, self.stack, self.bounds_min, self.bounds_max, new)
            self.cuts = tuple(np.concatenate([old, part]) for old, part in zip(self.cuts, parts))
            self.covered[new] = True
            self.arcs = _Arcs(frames, self.cuts, self.covered, self.bounds_min, self.bounds_max)
        relevant = relevant[self.arcs.has_free[relevant]]
        # Pairs none of whose tangents fits a leg: a path through p ∈ i and q ∈ j is at least
        # ‖from − cᵢ‖ − rᵢ + gap(discs) + ‖cⱼ − to‖ − rⱼ long (either way round).
        ii, jj = np.triu_indices(len(relevant), k=1)
        ii, jj = relevant[ii], relevant[jj]
        fresh = ~self.pair_done[ii, jj]
        ii, jj = ii[fresh], jj[fresh]
        gap = np.maximum(_distance(c[ii], c[jj]) - r[ii] - r[jj], 0.0)
        keep = self._informed(bound, c[ii], gap - r[ii] - r[jj], c[jj])
        ii, jj = ii[keep], jj[keep]
        if len(ii):
            added = _pair_tangents(frames, self.arcs, ii, jj)
            self.segments = _Segments.concat([self.segments, added])
            self.status = np.concatenate([self.status, np.zeros(len(added.p), dtype=np.int8)])
            self.pair_done[ii, jj] = True

    def build(self, bound: FloatArray):
        """The graph within the bounds: (csr graph, node points, node owners, unwrapped angles, arc spans)."""
        self._grow(bound)
        frames, t = self.frames, len(self.terminals)
        arcs = self.arcs
        all_seg = self.segments
        length_all = _distance(all_seg.q, all_seg.p)
        pick = np.flatnonzero((self.status != 2) & self._informed(bound, all_seg.p, length_all, all_seg.q))
        seg, length = all_seg.take(pick), length_all[pick]

        # Tangent points must lie on a free arc (outside every other ellipse, inside the bounds).
        arc_p = np.full(len(seg.p), -1)
        arc_q = np.full(len(seg.p), -1)
        unw_p, unw_q = seg.theta_p.copy(), seg.theta_q.copy()
        on_p, on_q = seg.owner_p >= 0, seg.owner_q >= 0
        arc_p[on_p], unw_p[on_p] = arcs.locate(seg.owner_p[on_p], seg.theta_p[on_p])
        arc_q[on_q], unw_q[on_q] = arcs.locate(seg.owner_q[on_q], seg.theta_q[on_q])
        valid = (~on_p | arcs.free[np.maximum(arc_p, 0)]) & (~on_q | arcs.free[np.maximum(arc_q, 0)])
        self.status[pick[~valid]] = 2

        # Exact segment test against every ellipse but the two it touches, once per segment.
        untested = np.flatnonzero(valid & (self.status[pick] == 0))
        if self.deep is None and len(untested) >= _DEEP_MIN_SEGMENTS and len(self.stack):
            self.deep = _DeepCells(self.stack)
        for lo in range(0, len(untested), _CHUNK):
            k = untested[lo : lo + _CHUNK]
            if self.deep is not None:  # most are proved blocked cheaply; the rest get the exact test
                sure = self.deep.blocked(seg.p[k], seg.q[k])
                self.status[pick[k[sure]]] = 2
                k = k[~sure]
            rows, cols, levels = self.stack.segment_pairs(seg.p[k], seg.q[k])
            hit = (levels < 1.0 - _BLOCK_TOL) & (cols != seg.owner_p[k][rows]) & (cols != seg.owner_q[k][rows])
            blocked = np.zeros(len(k), dtype=bool)
            blocked[rows[hit]] = True
            self.status[pick[k]] = np.where(blocked, 2, 1)
        keep = self.status[pick] == 1
        seg, length = seg.take(keep), length[keep]
        arc_p, arc_q, unw_p, unw_q = arc_p[keep], arc_q[keep], unw_p[keep], unw_q[keep]
        return self._assemble(seg, length, arcs, arc_p, arc_q, unw_p, unw_q)

    def _assemble(self, seg, length, arcs, arc_p, arc_q, unw_p, unw_q):
        frames, t, terminals = self.frames, len(self.terminals), self.terminals
        # Nodes: terminals 0 … t − 1, then both ends of every segment that touch an ellipse.
        s = len(seg.p)
        node_p = np.where(seg.owner_p < 0, -1 - seg.owner_p, t + np.arange(s))
        node_q = np.where(seg.owner_q < 0, -1 - seg.owner_q, t + s + np.arange(s))
        points = np.vstack([terminals, seg.p, seg.q])
        owner = np.concatenate([np.full(t, -1), seg.owner_p, seg.owner_q])
        unwrapped = np.concatenate([np.zeros(t), unw_p, unw_q])
        arc = np.concatenate([np.full(t, -1), arc_p, arc_q])
        # Arcs: consecutive tangent points of one free arc, in angle order.
        on = np.flatnonzero(owner >= 0)
        on = on[np.lexsort((unwrapped[on], arc[on]))]
        consecutive = arc[on[:-1]] == arc[on[1:]]
        u, v = on[:-1][consecutive], on[1:][consecutive]
        arc_span = unwrapped[v] - unwrapped[u]
        arc_len = _arc_length(frames, owner[u], unwrapped[u], arc_span)
        # An ellipse with no cut is one free loop: also join its last tangent point to its first.
        whole = arcs.count[owner[on]] == 0
        ends = on[whole]
        if len(ends):
            o = owner[ends]
            last = np.r_[o[1:] != o[:-1], True]
            firstm = np.r_[True, o[1:] != o[:-1]]
            lu, fv = ends[last], ends[firstm]
            two = lu != fv
            lu, fv = lu[two], fv[two]
            wrap_span = unwrapped[fv] + 2.0 * np.pi - unwrapped[lu]
            wrap_len = _arc_length(frames, owner[lu], unwrapped[lu], wrap_span)
            u, v = np.concatenate([u, lu]), np.concatenate([v, fv])
            arc_len, arc_span = np.concatenate([arc_len, wrap_len]), np.concatenate([arc_span, wrap_span])
        i = np.concatenate([node_p, u])
        j = np.concatenate([node_q, v])
        w = np.concatenate([length, arc_len]) + 1e-12  # explicit zeros would be no edge
        span = np.concatenate([np.zeros(len(length)), arc_span])  # the angle from i to j along an arc
        # Keep the shorter of parallel edges (two arcs joining the only two points of a loop).
        lo_, hi_ = np.minimum(i, j), np.maximum(i, j)
        order = np.lexsort((w, hi_, lo_))
        first = np.ones(len(order), dtype=bool)
        first[1:] = (lo_[order][1:] != lo_[order][:-1]) | (hi_[order][1:] != hi_[order][:-1])
        order = order[first]
        n = len(points)
        # The order sorts by lo, then hi: the edges are already in CSR order, row lo, column hi.
        rows, cols = lo_[order], hi_[order]
        graph = csr_array((w[order], cols, np.searchsorted(rows, np.arange(n + 1))), shape=(n, n))
        # Each kept edge's key lo · n + hi, ascending, and its angle from lo.
        spans = _Spans(keys=rows * n + cols, from_lo=np.where(i == lo_, span, -span)[order], nodes=n)
        return graph, points, owner, unwrapped, spans


@dataclass(frozen=True)
class _Spans:
    """The angle each edge of the graph turns through along its arc (0 for a tangent segment), by edge."""

    keys: FloatArray  # lo · nodes + hi of each edge (lo < hi), ascending
    from_lo: FloatArray  # the signed angle from node lo to node hi
    nodes: int

    def between(self, a: FloatArray, b: FloatArray) -> FloatArray:
        """The signed angle from node a to node b of each edge a–b."""
        lo, hi = np.minimum(a, b), np.maximum(a, b)
        return np.where(a == lo, 1.0, -1.0) * self.from_lo[np.searchsorted(self.keys, lo * self.nodes + hi)]


def _polyline(frames: _Frames, points, owner, unwrapped, spans: _Spans, chain: list[int]) -> FloatArray:
    """The route's points along the node chain: tangent segments straight, arcs circumscribed."""
    out = [points[chain[:1]]]
    tails, heads = np.array(chain[:-1]), np.array(chain[1:])
    for a, b, span in zip(chain[:-1], chain[1:], spans.between(tails, heads).tolist()):
        if owner[a] >= 0 and owner[a] == owner[b]:
            out.append(_arc_polyline(frames, int(owner[a]), float(unwrapped[a]), span)[1:])
        else:
            out.append(points[[b]])
    return np.vstack(out)


def shortest_route(
    *,
    start: FloatArray,
    goals: FloatArray,
    ellipses: list[Ellipse],
    bounds_min: FloatArray,
    bounds_max: FloatArray,
    level: float = 1.01,
) -> Route | None:
    """The exact shortest route start → goal₁ → … outside every ellipse scaled to `level`; None if none.

    An ellipse that would contain a terminal at `level` is scaled only as far as leaves the terminal
    outside (never below the ellipse itself), so a robot just inside a margin can still leave.
    """
    start = np.asarray(start, dtype=float)
    goals = np.atleast_2d(np.asarray(goals, dtype=float))
    bounds_min, bounds_max = np.asarray(bounds_min, dtype=float), np.asarray(bounds_max, dtype=float)
    terminals = np.vstack([start, goals])
    stack = EllipseStack.of(ellipses)
    if len(stack):
        nearest = np.min(stack.levels(terminals), axis=0)
        scale = np.maximum(np.minimum(level, nearest * (1.0 - 1e-9)), 1.0)
    else:
        scale = np.zeros(0)
    frames = _Frames.of(stack, scale)
    scaled = EllipseStack(A=frames.A, b=frames.b)
    straight = np.linalg.norm(np.diff(terminals, axis=0), axis=1)
    legs: list[FloatArray | None] = [None] * len(goals)
    lengths = [np.inf] * len(goals)
    # Each leg's bound: the next factor, or the length of a route found beyond the last bound (any
    # route is an upper bound, and a tighter one than the next factor).
    step = np.zeros(len(goals), dtype=int)
    bound = _BOUND_FACTORS[0] * straight + 1e-9
    tangents = _TangentGraph(frames=frames, stack=scaled, terminals=terminals, bounds_min=bounds_min, bounds_max=bounds_max)
    while True:
        todo = [k for k in range(len(goals)) if legs[k] is None]
        if not todo:
            return Route(legs=legs, lengths_m=lengths)
        active = np.where(np.isin(np.arange(len(goals)), todo), bound, 0.0)
        graph, points, owner, unwrapped, spans = tangents.build(active)
        dist, pred = dijkstra(graph, directed=False, indices=todo, return_predecessors=True)
        for row, leg in enumerate(todo):
            target = leg + 1
            found = dist[row, target]
            if np.isfinite(found) and found <= bound[leg]:
                chain = [target]
                while chain[-1] != leg:
                    chain.append(int(pred[row, chain[-1]]))
                legs[leg] = _polyline(frames, points, owner, unwrapped, spans, chain[::-1])
                lengths[leg] = float(found)
            elif not np.isfinite(bound[leg]):
                return None  # the whole graph has no route
            elif np.isfinite(found):
                bound[leg] = found * (1.0 + 1e-9)
            else:
                step[leg] += 1
                bound[leg] = _BOUND_FACTORS[step[leg]] * straight[leg] + 1e-9


def tangent_route(
    *,
    start: FloatArray,
    goals: FloatArray,
    ellipses: list[Ellipse],
    bounds_min: FloatArray,
    bounds_max: FloatArray,
    level: float = 1.01,
) -> list[FloatArray] | None:
    """Shortest polylines start → goal₁ → … (one per leg) outside every ellipse; None if there is none.

    The polyline stays at level ≥ `level` (arcs circumscribed, tangents exact), inside the bounds.
    """
    route = shortest_route(
        start=start, goals=goals, ellipses=ellipses, bounds_min=bounds_min, bounds_max=bounds_max, level=level
    )
    return None if route is None else route.legs
