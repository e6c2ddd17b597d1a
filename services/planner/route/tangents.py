"""The candidate segments of the tangent graph: common tangents of ellipse pairs, and tangents from a terminal.

In i's unit-disc frame the tangent line at angle θ touches j (centre c, shape S there) exactly when
nᵀc ± √(nᵀSn) = 1 (``pair_tangents``, the derivation in its docstring); from a terminal q (in the
unit-disc frame) the tangents touch at ∠q ± acos(1/|q|).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from services.geometry import FloatArray
from services.planner.route.arcs import Arcs
from services.planner.route.frames import Frames, unit
from services.planner.route.roots import bracketed_root, trig_roots


def _window_roots(
    D: FloatArray, phi: FloatArray, S: FloatArray, sign: FloatArray, lo: FloatArray, hi: FloatArray
) -> FloatArray:
    """The root of g(θ) = D cos(θ − φ) − 1 + sign·√(nᵀSn) bracketed by [lo, hi] (sign ±1 each)."""
    s11, s12, s22 = S[:, 0, 0], S[:, 0, 1], S[:, 1, 1]

    def g(theta, k):
        c, s = np.cos(theta), np.sin(theta)
        a11, a12, a22, Dk, sk, off = s11[k], s12[k], s22[k], D[k], sign[k], theta - phi[k]  # each gathered once
        h = np.sqrt(a11 * c * c + 2.0 * a12 * c * s + a22 * s * s)
        dh = ((a22 - a11) * c * s + a12 * (c * c - s * s)) / h
        return Dk * np.cos(off) - 1.0 + sk * h, -Dk * np.sin(off) + sk * dh

    # Start from the root for a circle of j's radius √(nᵀSn) at the window's middle: Newton then
    # needs about three steps.
    mid = 0.5 * (lo + hi)
    radius = np.sqrt(s11 * np.cos(mid) ** 2 + 2.0 * s12 * np.cos(mid) * np.sin(mid) + s22 * np.sin(mid) ** 2)
    side = np.sign(np.sin(mid - phi))
    start = phi + side * np.arccos(np.clip((1.0 - sign * radius) / D, -1.0, 1.0))
    return bracketed_root(g, lo, hi, start)


@dataclass
class Segments:
    """Candidate tangent segments: end points, owning ellipses (−1 − k for terminal k), unit-frame angles."""

    p: FloatArray
    q: FloatArray
    owner_p: FloatArray
    owner_q: FloatArray
    theta_p: FloatArray
    theta_q: FloatArray

    @classmethod
    def concat(cls, parts: list[Segments]) -> Segments:
        return cls(*(np.concatenate([getattr(s, f) for s in parts]) for f in ("p", "q", "owner_p", "owner_q", "theta_p", "theta_q")))

    def take(self, keep: FloatArray) -> Segments:
        return Segments(self.p[keep], self.q[keep], self.owner_p[keep], self.owner_q[keep], self.theta_p[keep], self.theta_q[keep])


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


def pair_tangents(frames: Frames, arcs: Arcs, i: FloatArray, j: FloatArray) -> Segments:
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
        roots, real = trig_roots(coef)
        k, slot = np.nonzero(real)
        th = roots[k, slot]
        side = 1.0 - np.einsum("ki,ki->k", unit(th), cc[k])
        thetas.append(th)
        signs.append(np.where(side >= 0.0, 1.0, -1.0))
        rows.append(n_[k])
    if not thetas:
        return Segments(*(np.zeros((0, 2)),) * 2, *(np.zeros(0, dtype=int),) * 2, *(np.zeros(0),) * 2)
    theta, sign, row = np.concatenate(thetas), np.concatenate(signs), np.concatenate(rows)
    # The tangent points on i first: about half of those the windows let through are not on a free arc.
    theta_p = np.mod(theta, 2.0 * np.pi)
    on_free = arcs.free[arcs.locate(i[row], theta_p)[0]]
    theta, theta_p, sign, row = theta[on_free], theta_p[on_free], sign[on_free], row[on_free]
    n = unit(theta)
    Sn = np.einsum("kij,kj->ki", S[row], n)
    h = np.sqrt(np.einsum("ki,ki->k", n, Sn))
    touch = c[row] + sign[:, None] * Sn / h[:, None]
    q = frames.point(i[row], touch)
    theta_q = frames.angle(j[row], q)
    free = arcs.free[arcs.locate(j[row], theta_q)[0]]
    return Segments(frames.point(i[row[free]], n[free]), q[free], i[row[free]], j[row[free]], theta_p[free],
                    theta_q[free])


def terminal_tangents(frames: Frames, terminals: FloatArray, k: FloatArray, e: FloatArray) -> Segments:
    """Both tangents from terminal k to ellipse e, for each pair (k, e) with the terminal outside."""
    q = np.einsum("kij,kj->ki", frames.A[e], terminals[k]) + frames.b[e]
    r = np.linalg.norm(q, axis=1)
    outside = r > 1.0
    k, e, q, r = k[outside], e[outside], q[outside], r[outside]
    phi = np.arctan2(q[:, 1], q[:, 0])
    half = np.arccos(1.0 / r)
    theta = np.concatenate([phi - half, phi + half])
    kk, ee = np.concatenate([k, k]), np.concatenate([e, e])
    z = frames.point(ee, unit(theta))
    return Segments(terminals[kk], z, -1 - kk, ee, np.zeros(len(kk)), np.mod(theta, 2.0 * np.pi))
