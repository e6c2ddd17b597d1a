"""Global choice of the way round every obstacle: shortest route on a tangent graph.

The outside constraint ‖A z + b‖ ≥ 1 is not convex, so a local method started from the straight line
settles on whichever side of an obstacle it happens to start on, and a U-shaped group of obstacles
traps it. The shortest path among convex obstacles is made of segments tangent to them and arcs along
their boundaries; approximating each ellipse by a circumscribed polygon turns that into a visibility
graph whose edges are polygon sides and segments tangent at both ends (the reduced visibility graph).
Dijkstra on it picks the homotopy class globally; the convex refinement (`refine.py`) then straightens
the route against the true ellipses.
"""

from __future__ import annotations

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import dijkstra

from cvxnav.geometry import Ellipse, EllipseStack, FloatArray

_CHUNK = 400_000  # node pairs tested at once: bounds the memory of the vectorised tangency test
_EDGE_CHUNK = 5_000  # candidate edges tested at once against the ellipses near them


def _polygon_vertices(stack: EllipseStack, *, sides: int, level: float) -> FloatArray:
    """Vertices (m, sides, 2) of polygons circumscribing each ellipse scaled to ‖A z + b‖ = level.

    In the unit-disc frame a regular polygon with vertex radius level / cos(π / sides) has inscribed
    radius `level`, so every point of its boundary is at level ≥ `level` from its own ellipse.
    """
    angles = 2.0 * np.pi * np.arange(sides) / sides
    rho = level / np.cos(np.pi / sides)
    unit = rho * np.column_stack([np.cos(angles), np.sin(angles)])
    A_inv = np.linalg.inv(stack.A)
    return np.einsum("mij,mkj->mki", A_inv, unit[None, :, :] - stack.b[:, None, :])


def _cross(a: FloatArray, b: FloatArray) -> FloatArray:
    return a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]


def _candidate_edges(
    points: FloatArray, prev: FloatArray, nxt: FloatArray, owner: FloatArray, on_polygon: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """Pairs (i, j) whose segment is tangent to the polygon at each polygon-vertex end.

    A segment through vertex p is tangent when both polygon neighbours of p lie on one side of its
    line; any other segment through p enters the polygon, so it can never be part of a shortest path.
    """
    n = len(points)
    rows_i, rows_j = [], []
    ii, jj = np.triu_indices(n, k=1)
    different = (owner[ii] != owner[jj]) | (owner[ii] < 0)
    ii, jj = ii[different], jj[different]
    for lo in range(0, len(ii), _CHUNK):
        i, j = ii[lo : lo + _CHUNK], jj[lo : lo + _CHUNK]
        d = points[j] - points[i]
        ok = np.ones(len(i), dtype=bool)
        for end, sign in ((i, 1.0), (j, -1.0)):
            s1 = _cross(sign * d, prev[end] - points[end])
            s2 = _cross(sign * d, nxt[end] - points[end])
            ok &= ~on_polygon[end] | (s1 * s2 >= -1e-12)
        rows_i.append(i[ok])
        rows_j.append(j[ok])
    return np.concatenate(rows_i), np.concatenate(rows_j)


def tangent_route(
    *,
    start: FloatArray,
    goals: FloatArray,
    ellipses: list[Ellipse],
    bounds_min: FloatArray,
    bounds_max: FloatArray,
    sides: int = 16,
    level: float = 1.02,
) -> list[FloatArray] | None:
    """Shortest polylines start → goal₁ → … (one per leg) outside every ellipse; None if there is none.

    The polyline runs along the sides of the circumscribed polygons (at level ≥ `level`) and along
    segments that clear every ellipse exactly (eq. 2 on the continuous segment). Its vertices stay inside
    the bounds, so the whole route does.
    """
    start = np.asarray(start, dtype=float)
    goals = np.atleast_2d(np.asarray(goals, dtype=float))
    stack = EllipseStack.of(ellipses)
    m = len(stack)
    terminals = np.vstack([start, goals])
    if m:
        verts = _polygon_vertices(stack, sides=sides, level=level)
        flat = verts.reshape(-1, 2)
        k = np.arange(sides)
        prev = verts[:, (k - 1) % sides, :].reshape(-1, 2)
        nxt = verts[:, (k + 1) % sides, :].reshape(-1, 2)
        owner = np.repeat(np.arange(m), sides)
        index_in_polygon = np.tile(k, m)
        keep = np.all((flat >= bounds_min) & (flat <= bounds_max), axis=1)
        keep &= stack.min_levels(flat) >= 1.0
        flat, prev, nxt, owner, index_in_polygon = (
            a[keep] for a in (flat, prev, nxt, owner, index_in_polygon)
        )
    else:
        flat = prev = nxt = np.zeros((0, 2))
        owner = index_in_polygon = np.zeros(0, dtype=int)

    t = len(terminals)
    points = np.vstack([terminals, flat])
    prev = np.vstack([terminals, prev])
    nxt = np.vstack([terminals, nxt])
    owner = np.concatenate([-1 - np.arange(t), owner])
    on_polygon = owner >= 0
    index_in_polygon = np.concatenate([np.full(t, -1), index_in_polygon])

    i, j = _candidate_edges(points, prev, nxt, owner, on_polygon)
    # Sides of one polygon join consecutive vertices (sides and 0 wrap round).
    same = np.flatnonzero(
        (owner[:-1] == owner[1:])
        & on_polygon[:-1]
        & ((index_in_polygon[1:] - index_in_polygon[:-1]) == 1)
    )
    i = np.concatenate([i, same])
    j = np.concatenate([j, same + 1])
    for poly in np.unique(owner[on_polygon]):
        idx = np.flatnonzero(owner == poly)
        if index_in_polygon[idx[0]] == 0 and index_in_polygon[idx[-1]] == sides - 1:
            i = np.append(i, idx[-1])
            j = np.append(j, idx[0])

    if m and len(i):
        clear = np.ones(len(i), dtype=bool)
        for lo in range(0, len(i), _EDGE_CHUNK):
            sl = slice(lo, lo + _EDGE_CHUNK)
            clear[sl] = stack.min_segment_levels(points[i[sl]], points[j[sl]]) >= 1.0
        i, j = i[clear], j[clear]

    lengths = np.linalg.norm(points[i] - points[j], axis=1)
    graph = coo_matrix((lengths, (i, j)), shape=(len(points), len(points))).tocsr()
    legs = []
    for leg in range(len(goals)):
        dist, pred = dijkstra(graph, directed=False, indices=leg, return_predecessors=True)
        target = leg + 1
        if not np.isfinite(dist[target]):
            return None
        chain = [target]
        while chain[-1] != leg:
            chain.append(pred[chain[-1]])
        legs.append(points[chain[::-1]])
    return legs
