"""The ellipsoid stage core: Clusters → Ellipsoids (fit, split, group, grow).

Each cluster is covered by a few tight ellipses, tile by tile of a fixed grid (`tiles`, `tiled_cover`:
pieces split across the middle of fixed cells, so they stay put as points are added), the ellipses
whose gap is narrower than the robot's passage 2·inflation are grouped (the paper's eq. 3), and every
ellipse is grown by inflation = width/2 + safety_distance so the planner can treat the robot as a point:
of the growths that contain the fit ⊕ disc(inflation), the one that strays least beyond the inflation
from the cluster's points in and near the tile, a piece split where even that strays more than the
tolerance (`grown_cover`; the least-area growth of a wall is √2·inflation wide, and a door's jambs
closed a door with 0.2 m to spare).

Covers, and the grown ellipses, are cached by content, a cluster's and each of its tiles': the sensing
stage sends unchanged clusters byte-identical, and a cluster that grew has new points in a few tiles
only, so only those tiles are covered again, and within them only the cells that gained a point are
refitted (an earlier fit is kept where it is still exact, `tiled_cover`); an ellipse kept that way
keeps its grown ellipse and its gap samples too. What that costs: a cluster cut by tile edges has an
ellipse or so more per tile it spans.

A Clusters message holds at most as many points as the sensing stage remembers, all within the
sensor's reach of the map (``services.limits``). Degenerate clusters (one point, all points equal,
collinear: a wall seen edge-on) are real obstacles and are covered like any other.

A known map (``Map``, a robot's /map from the ROS 2 bridge) adds its walls: the wall cover of the grid
(`services.ellipsoids.grid_cover`, the cover `cvxnav plan` plans on a map with), fitted tile by tile
as the robot comes near, and every grown ellipse of it within `EllipsoidsConfig.map_window_m` of the
robot (the newest ``RobotState``) goes out with the sensed ones as one more cluster (`MAP_CLUSTER_ID`:
the building is one obstacle, so grouping examines only pairs of a wall and a sensed obstacle, and a
sensed one closer to a wall than the robot's passage joins the walls' group). So the planner, the
smoother and the path guard keep the margin from the map's walls as from sensed obstacles, with no
change of theirs; beyond the window the plan is what it is beyond a scan's reach, replanned as the
robot comes nearer. A new map replaces the cover; the ellipses sent are at most `MAX_ELLIPSES`, the
walls nearest the robot first.

The stage reads the goals (the scenario's, then each ``Goals``; those the newest state says are reached
no longer count): a sensed piece or a map's piece whose growth holds a goal ahead is fitted again
tighter until none does (`_goals_freed`, `GridCover.tighten`), so a goal a centimetre or two beyond the
margin from a wall can be planned to, as `cvxnav plan` plans to it.
"""

from __future__ import annotations

import hashlib
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from pydantic import BaseModel
from scipy.spatial import cKDTree

from schemas.messages import Clusters, Ellipsoids, Goals, Map, RobotState
from schemas.occupancy import MapError
from schemas.scenario import Scenario
from services.contract import Outputs, StageInputError
from services.convert import answer_header, ellipse_to_msg, grid_from_msg
from services.ellipsoids.cover import Cell, Piece, grown_cover, tiled_cover, tiles
from services.ellipsoids.gap import gap_samples, group_ellipses
from services.ellipsoids.grid_cover import GridCover, GridPiece
from services.geometry import Ellipse, EllipseStack
from services.limits import MAX_ELLIPSES, MAX_SENSED_POINTS, Reach, check_count

MAP_CLUSTER_ID = -1  # the cluster of a known map's walls (the sensing stage's ids count from 0)
_HALO_M = 1.0  # a tile's pieces are grown judged against the cluster's points this far round it too
_TIGHTER_M = (0.05, 0.025, 0.0125)  # tolerances an ellipse holding a goal is refitted at in turn
_GOAL_LEVEL_MARGIN = 0.02  # ... until every goal is at least at this level above 1 (the planner's start margin)


@dataclass(frozen=True)
class EllipsoidsConfig:
    inflation_m: float  # width/2 + safety_distance: how much each fitted ellipse is grown
    reach: Reach
    max_points: int = MAX_SENSED_POINTS  # over all clusters of one message
    tolerance_m: float = 0.1  # how far a fitted ellipse may stick out of its points
    max_pieces: int = 32  # ellipses per cluster and tile at most
    tile_m: float = 4.0  # a cluster is covered tile by tile of this fixed grid: new points refit their tiles only
    cache_size: int = 4096  # clusters' and tiles' covers remembered
    # A known map's walls within this of the robot join the sensed obstacles: the plan near the robot
    # keeps clear of them. Each metre more costs the planner (docs/ros2.md: on ACES, 100 ellipses and a
    # planner p50 of 230 ms at 5 m; 250 and 900 ms at 10 m).
    map_window_m: float = 5.0

    @property
    def min_gap_m(self) -> float:
        """Ellipses closer than the robot's passage width are one obstacle to the planner."""
        return 2.0 * self.inflation_m

    @classmethod
    def from_scenario(cls, scenario: Scenario) -> EllipsoidsConfig:
        return cls(inflation_m=scenario.inflation_m, reach=Reach.of(scenario),
                   map_window_m=min(cls.map_window_m, float(scenario.sensor.range)))


