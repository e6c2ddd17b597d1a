"""Ellipses in the paper's form {z : ‖A z + b‖₂ ≤ 1} and the exact tests the planner relies on.

A is symmetric positive definite. Writing A = R diag(1/a₁, 1/a₂) Rᵀ, the ellipse has semi-axes a₁, a₂
along the columns of R and centre c = −A⁻¹ b. The map u = A z + b sends the ellipse to the unit disc,
which turns every question below (inside? does a segment cross it? tangents from a point?) into the
same question about the unit circle.
"""

from __future__ import annotations

import math
from collections import OrderedDict
from collections.abc import Sequence
from dataclasses import dataclass, field
from functools import cached_property, lru_cache
from itertools import chain

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.optimize import brentq
from scipy.spatial import cKDTree

FloatArray = NDArray[np.float64]


def _frozen(array: FloatArray) -> FloatArray:
    array.flags.writeable = False
    return array


@dataclass(frozen=True, eq=False)
class Ellipse:
    """One ellipse {z : ‖A z + b‖₂ ≤ 1}.

    A and b are read-only views of one row of bytes (A₁₁, A₁₂, A₂₁, A₂₂, b₁, b₂ as float64): an ellipse
    never changes, so whatever is computed from it (its centre, a stack of it with others) can be
    kept, and a stack is one join of those rows.
    """

    A: FloatArray
    b: FloatArray
    _row: bytes = field(init=False, repr=False)

    def __post_init__(self) -> None:
        # Six numbers: plain floats are cheaper than numpy's calls on them.
        (a11, a12), (a21, a22) = np.asarray(self.A, dtype=float).reshape(2, 2).tolist()
        b1, b2 = np.asarray(self.b, dtype=float).reshape(2).tolist()
        off = 0.5 * (a12 + a21)  # A made symmetric, as 0.5 (A + Aᵀ)
        if not all(map(math.isfinite, (a11, off, a22, b1, b2))):
            raise ValueError("ellipse parameters must be finite")
        if not (a11 > 0.0 and a11 * a22 - off * off > 0.0):  # Sylvester's criterion
            raise ValueError("ellipse shape matrix A must be positive definite")
        object.__setattr__(self, "_row", np.array([a11, off, off, a22, b1, b2]).tobytes())
        row = np.frombuffer(self._row)  # read-only, as bytes are, and so are its views
        object.__setattr__(self, "A", row[:4].reshape(2, 2))
        object.__setattr__(self, "b", row[4:])

    @classmethod
    def from_axes(cls, *, center: ArrayLike, semi_axes: ArrayLike, angle_rad: float = 0.0) -> Ellipse:
        """Ellipse with the given centre, semi-axes (a₁ along angle_rad, a₂ across) and orientation."""
        c, s = np.cos(angle_rad), np.sin(angle_rad)
        R = np.array([[c, -s], [s, c]])
        A = R @ np.diag(1.0 / np.asarray(semi_axes, dtype=float)) @ R.T
        return cls(A=A, b=-A @ np.asarray(center, dtype=float))

    @classmethod
    def circle(cls, *, center: ArrayLike, radius: float) -> Ellipse:
        return cls.from_axes(center=center, semi_axes=(radius, radius))

    # Cached (read-only): an ellipse never changes, and the covers, the grouping and the planner ask
    # for these thousands of times a scan, each a 2 × 2 numpy call of some 10 µs.
    @cached_property
    def center(self) -> FloatArray:
        return _frozen(-np.linalg.solve(self.A, self.b))

    @cached_property
    def semi_axes(self) -> FloatArray:
        """Semi-axes, largest first."""
        return _frozen(1.0 / np.linalg.eigvalsh(self.A))

    @property
    def rotation(self) -> FloatArray:
        """Columns are the axis directions, in the order of `semi_axes`."""
        return np.linalg.eigh(self.A)[1]

    @property
    def area(self) -> float:
        return float(np.pi / np.linalg.det(self.A))

    def grown(self, margin_m: float, *, p: float | None = None) -> Ellipse:
        """The least-area ellipse of a family that contains the Minkowski sum with a disc of radius r (with
        `p`, that member of the family: every member contains the sum).

        Lengthening every semi-axis by r is NOT enough for a thin ellipse: near the tip of its major
        axis the sum is bounded by a circle of radius r, and the lengthened ellipse is sharper there
        (radius of curvature (a₂ + r)² / (a₁ + r) < r); for a₁ = 0.48, a₂ = 0.05, r = 0.65 a point
        0.65 m from the tip lies outside it. With Q = A⁻² the shape matrix ({z : (z − c)ᵀQ⁻¹(z − c) ≤ 1}),
        the sum of the ellipses of Q₁ and Q₂ lies in the ellipse of (1 + 1/p) Q₁ + (1 + p) Q₂ for every
        p > 0 (Kurzhanski & Vályi, Ellipsoidal Calculus, 1997); here Q₂ = r² I and p minimises the area,
        the root of Σᵢ (r² − λᵢ/p²) / ((1 + 1/p) λᵢ + (1 + p) r²) over Q₁'s eigenvalues λᵢ. For a disc
        of radius a it gives exactly radius a + r (p = a / r).
        """
        if margin_m <= 0.0:
            return self
        w, R = np.linalg.eigh(self.A)
        lam = 1.0 / w**2  # eigenvalues of Q₁ = semi-axes²
        r2 = margin_m**2
        if p is None:
            p = least_area_growth(lam, margin_m)
        semi_axes = np.sqrt((1 + 1 / p) * lam + (1 + p) * r2)
        A = R @ np.diag(1.0 / semi_axes) @ R.T
        return Ellipse(A=A, b=-A @ self.center)

    def level(self, points: ArrayLike) -> FloatArray:
        """‖A z + b‖ for each point (≤ 1 inside): the paper's eq. (2) for a set of points."""
        z = np.atleast_2d(np.asarray(points, dtype=float))
        return np.linalg.norm(z @ self.A.T + self.b, axis=1)

    def boundary(self, n: int = 64) -> FloatArray:
        """`n` points evenly spaced in angle on the boundary."""
        return np.linalg.solve(self.A, (_unit_circle(n) - self.b).T).T

    def tangent_points(self, point: ArrayLike) -> FloatArray | None:
        """The two points where lines through an outside `point` touch the ellipse; None from inside."""
        q = self.A @ np.asarray(point, dtype=float) + self.b
        r = float(np.hypot(*q))
        if r <= 1.0:
            return None
        phi = np.arctan2(q[1], q[0])
        half = np.arccos(1.0 / r)
        angles = np.array([phi - half, phi + half])
        u = np.column_stack([np.cos(angles), np.sin(angles)])
        return np.linalg.solve(self.A, (u - self.b).T).T

    def to_dict(self) -> dict[str, list]:
        return {"A": self.A.tolist(), "b": self.b.tolist()}


