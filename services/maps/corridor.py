"""Planning on an occupancy grid at a cost that follows the route, not the map.

A grid planner pays for the whole map (a distance transform and a Dijkstra over every cell). Here only
what the query can use is built:

1. A coarse search (`CoarseGrid`) over coarse cells of side s, Dijkstra (scipy.sparse.csgraph) over
   those a robot could be in. A point x of a map cell is within half the cell's diagonal of its centre,
   and a blocked square's nearest point is at least half a cell nearer than its centre, so x is r clear
   only if the cell's centre is at least r + res/2 − res/√2 from every blocked cell's centre. The cells
   nearer than that are closed (one dilation of the blocked mask, over the whole map: a few ms on a
   building's 1.4 M cells). A path at clearance r runs through open cells only, from each to one
   sharing an edge or a corner: a goal whose cell the start's does not reach so (a flood fill, under a
   millisecond) has no path, and the planner says so. A coarse cell is passable when one of its cells
   is open and reached, and a path runs through passable coarse cells only, from each to one sharing an
   edge or a corner, so the coarse graph keeps every cell and step a path can use: when it has no path,
   no path exists at all. Its answer is the shortest path and the corridor round it: every coarse cell
   on a path at most `slack` longer. (The coarse cells are as fine as the map's own can tell them: a
   door the robot does not fit is closed in the coarse grid too, and the corridor never runs through
   it.)
2. The cover (`services.ellipsoids.grid_cover`) of the tiles within `band_m` of the corridor, its pieces
   that hold the start or a goal fitted again tighter (`GridCover.tighten`), and those that hold the
   clearest points of the passages the coarse route runs through narrower than the margin plus the
   cover's tolerance on both sides (`_doors_along`: a door a few centimetres wider than the robot's
   passage, which the cover's excess may close). A wall beside the corridor lies up to the margin from
   its cells, its grown ellipses reach into it: the band is wider than the corridor by about the margin.
3. The exact route search and refinement (`services.planner.core.plan_until_verified`: tangent graph,
   convex refinement, verified smoothing) on the fitted ellipses near the corridor alone, the route's
   tangent segments kept to the corridor (`_Corridor`): without that the route search, which sees no
   wall it was not given, found its way through them, and every such way took another plan.
4. The paths are then held against every other fitted ellipse and every tile they come near: a grown
   ellipse reaches at most `GridCover.reach_m` beyond the tiles fitted with it, so a path further than
   that from every tile not fitted can touch no ellipse those tiles will get. If they touch or come near
   one, it is fitted and added and the plan made again. The path returned touches no ellipse of the
   whole map's cover, and its route is the shortest among a subset of them within the corridor: the
   exact optimum of the model within its corridor (a relaxation's optimum that is feasible is optimal).
   A plan whose curve fails verification is held against them too: made among too few ellipses, it may
   have failed on a turn through a wall mass no tile of which was fitted, and is made again with the
   ellipses it met. The shortest route within the corridor, each refined path and each curve are held
   against the cover as soon as they are made (`services.planner.core.plan_within`'s `meets_others`):
   no refinement, repair or smoothing is spent on a plan made among too few ellipses. Where a plan finds
   no route (or none refined clear), once, the pieces holding the points of the coarse route that are
   the margin clear of every blocked cell are fitted again tighter (`GridCover.tighten`) and the plan
   made again in the corridor: a gap open to the coarse grid that the cover's tolerance closes and the
   passages found before the first plan did not take in. A search kept to the corridor that still finds
   nothing (or nothing drivable, meeting no other ellipse) is made again without it; one without it
   that finds no route among some of the ellipses proves there is none among all of them — in this
   cover. After a curve that failed among all it meets, once, the pieces its path ran within their own
   tolerance of are fitted again tighter: a start facing along a wall a few centimetres beyond the
   margin may find no room to turn at the car's curvature in the cover's excess.
5. Where the plans still end without a verified curve, a path the car can drive is searched on the map
   itself, over the car's own turns, ordered by the coarse grid's distance left to each goal
   (`services.maps.seed`), and the plans go on from it, refined as the route: the tangent graph's routes
   are blind to the heading and the refinement is local, so a goal a little behind the car, a corner too
   tight for its turning radius, a way out on the other side of a pillar or a goal the next lies back
   from left no plan where the car could drive. The caller hands such paths one at a time (to the
   first goal, then through them all: `services.maps.seed.drivable_paths`); when the plans from every
   one end unverified, the answer (and its reason) is the plan before them.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator
from contextlib import AbstractContextManager, nullcontext
from dataclasses import dataclass, field
from itertools import chain
from typing import Literal

import cv2
import numpy as np
from scipy import ndimage, sparse
from scipy.sparse.csgraph import dijkstra
from scipy.spatial import cKDTree

from services.geometry import Ellipse, EllipseStack, FloatArray, arc_lengths, joined_legs, resample_polyline
from schemas.occupancy import OccupancyGrid
from services.ellipsoids.grid_cover import GridCover, GridPiece, IntArray, Tile
from services.planner.core import MeetsOthers, PathPlan
from services.planner.route import KeepTo
from services.smoother.core import Smoothed

_DIAGONAL = math.sqrt(2.0)
# The smoothed curve's samples are at most 0.05 m apart and its curvature κ ≤ 1.2 / m is verified, so it
# strays from their chords by at most κ h² / 8 < 4e-4 m; a grown ellipse's semi-axes are at least the
# margin r ≥ 0.2 m (so ‖A‖ ≤ 1 / r), so on the curve its level is within 2e-3 of the chords'.
_CURVE_LEVEL = 1.002


@dataclass(frozen=True)
class CorridorSettings:
    coarse_m: float = 0.2  # side of a coarse cell (rounded to a whole number of cells)
    # The corridor: coarse cells on a path at most this much longer than the shortest; above the graph's
    # metric error (2.7 %, `_STEPS`), which a route the optimum follows may be charged.
    slack: float = 0.03
    band_m: float = 0.5  # tiles within this of the corridor are fitted before the first plan
    near_m: float = 0.2  # ... and their ellipses within this of it planned among
    keep_to_corridor: bool = True  # search the route within the corridor (see `_Corridor`)
    keep_m: float = 1.5  # the corridor keeps this much round the start and goals
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
    cells: np.ndarray | None = None  # the corridor's coarse cells (a mask of the coarse grid)
    leg_lengths_m: tuple[float, ...] = ()  # of the string-pulled path, waypoint to waypoint


@dataclass(eq=False)
class CoarseGrid:
    """The coarse cells a robot of clearance `margin_m` may be in, on a grid of `coarse_m` cells (the map
    and a ring of blocked coarse cells round it), and the 16-connected shortest paths among them.

    With a `start`, only the map's open cells joined to the start's by open cells sharing an edge or a
    corner count (a path at clearance r runs through open cells only, from each to such a neighbour):
    pooled, the coarse cells could join two rooms through a gap a few centimetres narrower than the
    robot's passage, whose open cells on either side fall in neighbouring coarse cells."""

    grid: OccupancyGrid
    margin_m: float
    coarse_m: float
    start: FloatArray | None = None
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
        self.open = open_cells(blocked, margin_m=self.margin_m, resolution_m=res)
        self.reached = self.open
        if self.start is not None:
            (row, col), = self._cells(self.start)
            self.reached = reached_from(self.open, row, col)
        # A coarse cell is passable when one of its cells is open (and reached).
        self.passable = _pooled(self.reached, k)

    def _cells(self, points: FloatArray) -> IntArray:
        """(row, column) of each point's map cell in `open` (which counts the ring), clipped to it."""
        i, j, _ = self.grid.cells_of(points)
        cells = np.column_stack([j, i]) + self.k
        return np.clip(cells, 0, np.array(self.open.shape) - 1)

    def _nodes(self) -> tuple[np.ndarray, sparse.csr_array]:
        """(coarse cell of each node, the graph), built once."""
        if self._graph is None:
            nodes = np.flatnonzero(self.passable)
            index = np.full(self.passable.shape, -1, dtype=np.int64)
            index.flat[nodes] = np.arange(len(nodes))
            self._graph = (nodes, _grid_graph(self.passable, index, self.s))
        return self._graph

    def distances_to(self, point: FloatArray) -> Callable[[FloatArray], FloatArray]:
        """The length of the shortest 16-connected path from each of some world points' coarse cells to
        `point`'s, among the passable cells (∞ where none joins them): the distance left to go that a search
        over the car's own turns is ordered by (`services.maps.seed`), which sees the walls on the way."""
        nodes, graph = self._nodes()
        cell = int(self._coarse_index(np.reshape(point, (1, 2)))[0])
        at = int(np.searchsorted(nodes, cell))
        dist = np.full(self.passable.size, np.inf)
        if at < len(nodes) and nodes[at] == cell:
            dist[nodes] = dijkstra(graph, indices=at)

        def distance(points: FloatArray) -> FloatArray:
            return dist[self._coarse_index(points)]

        return distance

    def _coarse_index(self, points: FloatArray) -> IntArray:
        """Each world point's coarse cell (counting the ring, clipped to the grid) as an index into the
        flattened coarse grid: the numbering of `_nodes`."""
        g = self.grid.to_grid(points) / self.s + 1.0
        a = np.clip(np.floor(g[:, 0]).astype(int), 0, self.nc - 1)
        b = np.clip(np.floor(g[:, 1]).astype(int), 0, self.nr - 1)
        return b * self.nc + a

    def route(self, waypoints: FloatArray, *, slack: float) -> CoarseRoute:
        """The shortest 16-connected path through `waypoints` (start, goals) in order, and the corridor: for each leg
        a → b, the coarse cells c with d(a, c) + d(c, b) ≤ (1 + slack) d(a, b), every cell of a path at
        most `slack` longer — a route round the other side of an obstacle, hardly longer, is in it too
        (the graph's metric is up to 2.7 % off the Euclidean one)."""
        g = self.grid.to_grid(waypoints) / self.s + 1.0  # coarse cell coordinates, counting the ring
        names = ["start"] + [f"goal {k + 1}" for k in range(len(waypoints) - 1)]
        none = np.zeros((0, 2))
        for name, (row, col) in zip(names, self._cells(waypoints)):
            if not self.open[row, col]:
                return CoarseRoute("no_path", none, none, reason=f"the {name} is within the margin "
                                   f"({self.margin_m:.3f} m) of a blocked cell: no path")
            if not self.reached[row, col]:
                return CoarseRoute("no_path", none, none, reason=(
                    f"no path to {name}: the map's cells ({self.grid.resolution_m:.2f} m) that may hold a point "
                    f"at clearance {self.margin_m:.3f} m do not join it to the start, so none exists"))
        nodes, graph = self._nodes()
        targets = np.searchsorted(nodes, self._coarse_index(waypoints))
        # Only cells a near-shortest path can use matter: the search from each leg's start stops at twice
        # the longest leg's straight length and a turn round a building (and goes on without a limit if
        # that misses a goal). The last goal's distances serve only its leg's corridor, cells within
        # (1 + slack) of that leg's length of it: its search stops there.
        legs = np.linalg.norm(np.diff(waypoints, axis=0), axis=1)
        limit = 2.0 * float(legs.max()) + 20.0
        dist, pred = dijkstra(graph, indices=targets[:-1], return_predecessors=True, limit=limit)
        if not all(np.isfinite(dist[k, targets[k + 1]]) and dist[k, targets[k + 1]] * (1.0 + slack) <= limit
                   for k in range(len(targets) - 1)):
            dist, pred = dijkstra(graph, indices=targets[:-1], return_predecessors=True)
        last = float(dist[-1, targets[-1]])
        to_last = (dijkstra(graph, indices=targets[-1:], limit=(1.0 + slack) * last + 1e-6) if np.isfinite(last)
                   else np.full((1, len(nodes)), np.inf))
        dist = np.vstack([dist, to_last])
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
        kept = _pulled(path, self.passable, keep=keep)
        points = self.grid.to_world(path[kept] * self.s)
        corridor = self.grid.to_world(centres(np.flatnonzero(near)) * self.s)
        mask = np.zeros(self.passable.shape, dtype=bool)
        mask.flat[nodes[near]] = True
        along = arc_lengths(points)
        at_waypoints = along[np.searchsorted(kept, ends)]
        return CoarseRoute("ok", points, corridor, length_m=total, cells=mask,
                           leg_lengths_m=tuple(np.diff(at_waypoints).tolist()))


