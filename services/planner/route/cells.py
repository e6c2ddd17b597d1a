"""A grid of cells wholly inside some ellipse: a cheap proof that a candidate segment is blocked."""

from __future__ import annotations

import numpy as np

from services.geometry import EllipseStack, FloatArray, distance

_DEEP_CELL = 0.5  # grid cells of the blocked-segment proof, × the median smallest semi-axis
_FIRST_STRIDE = 8  # samples read in the proof's first pass: every 8th (docs/maps.md)


class DeepCells:
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
        """Whether a point of segment p→q, sampled one cell apart, lies in a marked cell.

        Every `_FIRST_STRIDE`-th sample is read first; only the segments none of those proves blocked
        have all their samples read. The points are the same either way (sample k is p + k/(n − 1) (q − p)
        of n, computed alike), so is the answer; a blocked segment crosses the depth of an ellipse for
        many cells, and most are found in the first pass.
        """
        count = np.ceil(distance(q, p) / self.cell).astype(int) + 2
        sure = self._hits(p, q, count, _FIRST_STRIDE)
        rest = np.flatnonzero(~sure)
        sure[rest] = self._hits(p[rest], q[rest], count[rest], 1)
        return sure

    def _hits(self, p: FloatArray, q: FloatArray, count: FloatArray, stride: int) -> FloatArray:
        """Whether one of samples 0, stride, 2 stride, … (< count) of each segment lies in a marked cell."""
        if not len(p):
            return np.zeros(0, dtype=bool)
        d = q - p
        taken = (count - 1) // stride + 1
        skip = np.cumsum(taken) - taken
        t = (np.arange(taken.sum()) - np.repeat(skip, taken)) * stride  # sample k of count, then scaled to [0, 1]
        t = t * np.repeat(1.0 / (count - 1), taken)
        # Truncation and clipping put every point off the grid on its unmarked border; the grid is read
        # flat, cell (x, y) at x · rows + y.
        flat = np.zeros(len(t), dtype=int)
        for axis, size in enumerate(self.deep.shape):
            start, step = (p[:, axis] - self.origin[axis]) / self.cell, d[:, axis] / self.cell  # in cells
            index = (np.repeat(start, taken) + t * np.repeat(step, taken)).astype(int)
            flat = flat * size + np.clip(index, 0, size - 1)
        return np.logical_or.reduceat(self.deep.ravel()[flat], skip)