@dataclass(frozen=True)
class _Fitted:
    """One ellipse of a cluster's cover, grown, and the samples grouping bounds its gaps with; `leaf`: the
    tiled cover's piece it was made from (itself, or one its growth split: `grown_cover`); `points`: the
    sensed points its fit covers (none for a map's wall)."""

    ellipse: Ellipse
    grown: Ellipse
    samples: np.ndarray
    leaf: Ellipse
    points: np.ndarray


_Cover = tuple[list[Piece], list[_Fitted]]  # a cover's split trees and its ellipses, fitted


class EllipsoidsStage:
    def __init__(self, *, config: EllipsoidsConfig, goals: np.ndarray | None = None) -> None:
        self.config = config
        # The goals (the scenario's, or the newest ``Goals``) and how many the robot has reached: an
        # ellipse holding one ahead is fitted tighter (`_goals_freed`).
        self.goals = np.zeros((0, 2)) if goals is None else np.asarray(goals, dtype=float).reshape(-1, 2)
        self.goals_reached = 0
        # The last message's refits for the goals, by the ellipse refitted: (it, the goals, its refit).
        self._freed: dict[int, tuple[_Fitted, bytes, list[_Fitted]]] = {}
        self._fits: OrderedDict[bytes, _Cover] = OrderedDict()  # a cluster's or a tile's cover, by content
        # The previous message's covers: their pieces (by cell) and their ellipses (by identity).
        self._cells: dict[Cell, list[Piece]] = {}
        self._fitted: dict[int, list[_Fitted]] = {}  # by the id of their leaf
        self._seq = 0
        self.map: GridCover | None = None  # a known map's wall cover
        self._map_message: Map | None = None  # ... and the message it came in
        self._map_fits: dict[int, _Fitted] = {}  # by piece
        # Every fitted piece's fit, centre and reach, as of a count of fitted tiles (the cover only grows).
        self._map_index: tuple[int, list[_Fitted], np.ndarray, np.ndarray] | None = None
        self._map_tightened_for: tuple[int, bytes] | None = None  # the tile count and goals last tightened for
        self.position: np.ndarray | None = None  # the robot's, from the newest state

    @classmethod
    def from_scenario(cls, scenario: Scenario) -> EllipsoidsStage:
        return cls(config=EllipsoidsConfig.from_scenario(scenario), goals=scenario.goals_array)

    def _cover(self, points: np.ndarray, *, cells: dict[Cell, list[Piece]]) -> list[_Fitted]:
        """A cluster's cover, tile by tile, each cached by its points' content (the cluster's too: most
        clusters are unchanged from one message to the next); its split trees go into `cells`."""
        roots, fitted = self._cached(b"cluster" + points.tobytes(), lambda: self._tiled(points))
        stack = list(roots)
        while stack:
            node = stack.pop()
            cells.setdefault(node.cell, []).append(node)
            stack.extend(node.children)
        return fitted

    def _tiled(self, points: np.ndarray) -> tuple[list[Piece], list[_Fitted]]:
        """A cluster's cover tile by tile, each cached by the content of its points and of the cluster's
        points within `_HALO_M` of it, which its pieces' growths are judged against (`grown_cover`: a wall
        runs on past the tile's edge, and a growth's tip along it is no excess)."""
        roots: list[Piece] = []
        fitted: list[_Fitted] = []
        for cell, tile_points in tiles(points, tile_m=self.config.tile_m):
            x0, y0, x1, y1 = cell
            h = _HALO_M
            near = points[(points[:, 0] >= x0 - h) & (points[:, 0] < x1 + h)
                          & (points[:, 1] >= y0 - h) & (points[:, 1] < y1 + h)]
            key = b"tile" + np.array(cell).tobytes() + near.tobytes()  # its points: the near ones in the cell
            tile_roots, tile_fitted = self._cached(key, lambda: self._tile(tile_points, near=near, cell=cell))
            roots.extend(tile_roots)
            fitted.extend(tile_fitted)
        return roots, fitted

    def _tile(self, points: np.ndarray, *, near: np.ndarray, cell: Cell) -> tuple[list[Piece], list[_Fitted]]:
        cover = tiled_cover(points, cell=cell, previous=self._cells, tolerance_m=self.config.tolerance_m,
                            max_pieces=self.config.max_pieces)
        tree = cKDTree(near)
        return [cover.root], [fitted for piece in cover.pieces for fitted in self._fit(piece, near=tree)]

    def _cached(self, key: bytes, make: Callable[[], _Cover]) -> _Cover:
        """The cover cached under `key` (a cluster's, or a tile's: they are told apart by a tag), else made."""
        digest = hashlib.blake2b(key, digest_size=16).digest()
        if digest in self._fits:
            self._fits.move_to_end(digest)
            return self._fits[digest]
        self._fits[digest] = made = make()
        while len(self._fits) > self.config.cache_size:
            self._fits.popitem(last=False)
        return made

    def _fit(self, piece: Piece, *, near: cKDTree) -> list[_Fitted]:
        """A piece's ellipses, grown to stray at most the tolerance beyond the margin from the points in and
        near its tile (`near`) where they can (`grown_cover`); the previous message's, if it is that piece."""
        known = self._fitted.get(id(piece.ellipse))
        if known is not None and known[0].leaf is piece.ellipse:
            return known
        return self._fitted_of(piece.points, piece.ellipse, leaf=piece.ellipse, near=near,
                               tolerance_m=self.config.tolerance_m)

    def _fitted_of(self, points: np.ndarray, fit: Ellipse, *, leaf: Ellipse, near: cKDTree,
                   tolerance_m: float) -> list[_Fitted]:
        made = grown_cover(points, fit, self.config.inflation_m, near, tolerance_m=tolerance_m)
        return [_Fitted(ellipse=part_fit, grown=grown, samples=gap_samples(part_fit), leaf=leaf, points=part)
                for part, part_fit, grown in made]

    def _goals_freed(self, fitted: list[_Fitted], cluster_ids: list[int]) -> tuple[list[_Fitted], list[int]]:
        """The sensed ellipses with those whose growth holds a goal ahead fitted again, to each of
        `_TIGHTER_M` in turn, until none of theirs does (each judged against its own points).

        A goal set a centimetre or two beyond the margin from a wall lies within the tolerance the growths
        may stray beyond it, and no plan can end inside an ellipse; `cvxnav plan` refits the map's pieces
        there (`GridCover.tighten`), and so does this stage the sensed ones. A goal truly within the
        margin of a sensed point stays inside at every tolerance.
        """
        goals = self.goals[self.goals_reached:]
        if not len(goals) or not fitted:
            return fitted, cluster_ids
        grown = EllipseStack.of([f.grown for f in fitted])
        holding = set(np.flatnonzero(np.any(grown.levels(goals) <= 1.0 + _GOAL_LEVEL_MARGIN, axis=0)).tolist())
        if not holding:
            return fitted, cluster_ids
        key = goals.tobytes()
        out, ids, freed = [], [], {}
        for k, (f, cid) in enumerate(zip(fitted, cluster_ids)):
            made = [f]
            if k in holding and len(f.points):
                known = self._freed.get(id(f))
                if known is not None and known[0] is f and known[1] == key:
                    made = known[2]
                else:
                    near = cKDTree(f.points)
                    for tolerance in _TIGHTER_M:
                        made = self._fitted_of(f.points, f.ellipse, leaf=f.leaf, near=near, tolerance_m=tolerance)
                        if EllipseStack.of([m.grown for m in made]).levels(goals).min() > 1.0 + _GOAL_LEVEL_MARGIN:
                            break
                freed[id(f)] = (f, key, made)
            out += made
            ids += [cid] * len(made)
        self._freed = freed
        return out, ids

    def _take_map(self, message: Map) -> None:
        """A new map: its wall cover replaces the old one, fitted as the robot comes near. The same map
        again (the bridge sends it to a stage that comes back) keeps the cover fitted so far."""
        same = ("width", "height", "resolution_m", "origin", "cells")
        if self._map_message is not None and all(getattr(message, f) == getattr(self._map_message, f) for f in same):
            return
        try:
            grid = grid_from_msg(message)
        except MapError as error:
            raise StageInputError(f"map: {error}") from None
        reach = self.config.reach
        lo, hi = grid.bounds()
        if np.any(hi < reach.bounds_min - reach.margin_m) or np.any(lo > reach.bounds_max + reach.margin_m):
            raise StageInputError(f"map: its extent ({lo[0]:.6g}, {lo[1]:.6g}) to ({hi[0]:.6g}, {hi[1]:.6g}) lies "
                                  f"more than {reach.margin_m:g} m outside the map bounds")
        self._map_message = message
        self.map, self._map_fits, self._map_index = GridCover(grid, margin_m=self.config.inflation_m), {}, None
        self._map_tightened_for = None

    def _map_walls(self, *, room: int) -> list[_Fitted]:
        """The map's wall ellipses whose grown ellipse comes within the window of the robot, nearest first,
        at most ``room``. Every fitted piece is a candidate, not only those kept under the tiles near the
        robot: a piece fitted with its neighbours' block is kept under the tile of its first cell, which
        may lie farther off than the wall it reaches."""
        if self.map is None or self.position is None:
            return []
        window = self.config.map_window_m
        self.map.pieces(self.map.tiles_near(self.position[None, :], window + self.map.reach_m))
        # The pieces holding a goal ahead fitted tighter (`GridCover.tighten`), once per set of tiles and goals.
        goals = self.goals[self.goals_reached:]
        tightened_for = (len(self.map.fitted), goals.tobytes())
        if len(goals) and tightened_for != self._map_tightened_for:
            self._map_tightened_for = tightened_for
            if self.map.tighten(goals):
                self._map_index = None
        if self._map_index is None or self._map_index[0] != len(self.map.fitted):
            fits = [self._map_fit(piece) for tile in self.map.fitted.values() for piece in tile]
            centres = np.array([f.grown.center for f in fits]).reshape(-1, 2)
            reach = np.array([f.grown.semi_axes[0] for f in fits])
            self._map_index = (len(self.map.fitted), fits, centres, reach)
        _, fits, centres, reach = self._map_index
        gap = np.linalg.norm(centres - self.position, axis=1) - reach
        near = np.flatnonzero(gap <= window)
        return [fits[k] for k in near[np.argsort(gap[near], kind="stable")][:room]]

    def _map_fit(self, piece: GridPiece) -> _Fitted:
        known = self._map_fits.get(id(piece))
        if known is None:
            known = _Fitted(ellipse=piece.raw, grown=piece.grown, samples=gap_samples(piece.raw), leaf=piece.raw,
                            points=np.zeros((0, 2)))
            self._map_fits[id(piece)] = known
        return known

    def process(self, *, topic: str, message: BaseModel, now_s: float) -> Outputs:
        if isinstance(message, Map):
            self._take_map(message)
            return []
        if isinstance(message, RobotState):
            self.config.reach.check_pose(message.pose, what="state")
            self.position = np.array([message.pose.x_m, message.pose.y_m])
            self.goals_reached = message.goals_reached
            return []
        if isinstance(message, Goals):
            goals = np.asarray(message.goals, dtype=float).reshape(-1, 2)
            self.config.reach.check_goals(goals, what="goals")
            self.goals, self.goals_reached = goals, 0
            return []
        if not isinstance(message, Clusters):
            raise StageInputError(f"ellipsoids does not handle {topic!r}")
        check_count(sum(len(c.points) for c in message.clusters), limit=self.config.max_points,
                    what="cluster points")
        clouds = []
        for cluster in message.clusters:
            if not cluster.points:  # the schema forbids it; a hand-built message may not
                raise StageInputError(f"cluster {cluster.cluster_id} has no points")
            points = np.asarray(cluster.points, dtype=float).reshape(-1, 2)
            self.config.reach.check_points(points, what=f"cluster {cluster.cluster_id}")
            clouds.append((cluster.cluster_id, points))
        fitted: list[_Fitted] = []
        cluster_ids: list[int] = []
        cells: dict[Cell, list[Piece]] = {}
        for cluster_id, points in clouds:
            cover = self._cover(points, cells=cells)
            fitted.extend(cover)
            cluster_ids.extend([cluster_id] * len(cover))
        self._cells = cells
        self._fitted = {}
        for f in fitted:
            self._fitted.setdefault(id(f.leaf), []).append(f)
        fitted, cluster_ids = self._goals_freed(fitted, cluster_ids)
        walls = self._map_walls(room=MAX_ELLIPSES - len(fitted))
        fitted.extend(walls)
        cluster_ids.extend([MAP_CLUSTER_ID] * len(walls))
        # A cluster is one obstacle, so its pieces share a group from the start (the default sensing
        # links points closer than r, so adjacent pieces are closer than the passage 2 r anyway); only
        # pairs across clusters are examined.
        labels = group_ellipses([f.ellipse for f in fitted], min_gap_m=self.config.min_gap_m,
                                connected=np.array(cluster_ids, dtype=int), samples=[f.samples for f in fitted])
        out = Ellipsoids(
            header=answer_header(scan_header=message.header, seq=self._seq),
            scan_seq=message.scan_seq,
            inflation_m=self.config.inflation_m,
            ellipsoids=[
                ellipse_to_msg(f.grown, group=int(label), cluster_id=cid)
                for f, label, cid in zip(fitted, labels, cluster_ids)
            ],
        )
        self._seq += 1
        return [("ellipsoids", out)]