def open_cells(blocked: np.ndarray, *, margin_m: float, resolution_m: float) -> np.ndarray:
    """The cells of which some point may be `margin_m` clear of every blocked square (beyond the mask
    everything is blocked). A point x of a cell c is at most ‖x − c‖ + ‖c − q‖ − res/2 ≤ ‖c − q‖ + res/√2 −
    res/2 from the square of a blocked cell q (centres c, q): no point of c is r clear when some blocked
    centre is nearer than r + res/2 − res/√2 to c's. Those cells are closed, the others open."""
    return ~_closed(blocked, (margin_m + resolution_m * (0.5 - 1.0 / _DIAGONAL)) / resolution_m)


def reached_from(mask: np.ndarray, row: int, col: int) -> np.ndarray:
    """The cells of a boolean mask joined to cell (row, col) by cells of it sharing an edge or a corner
    (none where that cell is not in it): OpenCV's flood fill, under a millisecond on ACES's open cells."""
    if not mask[row, col]:
        return np.zeros_like(mask)
    filled = mask.view(np.uint8).copy()
    cv2.floodFill(filled, None, (int(col), int(row)), 2, flags=8)
    return filled == 2


_DILATE_MAX_CELLS = 16  # beyond this radius a distance transform closes the cells faster than a dilation


