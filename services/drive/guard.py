"""The car's own check of every path before it drives on it: on the map, clear of what it sensed itself,
and clear of the obstacles the pipeline fitted.

The smoother verifies each curve against the ellipses the planner used, but that is the pipeline
checking itself, and on an open network any message could be forged. The guard holds three checks,
each at the run's hard floor, and a path that fails any of them is not driven (the car brakes, and the
reason names what and where):

1. The map's bounds (`bounds_min`, `bounds_max`): the centre line keeps `keep_out_m` inside them, as
   from a wall (the sim ends a run whose footprint leaves the map). Exact on the polyline: the depth
   inside a box is concave along a segment, so its least is at a vertex.
2. The car's own scan hits (`sense`): the centre line, on each continuous segment, keeps `keep_out_m`
   from every hit remembered. Remembered spatially, not for a time: one point per voxel (the first),
   the least recently seen dropped beyond `max_hits` (`services.geometry.PointMemory`, as the sensing
   stage remembers them), so an obstacle seen earlier and now behind the car still counts. A k-d tree
   over them answers each check with the few hits near the path (a small tree of the newest hits is
   rebuilt as they come, merged into the big one once it holds a quarter as many).
3. The newest grown ellipses the ellipsoid stage published (`know`), segment by segment with the
   paper's eq. (2) on the continuous segment (`EllipseStack.segment_pairs`).

No message moves checks 1 and 2: the bounds come from the map the run was given and the hits from the
car's own sensor. A forged ellipsoid set (even an empty one) or a forged path cannot take the car
closer to anything it has sensed than the floor, nor off the map.

The hard floor is `Scenario.keep_out_m` (half the footprint's diagonal plus half the safety distance:
the footprint keeps half the safety distance clear in any heading; never above the plan's full margin,
or the guard would refuse the planner's own clear plans), not the planner's margins. For the
ellipses, a grown ellipse scaled about its centre by `keep_out_scales` still contains its fit grown by
`keep_out_m`. The planner keeps the full margin wherever it can and gives it up down to that floor only
near a car that newly grown covers have boxed in (`services.planner.stage.relieved_scales`). Every fit
contains the points of its cluster, so a path the planner verified keeps `keep_out_m` from every hit
the sensing stage remembers, which are the hits the guard remembers (same voxels, same first points).

The robot may even be deeper than a floor already (a fit sticks out of a newly seen obstacle, an
obstacle first seen close by): the planner shrinks any ellipse the start is inside just enough to leave
it at level 1.02 (`free_start_scales`), so its path may run no deeper than level(start) / 1.02, and the
guard allows down to level(start) / (1 + START_SLACK) where that is deeper than the floor; likewise down
to the start's own distance to a hit or depth inside the bounds, divided by (1 + START_SLACK). With
START_SLACK above the planner's 0.02 it never rejects a path the planner verified, and still rejects one
that goes deeper towards an obstacle than the robot already is.

LEVEL_TOL absorbs the chords between the smoothed curve's samples (0.05 m apart: they stray from the
curve by κ s² / 8 ≈ 1e-4 m, below 2e-4 in level for the paper's car). DISTANCE_TOL_M is the same
tolerance in metres for the hits and the bounds: LEVEL_TOL at a grown ellipse's largest semi-axes
(a few metres) is a few millimetres.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike
from scipy.spatial import cKDTree

from schemas.messages import Ellipsoids
from schemas.scenario import Scenario
from services.geometry import EllipseStack, FloatArray, PointMemory, keep_out_scales
from services.limits import MAX_SENSED_POINTS

START_SLACK = 0.03
LEVEL_TOL = 1e-3
DISTANCE_TOL_M = 0.01
_MERGE_FRACTION = 0.25  # the newest hits' tree is merged into the big one once it holds this share of it
_MERGE_MIN = 512  # ... or this many, whichever is more


def ahead(points: ArrayLike, *, position: ArrayLike) -> FloatArray:
    """The part of a polyline from the robot's projection onto it to its end (the part still to drive)."""
    z = np.asarray(points, dtype=float).reshape(-1, 2)
    p = np.asarray(position, dtype=float)
    if len(z) < 2:
        return z
    a, e = z[:-1], z[1:] - z[:-1]
    ee = np.maximum(np.einsum("ij,ij->i", e, e), 1e-18)
    u = np.clip(np.einsum("ij,ij->i", p - a, e) / ee, 0.0, 1.0)
    foot = a + u[:, None] * e
    k = int(np.argmin(np.linalg.norm(foot - p, axis=1)))
    return np.vstack([foot[k], z[k + 1:]])


