"""Real roots of degree-2 trigonometric polynomials a₀ + a₁ cos θ + b₁ sin θ + a₂ cos 2θ + b₂ sin 2θ.

Tangents and cuts of ellipses are such roots (``tangents``, ``arcs``): bracketed on a grid and refined
by safeguarded Newton, with the quartic in e^{iθ} (companion matrix) where a grid step may hide two.
"""

from __future__ import annotations

import numpy as np

from services.geometry import FloatArray

_ROOT_TOL = 1e-6  # a quartic root this close to the unit circle is a real angle


def trig(coef: FloatArray, theta: FloatArray) -> tuple[FloatArray, FloatArray]:
    """a₀ + a₁ cos θ + b₁ sin θ + a₂ cos 2θ + b₂ sin 2θ and its derivative; coef (..., 5) broadcast on θ."""
    a0, a1, b1, a2, b2 = (coef[..., k, None] for k in range(5))
    c, s, c2, s2 = np.cos(theta), np.sin(theta), np.cos(2 * theta), np.sin(2 * theta)
    return a0 + a1 * c + b1 * s + a2 * c2 + b2 * s2, -a1 * s + b1 * c - 2 * a2 * s2 + 2 * b2 * c2


def quadratic_form_coef(K: FloatArray, e: FloatArray, const: FloatArray) -> FloatArray:
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


def bracketed_root(
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
        f, df = trig(coef, theta)
        theta = theta - np.where(np.abs(df) > 1e-12, f / np.where(np.abs(df) > 1e-12, df, 1.0), 0.0)
    return np.mod(theta, 2.0 * np.pi), real


def trig_roots(coef: FloatArray) -> tuple[FloatArray, FloatArray]:
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
        f, df = trig(coef[rows[idx]], x[:, None])
        return f[:, 0], df[:, 0]

    # Newton starts where the chord between the grid values crosses zero (regula falsi): a root on a grid
    # angle (an axis-aligned wall) is then found at once, where from the middle Newton overshoots the end
    # and bisects towards it.
    v_lo, v_hi = values[rows, cols], values[rows, (cols + 1) % len(_GRID)]
    start = _GRID[cols] + h * v_lo / (v_lo - v_hi)
    theta[rows, slot] = bracketed_root(g, _GRID[cols], _GRID[cols] + h, start, f_lo=v_lo)
    real[rows, slot] = True
    fallback = np.flatnonzero(hidden)
    if len(fallback):
        theta[fallback], real[fallback] = _companion_roots(coef[fallback])
    return np.mod(theta, 2.0 * np.pi), real