def _closed(blocked: np.ndarray, reach_cells: float) -> np.ndarray:
    """The blocked cells and those whose centre is nearer than `reach_cells` to a blocked cell's (beyond
    the mask everything is blocked). Offsets at exactly that distance are not taken: closing fewer is safe.
    A dilation by the disc of those offsets costs its area a cell (3 ms on ACES's 1.4 M cells at a radius
    of 9), OpenCV's exact Euclidean distance transform about 20 ms whatever the radius; its squared
    distances, rounded, are the whole numbers they are below 1 200 cells (`grid_cover._window`)."""
    n = max(0, int(math.ceil(reach_cells)))
    limit = reach_cells * reach_cells * (1.0 - 1e-12)
    if n <= _DILATE_MAX_CELLS:
        di, dj = np.mgrid[-n : n + 1, -n : n + 1]
        disc = di * di + dj * dj < limit
        disc[n, n] = True
        return cv2.dilate(blocked.view(np.uint8), disc.view(np.uint8), borderType=cv2.BORDER_CONSTANT,
                          borderValue=1).view(bool)
    padded = np.pad(blocked, n + 1, constant_values=True)
    cells = cv2.distanceTransform((~padded).view(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    cells = cells[n + 1 : -n - 1, n + 1 : -n - 1]
    return blocked | (np.rint(cells * cells) < limit)


def _pooled(mask: np.ndarray, k: int) -> np.ndarray:
    """Which k × k blocks of the mask hold a set cell (the coarse grid's: an open one): an OR of the k rows
    of each block, then of the k columns (numpy's `any` over the strided axes of a (rows, k, columns, k)
    view is ten times slower)."""
    rows = mask.reshape(-1, k, mask.shape[1])
    out = rows[:, 0].copy()
    for q in range(1, k):
        out |= rows[:, q]
    blocks = out.reshape(out.shape[0], -1, k)
    pooled = blocks[:, :, 0].copy()
    for q in range(1, k):
        pooled |= blocks[:, :, q]
    return pooled


def _pulled(path: FloatArray, passable: np.ndarray, *, keep: np.ndarray) -> IntArray:
    """The vertices of the path (coarse-cell coordinates from the map's corner) that string pulling keeps,
    in order: every vertex is dropped that a straight line over passable coarse cells can skip (an
    8-connected path wanders between equally long ones, and the route it stands for is straight).
    Greedy: from each vertex kept, the furthest later vertex in sight by bisection (sight: samples a
    quarter cell apart on passable cells); the vertices marked `keep` stay."""

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
    return np.asarray(out)


# Steps of the coarse graph: the 8 neighbours and the 8 knight's moves, one of each pair of opposites. With
# them the graph's shortest paths are within 2.7 % of the Euclidean length (8 neighbours: 8.2 %).
_STEPS = ((0, 1), (1, 0), (1, 1), (1, -1), (1, 2), (2, 1), (1, -2), (2, -1))


def _grid_graph(passable: np.ndarray, index: np.ndarray, step_m: float) -> sparse.csr_array:
    """The 16-connected graph of the passable cells, edges weighted by their centres' distance, each edge
    stored both ways (Dijkstra on it as a directed graph does not transpose it on every call, as
    scipy's undirected search does), built row by row as CSR (no sorting of pairs). A knight's move is
    taken only when both cells it passes beside are passable too (so it cuts no blocked corner the two
    king's moves round it would not)."""
    n_rows, n_cols = passable.shape
    open_ = np.pad(passable, 2)
    number = np.pad(index, 2, constant_values=-1)

    def at(dr: int, dc: int) -> tuple[slice, slice]:  # cells (r + dr, c + dc) of the padded grid for every (r, c)
        return slice(2 + dr, 2 + dr + n_rows), slice(2 + dc, 2 + dc + n_cols)

    steps = _STEPS + tuple((-dr, -dc) for dr, dc in _STEPS)
    n = int(passable.sum())
    ok = np.empty((n, len(steps)), dtype=bool)
    neighbour = np.empty((n, len(steps)), dtype=index.dtype)
    for k, (dr, dc) in enumerate(steps):
        step_ok = open_[at(dr, dc)]
        if abs(dr) + abs(dc) == 3:  # knight: the two cells beside its line
            sr, sc = (dr // 2, dc) if abs(dr) == 2 else (dr, dc // 2)
            step_ok = step_ok & open_[at(sr, sc)] & open_[at(dr - sr, dc - sc)]
        ok[:, k] = step_ok[passable]  # node by node, in the nodes' order (row-major)
        neighbour[:, k] = number[at(dr, dc)][passable]
    weights = np.broadcast_to(np.array([math.hypot(dr, dc) * step_m for dr, dc in steps]), ok.shape)
    indptr = np.concatenate([[0], np.cumsum(np.count_nonzero(ok, axis=1))])
    return sparse.csr_array((weights[ok], neighbour[ok], indptr), shape=(n, n))


@dataclass(frozen=True)
class CorridorPlan:
    """What `plan_in_corridor` found: the plan and its smoothed curve (as `plan_until_verified`), the
    ellipses it was made among, the coarse route, how much of the map's cover was fitted, and how many
    plans it took."""

    plan: PathPlan
    smoothed: Smoothed | None
    grown: list[Ellipse]
    coarse: CoarseRoute
    tiles_fitted: int
    tiles_total: int
    rounds: int
    kept_to_corridor: bool = False  # the route was searched within the corridor (`_Corridor`)


def plan_in_corridor(
    *,
    cover: GridCover,
    waypoints: FloatArray,
    fixed: list[Ellipse],
    plan_fn: Callable[[list[Ellipse], tuple[float, ...], KeepTo | None, MeetsOthers, list[FloatArray] | None],
                      tuple[PathPlan, Smoothed | None]],
    settings: CorridorSettings = CorridorSettings(),
    timer: Callable[[str], AbstractContextManager] = nullcontext,
    on_round: Callable[[int, int], None] | None = None,
    seed_fn: Callable[[CoarseGrid], Iterator[list[FloatArray]]] | None = None,
) -> CorridorPlan:
    """Plan start → goals (`waypoints`) among `fixed` ellipses (the scenario's other obstacles, grown) and
    the grid cover's, fitting only the tiles the plan comes near (see the module docstring).

    The plan is made among the fixed ellipses and the fitted ones that come within `near_m` of the
    corridor; then the paths are checked against every other fitted ellipse (the exact segment test on
    the refined points, and on the smoothed curve's samples at `_CURVE_LEVEL`) and against the tiles
    not fitted, and planned again with whatever they touch. `plan_fn(grown, leg_lengths_m, keep_to,
    meets_others, seed)` plans on a list of grown ellipses (`cvxnav.plan.plan_on_model`), told each leg's length
    on the coarse grid (where the route search starts its bounds), where the route may go (the corridor,
    or None), how to tell a plan that meets a piece it was not made among (which it hands back at
    once: `services.planner.core.plan_within`) and the legs to plan from where the plans failed (step 5 of the
    module docstring; None before), taken from `seed_fn(coarse grid)` one at a time while plans from them
    fail; `timer(stage)` wraps the "corridor" and "fit" steps;
    `on_round(round, ellipses)` is told as each plan starts (a progress display: a building's plan may
    take several).
    """
    total = cover.tiles_shape[0] * cover.tiles_shape[1]
    with timer("corridor"):
        coarse_grid = CoarseGrid(cover.grid, cover.margin_m, settings.coarse_m, start=waypoints[0])
        coarse = coarse_grid.route(waypoints, slack=settings.slack)
    if coarse.status != "ok":
        plan = PathPlan("no_path", np.zeros((0, 2)), reason=coarse.reason)
        return CorridorPlan(plan, None, list(fixed), coarse, len(cover.fitted), total, 0)
    with timer("fit"):
        line = np.vstack([resample_polyline(coarse.points, max_spacing_m=0.5 * settings.coarse_m), coarse.corridor])
        tiles = cover.tiles_near(line, settings.band_m)
        fitted = _pieces(cover, tiles, waypoints)
        if cover.tighten(_doors_along(cover, coarse)):  # before the first plan: a closed door costs a round
            fitted = cover.pieces(tiles)
        used = [fitted[k] for k in sorted(_near(fitted, line, settings.near_m))]  # in the tiles' order
        keep_to = (_Corridor.of(coarse_grid, coarse, waypoints, keep_m=settings.keep_m)
                   if settings.keep_to_corridor else None)
    held: dict[int, tuple[FloatArray, list[GridPiece]]] = {}  # polylines held against the rest of the cover

    def reached_by(points: FloatArray) -> set[Tile]:
        """The tiles whose pieces a polyline may come within reach of."""
        return cover.tiles_near(resample_polyline(points, max_spacing_m=0.1), cover.reach_m + 0.1)

    def met_by(points: FloatArray, level: float) -> list[GridPiece]:
        """The fitted pieces not planned among that the polyline comes within `level` of, the tiles it
        comes near fitted first. Once per polyline: the pieces of tiles fitted later are beyond its reach."""
        nonlocal fitted
        if (known := held.get(id(points))) is not None and known[0] is points:
            return known[1]
        with timer("fit"):
            new = reached_by(points) - tiles
            if new:
                tiles.update(new)
                fitted = _pieces(cover, tiles, waypoints)
            planned = {id(piece) for piece in used}
            others = [piece for piece in fitted if id(piece) not in planned]
            hit = [others[k] for k in _entered(_grown_stack(others), points, level=level).tolist()]
        held[id(points)] = (points, hit)
        return hit

    def meets(plan: PathPlan, smoothed: Smoothed | None) -> list[GridPiece]:
        """The fitted pieces not planned among that the plan's points (at level 1) or its smoothed curve's
        samples (at `_CURVE_LEVEL`) come within."""
        hit = met_by(plan.points, 1.0)
        if smoothed is None:
            return hit
        return hit + [piece for piece in met_by(smoothed.points, _CURVE_LEVEL) if piece not in hit]

    plan, smoothed, grown = PathPlan("no_path", np.zeros((0, 2))), None, list(fixed)
    corridor, opened, tightened = keep_to, False, False
    seed: list[FloatArray] | None = None
    seeds: Iterator[list[FloatArray]] | None = None
    unseeded: tuple[PathPlan, Smoothed | None, list[Ellipse]] | None = None  # the answer before the seed
    for rounds in range(1, settings.max_rounds + 1):
        grown = list(fixed) + [used[k].grown for k in _uncovered(used)]
        if on_round is not None:
            on_round(rounds, len(grown))
        # A plan that meets a piece it was not made among is handed back at once (no other route or margin
        # is tried on too few ellipses), and planned again with it.
        plan, smoothed = plan_fn(grown, coarse.leg_lengths_m, keep_to, lambda p, s: bool(meets(p, s)), seed)
        if plan.status == "ok":
            # Held against the rest of the cover whether its curve verified or not: a plan that failed
            # among too few ellipses (a route through a wall mass no tile of which was fitted, with a turn
            # there the car cannot make) says nothing of the map until the ellipses it met are in.
            if hit := meets(plan, smoothed):
                # With the pieces it met, those near its path: the next plan, moved off these, meets them.
                planned = {id(piece) for piece in used + hit}
                others = [piece for piece in fitted if id(piece) not in planned]
                used += hit + [others[k] for k in sorted(_near(others, plan.points, settings.near_m))]
                continue
            if smoothed is not None and smoothed.verification.ok:
                break
        # No route among the ellipses, or none refined clear: the cover, up to its tolerance more
        # conservative than the grown walls, may close a gap the coarse route passes through clear of them.
        # Its pieces there are fitted again tighter, once, and the plan made again in the corridor (first:
        # without it the route would roam the map past the gap). A curve that failed among all it meets
        # may have been pushed by that excess where the path runs along walls (a start facing along a wall
        # bulging into its way, a turn round specks): once, the pieces the path comes within their own
        # tolerance of are fitted again tighter instead.
        no_route = plan.status == "no_path"
        if (no_route and not opened) or (not no_route and keep_to is None and not tightened):
            if no_route:
                opened = True
            else:
                tightened = True
            with timer("fit"):
                if (cover.tighten(_clear_along(cover, coarse)) if no_route
                        else cover.tighten(plan.points, near=True)):
                    fitted = cover.pieces(tiles)
                    used = _renewed(used, fitted, line, settings.near_m)
                    keep_to = corridor
                    continue
        if keep_to is None:
            # No route among some of the ellipses (so none among all), or a curve failed among all it meets:
            # the next path the car can drive, searched on the map, and the plans go on from it.
            if seed_fn is not None:
                seeds = seed_fn(coarse_grid) if seeds is None else seeds
                with timer("corridor"):
                    seed = next(seeds, None)
                if seed is not None:
                    unseeded = unseeded or (plan, smoothed, grown)
                    driven = joined_legs(seed)
                    with timer("fit"):
                        tiles.update(reached_by(driven))
                        cover.tighten(driven, near=True)
                        fitted = _pieces(cover, tiles, waypoints)
                        used = _renewed(used, fitted, driven, settings.band_m)
                    continue
            break
        keep_to = None  # the corridor may have closed a way (its cells are coarse): plan without it
    else:
        if plan.status == "ok" and meets(plan, smoothed):  # never a path through walls it was not planned among
            plan, smoothed = PathPlan("no_path", np.zeros((0, 2)), reason=(
                f"every one of {settings.max_rounds} plans met walls of the map it was not made among")), None
    if unseeded is not None and not (plan.status == "ok" and smoothed is not None and smoothed.verification.ok):
        plan, smoothed, grown = unseeded
    return CorridorPlan(plan, smoothed, grown, coarse, len(cover.fitted), total, rounds, keep_to is not None)


@dataclass(frozen=True)
class _Corridor:
    """Where the route may go: anywhere but the passable coarse cells off the corridor (widened by a coarse
    cell, and by a disc of `keep_m` round each waypoint: a route leaves its start along the heading before
    it turns) and beyond the coarse grid. Those are the open floor and the rooms beyond the corridor, which
    the ellipses the route is searched among (the walls near the corridor) do not close off; impassable
    cells are walls within the margin, whose own ellipses bound the route. A tangent segment that touches
    one of them is no edge of the route search (`services.planner.route.shortest_route`)."""

    grid: CoarseGrid
    off: np.ndarray  # coarse cells a segment may not touch, with a ring of them round the grid

    @classmethod
    def of(cls, coarse_grid: CoarseGrid, coarse: CoarseRoute, waypoints: FloatArray, *, keep_m: float) -> _Corridor:
        mask = ndimage.binary_dilation(coarse.cells, structure=np.ones((3, 3), dtype=bool))
        nr, nc = mask.shape
        rows, cols = np.mgrid[0:nr, 0:nc]
        g = coarse_grid.grid.to_grid(waypoints) / coarse_grid.s + 0.5  # centres' coordinates: cell + 0.5 − ring
        radius = keep_m / coarse_grid.s
        for gx, gy in g:
            mask |= (cols - gx) ** 2 + (rows - gy) ** 2 <= radius**2
        return cls(coarse_grid, np.pad(coarse_grid.passable & ~mask, 1, constant_values=True))

    def __call__(self, starts: FloatArray, ends: FloatArray) -> np.ndarray:
        """Whether each segment keeps off the cells it may not touch, sighted at points half a coarse cell
        apart (it confines the search; what the path touches is checked exactly afterwards)."""
        if not len(starts):
            return np.zeros(0, dtype=bool)
        s = self.grid.s
        p = self.grid.grid.to_grid(starts) / s + 2.0  # coarse cells, counting the grid's ring and ours
        d = self.grid.grid.to_grid(ends) / s + 2.0 - p
        n = np.ceil(2.0 * np.max(np.abs(d), axis=1)).astype(np.intp) + 1
        offsets = np.cumsum(n) - n
        owner = np.repeat(np.arange(len(n)), n)
        t = (np.arange(len(owner)) - offsets[owner]) / np.maximum(n[owner] - 1, 1)
        c = np.floor(p[owner] + t[:, None] * d[owner]).astype(np.intp)
        rows, cols = self.off.shape
        c[:, 0], c[:, 1] = np.clip(c[:, 0], 0, cols - 1), np.clip(c[:, 1], 0, rows - 1)
        return ~np.logical_or.reduceat(self.off[c[:, 1], c[:, 0]], offsets)


def _pieces(cover: GridCover, tiles: set, waypoints: FloatArray) -> list[GridPiece]:
    """The tiles' pieces, those holding the start or a goal refitted tighter first (`GridCover.tighten`)."""
    fitted = cover.pieces(tiles)
    return cover.pieces(tiles) if cover.tighten(waypoints) else fitted


def _clear_along(cover: GridCover, coarse: CoarseRoute) -> FloatArray:
    """The coarse route's points, 5 cm apart, that are at least the margin from every blocked cell."""
    points = resample_polyline(coarse.points, max_spacing_m=0.05)
    return points[cover.grid.clearance(points) >= cover.margin_m]


_ACROSS = np.linspace(-1.0, 1.0, 9)  # where a passage is sampled across the route (`_doors_along`)


def _doors_along(cover: GridCover, coarse: CoarseRoute) -> FloatArray:
    """The clearest points of passages the coarse route runs through that the cover's tolerance may close.

    At each of the route's points, 10 cm apart, that are less than the margin plus the tolerance from a
    blocked cell, the clearance (as the cover's distance transforms read it, within a cell) is sampled
    across the route, out to the tolerance, two cells and the route's shortfall below the margin on
    either side (a route along one wall finds the margin plus the tolerance on its other side): where no
    sample is the margin plus the tolerance clear, the passage is narrower than that on both sides (a
    door, not a corner), and its clearest sample, if it may be the margin clear (read within a cell of
    it), is where the cover may close it."""
    points = resample_polyline(coarse.points, max_spacing_m=0.1)
    if len(points) < 2:
        return np.zeros((0, 2))
    margin, tolerance = cover.margin_m, cover.settings.tolerance_m
    clear = cover.distance_at(points)
    step = np.gradient(points, axis=0)
    normal = np.column_stack([-step[:, 1], step[:, 0]]) / np.maximum(np.linalg.norm(step, axis=1), 1e-12)[:, None]
    near = np.flatnonzero((clear > 0.0) & (clear < margin + tolerance))
    reach = tolerance + 2.0 * cover.grid.resolution_m + np.maximum(margin - clear[near], 0.0)
    across = points[near, None, :] + (reach[:, None] * _ACROSS)[:, :, None] * normal[near, None, :]
    sampled = cover.distance_at(across.reshape(-1, 2)).reshape(len(near), len(_ACROSS))
    widest = np.argmax(sampled, axis=1)
    best = sampled[np.arange(len(near)), widest]
    door = (best >= margin - cover.grid.resolution_m) & (best < margin + tolerance)
    return across[np.flatnonzero(door), widest[door]]


def _renewed(used: list[GridPiece], fitted: list[GridPiece], line: FloatArray, near_m: float) -> list[GridPiece]:
    """The pieces planned among once some were fitted again: those still in the cover, then the fitted
    ones near the corridor not among them (the new pieces where the old were)."""
    present = {id(piece) for piece in fitted}
    kept = [piece for piece in used if id(piece) in present]
    have = {id(piece) for piece in kept}
    return kept + [fitted[k] for k in sorted(_near(fitted, line, near_m)) if id(fitted[k]) not in have]


def _uncovered(pieces: list[GridPiece], *, samples: int = 64) -> list[int]:
    """The pieces whose grown ellipse lies in no other's (the others' union is the same without them, so
    a route among them is one among all): a walls' cover overlaps itself, and specks lie in their walls'.

    Gᵢ ⊆ Gⱼ when ‖Aⱼ x + bⱼ‖ ≤ 1 all round Gᵢ's boundary x(θ) = cᵢ + Lᵢ u(θ) (Lᵢ = Aᵢ⁻¹): that level is
    ‖M u(θ) + d‖ with M = Aⱼ Lᵢ, whose derivative in θ is at most ‖M‖₂, so it is at most its largest value
    at `samples` evenly spaced angles plus ‖M‖_F π / samples, which is required to be ≤ 1. Of two equal
    ellipses the later is the one dropped, and a dropped one's container is kept or is itself inside a
    larger one that is.
    """
    if len(pieces) < 2:
        return list(range(len(pieces)))
    A = np.array([p.grown_Ab[:, :2] for p in pieces])
    b = np.array([p.grown_Ab[:, 2] for p in pieces])
    stack = EllipseStack(A=A, b=b)
    centre, (major, minor) = stack.centers, stack.semi_axes.T
    area = major * minor
    # Candidates: a container reaches past the other's centre by at least its minor semi-axis.
    tree = cKDTree(centre)
    lists = tree.query_ball_point(centre, r=np.maximum(major.max() - minor, 0.0))
    i = np.repeat(np.arange(len(pieces)), [len(x) for x in lists])
    j = np.concatenate([np.asarray(x, dtype=np.intp) for x in lists])
    gap = np.linalg.norm(centre[i] - centre[j], axis=1)
    keep = (i != j) & (gap <= major[j] - minor[i]) & ((area[j] > area[i]) | ((area[j] == area[i]) & (j < i)))
    i, j = i[keep], j[keep]
    if not len(i):
        return list(range(len(pieces)))
    L = np.linalg.inv(A[i])
    M = np.einsum("kab,kbc->kac", A[j], L)
    d = np.einsum("kab,kb->ka", A[j], centre[i]) + b[j]
    theta = 2.0 * np.pi * np.arange(samples) / samples
    u = np.stack([np.cos(theta), np.sin(theta)])  # (2, samples)
    level = np.linalg.norm(np.einsum("kab,bs->kas", M, u) + d[:, :, None], axis=1).max(axis=1)
    inside = level + np.sqrt(np.einsum("kab,kab->k", M, M)) * np.pi / samples <= 1.0
    dropped = np.zeros(len(pieces), dtype=bool)
    dropped[i[inside]] = True
    return np.flatnonzero(~dropped).tolist()


def _grown_stack(pieces: list[GridPiece]) -> EllipseStack:
    """The pieces' grown ellipses stacked from their arrays, A made symmetric as `Ellipse` makes it (the
    same stack as `EllipseStack.of` their `grown`, without making an `Ellipse` of each)."""
    Ab = np.array([p.grown_Ab for p in pieces]).reshape(-1, 2, 3)
    A = Ab[:, :, :2]
    return EllipseStack(A=0.5 * (A + A.transpose(0, 2, 1)), b=np.ascontiguousarray(Ab[:, :, 2]))


def _near(pieces: list[GridPiece], line: FloatArray, distance_m: float) -> set[int]:
    """The pieces whose grown ellipse may come within `distance_m` of one of the points: those with a
    point z where neither lower bound on its distance to the ellipse exceeds it, the bounding disc's
    (‖z − c‖ − reach) nor the level's ((‖A z + b‖ − 1) × the smallest semi-axis, since ‖A‖ is its
    inverse)."""
    if not pieces:
        return set()
    stack = _grown_stack(pieces)
    tree = cKDTree(line)
    lists = tree.query_ball_point(stack.centers, r=stack.reach + distance_m)
    counts = np.fromiter(map(len, lists), dtype=int, count=len(lists))
    cols = np.repeat(np.arange(len(stack)), counts)
    points = line[np.fromiter(chain.from_iterable(lists), dtype=int, count=int(counts.sum()))]
    u = np.einsum("kij,kj->ki", stack.A[cols], points) + stack.b[cols]
    gap = (np.linalg.norm(u, axis=1) - 1.0) * stack.semi_axes[cols, 1]
    return set(np.unique(cols[gap <= distance_m]).tolist())


def _entered(stack: EllipseStack, path: FloatArray, *, level: float) -> IntArray:
    """Indices of the ellipses some segment of the polyline comes within `level` of (eq. 2, exact)."""
    if not len(stack) or len(path) < 2:
        return np.zeros(0, dtype=np.intp)
    _, cols, levels = stack.segment_pairs(path[:-1], path[1:])
    return np.unique(cols[levels < level])