@dataclass(frozen=True, eq=False)
class EllipseStack:
    """Many ellipses stacked for vectorised tests: A is (m, 2, 2), b is (m, 2).

    The `min_*` queries answer "how deep into the nearest ellipse" for many points or segments at once,
    with a broad phase: an ellipse lies within its largest semi-axis (its reach) of its centre, so a
    KD-tree over the centres finds the few ellipses a point or segment can touch, and only those pairs
    get the exact test. Where no ellipse is near, the answer is +inf.
    """

    A: FloatArray
    b: FloatArray

    @classmethod
    def of(cls, ellipses: list[Ellipse]) -> EllipseStack:
        """The stack of `ellipses`, in order; the same object for the same ellipses asked again soon.

        A plan asks for the stack of one list many times (the planner, its route search and
        refinement, the smoother); ellipses are immutable and compare by identity, so the last few
        stacks are kept, with whatever each has cached (centres, KD-tree).
        """
        return _stack_of(tuple(ellipses))

    @staticmethod
    def forget() -> None:
        """Drop the stacks `of` keeps, so the next one is built afresh (benchmarks time that build)."""
        _stack_of.cache_clear()

    def __len__(self) -> int:
        return self.A.shape[0]

    @cached_property
    def centers(self) -> FloatArray:
        return -np.linalg.solve(self.A, self.b[:, :, None])[:, :, 0] if len(self) else np.zeros((0, 2))

    @cached_property
    def reach(self) -> FloatArray:
        """Largest semi-axis of each ellipse: 1 / smallest eigenvalue of A."""
        return self.semi_axes[:, 0]

    @cached_property
    def semi_axes(self) -> FloatArray:
        """(m, 2) semi-axes of each ellipse, largest first."""
        return 1.0 / np.linalg.eigvalsh(self.A) if len(self) else np.zeros((0, 2))

    @cached_property
    def stretch(self) -> FloatArray:
        """‖Aⱼ‖₂: how much a displacement grows in each ellipse's unit-disc frame."""
        return np.linalg.eigvalsh(self.A)[:, 1] if len(self) else np.zeros(0)

    @cached_property
    def _tree(self) -> cKDTree:
        return cKDTree(self.centers)

    @cached_property
    def _columns(self) -> tuple[FloatArray, FloatArray, FloatArray]:
        """A's two columns and b, each (2, m), component first: Aⱼ z + bⱼ = c₁ⱼ x + c₂ⱼ y + bⱼ.

        The kernels below work on these with plain products: on a few hundred numbers einsum's
        parsing costs more than its arithmetic (a segment against 128 ellipses: 28 µs, was 49).
        The sums are formed in the same order, so the results are the same to the bit.
        """
        return tuple(np.ascontiguousarray(c.T) for c in (self.A[:, :, 0], self.A[:, :, 1], self.b))

    def levels(self, points: ArrayLike) -> FloatArray:
        """‖Aⱼ zᵢ + bⱼ‖ as an (n_points, m) array."""
        z = np.atleast_2d(np.asarray(points, dtype=float))
        u = _affine([c[:, None, :] for c in self._columns], z[:, 0, None], z[:, 1, None])
        return np.sqrt(_dot(u, u))

    def segment_levels(self, starts: ArrayLike, ends: ArrayLike) -> FloatArray:
        """min over t ∈ [0, 1] of ‖Aⱼ (p + t (q − p)) + bⱼ‖ for each segment p→q: (n_segments, m).

        The paper's eq. (2) checked on the whole continuous segment rather than at sample points: in
        the unit-disc frame the segment is u₀ + t v, and ‖u₀ + t v‖² is a parabola in t whose minimum
        on [0, 1] is at t* = clip(−u₀·v / ‖v‖², 0, 1). A value below 1 means the segment enters the
        ellipse.
        """
        p = np.atleast_2d(np.asarray(starts, dtype=float))
        return self._segment_levels_among(p, np.atleast_2d(np.asarray(ends, dtype=float)), slice(None))

    def _segment_levels_among(self, p: FloatArray, q: FloatArray, among: slice | np.ndarray) -> FloatArray:
        """`segment_levels` against the ellipses `among` alone: (n_segments, len(among))."""
        columns = [c[:, None, among] for c in self._columns]
        d = q - p
        return _segment_minimum(
            _affine(columns, p[:, 0, None], p[:, 1, None]), _affine(columns, d[:, 0, None], d[:, 1, None], shift=False)
        )

    def segments_clear(self, starts: ArrayLike, ends: ArrayLike, *, level: float) -> np.ndarray:
        """Whether each segment keeps at least `level` from every ellipse (its `segment_levels` minimum).

        For a few segments close together (the next motions of a car's search): only the ellipses whose
        bounding disc scaled to `level` meets the segments' bounding box are tested, with the same
        arithmetic. The others pass: a point z further than level · reach from an ellipse's centre c has
        ‖A z + b‖ = ‖A (z − c)‖ ≥ ‖z − c‖ / reach > level (A symmetric, its least eigenvalue 1 / reach).
        """
        p = np.atleast_2d(np.asarray(starts, dtype=float))
        q = np.atleast_2d(np.asarray(ends, dtype=float))
        if len(self) == 0 or len(p) == 0:
            return np.ones(len(p), dtype=bool)
        lo, hi = np.minimum(p.min(axis=0), q.min(axis=0)), np.maximum(p.max(axis=0), q.max(axis=0))
        near = _discs_meeting_box(self.centers, level * self.reach * (1.0 + 1e-9), lo, hi)  # 1e-9: the reach's rounding
        if not len(near):
            return np.ones(len(p), dtype=bool)
        return self._segment_levels_among(p, q, near).min(axis=1) >= level

    def polyline_level(self, points: ArrayLike) -> float:
        """min over a short polyline's segments and every ellipse of the `segment_levels` level (+inf
        without ellipses): the exact test on all pairs, a segment at a time with its ends as plain
        floats. For a leg or two (a straight reference, a chord) that is cheaper than a broad phase or
        the batched kernel, and the same arithmetic, to the bit.

        The answer is a function of the stack's frozen arrays and the points alone, so the last few are
        kept: the planner's straight line and the smoother's chord over it ask the same question.
        """
        if len(self) == 0:
            return math.inf
        xy = np.asarray(points, dtype=float).tolist()
        key = tuple(map(tuple, xy))
        level = self._polyline_levels.get(key)
        if level is not None:
            return level
        level = math.inf
        for (px, py), (qx, qy) in zip(xy, xy[1:]):
            u0 = _affine(self._columns, px, py)
            v = _affine(self._columns, qx - px, qy - py, shift=False)
            here = float(_segment_minimum(u0, v).min())
            if not here >= level:  # (a NaN is kept: it fails every test)
                level = here
        if len(self._polyline_levels) >= 8:
            self._polyline_levels.clear()
        self._polyline_levels[key] = level
        return level

    @cached_property
    def _polyline_levels(self) -> dict[tuple[tuple[float, float], ...], float]:
        return {}

    def _pair_segment_levels(self, p: FloatArray, q: FloatArray, rows: FloatArray, cols: FloatArray) -> FloatArray:
        columns = [c[:, cols] for c in self._columns]
        z, d = p[rows], q[rows] - p[rows]
        return _segment_minimum(_affine(columns, z[:, 0], z[:, 1]), _affine(columns, d[:, 0], d[:, 1], shift=False))

    def near_pairs(self, centers: FloatArray, radii: FloatArray, *, run: int = 1) -> tuple[FloatArray, FloatArray]:
        """Pairs (i, j) where the disc (centers[i], radii[i]) meets ellipse j's bounding disc, by row
        then column.

        With `run` > 1 the KD-tree is asked once per `run` consecutive discs, for the disc that bounds
        them, and each of them is then tested against the ellipses found: the same pairs, far fewer
        queries when consecutive discs lie close together (the samples of a curve).
        """
        if len(self) == 0 or len(centers) == 0:
            return np.zeros(0, dtype=int), np.zeros(0, dtype=int)
        if len(self._reach_classes) > 1:  # each class of similar reach asked with its own largest reach
            parts = [stack.near_pairs(centers, radii, run=run) for _, stack in self._reach_classes]
            rows = np.concatenate([r for r, _ in parts])
            cols = np.concatenate([index[c] for (index, _), (_, c) in zip(self._reach_classes, parts)])
            order = np.lexsort((cols, rows))
            return rows[order], cols[order]
        if run > 1:
            starts = np.arange(0, len(centers), run)
            size = np.diff(np.append(starts, len(centers)))
            middle = 0.5 * (np.minimum.reduceat(centers, starts) + np.maximum.reduceat(centers, starts))
            around = np.maximum.reduceat(np.linalg.norm(centers - np.repeat(middle, size, axis=0), axis=1) + radii, starts)
            lists = self._tree.query_ball_point(middle, r=around + self.reach.max())
        else:
            lists = self._tree.query_ball_point(centers, r=radii + self.reach.max())
        counts = np.fromiter(map(len, lists), dtype=int, count=len(lists))
        cols = np.fromiter(chain.from_iterable(lists), dtype=int, count=int(counts.sum()))
        if run > 1:
            # The tree was asked with the largest reach; an ellipse whose own bounding disc misses the disc
            # round the run meets none of the run's discs.
            owner = np.repeat(np.arange(len(lists)), counts)
            found = np.linalg.norm(middle[owner] - self.centers[cols], axis=1) <= around[owner] + self.reach[cols]
            cols = cols[found]
            counts = np.bincount(owner[found], minlength=len(lists))
            # Every disc of a run against every ellipse found for the run, row by row.
            pairs = size * counts
            group = np.repeat(np.arange(len(lists)), pairs)
            local = np.arange(len(group)) - np.repeat(np.cumsum(pairs) - pairs, pairs)
            rows = starts[group] + local // counts[group]
            cols = cols[(np.cumsum(counts) - counts)[group] + local % counts[group]]
        else:
            rows = np.repeat(np.arange(len(centers)), counts)
        close = np.linalg.norm(centers[rows] - self.centers[cols], axis=1) <= radii[rows] + self.reach[cols]
        return rows[close], cols[close]

    @cached_property
    def _reach_classes(self) -> list[tuple[FloatArray, EllipseStack]]:
        """The ellipses (indices, stack) in classes of reach within a factor 4, when there is more than one:
        the broad phase asks each class's tree with that class's largest reach, not the stack's (a few
        walls' long ellipses among many small ones otherwise make every query a wide one)."""
        reach = self.reach
        if len(reach) < 64 or reach.max() <= 4.0 * reach.min():
            return []
        level = np.floor(np.log(reach / reach.min()) / np.log(4.0)).astype(int)
        return [(index, EllipseStack(A=self.A[index], b=self.b[index]))
                for index in (np.flatnonzero(level == k) for k in np.unique(level))]

    def min_levels(self, points: ArrayLike) -> FloatArray:
        """min over ellipses of ‖Aⱼ z + bⱼ‖ for each point (+inf where no ellipse is near)."""
        z = np.atleast_2d(np.asarray(points, dtype=float))
        rows, cols = self.near_pairs(z, np.zeros(len(z)))
        out = np.full(len(z), np.inf)
        u = _affine([c[:, cols] for c in self._columns], z[rows, 0], z[rows, 1])
        np.minimum.at(out, rows, np.sqrt(_dot(u, u)))
        return out

    def min_segment_levels(
        self, starts: ArrayLike, ends: ArrayLike, *, sag_m: ArrayLike | None = None, run: int = 1
    ) -> FloatArray:
        """min over ellipses of the eq. (2) segment level for each segment (+inf where none is near).

        `sag_m` optionally bounds how far the real curve strays from each chord: it is widened into the
        broad phase and subtracted in each ellipse's frame (‖Aⱼ‖₂ · sag), giving a lower bound for the curve.
        `run`: see `near_pairs`.
        """
        p = np.atleast_2d(np.asarray(starts, dtype=float))
        q = np.atleast_2d(np.asarray(ends, dtype=float))
        sag = np.zeros(len(p)) if sag_m is None else np.asarray(sag_m, dtype=float)
        rows, cols, levels = self.segment_pairs(p, q, sag_m=sag, run=run)
        out = np.full(len(p), np.inf)
        np.minimum.at(out, rows, levels)
        return out

    def segment_pairs(
        self, starts: ArrayLike, ends: ArrayLike, *, sag_m: ArrayLike | None = None, run: int = 1
    ) -> tuple[FloatArray, FloatArray, FloatArray]:
        """(segment, ellipse, level) for every pair the broad phase keeps; see `min_segment_levels`."""
        p = np.atleast_2d(np.asarray(starts, dtype=float))
        q = np.atleast_2d(np.asarray(ends, dtype=float))
        sag = np.zeros(len(p)) if sag_m is None else np.asarray(sag_m, dtype=float)
        rows, cols = self.near_pairs(0.5 * (p + q), 0.5 * np.linalg.norm(q - p, axis=1) + sag, run=run)
        return rows, cols, self._pair_segment_levels(p, q, rows, cols) - sag[rows] * self.stretch[cols]

    def segment_pairs_swept(self, starts: ArrayLike, ends: ArrayLike) -> tuple[FloatArray, FloatArray, FloatArray]:
        """(segment, ellipse, level) for every pair whose segment comes within the ellipse's bounding disc,
        by segment then ellipse, each level as `segment_pairs` gives it.

        The segments are taken in blocks of `_SWEEP_BLOCK` neighbours (in the Morton order of their
        midpoints); each block is tested exactly against every disc that meets the block's bounding box.
        For segments metres long along walls of many ellipses (a tangent graph's) the KD-tree's disc round
        each segment holds most of them, and this keeps a fraction of its pairs in less time; for many short
        segments among many small ellipses each block's box is small, so its discs are few. The pairs it
        leaves out have the segment outside the ellipse's bounding disc, so at a level above 1.
        """
        p = np.atleast_2d(np.asarray(starts, dtype=float))
        q = np.atleast_2d(np.asarray(ends, dtype=float))
        if len(self) == 0 or len(p) == 0:
            return np.zeros(0, dtype=np.intp), np.zeros(0, dtype=np.intp), np.zeros(0)
        c, reach = self.centers, self.reach * (1.0 + 1e-9)
        order = _morton_order(0.5 * (p + q))
        rows, cols = [], []
        for lo in range(0, len(p), _SWEEP_BLOCK):
            k = order[lo : lo + _SWEEP_BLOCK]
            a, d = p[k], q[k] - p[k]
            low, high = np.minimum(a, q[k]).min(axis=0), np.maximum(a, q[k]).max(axis=0)
            near = _discs_meeting_box(c, reach, low, high)
            ex, ey = c[None, near, 0] - a[:, 0, None], c[None, near, 1] - a[:, 1, None]
            dd = d[:, 0] * d[:, 0] + d[:, 1] * d[:, 1]
            t = np.clip((ex * d[:, 0, None] + ey * d[:, 1, None]) / np.where(dd > 0.0, dd, 1.0)[:, None], 0.0, 1.0)
            wx, wy = ex - t * d[:, 0, None], ey - t * d[:, 1, None]
            i, j = np.nonzero(wx * wx + wy * wy <= reach[near] * reach[near])
            rows.append(k[i])
            cols.append(near[j])
        rows, cols = np.concatenate(rows), np.concatenate(cols)
        by = np.lexsort((cols, rows))
        rows, cols = rows[by], cols[by]
        return rows, cols, self._pair_segment_levels(p, q, rows, cols)


