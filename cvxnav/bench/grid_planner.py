"""A NavFn-like grid planner, the kind Nav2 ships, written with scipy: the benchmark's peer on maps.

Inflation by a distance transform: a cell is free when its centre is at least the margin plus half a
cell from the nearest blocked cell's centre (scipy.ndimage's exact Euclidean distance transform), so
its centre keeps the margin from the blocked squares to within a fifth of a cell (a square's nearest
point is at least half a cell and at most half a diagonal nearer than its centre). Then Dijkstra
(scipy.sparse.csgraph) over the 8-connected free cells, edges weighted by their length, from each leg's
start to its goal, as NavFn propagates its potential over the whole grid. The path runs through cell
centres, from the start to the goals.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy import ndimage, sparse
from scipy.sparse.csgraph import dijkstra

from services.geometry import FloatArray
from schemas.occupancy import OccupancyGrid, load_map


@dataclass(frozen=True)
class GridPlan:
    path: FloatArray | None  # world points start → goals, None when there is none
    time_s: float
    stages_ms: dict[str, float]
    reason: str = ""


def plan_on_grid_file(map_path: Path, *, start: FloatArray, goals: FloatArray, margin_m: float) -> GridPlan:
    """Read the map file and plan start → goals on it; timed from reading the file to the path."""
    t0 = time.perf_counter()
    grid = load_map(map_path)
    load_s = time.perf_counter() - t0
    plan = plan_on_grid(grid, start=start, goals=goals, margin_m=margin_m)
    return GridPlan(plan.path, load_s + plan.time_s, {"load": 1e3 * load_s, **plan.stages_ms}, plan.reason)


def inflated_free(grid: OccupancyGrid, *, margin_m: float) -> np.ndarray:
    """The cells whose centre is at least the margin plus half a cell from the nearest blocked cell's centre
    (the map and the ring of blocked cells round it: beyond the map is unknown)."""
    rows, cols = grid.shape
    distance = ndimage.distance_transform_edt(~grid.padded_blocked(slice(-1, rows + 1), slice(-1, cols + 1)))
    return distance[1:-1, 1:-1] * grid.resolution_m >= margin_m + 0.5 * grid.resolution_m


def plan_on_grid(grid: OccupancyGrid, *, start: FloatArray, goals: FloatArray, margin_m: float) -> GridPlan:
    """Distance-transform inflation and an 8-connected Dijkstra over the whole grid."""
    t0 = time.perf_counter()
    rows, cols = grid.shape
    res = grid.resolution_m
    free = inflated_free(grid, margin_m=margin_m)
    t1 = time.perf_counter()
    index = np.full(free.shape, -1, dtype=np.int64)
    nodes = np.flatnonzero(free)
    index.flat[nodes] = np.arange(len(nodes))
    heads, tails, weights = [], [], []
    for dr, dc, w in ((0, 1, 1.0), (1, 0, 1.0), (1, 1, math.sqrt(2.0)), (1, -1, math.sqrt(2.0))):
        a = (slice(0, rows - dr), slice(max(0, -dc), cols - max(0, dc)))
        b = (slice(dr, rows), slice(max(0, dc), cols - max(0, -dc)))
        both = free[a] & free[b]
        heads.append(index[a][both])
        tails.append(index[b][both])
        weights.append(np.full(len(heads[-1]), w * res))
    graph = sparse.csr_array((np.concatenate(weights), (np.concatenate(heads), np.concatenate(tails))),
                             shape=(len(nodes), len(nodes)))
    t2 = time.perf_counter()
    waypoints = np.vstack([start, goals])
    i, j, inside = grid.cells_of(waypoints)
    if not np.all(inside) or np.any(~free[j.clip(0, rows - 1), i.clip(0, cols - 1)]):
        stages = {"inflate": 1e3 * (t1 - t0), "graph": 1e3 * (t2 - t1), "search": 0.0}
        return GridPlan(None, time.perf_counter() - t0, stages, "a start or goal cell is within the margin")
    targets = index[j, i]
    dist, pred = dijkstra(graph, directed=False, indices=targets[:-1], return_predecessors=True)
    pieces = [waypoints[:1]]
    for leg in range(len(targets) - 1):
        if not np.isfinite(dist[leg, targets[leg + 1]]):
            stages = {"inflate": 1e3 * (t1 - t0), "graph": 1e3 * (t2 - t1), "search": 1e3 * (time.perf_counter() - t2)}
            return GridPlan(None, time.perf_counter() - t0, stages, f"no path to goal {leg + 1} on the inflated grid")
        chain = [targets[leg + 1]]
        while chain[-1] != targets[leg]:
            chain.append(pred[leg, chain[-1]])
        r, c = np.divmod(nodes[np.asarray(chain[::-1][1:-1], dtype=np.int64)], cols)
        # From each leg's start through the cell centres between, to its goal itself.
        pieces += [grid.to_world((np.column_stack([c, r]) + 0.5) * res), waypoints[leg + 1 : leg + 2]]
    path = np.vstack(pieces)
    t3 = time.perf_counter()
    stages = {"inflate": 1e3 * (t1 - t0), "graph": 1e3 * (t2 - t1), "search": 1e3 * (t3 - t2)}
    return GridPlan(path, t3 - t0, stages)


def main(argv: list[str] | None = None) -> int:
    """`python -m cvxnav.bench.grid_planner SCENARIO`: one plan, printed (what the bench's memory figure runs)."""
    import sys

    from schemas.scenario import OccupancyGridObstacle, load_scenario

    path = Path((argv or sys.argv[1:])[0])
    scenario = load_scenario(path)
    grid = next(o.grid for o in scenario.obstacles if isinstance(o, OccupancyGridObstacle))
    plan = plan_on_grid(grid, start=scenario.start.xy, goals=scenario.goals_array, margin_m=scenario.inflation_m)
    print(f"{scenario.name}: " + (f"{len(plan.path)} cells in {1e3 * plan.time_s:.0f} ms" if plan.path is not None
                                  else plan.reason))
    return 0 if plan.path is not None else 3


if __name__ == "__main__":
    raise SystemExit(main())
