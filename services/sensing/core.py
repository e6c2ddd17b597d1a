"""Sensing stage core: split the remembered scan hits (`services.geometry.PointMemory`) into obstacle clusters.

A pure function; the Zenoh shell feeds the stage scans and publishes clusters.
"""

from __future__ import annotations

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