_SWEEP_BLOCK = 256  # segments tested at once by `segment_pairs_swept`


def _morton_order(points: FloatArray) -> FloatArray:
    """The points' indices in the Morton (Z) order of a 1024 × 1024 grid over their bounding box: runs of
    consecutive ones lie close together."""
    low = points.min(axis=0)
    span = max(float((points.max(axis=0) - low).max()), 1e-300)
    cell = np.minimum((points - low) * (1023.0 / span), 1023.0).astype(np.int64)
    code = np.zeros(len(points), dtype=np.int64)
    for bit in range(10):
        code |= ((cell[:, 0] >> bit) & 1) << (2 * bit) | ((cell[:, 1] >> bit) & 1) << (2 * bit + 1)
    return np.argsort(code, kind="stable")


@lru_cache(maxsize=64)
def _unit_circle(n: int) -> FloatArray:
    """`n` points evenly spaced in angle on the unit circle (read-only, kept: a cover samples thousands of
    ellipse boundaries at a few sizes)."""
    t = np.linspace(0.0, 2.0 * np.pi, n, endpoint=False)
    return _frozen(np.column_stack([np.cos(t), np.sin(t)]))


@lru_cache(maxsize=8)
def _stack_of(ellipses: tuple[Ellipse, ...]) -> EllipseStack:
    # The ellipses' rows of bytes joined (np.concatenate of 128 small arrays costs 16 µs, a join of them
    # as buffers 5 to 14, of bytes 3 to 8); A and b are views of the rows, read-only as bytes are: the
    # stack is shared.
    rows = np.frombuffer(b"".join([e._row for e in ellipses])).reshape(-1, 6) if ellipses else _frozen(np.zeros((0, 6)))
    return EllipseStack(A=rows[:, :4].reshape(-1, 2, 2), b=rows[:, 4:])