class _Hits:
    """The remembered hits as two k-d trees: all of them as of the last merge, and the newest since."""

    def __init__(self, *, max_points: int) -> None:
        self.memory = PointMemory(max_points=max_points)
        self._old = np.zeros((0, 2))
        self._old_tree: cKDTree | None = None
        self._new: list[FloatArray] = []
        self._new_tree: cKDTree | None = None
        self._forgotten = 0  # the memory's count when the big tree was built

    def __len__(self) -> int:
        return len(self.memory)

    def add(self, points: ArrayLike) -> None:
        added = self.memory.remember(points)
        if len(added):
            self._new.append(added)
            self._new_tree = None

    def trees(self) -> list[tuple[FloatArray, cKDTree]]:
        """(points, tree) pairs that together hold exactly the remembered hits."""
        pending = sum(len(chunk) for chunk in self._new)
        if self.memory.forgotten != self._forgotten or pending > max(_MERGE_MIN, _MERGE_FRACTION * len(self._old)):
            self._old = self.memory.points()  # some were forgotten (the tree must drop them), or many are new
            self._old_tree = cKDTree(self._old) if len(self._old) else None
            self._new, self._new_tree, self._forgotten = [], None, self.memory.forgotten
        out = [(self._old, self._old_tree)] if self._old_tree is not None else []
        if self._new:
            if self._new_tree is None:
                self._new = [np.concatenate(self._new)]
                self._new_tree = cKDTree(self._new[0])
            out.append((self._new[0], self._new_tree))
        return out


