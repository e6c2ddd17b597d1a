"""A cover of an occupancy grid's walls by few ellipses, fitted tile by tile where a plan needs them.

What must be covered. A path from free space into the blocked region crosses a blocked cell that shares
an edge or a corner with a free cell (`OccupancyGrid.border_cells`), so ellipses containing every such
cell keep a robot that starts free out of every blocked cell; the interior of a wall or of unknown space
needs nothing. Each piece of border cells gets the Löwner–John ellipse (eq. 1) of its bounding rectangle
— along the piece's principal axes, or the grid's when that rectangle is smaller — which eq. 1 solves in
closed form: by affine equivariance the MVEE of a rectangle of half-sides w ≥ h is the coaxial ellipse of
semi-axes √2 w, √2 h (a square's is its circumscribed circle). (`mvee_fast` on the cells' corners gives
a slightly smaller ellipse at about a millisecond a piece, which a map's thousands of pieces cannot
afford.) After the fit every corner of the piece's hull is checked, in floats, to have level
‖A z + b‖ ≤ 1 − `_PROOF_MARGIN`, the ellipse enlarged about its centre until it does; the rounding of that
computation is below 1e-12 at map coordinates, so every corner is inside, and, the ellipse being convex,
every cell.

How pieces are chosen. The robot is planned as a point outside the ellipses grown by r = width/2 +
safety: a piece is judged by how far its GROWN ellipse sticks out of the true grown blocked region
B ⊕ disc(r), read off a distance transform of the blocked mask (excess = max over the grown ellipse of
dist(·, B) − r, sampled at cell centres), not by how far the raw ellipse sticks out of its cells. That
matters for thin pieces: a long wall's ellipse is long and thin, and the least-area growth
(`Ellipse.grown`) of it has a minor semi-axis of about √2·r, which narrows corridors and closes doors.
The growth here is chosen per piece: every ellipse (1 + 1/p) Q + (1 + p) r² I contains the Minkowski sum
of the fit Q with disc(r) for any p > 0 (Kurzhanski & Vályi), a small p keeps the width near r at the
price of long tips, and a long tip does no harm in the middle of a straight wall, where it lies in the
wall's own grown strip; so p is picked, among a few from (minor semi-axis)/r to (major semi-axis)/r, for
the least excess. A piece whose excess is above the tolerance is split in two across its principal axis
(the recursive bisection of `services.ellipsoids.cover`), so long walls end up as a few long ellipses
and corners, wall ends and door jambs as short ones: the count follows the outline, not the cells.
Every piece of one level of the bisection is fitted, judged and split in one batch of array operations.
A piece that holds a start or goal (which may lie within the tolerance of the grown region) is fitted
again at smaller tolerances until none does (`GridCover.tighten`).

Tiles. The grid (with the ring of blocked cells round it: beyond the map is unknown) is cut into square
tiles, fitted when a plan first asks for them (`GridCover.pieces`) and kept. The tiles asked for at once
are fitted as whole rectangles of tiles, their border cells pieces across the tiles' edges (a wall is
not cut at every tile), neighbouring ones on one distance transform over them and their halo. A piece's grown ellipse must stay
within its rectangle widened by `halo_m` (a growth that does not is not taken), so a path further than
`halo_m` from every tile not yet fitted can touch no ellipse those tiles will get (`GridCover.reach_m`).
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass, field
from functools import cached_property
from typing import NamedTuple

import cv2
import numpy as np
from numpy.typing import NDArray

from services.geometry import Ellipse, FloatArray, grown_semi_axes, growth_family
from schemas.occupancy import OccupancyGrid

IntArray = NDArray[np.intp]
Tile = tuple[int, int]  # (tile column, tile row)

# OpenCV's thread pool costs these windows more CPU time than it saves (docs/maps.md): one thread.
cv2.setNumThreads(1)

_PROOF_MARGIN = 1e-9  # every corner's computed level stays this far below 1 (rounding is < 1e-12)
_GOLDEN_RAD = math.pi * (3.0 - math.sqrt(5.0))  # sunflower samples of a disc
# Tolerances a piece holding a start or goal is refitted at in turn (`GridCover.tighten`).
_TIGHTER_M = (0.05, 0.025, 0.0125)
_EXACT_CELLS = 1_200.0  # a distance window is the exact distance's rounding up to this many cells (`_window`)


@dataclass(frozen=True)
class GridCoverSettings:
    tolerance_m: float = 0.1  # largest excess of a grown ellipse over the grown blocked region
    tile_m: float = 2.4  # side of a tile
    halo_m: float = 1.0  # how far a grown ellipse may reach beyond its tile
    growths: int = 4  # growth parameters p tried per piece
    join_m: float = 0.4  # border cells closer than this start in one piece


@dataclass(frozen=True, eq=False)
class GridPiece:
    """One ellipse of the cover: the fit of its cells and its growth (world frame, {z : ‖A z + b‖ ≤ 1},
    as `Ellipse`s when asked for), and how it was judged."""

    raw_Ab: FloatArray  # (2, 3): A, then b as a column
    grown_Ab: FloatArray
    p: float  # the Kurzhanski–Vályi parameter of the growth
    excess_m: float  # of the grown ellipse over the grown blocked region (sampled at cell centres)
    cells: IntArray  # (n, 2) column, row of the border cells it covers
    tolerance_m: float  # the largest excess it was fitted to take (smaller once tightened)

    @cached_property
    def raw(self) -> Ellipse:
        return Ellipse(A=self.raw_Ab[:, :2], b=self.raw_Ab[:, 2])

    @cached_property
    def grown(self) -> Ellipse:
        return Ellipse(A=self.grown_Ab[:, :2], b=self.grown_Ab[:, 2])


@dataclass(frozen=True)
class DistanceWindow:
    """A distance transform over a block of cells: D = metres from each cell centre to the nearest blocked
    cell's centre, less half a cell, rows × columns from (row0, col0). D is at least the distance from the
    centre to the nearest blocked square (that square is no further than its centre less half a cell),
    and exact, or above the margin plus the tolerance, everywhere in the window."""

    row0: int
    col0: int
    distance: NDArray[np.float32]


@dataclass(eq=False)
class GridCover:
    """The cover of one grid's border cells for one margin, fitted tile by tile on demand."""

    grid: OccupancyGrid
    margin_m: float
    settings: GridCoverSettings = field(default_factory=GridCoverSettings)
    fitted: dict[Tile, list[GridPiece]] = field(default_factory=dict)

    def __post_init__(self) -> None:
        res = self.grid.resolution_m
        self.tile_cells = max(8, int(round(self.settings.tile_m / res)))
        self.halo_cells = int(math.ceil(self.settings.halo_m / res))
        self.join_cells = int(round(self.settings.join_m / (2.0 * res)))  # dilating both by half joins them
        # Distances are needed up to margin + tolerance beyond the halo, plus a cell of rounding.
        self.reach_cells = int(math.ceil((self.margin_m + self.settings.tolerance_m) / res)) + 2
        rows, cols = self.grid.shape
        self.tiles_shape = (-(-(cols + 2) // self.tile_cells), -(-(rows + 2) // self.tile_cells))
        self.fit_count = 0  # ellipse fits made (a piece that is split counts too), for reports
        self._distances: dict[Tile, NDArray[np.float32]] = {}  # each fitted tile's cells' D (`DistanceWindow`)

    @property
    def reach_m(self) -> float:
        """How far beyond the tiles fitted with it any grown ellipse can reach."""
        return self.settings.halo_m

    def tile_range(self, tile: Tile) -> tuple[slice, slice]:
        """(rows, columns) of a tile's cells; the tiles start one cell before the map (its blocked ring)."""
        t = self.tile_cells
        a, b = tile
        rows, cols = self.grid.shape
        return slice(b * t - 1, min((b + 1) * t - 1, rows + 1)), slice(a * t - 1, min((a + 1) * t - 1, cols + 1))

    def _extent(self, tiles: Iterable[Tile]) -> tuple[slice, slice]:
        """(rows, columns) of the cells of the rectangle bounding the tiles."""
        ranges = [self.tile_range(t) for t in tiles]
        return (slice(min(r.start for r, _ in ranges), max(r.stop for r, _ in ranges)),
                slice(min(c.start for _, c in ranges), max(c.stop for _, c in ranges)))

    def _halo_box(self, rows: slice, cols: slice) -> tuple[int, int, int, int]:
        """Rows r0…r1, columns c0…c1 of a rectangle of cells widened by the halo: where the grown
        ellipses of its pieces must stay."""
        h = self.halo_cells
        return rows.start - h, rows.stop + h, cols.start - h, cols.stop + h

    def tiles_near(self, points: FloatArray, radius_m: float) -> set[Tile]:
        """Tiles whose cells come within `radius_m` of some world point (a square round each point)."""
        if not len(points):
            return set()
        g = self.grid.to_grid(points) / self.grid.resolution_m + 1.0  # in cells, from the ring's corner
        reach = radius_m / self.grid.resolution_m
        top = np.array(self.tiles_shape) - 1
        lo = np.clip(np.floor((g - reach) / self.tile_cells).astype(int), 0, top)
        hi = np.clip(np.floor((g + reach) / self.tile_cells).astype(int), 0, top)
        # Each point's square spans a few tiles each way: marked offset by offset, clipped to its last tile.
        hit = np.zeros(self.tiles_shape, dtype=bool)
        wide = hi - lo
        for dx in range(int(wide[:, 0].max()) + 1):
            for dy in range(int(wide[:, 1].max()) + 1):
                hit[np.minimum(lo[:, 0] + dx, hi[:, 0]), np.minimum(lo[:, 1] + dy, hi[:, 1])] = True
        return set(zip(*(axis.tolist() for axis in np.nonzero(hit))))

    def pieces(self, tiles: Iterable[Tile]) -> list[GridPiece]:
        """The pieces of the given tiles, fitting the tiles not fitted yet."""
        wanted = sorted(set(tiles))
        missing = [t for t in wanted if t not in self.fitted]
        if missing:
            self._fit_blocks(_blocks(missing))
        return [piece for t in wanted for piece in self.fitted[t]]

    def distance_at(self, points: FloatArray) -> FloatArray:
        """D (`DistanceWindow`) at the cells under world points, as the tiles were fitted on it (tiles not
        fitted are fitted first): within a cell of a point's clearance up to the margin plus the tolerance,
        above that beyond; 0 beyond the map's ring of blocked cells."""
        g = self.grid.to_grid(points) / self.grid.resolution_m + 1.0  # cells from the ring's corner
        i, j = np.floor(g[:, 0]).astype(np.intp), np.floor(g[:, 1]).astype(np.intp)
        tiles = np.column_stack([i // self.tile_cells, j // self.tile_cells])
        rows, cols = self.grid.shape
        inside = (i >= 0) & (j >= 0) & (i < cols + 2) & (j < rows + 2)
        out = np.zeros(len(g))
        wanted = [tuple(t) for t in np.unique(tiles[inside], axis=0).tolist()]
        self.pieces(wanted)
        for a, b in wanted:
            here = np.flatnonzero(inside & (tiles[:, 0] == a) & (tiles[:, 1] == b))
            out[here] = self._distances[a, b][j[here] - b * self.tile_cells, i[here] - a * self.tile_cells]
        return out

    def tighten(self, points: FloatArray, *, tolerances_m: tuple[float, ...] = _TIGHTER_M, near: bool = False) -> bool:
        """Refit the fitted pieces whose grown ellipse holds one of the world points, at each of the smaller
        tolerances in turn, until none does; whether any piece was refitted. A piece already fitted to a
        tolerance is not refitted to it again (a point within the margin stays held by the tightest).
        `near`: also the pieces a point may come within the piece's own tolerance of (its level ℓ with
        (ℓ − 1) × the minor semi-axis, a lower bound on the distance, at most that): the points of a path
        whose curve failed along them, which the pieces' excess over the grown walls may have pushed.

        A start or goal in free space may lie within the tolerance of the grown blocked region (a goal
        set 2 cm beyond the margin from a wall): the cover, up to `tolerance_m` more conservative than
        the region, would hold it, and no plan could start or end there. Refitted, the same cells are
        covered (each new piece proved as every piece is), by more and tighter ellipses where the points
        are; a point truly within the margin of a blocked cell stays inside at every tolerance.
        """
        points = np.asarray(points, dtype=float).reshape(-1, 2)
        if not len(points):
            return False
        changed = False
        for tolerance in tolerances_m:
            pieces = [(tile, piece) for tile, kept in self.fitted.items() for piece in kept]
            if not pieces:
                break
            Ab = np.array([piece.grown_Ab for _, piece in pieces])  # (k, 2, 3)
            u = np.einsum("kij,pj->kpi", Ab[:, :, :2], points) + Ab[:, None, :, 2]
            level = np.sqrt(np.min(np.einsum("kpi,kpi->kp", u, u), axis=1))
            reach = np.zeros(len(pieces))
            if near:  # the minor semi-axis is 1 / the largest singular value of A
                minor = 1.0 / np.linalg.svd(Ab[:, :, :2], compute_uv=False)[:, 0]
                reach = np.array([piece.tolerance_m for _, piece in pieces]) / minor
            holding = [pieces[k] for k in np.flatnonzero(level <= 1.0 + reach)]
            if not holding:
                break
            for tile, piece in holding:
                if piece.tolerance_m <= tolerance:
                    continue
                self.fitted[tile].remove(piece)
                for made in self._refit(piece.cells, tolerance=tolerance):
                    self.fitted[self._tile_of(made.cells[0])].append(made)
                changed = True
        return changed

    def _refit(self, cells: IntArray, *, tolerance: float):
        """One piece's cells fitted again to `tolerance`, on a distance transform over their tiles, each
        new piece kept within those tiles and their halo (as the tiles' own pieces are)."""
        group = sorted({self._tile_of(cell) for cell in cells})
        window = self._window(group)
        box = self._halo_box(*self._extent(group))
        where = (0, window.row0, window.col0, window.distance.shape[1])
        yield from self._bisect(cells, np.zeros(len(cells), dtype=np.intp), np.array([box + where]),
                                window.distance.reshape(-1), tolerance=tolerance)

    # ------------------------------------------------------------------ one batch of tiles

    def _fit_blocks(self, groups: list[list[Tile]]) -> None:
        """Fit groups of neighbouring tiles, each on one distance transform over it and its halo, as whole
        rectangles of tiles (`_rectangles`): a rectangle's border cells are pieces across its tiles' edges
        (a wall is not cut at every tile), each kept under the tile of its first cell. Every rectangle's
        pieces go through one bisection: a level is one batch of array operations, whatever the groups."""
        parts, distances, start = [], [], 0
        for group in groups:
            window = self._window(group)
            distances.append(window.distance.reshape(-1))
            rows, cols = window.distance.shape
            for tile in group:
                self.fitted[tile] = []
                r, c = self.tile_range(tile)
                self._distances[tile] = window.distance[r.start - window.row0 : r.stop - window.row0,
                                                        c.start - window.col0 : c.stop - window.col0].copy()
            for block in _rectangles(group):
                if (part := self._pieces_of(block)) is not None:
                    cells, piece, boxes = part
                    # Each piece's box also says where its window's distances are (`_sample_max`).
                    where = np.tile((start, window.row0, window.col0, cols), (len(boxes), 1))
                    parts.append((cells, piece, np.column_stack([boxes, where])))
            start += rows * cols
        if not parts:
            return
        offsets = np.cumsum([0] + [int(part[1].max()) + 1 for part in parts[:-1]])
        cells = np.vstack([part[0] for part in parts])
        piece = np.concatenate([part[1] + offset for part, offset in zip(parts, offsets)])
        boxes = np.vstack([part[2] for part in parts])
        for made in self._bisect(cells, piece, boxes, np.concatenate(distances)):
            self.fitted[self._tile_of(made.cells[0])].append(made)

    def _window(self, group: list[Tile]) -> DistanceWindow:
        """The distance transform over a group of tiles and their halo: the exact Euclidean transform
        (OpenCV's, Felzenszwalb–Huttenlocher) of the window widened by `reach_cells` on every side, so
        exact wherever the distance is at most that, and above it elsewhere."""
        rows, cols = self._extent(group)
        h, k = self.halo_cells + 1, self.reach_cells
        r0, r1, c0, c1 = rows.start - h, rows.stop + h, cols.start - h, cols.stop + h
        free = ~self.grid.padded_blocked(slice(r0 - k, r1 + k), slice(c0 - k, c1 + k))
        # Cells to the nearest blocked cell's centre (0 on blocked cells), the square root of a whole
        # number. OpenCV's single-precision value of it is within one epsilon (relative) of the exact one
        # but not the same from call to call on the same cells (docs/maps.md); its square is then within
        # 0.5 of the whole number below 1 200 cells, so the root of the rounded square (single precision:
        # correctly rounded) is the rounding of the exact distance, the same every time. (Further away a
        # neighbouring whole number moves the distance by under 1/2 400 of a cell, far above `reach_cells`.)
        # A window with no blocked cell gets 2⁶⁴ everywhere, whose square overflows: distances are capped
        # where they are no longer exact, which keeps them above `reach_cells`.
        cells = cv2.distanceTransform(free.view(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)[k:-k, k:-k]
        np.minimum(cells, max(_EXACT_CELLS, self.reach_cells), out=cells)
        cells = np.sqrt(np.rint(cells * cells))
        edt = cells.astype(float) * self.grid.resolution_m - 0.5 * self.grid.resolution_m
        return DistanceWindow(row0=r0, col0=c0, distance=np.maximum(edt, 0.0, out=edt).astype(np.float32))

    def _pieces_of(self, block: list[Tile]) -> tuple[IntArray, IntArray, IntArray] | None:
        """A rectangle of tiles' border cells (by piece, then row, then column), their first pieces, and
        each piece's box: the rectangle and its halo, where its grown ellipse must stay (its tiles are
        fitted together, so that is within `reach_m` of tiles fitted with it)."""
        rows, cols = self._extent(block)
        border = self.grid.border_cells(rows, cols)
        if not len(border):
            return None
        mask = np.zeros((rows.stop - rows.start, cols.stop - cols.start), dtype=bool)
        mask[border[:, 1] - rows.start, border[:, 0] - cols.start] = True
        # Cells closer than `join_m` are one piece to begin with: a speck beside a wall is split off again
        # only if the wall's ellipse cannot take it within the tolerance.
        # (k dilations by the 8-neighbourhood are one by a (2k + 1)-square; Wu's labelling, SAUF, numbers
        # the components in the order a raster scan first meets them.)
        near = cv2.dilate(mask.view(np.uint8), np.ones((2 * self.join_cells + 1,) * 2, dtype=np.uint8))
        count, labels = cv2.connectedComponentsWithAlgorithm(near, 8, cv2.CV_32S, cv2.CCL_SAUF)
        count -= 1  # not the background
        js, is_ = np.nonzero(mask)  # row by row, then column
        piece = labels[js, is_].astype(np.intp) - 1  # every label 1…count holds a border cell: `near` is their dilation
        order = np.argsort(piece, kind="stable")
        box = self._halo_box(rows, cols)
        return (np.column_stack([is_ + cols.start, js + rows.start])[order], piece[order], np.array([box] * count))

    def _tile_of(self, cell: IntArray) -> Tile:
        return (int(cell[0] + 1) // self.tile_cells, int(cell[1] + 1) // self.tile_cells)

    def _bisect(self, cells: IntArray, piece: IntArray, boxes: IntArray, distance: NDArray[np.float32], *,
                tolerance: float | None = None):
        """Fit, judge and split every piece of a level at once, level after level; yields the pieces taken
        (in the order of their levels), proved and made in one batch after the last level (`_accepted`).
        `distance`: the windows' distances, one after another (each piece's box says where its window is).
        `tolerance`: the largest excess taken (the settings' unless given)."""
        tolerance = self.settings.tolerance_m if tolerance is None else tolerance
        res = self.grid.resolution_m
        taken: list[_Taken] = []  # each level's accepted pieces
        while len(cells):
            fit = _fit_boxes(cells, piece, res=res)
            self.fit_count += fit.count
            p, grown, excess = self._grow(fit, distance, boxes, tolerance=tolerance)
            side = _sides(cells, piece, fit)
            below = np.bincount(piece, weights=side, minlength=fit.count)
            splittable = (below > 0) & (below < fit.count_cells)
            accept = (excess <= tolerance) | ~splittable
            if len(idx := np.flatnonzero(accept)):
                on = accept[fit.corner_piece]
                starts, ends = np.searchsorted(piece, idx), np.searchsorted(piece, idx, side="right")
                taken.append(_Taken(centre=fit.centre[idx], axes=fit.axes[idx], semi=fit.semi_axes[idx], p=p[idx],
                                    excess=excess[idx], corners=fit.corners[on],
                                    corner_owner=np.searchsorted(idx, fit.corner_piece[on]),
                                    cells=[cells[a:b] for a, b in zip(starts.tolist(), ends.tolist())]))
            # The split pieces' halves: piece 2k + side, renumbered, still by row then column within.
            keep = ~accept[piece]
            halves = 2 * piece[keep] + side[keep].astype(np.intp)
            present = np.bincount(halves, minlength=2 * fit.count) > 0
            labels = np.flatnonzero(present)
            halves = (np.cumsum(present) - 1)[halves]  # numbered in order, as np.unique's inverse
            order = np.argsort(halves, kind="stable")
            cells, piece = cells[keep][order], halves[order]
            boxes = boxes[labels // 2]
        if taken:
            yield from self._accepted(taken, tolerance=tolerance)

    def _grow(self, fit: _Fits, distance: NDArray[np.float32], boxes: IntArray, *,
              tolerance: float) -> tuple[FloatArray, FloatArray, FloatArray]:
        """Each piece's growth parameter, grown semi-axes (P, 2) and excess, the least-excess growth among
        `growths` values of p per piece.

        Every candidate's boundary is sampled two cells apart first: the maximum is a lower bound on the
        excess. The candidate with the least bound then gets its boundary sampled a cell apart and its
        interior two cells apart; a piece whose bound already exceeds the tolerance is split without that.
        """
        r, res = self.margin_m, self.grid.resolution_m
        p = growth_family(fit.semi_axes, r, self.settings.growths)  # (P, G)
        grown = grown_semi_axes(fit.semi_axes[:, None, :], p, r)
        P, G = p.shape
        rows = np.repeat(np.arange(P), G)
        bound = _sample_max(fit.centre[rows], fit.axes[rows], grown.reshape(-1, 2), boxes[rows], distance, res=res,
                            step_cells=2.0, interior=False).reshape(P, G)
        best = np.argmin(bound, axis=1)
        take = np.arange(P)
        excess = bound[take, best] - r
        near = np.flatnonzero(excess <= tolerance)
        if len(near):
            chosen = (fit.centre[near], fit.axes[near], grown[near, best[near]], boxes[near], distance)
            edge_and_inner = _sample_max(*chosen, res=res, step_cells=1.0, interior=False, interior_step_cells=2.0)
            excess[near] = np.maximum(excess[near], edge_and_inner - r)
        return p[take, best], grown[take, best], excess

    def _accepted(self, taken: list[_Taken], *, tolerance: float):
        """The pieces every level took, as world ellipses, each proved to contain its cells (see the module)."""
        def joined(name: str) -> np.ndarray:
            return np.concatenate([getattr(level, name) for level in taken])

        centre, axes, semi = joined("centre"), joined("axes"), joined("semi")
        p, excess, corners = joined("p"), joined("excess"), joined("corners")
        offsets = np.cumsum([0] + [len(level.p) for level in taken[:-1]])  # a level's first piece among them all
        corner_owner = np.concatenate([level.corner_owner + offset for level, offset in zip(taken, offsets)])
        cells = [piece_cells for level in taken for piece_cells in level.cells]
        res = self.grid.resolution_m
        R = self.grid.rotation
        origin = np.array([self.grid.origin_x_m, self.grid.origin_y_m])
        centre = centre @ R.T + origin  # world centres
        axes = np.einsum("ij,kjl->kil", R, axes)  # world axis directions (columns)
        # The hull's corners of each accepted piece, in the world.
        first_corner = np.searchsorted(corner_owner, np.arange(len(centre)))
        corners = self.grid.to_world(corners * res)
        for _ in range(2):
            A = _shape(axes, semi)
            u = np.einsum("kij,kj->ki", A[corner_owner], corners - centre[corner_owner])
            worst = np.maximum.reduceat(np.sqrt(np.einsum("ki,ki->k", u, u)), first_corner)
            over = worst > 1.0 - _PROOF_MARGIN
            if not over.any():
                break
            semi[over] *= (worst[over] / (1.0 - 2.0 * _PROOF_MARGIN))[:, None]  # aimed past the bound by its rounding
        else:
            raise AssertionError("a fitted ellipse does not contain its cells")
        grown_semi = grown_semi_axes(semi, p, self.margin_m)
        grown_A = _shape(axes, grown_semi)
        raw_Ab = np.concatenate([A, -np.einsum("kij,kj->ki", A, centre)[:, :, None]], axis=2)
        grown_Ab = np.concatenate([grown_A, -np.einsum("kij,kj->ki", grown_A, centre)[:, :, None]], axis=2)
        for k, (pk, ek) in enumerate(zip(p.tolist(), excess.tolist())):
            yield GridPiece(raw_Ab=raw_Ab[k], grown_Ab=grown_Ab[k], p=pk, excess_m=ek, cells=cells[k],
                            tolerance_m=tolerance)


class _Taken(NamedTuple):
    """The pieces one level of `GridCover._bisect` accepted: their fits (grid-frame centres, axis directions,
    semi-axes), growth parameters and excesses, their hulls' corners (in cells; `corner_owner`: each
    one's piece among them, ascending) and each piece's cells."""

    centre: FloatArray
    axes: FloatArray
    semi: FloatArray
    p: FloatArray
    excess: FloatArray
    corners: IntArray
    corner_owner: IntArray
    cells: list[IntArray]


def _shape(axes: FloatArray, semi: FloatArray) -> FloatArray:
    """A = V diag(1/a) Vᵀ for each ellipse: (k, 2, 2) from axis directions (k, 2, 2) and semi-axes (k, 2)."""
    return np.einsum("kij,kj,klj->kil", axes, 1.0 / semi, axes)


@dataclass(frozen=True)
class _Fits:
    """A level's pieces: cell counts, principal directions, the hull corners, and the ellipses fitted
    (grid-frame metres: centres, semi-axes largest first, axis directions as columns)."""

    count: int
    count_cells: FloatArray
    mean: FloatArray  # mean cell centre, in cells
    direction: FloatArray  # principal direction (unit), in cells
    corners: IntArray  # hull corners (in cells) of every piece, piece by piece
    corner_piece: IntArray
    centre: FloatArray
    semi_axes: FloatArray
    axes: FloatArray


def _fit_boxes(cells: IntArray, piece: IntArray, *, res: float) -> _Fits:
    """Every piece's Löwner–John ellipse of its smaller bounding rectangle (see the module docstring)."""
    starts, ends = _runs(piece[1:] != piece[:-1])
    count = len(starts)
    n = (ends - starts).astype(float)
    xy = cells + 0.5
    mean = np.add.reduceat(xy, starts, axis=0) / n[:, None]
    d = xy - mean[piece]
    sxx = np.add.reduceat(d[:, 0] * d[:, 0], starts)
    syy = np.add.reduceat(d[:, 1] * d[:, 1], starts)
    sxy = np.add.reduceat(d[:, 0] * d[:, 1], starts)
    angle = 0.5 * np.arctan2(2.0 * sxy, sxx - syy)  # of the major axis
    direction = np.column_stack([np.cos(angle), np.sin(angle)])
    # The first and last cell of each row of each piece: the corners of their cells bound the piece (a
    # cell lies between its row's first and last, inside the rectangle of their corners).
    row = cells[:, 1]
    first, after = _runs((row[1:] != row[:-1]) | (piece[1:] != piece[:-1]))
    last = after - 1
    i0, i1, j = cells[first, 0], cells[last, 0] + 1, row[first]
    corners = np.empty((len(first), 4, 2), dtype=cells.dtype)  # (i0, j), (i0, j + 1), (i1, j), (i1, j + 1)
    corners[:, :2, 0], corners[:, 2:, 0] = i0[:, None], i1[:, None]
    corners[:, ::2, 1], corners[:, 1::2, 1] = j[:, None], j[:, None] + 1
    corners = corners.reshape(-1, 2)
    corner_piece = np.repeat(piece[first], 4)
    cstarts = 4 * np.searchsorted(first, starts)  # each piece's first row starts a run: 4 corners a run
    cf = corners.astype(float)
    # The rectangle along the principal axes, and along the grid's; the smaller is fitted.
    normal = np.column_stack([-direction[:, 1], direction[:, 0]])
    u, v = direction[corner_piece], normal[corner_piece]
    along = np.column_stack([np.einsum("ij,ij->i", cf, u), np.einsum("ij,ij->i", cf, v)])
    lo_p, hi_p = np.minimum.reduceat(along, cstarts, axis=0), np.maximum.reduceat(along, cstarts, axis=0)
    lo_g, hi_g = np.minimum.reduceat(cf, cstarts, axis=0), np.maximum.reduceat(cf, cstarts, axis=0)
    principal = np.prod(hi_p - lo_p, axis=1) < np.prod(hi_g - lo_g, axis=1) * (1.0 - 1e-9)
    axes = np.zeros((count, 2, 2))
    axes[:, :, 0] = np.where(principal[:, None], direction, [1.0, 0.0])
    axes[:, :, 1] = np.where(principal[:, None], normal, [0.0, 1.0])
    lo = np.where(principal[:, None], lo_p, lo_g)
    hi = np.where(principal[:, None], hi_p, hi_g)
    half = 0.5 * res * (hi - lo)
    centre = np.einsum("kij,kj->ki", axes, 0.5 * res * (lo + hi))
    swap = half[:, 1] > half[:, 0]  # the larger semi-axis first
    half[swap] = half[swap][:, ::-1]
    axes[swap] = axes[swap][:, :, ::-1]
    return _Fits(count=count, count_cells=n, mean=mean, direction=direction, corners=corners,
                 corner_piece=corner_piece, centre=centre, semi_axes=math.sqrt(2.0) * half, axes=axes)


def _runs(change: NDArray[np.bool_]) -> tuple[IntArray, IntArray]:
    """Where the runs of a sequence start and end (one past their last): a run starts at 0 and at i + 1
    wherever `change[i]` (element i + 1 differs from element i), and ends where the next starts."""
    inner = np.flatnonzero(change) + 1
    return np.concatenate(([0], inner)), np.concatenate((inner, [len(change) + 1]))


def _sides(cells: IntArray, piece: IntArray, fit: _Fits) -> NDArray[np.bool_]:
    """Which side of the line through its piece's mean, across the principal axis, each cell lies on."""
    d = cells + 0.5 - fit.mean[piece]
    return np.einsum("ij,ij->i", d, fit.direction[piece]) <= 0.0


def _sample_max(centre: FloatArray, axes: FloatArray, semi: FloatArray, boxes: IntArray,
                distance: NDArray[np.float32], *, res: float, step_cells: float, interior: bool,
                interior_step_cells: float | None = None) -> FloatArray:
    """For each ellipse (grid-frame metres): the max over samples of its boundary, or of its disc
    (`interior`), about `step_cells` apart, of the distance to the blocked region (and, with
    `interior_step_cells`, over samples of its disc that far apart too: the larger of the two maxima);
    +inf for one that reaches outside its halo box (rows r0…r1, columns c0…c1, in cells). The box's last
    four numbers say where its window is in `distance`: where it starts, its first row and column, its
    width."""
    ext = np.hypot(semi[:, 0:1] * axes[:, :, 0], semi[:, 1:2] * axes[:, :, 1])  # extent along x and y, metres
    c = centre / res
    e = ext / res
    inside = ((c[:, 0] - e[:, 0] >= boxes[:, 2]) & (c[:, 0] + e[:, 0] <= boxes[:, 3])
              & (c[:, 1] - e[:, 1] >= boxes[:, 0]) & (c[:, 1] + e[:, 1] <= boxes[:, 1]))
    out = np.full(len(centre), np.inf)
    k = np.flatnonzero(inside)
    if not len(k):
        return out
    # A sample (u, v) of the unit disc, in cells from its window's corner: c + V diag(semi) (u, v) / res,
    # its coefficients formed once per ellipse and repeated to its samples. Inside the box, so inside the
    # window: ≥ 0, and a cast truncates as the floor does.
    start, row0, col0, width = boxes[k, 4:8].T
    sa, sb = semi[k, 0] / res, semi[k, 1] / res
    coefficients = np.stack([centre[k, 0] / res - col0, axes[k, 0, 0] * sa, axes[k, 0, 1] * sb,
                             centre[k, 1] / res - row0, axes[k, 1, 0] * sa, axes[k, 1, 1] * sb])
    where = np.stack([start, width])
    sets = [(step_cells, interior)] + ([] if interior_step_cells is None else [(interior_step_cells, True)])
    peak = None
    for spacing, disc in sets:
        a, b = semi[k, 0] / (res * spacing), semi[k, 1] / (res * spacing)
        if disc:
            counts = np.clip(np.ceil(np.pi * a * b), 8, 20_000).astype(np.intp)
        else:
            counts = np.clip(np.ceil(2.0 * np.pi * np.maximum(a, b)), 16, 20_000).astype(np.intp)
        offsets = np.cumsum(counts) - counts
        each = np.repeat(counts, counts)
        step = np.arange(len(each)) - np.repeat(offsets, counts)
        # The angles' cosines and sines in single precision (numpy's are vectorised there, 30 times faster
        # than in double): a sample moves by some 1e-7 of its semi-axis, the angle being below 2π.
        if disc:  # sunflower: evenly spread over the disc
            radius = np.sqrt((step + 0.5) / each)
            theta = np.remainder(step * _GOLDEN_RAD, 2.0 * np.pi).astype(np.float32)
            u, v = radius * np.cos(theta), radius * np.sin(theta)
        else:
            theta = ((2.0 * np.pi) * step / each).astype(np.float32)
            u, v = np.cos(theta), np.sin(theta)
        cx, xu, xv, cy, yu, yv = np.repeat(coefficients, counts, axis=1)
        first, stride = np.repeat(where, counts, axis=1)
        i = (cx + xu * u + xv * v).astype(np.intp)
        j = (cy + yu * u + yv * v).astype(np.intp)
        here = np.maximum.reduceat(distance[first + j * stride + i], offsets)
        peak = here if peak is None else np.maximum(peak, here)
    out[k] = peak
    return out


def _blocks(tiles: list[Tile]) -> list[list[Tile]]:
    """Group tiles into batches that share one distance transform: the 8-connected groups of tiles,
    each cut in halves along its longer side while its bounding box is more than twice its tiles."""
    out: list[list[Tile]] = []
    remaining = set(tiles)
    while remaining:
        seed = remaining.pop()
        group, frontier = [seed], [seed]
        while frontier:
            x, y = frontier.pop()
            for n in ((x + dx, y + dy) for dx in (-1, 0, 1) for dy in (-1, 0, 1)):
                if n in remaining:
                    remaining.remove(n)
                    group.append(n)
                    frontier.append(n)
        out.extend(_halve(sorted(group)))
    return out


def _halve(group: list[Tile]) -> list[list[Tile]]:
    xs, ys = [t[0] for t in group], [t[1] for t in group]
    w, h = max(xs) - min(xs) + 1, max(ys) - min(ys) + 1
    if w * h <= 2 * len(group) or len(group) <= 2:
        return [group]
    axis, mid = (0, (min(xs) + max(xs) + 1) / 2) if w >= h else (1, (min(ys) + max(ys) + 1) / 2)
    return _halve([t for t in group if t[axis] < mid]) + _halve([t for t in group if t[axis] >= mid])


def _rectangles(tiles: list[Tile]) -> list[list[Tile]]:
    """The tiles as whole rectangles of tiles: greedily from the lowest row's first tile, as far along
    the row as the tiles go, then down the rows while the same run is there."""
    remaining = set(tiles)
    out: list[list[Tile]] = []
    while remaining:
        x0, y0 = min(remaining, key=lambda t: (t[1], t[0]))
        x1 = x0
        while (x1 + 1, y0) in remaining:
            x1 += 1
        y1 = y0
        while all((x, y1 + 1) in remaining for x in range(x0, x1 + 1)):
            y1 += 1
        block = [(x, y) for y in range(y0, y1 + 1) for x in range(x0, x1 + 1)]
        remaining.difference_update(block)
        out.append(block)
    return out