def _discs_meeting_box(centers: FloatArray, radii: FloatArray, low: FloatArray, high: FloatArray) -> np.ndarray:
    """Indices of the discs (centres, radii) that meet the axis-aligned box low … high."""
    out = np.maximum(np.maximum(low - centers, centers - high), 0.0)  # each centre's offset from the box
    return np.flatnonzero(out[:, 0] * out[:, 0] + out[:, 1] * out[:, 1] <= radii * radii)


def _affine(columns: list[FloatArray], x: FloatArray, y: FloatArray, *, shift: bool = True) -> FloatArray:
    """c₁ x + c₂ y (+ b) for `columns` (c₁, c₂, b) from `EllipseStack._columns`: A z (+ b), component first."""
    c1, c2, b = columns
    u = c1 * x + c2 * y
    return u + b if shift else u


def _dot(u: FloatArray, v: FloatArray) -> FloatArray:
    """u · v over the first axis (the two components)."""
    w = u * v
    return w[0] + w[1]


def _segment_minimum(u0: FloatArray, v: FloatArray) -> FloatArray:
    """min over t ∈ [0, 1] of ‖u₀ + t v‖ over the first axis (segments in unit-disc frames)."""
    vv = _dot(v, v)
    t = np.minimum(np.maximum(-_dot(u0, v) / np.where(vv > 0.0, vv, 1.0), 0.0), 1.0)  # clipped to [0, 1]
    w = u0 + t * v
    return np.sqrt(_dot(w, w))


