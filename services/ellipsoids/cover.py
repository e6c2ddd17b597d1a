"""Tight covers of obstacles by a few ellipses, each a Löwner–John ellipse (eq. 1) of one piece.

One MVEE per obstacle over-covers badly — the MVEE of a w × h box has semi-axes √2·(w/2, h/2), so it
sticks out by (√2 − 1)/2 ≈ 0.21 of each side — and closes passages the robot fits through. A cover
here is grown by recursive bisection: fit the MVEE of a piece, measure its *excess* (the largest
distance from the ellipse boundary to the piece), and while the worst piece's excess exceeds
`tolerance_m` split that piece in two across its principal axis (a priority queue keyed on excess),
up to `max_pieces`. Every piece's ellipse contains the piece, so the union of the ellipses contains
the obstacle whatever the stopping point.
"""

from __future__ import annotations

import heapq
import itertools
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike
from scipy.spatial import cKDTree

from services.ellipsoids.mvee import FitError, IntArray, mvee_fast, mvee_fast_support
from services.geometry import (Ellipse, FloatArray, as_complex, counter_clockwise, grown_semi_axes, growth_family,
                               least_area_growth, ring_next, signed_area)

__all__ = ["Cell", "Cover", "Piece", "cover_points", "cover_polygon", "excess_over_points", "excess_over_polygon",
           "grown_cover", "grown_near", "tiled_cover", "tiles"]

Fit = Callable[[FloatArray], Ellipse]
_ISOTROPIC_RATIO = 1.01  # second moments closer than this: the principal axis is ill-defined
_AREA_EPS = 1e-12
_COARSE = 4  # excess_over_points: the coarse samples are every 4th ring and angle ...
_COARSE_FROM = 256  # ... when there are more samples than this
_BOUND_SLACK_M = 1e-9  # a bound this close to the coarse maximum is queried (rounding)
_DEGENERATE_M = 1e-3  # mvee_fast's eps_m: a thinner set is fattened before it is fitted
_PREFER_LEAST_M = 1e-3  # grown_near: another growth is taken over the least-area one if it strays this much less


# --------------------------------------------------------------------------- excess


def _boundary_samples(ellipse: Ellipse, *, tolerance_m: float) -> FloatArray:
    """Boundary points spaced at most a quarter tolerance apart (32 … 2048 of them)."""
    a1, a2 = ellipse.semi_axes
    h = ((a1 - a2) / (a1 + a2)) ** 2
    perimeter = np.pi * (a1 + a2) * (1.0 + 3.0 * h / (10.0 + np.sqrt(4.0 - 3.0 * h)))  # Ramanujan
    n = int(np.clip(np.ceil(perimeter / (0.25 * tolerance_m)), 32, 2048))
    return ellipse.boundary(n)


class _ConvexPolygon:
    """A convex CCW polygon (1-2 vertices allowed) with its edges formed once: a cover measures the
    excess of every piece's ellipse against the same polygon."""

    def __init__(self, vertices: FloatArray) -> None:
        self.vertices = vertices
        self.edge = ring_next(vertices) - vertices
        length2 = np.einsum("ij,ij->i", self.edge, self.edge)
        self.divisor = np.where(length2 > 0.0, length2, 1.0)
        self.solid = len(vertices) >= 3 and signed_area(vertices) > _AREA_EPS

    def distance(self, points: FloatArray) -> FloatArray:
        """Exact Euclidean distance from each point to the polygon (0 inside)."""
        edge = self.edge
        rel = points[:, None, :] - self.vertices[None, :, :]
        t = np.clip(np.einsum("nij,ij->ni", rel, edge) / self.divisor, 0.0, 1.0)
        nearest = rel - t[:, :, None] * edge[None, :, :]
        distance = np.min(np.linalg.norm(nearest, axis=2), axis=1)
        if self.solid:
            cross = edge[None, :, 0] * rel[:, :, 1] - edge[None, :, 1] * rel[:, :, 0]
            distance = np.where(np.all(cross >= 0.0, axis=1), 0.0, distance)
        return distance

    def excess(self, ellipse: Ellipse, *, tolerance_m: float) -> float:
        """Largest distance from the ellipse boundary to the polygon (boundary sampled finely)."""
        return float(np.max(self.distance(_boundary_samples(ellipse, tolerance_m=tolerance_m))))


