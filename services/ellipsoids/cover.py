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

import functools
import heapq
import itertools
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike
from scipy.spatial import cKDTree

from services.ellipsoids.mvee import FitError, IntArray, mvee_fast, mvee_fast_support
from services.geometry import Ellipse, FloatArray, as_complex, counter_clockwise, ring_next, signed_area

__all__ = ["Cover", "Piece", "cover_points", "cover_polygon", "excess_over_points", "excess_over_polygon", "point_cover"]

Fit = Callable[[FloatArray], Ellipse]
_ISOTROPIC_RATIO = 1.01  # second moments closer than this: the principal axis is ill-defined
_AREA_EPS = 1e-12
_COARSE = 4  # excess_over_points: the coarse samples are every 4th ring and angle ...
_COARSE_FROM = 256  # ... when there are more samples than this
_BOUND_SLACK_M = 1e-9  # a bound this close to the coarse maximum is queried (rounding)
_DEGENERATE_M = 1e-3  # mvee_fast's eps_m: a thinner set is fattened before it is fitted


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


@dataclass(eq=False)
class Piece:
    """A node of a cover's split tree: a piece of the obstacle, its ellipse and how far that sticks out.

    A point cover's tree is what the next cover of the same cloud may reuse (`point_cover`): there
    `support` holds the piece's points that carry the fit's dual weight (None when not known: a
    degenerate piece, or another fit) and `worst` a region sample at which `excess_m` is attained.
    """

    points: FloatArray  # polygon vertices, or sensed points in the cloud's order
    ellipse: Ellipse
    excess_m: float
    support: FloatArray | None = None
    worst: FloatArray | None = None
    children: list[Piece] = field(default_factory=list)

    @functools.cached_property
    def box(self) -> FloatArray:
        """Bounding box: rows low, high."""
        return np.array([self.points.min(axis=0), self.points.max(axis=0)])


@dataclass(frozen=True)
class Cover:
    root: Piece  # the split tree, to pass to the next cover of the same cloud as `previous`
    pieces: list[Piece]  # its leaves: the cover


def _cover(
    first: FloatArray,
    *,
    make: Callable[[FloatArray, Piece | None], Piece],
    split: Callable[[FloatArray], list[FloatArray]],
    tolerance_m: float,
    max_pieces: int,
) -> Cover:
    """Split the worst piece while its excess exceeds the tolerance and the piece budget allows.

    `make(points, parent)` fits a piece and measures its excess.
    """
    if tolerance_m <= 0.0 or max_pieces < 1:
        raise ValueError("tolerance_m must be positive and max_pieces at least 1")
    order = itertools.count()
    done: list[Piece] = []
    root = make(first, None)
    heap = [(-root.excess_m, next(order), root)]
    while heap:
        worst, _, piece = heap[0]
        if -worst <= tolerance_m or len(heap) + len(done) >= max_pieces:
            break
        heapq.heappop(heap)
        children = split(piece.points)
        if len(children) < 2:  # cannot be split further (e.g. duplicated points): keep it as is
            done.append(piece)
            continue
        for child in children:
            piece.children.append(make(child, piece))
            heapq.heappush(heap, (-piece.children[-1].excess_m, next(order), piece.children[-1]))
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

    cover = _cover(polygon, make=make, split=_split_polygon, tolerance_m=tolerance_m, max_pieces=max_pieces)
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
    fit_support = mvee_fast_support if fit is mvee_fast else lambda piece: (fit(piece), None)
    cover = _point_cover(points, fit=fit_support, previous=(), tolerance_m=tolerance_m, max_pieces=max_pieces)
    return [piece.ellipse for piece in cover.pieces]


def point_cover(
    points: ArrayLike, *, previous: Sequence[Piece] = (), tolerance_m: float = 0.1, max_pieces: int = 64
) -> Cover:
    """`cover_points`' cover with its split tree, reusing the fits of `previous` trees where they are exact.

    A sensed cloud grows a few points per scan. The MVEE of a set is
    fixed by its support (the points carrying dual weight): if a new piece holds every support point
    of an earlier piece and lies inside its ellipse E, its MVEE is E (E contains it; any ellipse that
    contains it contains the support, whose MVEE is E; the MVEE is unique). A piece is compared with
    the earlier pieces at its place in the tree whose bounding boxes meet its own: the roots of
    `previous` for the root, the children of those its parent was compared with for a child. The
    excess of a reused ellipse is kept when no earlier point is lost and every added point is at
    least the excess away from the sample where it was attained (adding points lowers the distance
    nowhere else above it), and measured afresh otherwise. Splits are computed from the points as
    always, so the cover is the one `cover_points` gives, up to the fit's own tolerance. (The split
    lines run through the pieces' means, so points added at one end move them all: a point that
    crosses one is a support point of the piece it leaves, and both pieces are refitted.)
    """
    return _point_cover(points, fit=mvee_fast_support, previous=previous, tolerance_m=tolerance_m,
                        max_pieces=max_pieces)


def _point_cover(
    points: ArrayLike,
    *,
    fit: Callable[[FloatArray], tuple[Ellipse, IntArray | None]],
    previous: Sequence[Piece],
    tolerance_m: float,
    max_pieces: int,
) -> Cover:
    z = np.atleast_2d(np.asarray(points, dtype=float))
    if z.ndim != 2 or z.shape[1] != 2 or len(z) == 0:
        raise FitError(f"points must be a non-empty (n, 2) array, got shape {z.shape}")
    compared: dict[int, list[Piece]] = {}  # id(piece) -> the earlier pieces it was compared with

    def make(piece: FloatArray, parent: Piece | None) -> Piece:
        earlier = previous if parent is None else [child for e in compared[id(parent)] for child in e.children]
        box = np.array([piece.min(axis=0), piece.max(axis=0)])
        earlier = [e for e in earlier if np.all(e.box[0] <= box[1]) and np.all(box[0] <= e.box[1])]
        made = next((p for e in earlier if (p := _reused(e, piece, tolerance_m=tolerance_m)) is not None), None)
        if made is None:
            ellipse, support = fit(piece)
            excess, worst = _excess_over_points(ellipse, cKDTree(piece), tolerance_m=tolerance_m)
            made = Piece(points=piece, ellipse=ellipse, excess_m=excess,
                         support=None if support is None else piece[support], worst=worst)
        made.box = box
        compared[id(made)] = earlier
        return made

    return _cover(z, make=make, split=_split_points, tolerance_m=tolerance_m, max_pieces=max_pieces)


def _reused(earlier: Piece, points: FloatArray, *, tolerance_m: float) -> Piece | None:
    """A piece of `points` with `earlier`'s ellipse, if that is their MVEE (see `point_cover`); else None.

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