def least_area_growth(squared_semi_axes: FloatArray, margin_m: float) -> float:
    """The Kurzhanski–Vályi parameter p of the least-area ellipse (1 + 1/p) Q + (1 + p) r² I containing an
    ellipse of these squared semi-axes (Q's eigenvalues λᵢ) ⊕ disc(r): the root of
    Σᵢ (r² − λᵢ/p²) / ((1 + 1/p) λᵢ + (1 + p) r²) (`Ellipse.grown`)."""
    lam1, lam2 = np.asarray(squared_semi_axes, dtype=float).tolist()
    r2 = margin_m**2

    def slope(log_p: float) -> float:
        # Two terms in plain floats (brentq calls this some forty times; numpy's calls on two
        # numbers cost more than the arithmetic), the same operations in the same order.
        p = float(np.exp(log_p))
        p2, q, s = p**2, 1 + 1 / p, (1 + p) * r2
        return (r2 - lam1 / p2) / (q * lam1 + s) + (r2 - lam2 / p2) / (q * lam2 + s)

    return float(np.exp(brentq(slope, -40.0, 40.0, xtol=1e-12)))


def growth_family(semi_axes: FloatArray, margin_m: float, count: int) -> FloatArray:
    """Per fit of semi-axes f₁ ≥ f₂ (rows of `semi_axes`), `count` Kurzhanski–Vályi parameters p spaced
    geometrically from f₂/r to f₁/r, (fits, count): a small p keeps the growth's width near r at the price
    of long tips, a large one the reverse; the covers take the one that strays least (`grown_semi_axes`)."""
    a, b = semi_axes[:, 0], semi_axes[:, 1]
    lo, hi = np.maximum(b, 1e-6) / margin_m, np.maximum(a, 1e-6) / margin_m
    steps = np.arange(count) / max(count - 1, 1)
    return lo[:, None] * (hi / lo)[:, None] ** steps[None, :]


