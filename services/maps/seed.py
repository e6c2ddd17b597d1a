"""Paths the car can drive to its goals, searched on the map itself, for the planner to refine where
its own routes fail.

The planner's route search is blind to the heading, and its refinement is local: where the shortest
route asks for a turn the car cannot make (a goal a little behind it, a corner too tight for its
turning radius, a car set down across a corridor), it tries the turning lead-ins it knows and, failing,
says `no_path` — while the car could have driven there, round a wider loop or turning earlier. This
search looks for such a way over the car's own turns (`services.planner.lattice.search`: arcs a little
wider than its turning radius and straight runs), on the grid's exact clearance
(`OccupancyGrid.clearance`), so that it sees every wall of the map, not only those whose cover was
fitted. It is a heuristic, not a proof: a path where it finds one, through the goals leg by leg, each
leg leaving a goal the way the one before arrived (greedy: an arrival that leaves no room to turn onward
ends the chain there, and the planner's routes go on from the last goal reached).

A chord is clear when points at most `_SAMPLE_M` apart along it are at least the margin plus half that
from every blocked cell: every point of the chord is within half of it of one of them, and the
clearance is 1-Lipschitz. A point's clearance is first bounded from the distance transform of the map's
cells (exact between cell centres, OpenCV's): a point of a cell whose centre is d from the nearest
blocked cell's centre is at least d − √2·res and at most d + res/√2 from the nearest blocked square; only
where those bounds straddle the margin is the exact distance (`OccupancyGrid.clearance`) read.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator

import cv2
import numpy as np

from schemas.occupancy import OccupancyGrid
from services.geometry import FloatArray
from services.planner.lattice import MAX_NODES, ToGo, through

_SAMPLE_M = 0.02  # points along a chord at most this far apart are tested


def drivable_paths(grid: OccupancyGrid, *, start: FloatArray, heading_rad: float, goals: FloatArray, radius_m: float,
                   margin_m: float, spacing_m: float, bounds_min: FloatArray, bounds_max: FloatArray,
                   max_nodes: int = MAX_NODES,
                   to_go: Callable[[FloatArray], ToGo] | None = None) -> Iterator[list[FloatArray]]:
    """Legs from the start, leaving along its heading, each searched when the caller asks for the next:
    to the first goal, arriving any way round (the caller's routes go on from it); then, with more goals,
    through them all (`lattice.through`: each arrived at facing the way on where that is found). Points at
    most `spacing_m` apart, along forward arcs of `radius_m` and straight runs, every point at least
    `margin_m` from every blocked cell of `grid`; a search that finds not even its first leg within
    `max_nodes` poses yields nothing. `to_go(goal)`: the distance left from points to the goal, round the
    walls (`CoarseGrid.distances_to`), which the search is ordered by (None: the straight distance, which
    leads it into every room on the way)."""
    needed = margin_m + 0.5 * _SAMPLE_M
    res = grid.resolution_m
    rows, cols = grid.shape
    blocked = grid.padded_blocked(slice(-1, rows + 1), slice(-1, cols + 1))  # beyond the map is blocked
    centres_m = res * cv2.distanceTransform((~blocked).astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)

    def clearance_ok(points: FloatArray) -> np.ndarray:
        i, j, _ = grid.cells_of(points)
        d = centres_m[np.clip(j + 1, 0, rows + 1), np.clip(i + 1, 0, cols + 1)]
        ok = d - math.sqrt(2.0) * res >= needed
        unsure = ~ok & (d + res / math.sqrt(2.0) >= needed)
        if unsure.any():
            ok[unsure] = grid.clearance(points[unsure]) >= needed
        return ok

    def clear(starts: FloatArray, ends: FloatArray) -> np.ndarray:
        lengths = np.linalg.norm(ends - starts, axis=1)
        counts = np.ceil(lengths / _SAMPLE_M).astype(int) + 1
        chord = np.repeat(np.arange(len(starts)), counts)
        first = np.concatenate([[0], np.cumsum(counts)[:-1]])
        fraction = (np.arange(int(counts.sum())) - first[chord]) / np.maximum(counts[chord] - 1, 1)
        points = starts[chord] + fraction[:, None] * (ends - starts)[chord]
        return np.logical_and.reduceat(clearance_ok(points), first)

    goals = np.asarray(goals, dtype=float).reshape(-1, 2)
    for count in sorted({1, len(goals)}):
        legs = through(start=start, heading_rad=heading_rad, goals=goals[:count], clear=clear,
                       bounds_min=bounds_min, bounds_max=bounds_max, radius=radius_m, spacing_m=spacing_m,
                       max_nodes=max_nodes, to_go=to_go)
        if legs is not None:
            yield legs