def excess_over_polygon(ellipse: Ellipse, vertices: ArrayLike, *, tolerance_m: float = 0.1) -> float:
    """Largest distance from the ellipse boundary to the convex polygon (boundary sampled finely)."""
    polygon = _ConvexPolygon(counter_clockwise(np.atleast_2d(np.asarray(vertices, dtype=float))))
    return polygon.excess(ellipse, tolerance_m=tolerance_m)


def excess_over_points(ellipse: Ellipse, points: ArrayLike | cKDTree, *, tolerance_m: float = 0.1) -> float:
    """Largest distance from the ellipse REGION to the nearest of `points` (a cKDTree or an array).

    Distance to a point cloud is not convex, so unlike the polygon case the boundary alone does not
    bound it: a ring of samples (a round room seen from inside) has an MVEE whose boundary hugs the
    samples while its interior is free space. The region is therefore sampled on concentric rings
    (levels k/m, m ≤ 16, plus the centre) as well as the boundary.

    The maximum over the samples is found without querying most of them: the distance to the points
    is 1-Lipschitz, so a sample s no further than δ from a coarse sample c (every `_COARSE`-th ring
    and angle) has d(s) ≤ d(c) + δ, and only samples whose bound reaches the coarse maximum are
    queried. The result is the same maximum over the same samples.
    """
    tree = points if isinstance(points, cKDTree) else cKDTree(np.atleast_2d(np.asarray(points, dtype=float)))
    return _excess_over_points(ellipse, tree, tolerance_m=tolerance_m)[0]


def _excess_over_points(ellipse: Ellipse, tree: cKDTree, *, tolerance_m: float) -> tuple[float, FloatArray]:
    """`excess_over_points` and a region sample at which it is attained."""
    boundary = _boundary_samples(ellipse, tolerance_m=tolerance_m)
    centre = ellipse.center
    rings = int(np.clip(np.ceil(ellipse.semi_axes[0] / (0.5 * tolerance_m)), 1, 16))
    levels = np.arange(rings + 1)[:, None, None] / rings
    samples = centre + levels * (boundary - centre)[None, :, :]  # (rings + 1, n, 2)
    if samples.shape[0] * samples.shape[1] <= _COARSE_FROM:
        flat = samples.reshape(-1, 2)
        distance = tree.query(flat)[0]
        worst = int(np.argmax(distance))
        return float(distance[worst]), flat[worst]
    k = np.minimum(np.rint(np.arange(rings + 1) / _COARSE) * _COARSE, rings).astype(int)
    j = (np.rint(np.arange(samples.shape[1]) / _COARSE) * _COARSE).astype(int) % samples.shape[1]
    coarse_k, coarse_j = np.unique(k), np.unique(j)
    coarse = np.full((rings + 1, samples.shape[1]), np.nan)
    coarse[np.ix_(coarse_k, coarse_j)] = tree.query(samples[np.ix_(coarse_k, coarse_j)].reshape(-1, 2))[0].reshape(
        len(coarse_k), len(coarse_j))
    lower = float(np.nanmax(coarse))
    nearest = samples[k[:, None], j[None, :]]
    bound = coarse[k[:, None], j[None, :]] + np.linalg.norm(samples - nearest, axis=2)
    candidates = samples[bound + _BOUND_SLACK_M >= lower]  # the coarse maximum's sample among them
    distance = tree.query(candidates)[0]
    worst = int(np.argmax(distance))
    return float(distance[worst]), candidates[worst]