def grown_semi_axes(semi_axes: FloatArray, p: FloatArray, margin_m: float) -> FloatArray:
    """The semi-axes √((1 + 1/p) fᵢ² + (1 + p) r²) of the growths of parameter p (one per row of
    `semi_axes`, broadcast against p's shape), each containing its fit ⊕ disc(r) (`Ellipse.grown`)."""
    p = np.asarray(p, dtype=float)
    return np.sqrt((1.0 + 1.0 / p)[..., None] * semi_axes**2 + ((1.0 + p) * margin_m * margin_m)[..., None])


def keep_out_scales(semi_axes: ArrayLike, *, inflation_m: float, keep_m: float) -> FloatArray:
    """For ellipses grown by `inflation_m` from their fits: the least scale s ≤ 1 about its centre at which
    each still provably contains its fit grown by `keep_m` (so a path outside the scaled ellipse keeps
    `keep_m` from the fit).

    Growth (`Ellipse.grown`) gives each semi-axis aᵢ² = (1 + 1/p) fᵢ² + (1 + p) r² ≥ (fᵢ + r)², since the
    difference is (fᵢ/√p − √p r)²; so the fit's semi-axes are fᵢ ≤ aᵢ − r, along the same axes. For any
    q > 0 the coaxial ellipse hᵢ² = (1 + 1/q)(aᵢ − r)² + (1 + q) k² contains the fit plus a disc of
    radius k (Kurzhanski–Vályi, as in `grown`); of q = f₁/k, √(f₁f₂)/k (exact for a disc) and f₂/k the
    one that needs the least scale is taken. The grown ellipse scaled by s = maxᵢ hᵢ/aᵢ contains it.
    `semi_axes` is (m, 2); k = 0 gives the fit's own bound, s = maxᵢ (aᵢ − r)/aᵢ.
    """
    a = np.atleast_2d(np.asarray(semi_axes, dtype=float))
    f = np.maximum(a - inflation_m, 0.0)
    if keep_m <= 0.0:  # nothing to keep beyond the fit itself
        return np.minimum(np.max(f / a, axis=1), 1.0)
    with np.errstate(over="ignore"):  # a keep-out distance tiny beside the fit: q is clipped to 1e12 below
        candidates = np.column_stack([f[:, 0], np.sqrt(f[:, 0] * f[:, 1]), f[:, 1]]) / keep_m
    q = np.clip(candidates, 1e-9, 1e12)[:, :, None]  # (m, 3 choices, 1)
    h = np.sqrt((1.0 + 1.0 / q) * f[:, None, :] ** 2 + (1.0 + q) * keep_m**2)
    return np.minimum(np.min(np.max(h / a[:, None, :], axis=2), axis=1), 1.0)