class PathGuard:
    """The map's bounds, the car's own remembered hits and the newest grown ellipses; the check of a path
    against all three."""

    def __init__(self, *, inflation_m: float, keep_out_m: float, bounds_min: ArrayLike | None = None,
                 bounds_max: ArrayLike | None = None, max_hits: int = MAX_SENSED_POINTS) -> None:
        self.inflation_m = inflation_m  # the scenario's: how much the ellipses were grown from their fits
        self.keep_out_m = keep_out_m
        self.bounds_min = None if bounds_min is None else np.asarray(bounds_min, dtype=float)
        self.bounds_max = None if bounds_max is None else np.asarray(bounds_max, dtype=float)
        self.hits = _Hits(max_points=max_hits)
        self.stack = EllipseStack.of([])
        self.hard = np.ones(0)  # per ellipse, the scale of its hard floor (level ≥ this)
        self.cluster_ids: list[int] = []
        self.scan_seq = -1  # the scan the known ellipses answer; -1: none yet

    @classmethod
    def from_scenario(cls, scenario: Scenario) -> PathGuard:
        return cls(inflation_m=scenario.inflation_m, keep_out_m=scenario.keep_out_m, bounds_min=scenario.bounds.min,
                   bounds_max=scenario.bounds.max)

    def sense(self, hits: ArrayLike) -> None:
        """Remember the car's own scan hits, in the map frame."""
        self.hits.add(hits)

    def know(self, message: Ellipsoids) -> None:
        """Take newer ellipses (an older message, delivered late, is ignored)."""
        if message.scan_seq < self.scan_seq:
            return
        self.scan_seq = message.scan_seq
        if message.ellipsoids:
            self.stack = EllipseStack(A=np.array([e.A for e in message.ellipsoids], dtype=float),
                                      b=np.array([e.b for e in message.ellipsoids], dtype=float))
        else:
            self.stack = EllipseStack.of([])
        self.cluster_ids = [e.cluster_id for e in message.ellipsoids]
        self.hard = keep_out_scales(self.stack.semi_axes, inflation_m=self.inflation_m, keep_m=self.keep_out_m)

    def check(self, points: ArrayLike, *, start: ArrayLike) -> str | None:
        """Why the polyline `points`, driven from `start`, may not be driven (off the map, too close to a hit,
        into a known ellipse); None if it may."""
        z = np.asarray(points, dtype=float).reshape(-1, 2)
        if len(z) == 0:
            return None
        start = np.asarray(start, dtype=float)
        return self._off_map(z, start) or self._near_hit(z, start) or self._in_ellipse(z, start)

    def _floor(self, start_m: FloatArray | float) -> FloatArray | float:
        """The least distance allowed, from the start's own (deeper than the floor: START_SLACK deeper still)."""
        return np.minimum(self.keep_out_m, np.asarray(start_m) / (1.0 + START_SLACK)) - DISTANCE_TOL_M

    def _off_map(self, z: FloatArray, start: FloatArray) -> str | None:
        if self.bounds_min is None or self.bounds_max is None:
            return None
        depth = np.minimum(z - self.bounds_min, self.bounds_max - z).min(axis=1)  # < 0 outside
        floor = float(self._floor(np.minimum(start - self.bounds_min, self.bounds_max - start).min()))
        worst = int(np.argmin(depth))
        if depth[worst] >= floor:
            return None
        (x, y), (x0, y0), (x1, y1) = z[worst], self.bounds_min, self.bounds_max
        where = "outside" if depth[worst] < 0.0 else f"{depth[worst]:.3f} m inside (< {floor + DISTANCE_TOL_M:.3f})"
        return f"the path leaves the map: ({x:.2f}, {y:.2f}) is {where} its bounds ({x0:g}, {y0:g})..({x1:g}, {y1:g})"

    def _near_hit(self, z: FloatArray, start: FloatArray) -> str | None:
        if len(z) < 2 or len(self.hits) == 0:
            return None
        a, e = z[:-1], z[1:] - z[:-1]
        half = 0.5 * np.linalg.norm(e, axis=1)
        ee = np.maximum(np.einsum("ij,ij->i", e, e), 1e-18)
        worst: tuple[float, float, FloatArray, FloatArray] | None = None  # (depth, floor, hit, nearest point)
        mid, reach = a + 0.5 * e, self.keep_out_m + half
        for hits, tree in self.hits.trees():
            # Most segments have no hit within reach: the nearest one says so in one vectorised query.
            nearest_m, _ = tree.query(mid, distance_upper_bound=float(reach.max()))
            close = np.flatnonzero(nearest_m <= reach)
            if close.size == 0:
                continue
            near = tree.query_ball_point(mid[close], r=reach[close])
            counts = np.fromiter((len(found) for found in near), dtype=int, count=len(near))
            rows = np.repeat(close, counts)
            cols = np.fromiter((j for found in near for j in found), dtype=int, count=int(counts.sum()))
            h = hits[cols]
            u = np.clip(np.einsum("ij,ij->i", h - a[rows], e[rows]) / ee[rows], 0.0, 1.0)
            nearest = a[rows] + u[:, None] * e[rows]
            floor = self._floor(np.linalg.norm(h - start, axis=1))
            depth = np.linalg.norm(h - nearest, axis=1) - floor
            k = int(np.argmin(depth))
            if depth[k] < 0.0 and (worst is None or depth[k] < worst[0]):
                worst = (float(depth[k]), float(floor[k]), h[k], nearest[k])
        if worst is None:
            return None
        depth, floor, (hx, hy), (x, y) = worst
        return (f"the path passes {depth + floor:.3f} m < {floor + DISTANCE_TOL_M:.3f} from a hit of the car's own "
                f"scans at ({hx:.2f}, {hy:.2f}), near ({x:.2f}, {y:.2f})")

    def _in_ellipse(self, z: FloatArray, start: FloatArray) -> str | None:
        if len(self.stack) == 0 or len(z) < 2:
            return None
        floor = np.minimum(self.hard, self.stack.levels(start)[0] / (1.0 + START_SLACK)) - LEVEL_TOL
        rows, cols, levels = self.stack.segment_pairs(z[:-1], z[1:])
        depth = levels - floor[cols]
        if depth.size == 0 or depth.min() >= 0.0:
            return None
        worst = int(np.argmin(depth))
        row, col = int(rows[worst]), int(cols[worst])
        where = 0.5 * (z[row] + z[row + 1])
        return (f"the path enters a known obstacle's ellipse (cluster {self.cluster_ids[col]}, of scan "
                f"{self.scan_seq}) at level {levels[worst]:.3f} < {floor[col] + LEVEL_TOL:.3f} near "
                f"({where[0]:.2f}, {where[1]:.2f})")
