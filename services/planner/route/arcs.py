"""Each ellipse's boundary cut where another ellipse or a map bound crosses it, into free and blocked arcs.

A cut is a root of ‖M u(θ) + d‖² − 1 (another ellipse, a degree-2 trigonometric polynomial) or of a
cosine (a bound); between consecutive cuts an arc is wholly free or wholly blocked, counted round the
boundary. Arcs join consecutive tangent points at their exact length (Gauss–Legendre on the speed
‖A⁻¹ u′(θ)‖), and are drawn as polylines circumscribing the ellipse.
"""

from __future__ import annotations

import numpy as np

from services.geometry import EllipseStack, FloatArray
from services.planner.route.frames import Frames, unit
from services.planner.route.roots import quadratic_form_coef, trig, trig_roots

_ARC_PIECE_RAD = np.pi / 8  # Gauss–Legendre pieces for arc lengths
_ARC_VERTEX_RAD = np.pi / 16  # polyline vertices of an arc in the route returned
_GL_NODES, _GL_WEIGHTS = np.polynomial.legendre.leggauss(6)
_EDGE_RAD = 1e-9  # a cut's side is read this far either side of it
_FREE_BINS = 128  # angle bins of each ellipse's boundary, for a quick test of which windows meet a free arc


def _bin(theta: FloatArray) -> FloatArray:
    """The angle bin of θ ≥ 0 (not reduced: θ + 2π is in bin + _FREE_BINS, up to rounding)."""
    return np.floor(theta * (_FREE_BINS / (2.0 * np.pi))).astype(int)


def _bound_sources(frames: Frames, owner: FloatArray, bounds_min: FloatArray, bounds_max: FloatArray):
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


def cuts(frames: Frames, stack: EllipseStack, bounds_min: FloatArray, bounds_max: FloatArray, relevant: FloatArray):
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
    coef = quadratic_form_coef(
        np.einsum("kji,kjl->kil", M, M), np.einsum("kji,kj->ki", M, d), np.einsum("ki,ki->k", d, d) - 1.0
    )
    if len(i):
        roots, real = trig_roots(coef)
        k, slot = np.nonzero(real)
        theta = roots[k, slot]
        after = trig(coef[k], (theta + _EDGE_RAD)[:, None])[0][:, 0] < 0.0
        before = trig(coef[k], (theta - _EDGE_RAD)[:, None])[0][:, 0] < 0.0
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


class Arcs:
    """Free and blocked arcs of each ellipse's boundary between consecutive cuts.

    How many ellipses (and bounds) cover an arc is counted at one point of each boundary — the middle
    of its wrap-round arc, away from every cut — and carried round by the cuts' Δ: an arc is free where
    the count is 0.
    """

    def __init__(self, frames: Frames, cuts, covered: FloatArray, bounds_min, bounds_max) -> None:
        """`cuts` from `cuts` for the ellipses `covered` (a mask); the others get no free arc."""
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
            inside = trig(pair_coef, reference[pair_i][:, None])[0][:, 0] < 0.0
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


def arc_length(frames: Frames, owner: FloatArray, start: FloatArray, span: FloatArray) -> FloatArray:
    """∫ ‖A⁻¹ u′(θ)‖ dθ from `start` over `span` (signed) on each scaled ellipse (Gauss–Legendre)."""
    pieces = np.maximum(1, np.ceil(np.abs(span) / _ARC_PIECE_RAD).astype(int))
    arc = np.repeat(np.arange(len(owner)), pieces)
    k = np.arange(len(arc)) - np.repeat(np.cumsum(pieces) - pieces, pieces)
    width = (span / pieces)[arc]
    theta = start[arc, None] + width[:, None] * (k[:, None] + 0.5 * (_GL_NODES[None, :] + 1.0))
    du = np.stack([-np.sin(theta), np.cos(theta)], axis=-1)
    speed = np.linalg.norm(np.einsum("kij,knj->kni", frames.Ainv[owner[arc]], du), axis=2)
    return np.bincount(arc, weights=0.5 * np.abs(width) * (speed @ _GL_WEIGHTS), minlength=len(owner))


def arc_polyline(frames: Frames, owner: int, start: float, span: float) -> FloatArray:
    """Points of the arc from `start` over `span` (signed), chords tangent to the ellipse, ends on it."""
    pieces = max(1, int(np.ceil(abs(span) / _ARC_VERTEX_RAD)))
    step = span / pieces
    angles = start + step * (np.arange(pieces) + 0.5)
    u = np.vstack([unit(np.array([start])), unit(angles) / np.cos(0.5 * step), unit(np.array([start + span]))])
    return frames.point(np.full(len(u), owner), u)