def as_complex(points: ArrayLike) -> NDArray[np.complex128]:
    """(n, 2) points as n complex numbers x + iy, exactly: a view of C-ordered float64 points, else of
    a float64 copy. A turn is then one product and a distance one subtraction and one |·|."""
    return np.ascontiguousarray(points, dtype=float).view(np.complex128)[:, 0]


def ring_next(ring: FloatArray) -> FloatArray:
    """Each vertex's successor round a ring, the first after the last: np.roll(ring, -1, axis=0) without
    its overhead (a tight cover calls it thousands of times on a few vertices)."""
    return np.concatenate((ring[1:], ring[:1]))


def signed_area(ring: FloatArray) -> float:
    """The shoelace area of an (n, 2) ring: positive when it runs counter-clockwise."""
    x, y = ring[:, 0], ring[:, 1]
    return float(0.5 * np.sum(x * ring_next(y) - ring_next(x) * y))


def counter_clockwise(ring: FloatArray) -> FloatArray:
    """The same ring counter-clockwise: as given, or reversed (a copy)."""
    return ring[::-1].copy() if signed_area(ring) < 0.0 else ring


def norms(v: FloatArray) -> FloatArray:
    """‖vᵢ‖ row by row, as np.linalg.norm(v, axis=-1) sums it (the same squares, in the same order),
    without its reduction over a 2-long axis (7 against 42 µs on 3 000 rows)."""
    x, y = v[..., 0], v[..., 1]
    return np.sqrt(x * x + y * y)


