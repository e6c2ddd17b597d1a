"""Planning on an occupancy grid at a cost that follows the route, not the map.

A grid planner pays for the whole map (a distance transform and a Dijkstra over every cell). Here only
what the query can use is built:

1. A coarse search (`CoarseGrid`): the blocked cells pooled into coarse cells of side s (a coarse cell
   is blocked when any of its cells is), one distance transform of that small grid, and Dijkstra
   (scipy.sparse.csgraph) over the coarse cells a robot could be in. A coarse cell C holding a point x at
   least r from every blocked cell is at most r − s√2 from the nearest blocked coarse cell C′ (centre to
   centre): else, with q any blocked cell in C′, dist(x, q) ≤ s/√2 + dist(C, C′) + s/√2 < r. So the
   coarse graph keeps every coarse cell a path can use and every step between neighbours it can take:
   when it has no path, no path exists at all, and the planner says so. Its answer is the shortest path
   and the corridor round it: every coarse cell on a path at most `slack` longer.
2. The cover (`services.ellipsoids.grid_cover`) of the tiles within `band_m` of the corridor. Fitting
   them computes the distance transform there, which tells the coarse cells there apart more finely (a
   coarse cell is kept only if one of its cells is within half a cell's diagonal of being r clear, which
   still keeps every cell a path can use); the coarse search runs again, and again, until its corridor
   lies in tiles already fitted. An optimistic coarse grid would otherwise send the corridor through a
   door the robot does not fit.
3. The exact route search and refinement (`services.planner.core.plan_until_verified`: tangent graph,
   convex refinement, verified smoothing) on the fitted ellipses near the corridor alone.
4. The paths are then held against every other fitted ellipse and every tile they come near: a tile's
   grown ellipses reach at most `GridCover.reach_m` beyond it, so a path further than that from every
   tile not fitted can touch no ellipse of them. If they touch or come near one, it is fitted and added
   and the plan made again. The path returned touches no ellipse of the whole map's cover, and it is the
   shortest route among a subset of those ellipses: the exact optimum of the whole model (a relaxation's
   optimum that is feasible is optimal). For the same reason a route search that finds no route among
   some of the ellipses proves there is none among all of them.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from contextlib import AbstractContextManager, nullcontext
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
from scipy import ndimage, sparse
from scipy.sparse.csgraph import dijkstra
from scipy.spatial import cKDTree

from cvxnav.geometry import Ellipse, EllipseStack, FloatArray
from schemas.occupancy import OccupancyGrid
from services.ellipsoids.grid_cover import DistanceWindow, GridCover, GridPiece, IntArray
from services.planner.core import PathPlan
from services.smoother.core import Smoothed

_DIAGONAL = math.sqrt(2.0)
# The smoothed curve's samples are at most 0.05 m apart and its curvature κ ≤ 1.2 / m is verified, so it
# strays from their chords by at most κ h² / 8 < 4e-4 m; a grown ellipse's semi-axes are at least the
# margin r ≥ 0.2 m (so ‖A‖ ≤ 1 / r), so on the curve its level is within 2e-3 of the chords'.
_CURVE_LEVEL = 1.002


@dataclass(frozen=True)
class CorridorSettings:
    coarse_m: float = 0.2  # side of a coarse cell (rounded to a whole number of cells)
    slack: float = 0.1  # the corridor: coarse cells on a path at most this much longer than the shortest
    band_m: float = 0.5  # tiles within this of the corridor are fitted before the first plan
    near_m: float = 1.0  # ... and their ellipses within this of it planned among
    max_searches: int = 12  # coarse searches at most while the corridor keeps leaving the fitted tiles
    max_rounds: int = 12  # plans at most while the path keeps meeting ellipses not planned among


@dataclass(frozen=True)
class CoarseRoute:
    """The coarse search's answer: its shortest path (world points, string-pulled) start → goals, the
    centres of every coarse cell on a path at most `slack` longer (the corridor), or why there is none."""

    status: Literal["ok", "no_path"]
    points: FloatArray
    corridor: FloatArray
    length_m: float = 0.0
    reason: str = ""


@dataclass(eq=False)
class CoarseGrid:
    """The coarse cells a robot of clearance `margin_m` may be in, on a grid of `coarse_m` cells (the map
    and a ring of blocked coarse cells round it), and the 8-connected shortest paths among them."""

    grid: OccupancyGrid
    margin_m: float
    coarse_m: float
    passable: np.ndarray = field(init=False)
    _graph: tuple[np.ndarray, sparse.csr_array] | None = field(init=False, default=None)

    def __post_init__(self) -> None:
        res = self.grid.resolution_m
        self.k = k = max(1, int(round(self.coarse_m / res)))
        self.s = k * res
        rows, cols = self.grid.shape
        # Coarse cell (a, b) holds the map's cells from ((a − 1) k, (b − 1) k): a ring beyond the map.
        self.nr, self.nc = -(-rows // k) + 2, -(-cols // k) + 2
        blocked = self.grid.padded_blocked(slice(-k, (self.nr - 1) * k), slice(-k, (self.nc - 1) * k))
        pooled = blocked.reshape(self.nr, k, self.nc, k).any(axis=(1, 3))
        self.passable = ndimage.distance_transform_edt(~pooled) * self.s >= self.margin_m - self.s * _DIAGONAL

    def refine(self, window: DistanceWindow) -> int:
        """Close the coarse cells inside the window none of whose cells is within half a cell's diagonal
        of being `margin_m` clear (the window's D bounds a cell centre's distance from above, and a point
        of the cell is within half a diagonal of the centre); how many were closed."""
        k, res = self.k, self.grid.resolution_m
        rows, cols = window.distance.shape
        # The coarse cells wholly inside the window: cell b spans map rows (b − 1) k … b k.
        b0, b1 = max(-(-(window.row0 + k) // k), 0), min((window.row0 + rows + k) // k, self.nr)
        a0, a1 = max(-(-(window.col0 + k) // k), 0), min((window.col0 + cols + k) // k, self.nc)
        if b1 <= b0 or a1 <= a0:
            return 0
        r0, c0 = (b0 - 1) * k - window.row0, (a0 - 1) * k - window.col0
        block = window.distance[r0 : r0 + (b1 - b0) * k, c0 : c0 + (a1 - a0) * k]
        best = block.reshape(b1 - b0, k, a1 - a0, k).max(axis=(1, 3))
        close = (best < self.margin_m - res / _DIAGONAL) & self.passable[b0:b1, a0:a1]
        if close.any():
            self.passable[b0:b1, a0:a1] &= ~close
            self._graph = None
        return int(close.sum())

    def _nodes(self) -> tuple[np.ndarray, sparse.csr_array]:
        """(coarse cell of each node, the graph), rebuilt after a refinement."""
        if self._graph is None:
            nodes = np.flatnonzero(self.passable)
            index = np.full(self.passable.shape, -1, dtype=np.int64)
            index.flat[nodes] = np.arange(len(nodes))
            self._graph = (nodes, _grid_graph(self.passable, index, self.s))
        return self._graph

    def route(self, waypoints: FloatArray, *, slack: float) -> CoarseRoute:
        """The shortest path through `waypoints` (start, goals) in order, and the corridor: for each leg
        a → b, the coarse cells c with d(a, c) + d(c, b) ≤ (1 + slack) d(a, b), every cell of a path at
        most `slack` longer — a route round the other side of an obstacle, hardly longer, is in it too
        (the 8-connected metric is up to 8 % off the Euclidean one)."""
        g = self.grid.to_grid(waypoints) / self.s + 1.0  # coarse cell coordinates, counting the ring
        wa, wb = np.floor(g[:, 0]).astype(int), np.floor(g[:, 1]).astype(int)
        names = ["start"] + [f"goal {k + 1}" for k in range(len(waypoints) - 1)]
        none = np.zeros((0, 2))
        for name, a, b in zip(names, wa, wb):
            if not (0 <= a < self.nc and 0 <= b < self.nr) or not self.passable[b, a]:
                return CoarseRoute("no_path", none, none, reason=f"the {name} is within the margin "
                                   f"({self.margin_m:.3f} m) of a blocked cell: no path")
        nodes, graph = self._nodes()
        targets = np.searchsorted(nodes, wb * self.nc + wa)
        dist, pred = dijkstra(graph, directed=False, indices=targets, return_predecessors=True)
        chain, ends = [int(targets[0])], [0]
        near = np.zeros(len(nodes), dtype=bool)
        total = 0.0
        for leg in range(len(targets) - 1):
            here = float(dist[leg, targets[leg + 1]])
            if not np.isfinite(here):
                return CoarseRoute("no_path", none, none, reason=(
                    f"no path to {names[leg + 1]}: the coarse grid ({self.s:.2f} m cells), which keeps every "
                    f"cell a path at clearance {self.margin_m:.3f} m can use, has none, so none exists"))
            total += here
            near |= dist[leg] + dist[leg + 1] <= (1.0 + slack) * here + 1e-9
            leg_nodes = [int(targets[leg + 1])]
            while leg_nodes[-1] != targets[leg]:
                leg_nodes.append(int(pred[leg, leg_nodes[-1]]))
            chain.extend(leg_nodes[::-1][1:])
            ends.append(len(chain) - 1)

        def centres(at: np.ndarray) -> FloatArray:  # coarse cells' centres, in coarse cells from the map's corner
            b, a = np.divmod(nodes[at], self.nc)
            return np.column_stack([a, b]) - 0.5

        path = centres(np.asarray(chain))
        path[ends] = g - 1.0  # the waypoints themselves, each a vertex of the string-pulled path
        keep = np.zeros(len(path), dtype=bool)
        keep[ends] = True
        points = self.grid.to_world(_pulled(path, self.passable, keep=keep) * self.s)
        corridor = self.grid.to_world(centres(np.flatnonzero(near)) * self.s)
        return CoarseRoute("ok", points, corridor, length_m=total)


def _pulled(path: FloatArray, passable: np.ndarray, *, keep: np.ndarray) -> FloatArray:
    """The path (coarse-cell coordinates from the map's corner) with every vertex dropped that a straight
    line over passable coarse cells can skip (string pulling): an 8-connected path wanders between
    equally long ones, and the route it stands for is straight. Greedy: from each vertex kept, the
    furthest later vertex in sight by bisection (sight: samples a quarter cell apart on passable cells);
    the vertices marked `keep` stay."""

    def clear(p: FloatArray, q: FloatArray) -> bool:
        n = int(math.ceil(4.0 * float(np.max(np.abs(q - p))))) + 1
        t = np.linspace(0.0, 1.0, n)[:, None]
        c = np.floor(p + t * (q - p)).astype(np.intp) + 1  # counting the ring
        return bool(np.all(passable[c[:, 1], c[:, 0]]))

    out = [0]
    while out[-1] < len(path) - 1:
        i = out[-1]
        stop = i + 1 + int(np.argmax(keep[i + 1 :]))  # the next vertex that must stay
        lo, hi = i + 1, stop
        while lo < hi:
            mid = (lo + hi + 1) // 2
            if clear(path[i], path[mid]):
                lo = mid
            else:
                hi = mid - 1
        out.append(lo)
    return path[out]


def _grid_graph(passable: np.ndarray, index: np.ndarray, step_m: float) -> sparse.csr_array:
    """The 8-connected graph of the passable cells, edges weighted by their centres' distance."""
    rows, cols, weights = [], [], []
    n_rows, n_cols = passable.shape
    for dr, dc, w in ((0, 1, 1.0), (1, 0, 1.0), (1, 1, _DIAGONAL), (1, -1, _DIAGONAL)):
        a = (slice(0, n_rows - dr), slice(max(0, -dc), n_cols - max(0, dc)))
        b = (slice(dr, n_rows), slice(max(0, dc), n_cols - max(0, -dc)))
        both = passable[a] & passable[b]
        rows.append(index[a][both])
        cols.append(index[b][both])
        weights.append(np.full(len(rows[-1]), w * step_m))
    n = int(passable.sum())
    return sparse.csr_array((np.concatenate(weights), (np.concatenate(rows), np.concatenate(cols))), shape=(n, n))


@dataclass(frozen=True)
class CorridorPlan:
    """What `plan_in_corridor` found: the plan and its smoothed curve (as `plan_until_verified`), the
    ellipses it was made among, the coarse route, how much of the map's cover was fitted, and how many
    coarse searches and plans it took."""

    plan: PathPlan
    smoothed: Smoothed | None
    grown: list[Ellipse]
    coarse: CoarseRoute
    tiles_fitted: int
    tiles_total: int
    searches: int
    rounds: int


def plan_in_corridor(
    *,
    cover: GridCover,
    waypoints: FloatArray,
    fixed: list[Ellipse],
    plan_fn: Callable[[list[Ellipse]], tuple[PathPlan, Smoothed | None]],
    settings: CorridorSettings = CorridorSettings(),
    timer: Callable[[str], AbstractContextManager] = nullcontext,
) -> CorridorPlan:
    """Plan start → goals (`waypoints`) among `fixed` ellipses (the scenario's other obstacles, grown) and
    the grid cover's, fitting only the tiles the plan comes near (see the module docstring).

    The plan is made among the fixed ellipses and the fitted ones that come within `near_m` of the
    corridor; then the paths are checked against every other fitted ellipse (the exact segment test on
    the refined points, and on the smoothed curve's samples at `_CURVE_LEVEL`) and against the tiles
    not fitted, and planned again with whatever they touch. `plan_fn(grown)` plans on a list of grown
    ellipses (`cvxnav.plan.plan_on_model`); `timer(stage)` wraps the "corridor" and "fit" steps.
    """
    total = cover.tiles_shape[0] * cover.tiles_shape[1]
    with timer("corridor"):
        coarse_grid = CoarseGrid(cover.grid, cover.margin_m, settings.coarse_m)
    tiles: set = set()
    refined = len(cover.windows)
    for searches in range(1, settings.max_searches + 1):
        with timer("corridor"):
            for window in cover.windows[refined:]:
                coarse_grid.refine(window)
            refined = len(cover.windows)
            coarse = coarse_grid.route(waypoints, slack=settings.slack)
        if coarse.status != "ok":
            plan = PathPlan("no_path", np.zeros((0, 2)), reason=coarse.reason)
            return CorridorPlan(plan, None, list(fixed), coarse, len(cover.fitted), total, searches, 0)
        with timer("fit"):
            line = np.vstack([_densify(coarse.points, 0.5 * settings.coarse_m), coarse.corridor])
            new = cover.tiles_near(line, settings.band_m) - tiles
            if not new:
                break
            tiles |= new
            cover.pieces(new)
    with timer("fit"):
        fitted = cover.pieces(tiles)
        used = _near(fitted, line, settings.near_m)
    plan, smoothed, grown = PathPlan("no_path", np.zeros((0, 2))), None, list(fixed)
    for rounds in range(1, settings.max_rounds + 1):
        grown = list(fixed) + [fitted[k].grown for k in sorted(used)]
        plan, smoothed = plan_fn(grown)
        if plan.status != "ok":
            break  # no route among a subset of the ellipses: none among all of them
        with timer("fit"):
            new = cover.tiles_near(_touched(plan, smoothed), cover.reach_m + 0.1) - tiles
            if new:
                tiles |= new
                fitted = cover.pieces(tiles)
            others = [k for k in range(len(fitted)) if k not in used]
            curve = smoothed.points if smoothed is not None else plan.points
            hit = np.union1d(_entered([fitted[k].grown for k in others], plan.points, level=1.0),
                             _entered([fitted[k].grown for k in others], curve, level=_CURVE_LEVEL))
            if not len(hit):
                break
            used.update(others[k] for k in hit.tolist())
    return CorridorPlan(plan, smoothed, grown, coarse, len(cover.fitted), total, searches, rounds)


def _near(pieces: list[GridPiece], line: FloatArray, distance_m: float) -> set[int]:
    """The pieces whose grown ellipse's bounding disc comes within `distance_m` of one of the points."""
    if not pieces:
        return set()
    stack = EllipseStack.of([p.grown for p in pieces])
    gap = cKDTree(line).query(stack.centers)[0] - stack.reach
    return set(np.flatnonzero(gap <= distance_m).tolist())


def _entered(ellipses: list[Ellipse], path: FloatArray, *, level: float) -> IntArray:
    """Indices of the ellipses some segment of the polyline comes within `level` of (eq. 2, exact)."""
    if not ellipses or len(path) < 2:
        return np.zeros(0, dtype=np.intp)
    _, cols, levels = EllipseStack.of(ellipses).segment_pairs(path[:-1], path[1:])
    return np.unique(cols[levels < level])


def _touched(plan: PathPlan, smoothed: Smoothed | None) -> FloatArray:
    """The plan's refined points and its smoothed curve's, as one polyline sampled at most 0.1 m apart
    (the jump from one to the other is a segment of it too, which only makes the check stricter)."""
    parts = [plan.points] + ([smoothed.points] if smoothed is not None else [])
    return _densify(np.vstack([p for p in parts if len(p)]), 0.1)


def _densify(points: FloatArray, step_m: float) -> FloatArray:
    """The polyline with extra points so that consecutive ones are at most `step_m` apart."""
    if len(points) < 2:
        return points
    d = np.linalg.norm(np.diff(points, axis=0), axis=1)
    n = np.maximum(1, np.ceil(d / step_m).astype(np.intp))
    seg = np.repeat(np.arange(len(d)), n)
    t = (np.arange(len(seg)) - np.repeat(np.cumsum(n) - n, n)) / n[seg]
    return np.vstack([points[seg] + t[:, None] * (points[seg + 1] - points[seg]), points[-1:]])