def grown_near(ellipse: Ellipse, margin_m: float, points: cKDTree, *, growths: int = 4, spacing_m: float = 0.05
               ) -> tuple[Ellipse, float]:
    """`ellipse`, a fit of some of `points`, grown by `margin_m`: of the Kurzhanski–Vályi growths, each of
    which contains the fit ⊕ disc(margin) (`Ellipse.grown`), the one whose boundary strays least beyond
    the margin from the points; and that excess (the largest distance from its boundary, sampled about
    `spacing_m` apart, to the nearest point, less the margin).

    The least-area growth of a long thin fit (a wall's) is about √2·r wide, some 0.2 m more than the
    wall's own grown strip for the depot car; a small p keeps the width near r at the price of long
    tips, which do no harm where they lie along the wall's own points (as the map's cover chooses its
    growths, `services.ellipsoids.grid_cover`). The candidates: the least-area growth, kept unless another
    strays `_PREFER_LEAST_M` less (so that points moved by a rounding, a map in UTM metres, choose alike),
    and the map cover's `growth_family` of the fit.
    """
    w, R = np.linalg.eigh(ellipse.A)
    fit = 1.0 / w  # the fit's semi-axes, largest first (its axes: R's columns)
    p = np.concatenate([[least_area_growth(fit**2, margin_m)], growth_family(fit[None], margin_m, growths)[0]])
    semi = grown_semi_axes(fit, p, margin_m)  # (candidates, 2)

    def excess(k: np.ndarray) -> np.ndarray:
        """Candidates k's boundaries, each at as many angles as its perimeter (≥ π (a₁ + a₂)) needs."""
        counts = np.clip(np.ceil(np.pi * semi[k].sum(axis=1) / spacing_m), 32, 2048).astype(np.intp)
        offsets = np.cumsum(counts) - counts
        owner = np.repeat(k, counts)
        angle = 2.0 * np.pi * (np.arange(len(owner)) - np.repeat(offsets, counts)) / np.repeat(counts, counts)
        local = semi[owner] * np.column_stack([np.cos(angle), np.sin(angle)])
        return np.maximum.reduceat(points.query(ellipse.center + local @ R.T)[0], offsets) - margin_m

    least = float(excess(np.array([0]))[0])
    # A small p's growth of a thin fit has tips many times its length: where even the ends of its axes
    # stray further than the least-area growth does anywhere, it cannot be taken, and is not sampled.
    ends = np.array([[1.0, 0.0], [-1.0, 0.0], [0.0, 1.0], [0.0, -1.0]])
    reach = points.query(ellipse.center + (semi[1:, None, :] * ends[None]) @ R.T)[0].max(axis=1) - margin_m
    others = 1 + np.flatnonzero(reach < least - _PREFER_LEAST_M)
    if not len(others):
        return ellipse.grown(margin_m, p=float(p[0])), least
    strays = excess(others)
    best = int(np.argmin(strays))
    if least - strays[best] < _PREFER_LEAST_M:
        return ellipse.grown(margin_m, p=float(p[0])), least
    return ellipse.grown(margin_m, p=float(p[others[best]])), float(strays[best])


def grown_cover(part: FloatArray, fit: Ellipse, margin_m: float, points: cKDTree, *, tolerance_m: float = 0.1,
                depth: int = 4) -> list[tuple[FloatArray, Ellipse, Ellipse]]:
    """A cover's piece, its points `part` and their `fit`, as (points, fit, growth): the fit grown by
    `grown_near` while that strays no more than `tolerance_m` beyond the margin from `points`, else its
    points split in two (`_split_points`), each half fitted (`mvee_fast`) and grown so, `depth` times at most.

    A piece is judged by its growth, not by its fit: a fit that ends at a door's jamb within tolerance of
    its points still has a growth whose tip runs into the doorway (for a 0.5 m piece of wall with the
    depot car's margin, 0.06 m beyond the jamb's own grown disc), and a door with that to spare on both
    sides closes. Shorter pieces there have shorter tips. Every growth contains its fit ⊕ disc(margin),
    and the halves' fits contain their points, so the growths cover what the piece's did.
    """
    grown, excess = grown_near(fit, margin_m, points)
    halves = _split_points(part) if excess > tolerance_m and depth > 0 else []
    if not halves:
        return [(part, fit, grown)]
    return [made for half in halves
            for made in grown_cover(half, mvee_fast(half), margin_m, points, tolerance_m=tolerance_m, depth=depth - 1)]