def distance(x: FloatArray, y: FloatArray) -> FloatArray:
    """‖x − y‖ row by row (as np.linalg.norm sums it, without its (k, 2) temporaries)."""
    dx, dy = x[..., 0] - y[..., 0], x[..., 1] - y[..., 1]
    return np.sqrt(dx * dx + dy * dy)


def polyline_length(points: ArrayLike) -> float:
    z = np.asarray(points, dtype=float)
    return float(np.sum(np.linalg.norm(np.diff(z, axis=0), axis=1)))


def arc_lengths(points: ArrayLike) -> FloatArray:
    """The length along the polyline to each of its points (0 at the first)."""
    z = np.asarray(points, dtype=float)
    return np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(z, axis=0), axis=1))])


def joined_legs(legs: Sequence[ArrayLike]) -> FloatArray:
    """Legs that each start where the one before ends, as one polyline (each joint once)."""
    return np.vstack([np.asarray(legs[0], dtype=float), *(np.asarray(leg, dtype=float)[1:] for leg in legs[1:])])


def resample_polyline(points: ArrayLike, *, max_spacing_m: float) -> FloatArray:
    """The same polyline with extra vertices so that no two neighbours are more than `max_spacing_m` apart:
    each segment p → q cut into n = ⌈|q − p| / spacing⌉ equal parts, its points p + (j / n)(q − p) for
    j = 1 … n after the first vertex (all segments at once)."""
    z = np.asarray(points, dtype=float)
    d = z[1:] - z[:-1]
    n = np.maximum(1, np.ceil(np.linalg.norm(d, axis=1) / max_spacing_m).astype(np.intp))
    segment = np.repeat(np.arange(len(d)), n)
    j = np.arange(1, len(segment) + 1) - np.repeat(np.cumsum(n) - n, n)
    return np.concatenate([z[:1], z[:-1][segment] + (j / n[segment])[:, None] * d[segment]])


class PointMemory:
    """Scan hits accumulated in the map frame, one point per occupied `voxel_m` grid cell.

    Obstacles seen earlier stay remembered while they are out of the sensor's view (the sensor only
    sees 180° ahead; the planner must not forget what is behind or beside it). The sensing stage
    clusters what it remembers; the path guard (`services.drive.guard`) keeps the car's own hits the same way, so
    with the same scans it remembers the very points the ellipses were fitted to.

    Each voxel keeps the first point that fell in it, so re-observing a static obstacle does not move
    the remembered points and the downstream clustering and ellipse fits stay still. Re-observing a
    voxel refreshes its age. Beyond `max_points` voxels the least recently observed ones are dropped
    first: memory is bounded, and what is forgotten is what has been out of view longest.
    """

    def __init__(self, *, voxel_m: float = 0.05, max_points: int = 50_000) -> None:
        if not (np.isfinite(voxel_m) and voxel_m > 0.0):
            raise ValueError(f"voxel_m must be finite and positive, got {voxel_m!r}")
        if int(max_points) != max_points or max_points < 1:
            raise ValueError(f"max_points must be a positive integer, got {max_points!r}")
        self.voxel_m = float(voxel_m)
        self.max_points = int(max_points)
        self._voxels: OrderedDict[tuple[int, int], tuple[float, float]] = OrderedDict()
        self.forgotten = 0  # voxels dropped so far to stay within max_points


    def __len__(self) -> int:
        return len(self._voxels)

    def add(self, points: ArrayLike) -> int:
        """Remember map-frame points (k, 2); returns how many voxels were newly occupied.

        Non-finite rows (e.g. misses encoded as inf) are ignored.
        """
        return len(self.remember(points))

    def remember(self, points: ArrayLike) -> FloatArray:
        """Remember map-frame points (k, 2) as `add` does; returns the points that newly occupied a voxel."""
        z = np.asarray(points, dtype=float).reshape(-1, 2)
        z = z[np.all(np.isfinite(z), axis=1)]
        keys = np.floor(z / self.voxel_m).astype(np.int64)
        added = []
        for key, point in zip(map(tuple, keys.tolist()), z.tolist()):
            if key in self._voxels:
                self._voxels.move_to_end(key)
            else:
                self._voxels[key] = (point[0], point[1])
                added.append(point)
        while len(self._voxels) > self.max_points:
            self._voxels.popitem(last=False)
            self.forgotten += 1
        return np.array(added, dtype=float).reshape(-1, 2)

    def points(self) -> FloatArray:
        """The remembered points (n, 2), least recently observed first."""
        if not self._voxels:
            return np.zeros((0, 2))
        return np.array(list(self._voxels.values()), dtype=float)

    def clear(self) -> None:
        self._voxels.clear()
