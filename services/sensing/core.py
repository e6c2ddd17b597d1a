"""Sensing stage core: split the remembered scan hits (`services.geometry.PointMemory`) into obstacle clusters.

A pure function, and the same clusters kept as points are added (`LinkedClusters`); the Zenoh shell
feeds the stage scans and publishes clusters.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

FloatArray = NDArray[np.float64]


def cluster_points(points: ArrayLike, *, link_m: float) -> list[FloatArray]:
    """Single-linkage clusters: points joined by a chain of neighbours at most `link_m` apart share one.

    The neighbour pairs come from a k-d tree (`query_pairs`, distance ≤ link_m) and the clusters are
    the connected components of that graph (scipy.sparse.csgraph), so the cost is near-linear.

    Why `link_m` may be as large as the robot's passage width 2·(width/2 + safety_distance): the
    robot's centre has to stay width/2 + safety_distance from every obstacle point, so two points
    closer than twice that leave no room between them. Joining them into one obstacle loses no path
    the robot could take, and is exactly the paper's grouping of obstacles whose gap is too narrow
    (CONTRACTS §2). A smaller link only yields more, smaller clusters for the later grouping step.

    Returns the clusters as (k, 2) arrays, ordered by their first point in the input; [] for no points.
    """
    z = np.asarray(points, dtype=float).reshape(-1, 2)
    if not (np.isfinite(link_m) and link_m >= 0.0):
        raise ValueError(f"link_m must be finite and non-negative, got {link_m!r}")
    n = len(z)
    if n == 0:
        return []
    pairs = cKDTree(z).query_pairs(r=link_m, output_type="ndarray")
    graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
    _, labels = connected_components(graph, directed=False)
    # connected_components numbers components in order of their lowest point index.
    order = np.argsort(labels, kind="stable")
    bounds = np.flatnonzero(np.diff(labels[order])) + 1
    return [z[idx] for idx in np.split(order, bounds)]


class LinkedClusters:
    """`cluster_points`' single-linkage clusters of a point set that only grows, kept as points are added.

    A hash grid of `link_m` squares finds a new point's neighbours (every point within `link_m` lies
    in the 3 × 3 squares round it) and a union-find joins their clusters, so adding k points costs
    about k neighbour lookups, not a clustering of everything remembered. `changed` collects the
    clusters (by their root point) that gained points since the caller last cleared it.
    """

    def __init__(self, *, link_m: float) -> None:
        if not (np.isfinite(link_m) and link_m >= 0.0):
            raise ValueError(f"link_m must be finite and non-negative, got {link_m!r}")
        self._r2 = float(link_m) ** 2
        self._cell_m = float(link_m) if link_m > 0.0 else 1.0
        self._grid: dict[tuple[int, int], list[int]] = {}
        self._xy: list[tuple[float, float]] = []
        self._parent: list[int] = []
        self._members: dict[int, list[int]] = {}  # root -> the indices of its cluster's points
        self.changed: set[int] = set()

    def add(self, points: ArrayLike) -> None:
        """Add points (k, 2), joining each to every cluster with a point within `link_m` of it."""
        for x, y in np.asarray(points, dtype=float).reshape(-1, 2).tolist():
            i = len(self._xy)
            self._xy.append((x, y))
            self._parent.append(i)
            self._members[i] = [i]
            cx, cy = math.floor(x / self._cell_m), math.floor(y / self._cell_m)
            for dx in (-1, 0, 1):
                for dy in (-1, 0, 1):
                    for j in self._grid.get((cx + dx, cy + dy), ()):
                        xj, yj = self._xy[j]
                        if (x - xj) ** 2 + (y - yj) ** 2 <= self._r2:
                            self._union(i, j)
            self._grid.setdefault((cx, cy), []).append(i)
            self.changed.add(self._find(i))

    def points_of(self, root: int) -> FloatArray:
        """The points of the cluster rooted at `root`, in the order they were added."""
        return np.array([self._xy[i] for i in sorted(self._members[root])], dtype=float).reshape(-1, 2)

    def roots(self) -> list[int]:
        return list(self._members)

    def _find(self, i: int) -> int:
        parent = self._parent
        while parent[i] != i:
            parent[i] = parent[parent[i]]  # path halving
            i = parent[i]
        return i

    def _union(self, a: int, b: int) -> None:
        ra, rb = self._find(a), self._find(b)
        if ra == rb:
            return
        if len(self._members[ra]) < len(self._members[rb]):
            ra, rb = rb, ra
        self._parent[rb] = ra
        self._members[ra].extend(self._members.pop(rb))
        self.changed.discard(rb)
        self.changed.add(ra)