# --------------------------------------------------------------------------- splitting


def _polygon_axis(vertices: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Centroid and long direction of a convex polygon from its area second moments.

    With cross_i = x_i y_{i+1} − x_{i+1} y_i: A = Σ cross/2, c = Σ (p_i + p_{i+1}) cross / (6A),
    ∫x² = Σ (x_i² + x_i x_{i+1} + x_{i+1}²) cross / 12, ∫xy = Σ (x_i y_{i+1} + 2 x_i y_i + 2 x_{i+1} y_{i+1}
    + x_{i+1} y_i) cross / 24; the long direction is the top eigenvector of the central moments. When
    the moments are nearly isotropic (a square) the edge direction of largest extent is used instead,
    so that squares split into rectangles rather than along an arbitrary diagonal. Degenerate
    polygons (a point or a segment) use their vertices' spread.
    """
    shift = vertices.mean(axis=0)
    v = vertices - shift
    if len(v) < 3 or abs(signed_area(v)) <= _AREA_EPS:
        _, R = np.linalg.eigh(v.T @ v)
        return shift + 0.5 * (v.min(axis=0) + v.max(axis=0)), R[:, -1]
    x, y = v[:, 0], v[:, 1]
    xn, yn = ring_next(x), ring_next(y)
    cross = x * yn - xn * y
    area = 0.5 * np.sum(cross)
    centroid = np.array([np.sum((x + xn) * cross), np.sum((y + yn) * cross)]) / (6.0 * area)
    ixx = np.sum((x * x + x * xn + xn * xn) * cross) / 12.0
    iyy = np.sum((y * y + y * yn + yn * yn) * cross) / 12.0
    ixy = np.sum((x * yn + 2.0 * x * y + 2.0 * xn * yn + xn * y) * cross) / 24.0
    moments = np.array([[ixx, ixy], [ixy, iyy]]) - area * np.outer(centroid, centroid)
    w, R = np.linalg.eigh(moments)
    axis = R[:, -1]
    if w[-1] <= _ISOTROPIC_RATIO * w[0]:
        edges = ring_next(v) - v
        edges = edges[np.linalg.norm(edges, axis=1) > 0.0]
        directions = edges / np.linalg.norm(edges, axis=1)[:, None]
        extents = np.ptp(v @ directions.T, axis=0)
        axis = directions[int(np.argmax(extents))]
    return shift + centroid, axis


def _clip_half_plane(vertices: FloatArray, *, normal: FloatArray, offset: float) -> FloatArray:
    """Sutherland–Hodgman: the part of a convex polygon with normal · x ≤ offset (exact, convex)."""
    s = vertices @ normal - offset
    out = []
    n = len(vertices)
    for i in range(n):
        j = (i + 1) % n
        if s[i] <= 0.0:
            out.append(vertices[i])
        if (s[i] < 0.0 < s[j]) or (s[j] < 0.0 < s[i]):
            t = s[i] / (s[i] - s[j])
            out.append(vertices[i] + t * (vertices[j] - vertices[i]))
    if not out:
        return np.zeros((0, 2))
    clipped = np.array(out)
    keep = np.ones(len(clipped), dtype=bool)
    keep[1:] = np.linalg.norm(np.diff(clipped, axis=0), axis=1) > 1e-12
    clipped = clipped[keep]
    if len(clipped) > 1 and np.linalg.norm(clipped[0] - clipped[-1]) <= 1e-12:
        clipped = clipped[:-1]
    return clipped


def _split_polygon(vertices: FloatArray) -> list[FloatArray]:
    centroid, axis = _polygon_axis(vertices)
    offset = float(centroid @ axis)
    halves = [
        _clip_half_plane(vertices, normal=axis, offset=offset),
        _clip_half_plane(vertices, normal=-axis, offset=-offset),
    ]
    return [h for h in halves if len(h) > 0]


def _split_points(points: FloatArray) -> list[FloatArray]:
    centred = points - points.mean(axis=0)
    _, R = np.linalg.eigh(centred.T @ centred)
    side = centred @ R[:, -1] <= 0.0
    return [points[side], points[~side]] if 0 < np.count_nonzero(side) < len(points) else []


# --------------------------------------------------------------------------- covers


Cell = tuple[float, float, float, float]  # x0, y0, x1, y1: a piece of a tiled cover holds the points in [x0, x1) × [y0, y1)


@dataclass(eq=False)
class Piece:
    """A node of a cover's split tree: a piece of the obstacle, its ellipse and how far that sticks out.

    A tiled cover's tree is what the next cover of the same tile may reuse (`tiled_cover`): there
    `support` holds the piece's points that carry the fit's dual weight (None when not known: a
    degenerate piece, or another fit) and `worst` a region sample at which `excess_m` is attained.
    """

    points: FloatArray  # polygon vertices, or sensed points in the cloud's order
    ellipse: Ellipse
    excess_m: float
    support: FloatArray | None = None
    worst: FloatArray | None = None
    children: list[Piece] = field(default_factory=list)
    cell: Cell | None = None  # a tiled cover's piece: the rectangle its points are the cloud's points in


@dataclass(frozen=True)
class Cover:
    root: Piece  # the split tree, to pass to the next cover of the same cloud as `previous`
    pieces: list[Piece]  # its leaves: the cover


def _cover(
    root: Piece,
    *,
    split: Callable[[Piece], list[Piece]],
    tolerance_m: float,
    max_pieces: int,
) -> Cover:
    """Split the worst piece while its excess exceeds the tolerance and the piece budget allows.

    `split(piece)` returns the piece's children, fitted, with their excess measured ([] when it cannot
    be split further).
    """
    if tolerance_m <= 0.0 or max_pieces < 1:
        raise ValueError("tolerance_m must be positive and max_pieces at least 1")
    order = itertools.count()
    done: list[Piece] = []
    heap = [(-root.excess_m, next(order), root)]
    while heap:
        worst, _, piece = heap[0]
        if -worst <= tolerance_m or len(heap) + len(done) >= max_pieces:
            break
        heapq.heappop(heap)
        children = split(piece)
        if len(children) < 2:  # cannot be split further (e.g. duplicated points): keep it as is
            done.append(piece)
            continue
        piece.children = children
        for child in children:
            heapq.heappush(heap, (-child.excess_m, next(order), child))
    return Cover(root=root, pieces=done + [item[2] for item in sorted(heap, key=lambda item: item[1])])


def cover_polygon(
    vertices: ArrayLike, *, tolerance_m: float = 0.1, max_pieces: int = 64, fit: Fit = mvee_fast
) -> list[Ellipse]:
    """Ellipses whose union contains a SOLID convex polygon, each sticking out by ≤ tolerance_m if possible.

    Excess is measured to the WHOLE polygon: an ellipse that bulges into the solid next to its piece
    closes nothing, only what sticks out of the obstacle matters. (For a convex polygon the distance
    is a convex function, so its maximum over the ellipse is attained on the boundary.) Pieces are
    split by the line through their centroid perpendicular to their long axis (exact half-plane
    clipping, so every piece stays convex and the pieces tile the polygon). Degenerate
    polygons (1-2 vertices) are allowed and give thin ellipses. `fit` may be `mvee` to use the solver.
    """
    polygon = np.atleast_2d(np.asarray(vertices, dtype=float))
    if polygon.ndim != 2 or polygon.shape[1] != 2 or len(polygon) == 0:
        raise FitError(f"vertices must be a non-empty (n, 2) array, got shape {polygon.shape}")
    polygon = counter_clockwise(polygon)
    solid = _ConvexPolygon(polygon)

    def make(piece: FloatArray, parent: Piece | None) -> Piece:
        e = fit(piece)
        return Piece(points=piece, ellipse=e, excess_m=solid.excess(e, tolerance_m=tolerance_m))

    cover = _cover(make(polygon, None), split=lambda piece: [make(half, piece) for half in _split_polygon(piece.points)],
                   tolerance_m=tolerance_m, max_pieces=max_pieces)
    return [piece.ellipse for piece in cover.pieces]


def cover_points(
    points: ArrayLike, *, tolerance_m: float = 0.1, max_pieces: int = 64, fit: Fit = mvee_fast
) -> list[Ellipse]:
    """Ellipses covering sensed SURFACE points, each within tolerance_m of its own points if possible.

    The solid behind the samples is unknown, so excess is the largest distance from any point of the
    ellipse (region, not just boundary) to the nearest sample of the piece, never to their hull (a
    room's perimeter wall would otherwise swallow the room). Pieces are split by the
    line through their mean perpendicular to their principal axis; every input point ends up inside
    the ellipse of its piece. `fit` may be `mvee` to use the solver.
    """
    z = np.atleast_2d(np.asarray(points, dtype=float))
    if z.ndim != 2 or z.shape[1] != 2 or len(z) == 0:
        raise FitError(f"points must be a non-empty (n, 2) array, got shape {z.shape}")
    fit_support = mvee_fast_support if fit is mvee_fast else lambda piece: (fit(piece), None)
    cover = _cover(_fitted(z, fit=fit_support, tolerance_m=tolerance_m),
                   split=lambda piece: [_fitted(half, fit=fit_support, tolerance_m=tolerance_m)
                                        for half in _split_points(piece.points)],
                   tolerance_m=tolerance_m, max_pieces=max_pieces)
    return [piece.ellipse for piece in cover.pieces]


def _fitted(points: FloatArray, *, fit: Callable[[FloatArray], tuple[Ellipse, IntArray | None]],
            tolerance_m: float) -> Piece:
    """A piece of `points` with a fresh fit and its excess measured."""
    ellipse, support = fit(points)
    excess, worst = _excess_over_points(ellipse, cKDTree(points), tolerance_m=tolerance_m)
    return Piece(points=points, ellipse=ellipse, excess_m=excess, support=None if support is None else points[support],
                 worst=worst)


def tiles(points: ArrayLike, *, tile_m: float) -> list[tuple[Cell, FloatArray]]:
    """The cloud cut by the fixed grid of `tile_m` squares: each tile's cell and its points, in the cloud's
    order; tiles in row-major order of their cells."""
    z = np.atleast_2d(np.asarray(points, dtype=float))
    index = np.floor(z / tile_m).astype(np.int64)
    index -= index.min(axis=0)
    flat = index[:, 0] * (int(index[:, 1].max()) + 1) + index[:, 1]  # row-major, one integer per tile
    order = np.argsort(flat, kind="stable")
    starts = np.concatenate([[0], np.flatnonzero(np.diff(flat[order])) + 1])
    corners = np.floor(z[order[starts]] / tile_m) * tile_m
    return [((x, y, x + tile_m, y + tile_m), z[rows])
            for (x, y), rows in zip(corners.tolist(), np.split(order, starts[1:]))]


def tiled_cover(
    points: ArrayLike, *, cell: Cell, previous: Mapping[Cell, Sequence[Piece]] | None = None, tolerance_m: float = 0.1,
    max_pieces: int = 64,
) -> Cover:
    """`cover_points` of one tile's points with pieces that stay put: a piece is split across the middle
    of its cell (the longer side), never through its points' mean, so a cell's points are those of the
    cloud inside a fixed rectangle, and a point added to the cloud changes only the cells that contain
    it — the chain from the tile down to one leaf. Every other cell has the same points as before and
    takes its fit from `previous` (by cell) as it is; a changed cell's earlier fit is kept where it is
    still the MVEE (`_reused`), and fitted afresh otherwise.

    A half that holds no point is skipped (the cell shrinks to the other half) down to a side of a
    quarter tolerance, where a piece is kept as it is: points that close are within tolerance of its fit.
    """
    z = np.atleast_2d(np.asarray(points, dtype=float))
    if z.ndim != 2 or z.shape[1] != 2 or len(z) == 0:
        raise FitError(f"points must be a non-empty (n, 2) array, got shape {z.shape}")
    min_side_m = 0.25 * tolerance_m
    earlier = previous or {}

    def make(piece: FloatArray, at: Cell) -> Piece:
        made = next((p for e in earlier.get(at, ()) if (p := _reused(e, piece, tolerance_m=tolerance_m)) is not None),
                    None)
        if made is None:
            made = _fitted(piece, fit=mvee_fast_support, tolerance_m=tolerance_m)
        made.cell = at
        return made

    def split(piece: Piece) -> list[Piece]:
        x0, y0, x1, y1 = piece.cell
        while max(x1 - x0, y1 - y0) > min_side_m:
            axis, low, high = (0, x0, x1) if x1 - x0 >= y1 - y0 else (1, y0, y1)
            middle = 0.5 * (low + high)
            below = piece.points[:, axis] < middle
            halves = ((x0, y0, middle, y1), (middle, y0, x1, y1)) if axis == 0 else ((x0, y0, x1, middle), (x0, middle, x1, y1))
            if np.all(below) or not np.any(below):
                x0, y0, x1, y1 = halves[0] if np.all(below) else halves[1]
                continue
            return [make(piece.points[below], halves[0]), make(piece.points[~below], halves[1])]
        return []

    return _cover(make(z, cell), split=split, tolerance_m=tolerance_m, max_pieces=max_pieces)


def _reused(earlier: Piece, points: FloatArray, *, tolerance_m: float) -> Piece | None:
    """A piece of `points` with `earlier`'s ellipse, if that is their MVEE; else None.

    The MVEE of a set is fixed by its support (the points carrying dual weight): if a new piece holds
    every support point of an earlier piece and lies inside its ellipse E, its MVEE is E (E contains
    it; any ellipse that contains it contains the support, whose MVEE is E; the MVEE is unique). The
    excess of a reused ellipse is kept when no earlier point is lost and every added point is at least
    the excess away from the sample where it was attained (adding points lowers the distance nowhere
    else above it), and measured afresh otherwise.

    The support must also be no thinner than the fit's degenerate width: the MVEE E of a support S
    has E/2 ⊆ hull(S) about its centre (John), so a set holding S is at least E's minor semi-axis
    wide in every direction, and a fresh fit would not fatten it.
    """
    if len(points) == len(earlier.points) and np.array_equal(points, earlier.points):
        return Piece(points=points, ellipse=earlier.ellipse, excess_m=earlier.excess_m, support=earlier.support,
                     worst=earlier.worst)
    if earlier.support is None or earlier.ellipse.semi_axes[1] < _DEGENERATE_M:
        return None
    here = as_complex(points)
    if not np.all(np.isin(as_complex(earlier.support), here)) or np.max(earlier.ellipse.level(points)) > 1.0:
        return None
    before = as_complex(earlier.points)
    added = points[~np.isin(here, before)]
    if np.all(np.isin(before, here)) and (
            len(added) == 0 or np.min(np.linalg.norm(added - earlier.worst, axis=1)) >= earlier.excess_m):
        excess, worst = earlier.excess_m, earlier.worst
    else:
        excess, worst = _excess_over_points(earlier.ellipse, cKDTree(points), tolerance_m=tolerance_m)
    return Piece(points=points, ellipse=earlier.ellipse, excess_m=excess, support=earlier.support, worst=worst)
