"""The sim's own check of every path before the car drives on it: clear of the obstacles it knows.

The smoother verifies each curve against the ellipses the planner used, but that is the pipeline
checking itself. The sim keeps the newest grown ellipses the ellipsoid stage published (`know`) and
checks each path it receives, and the path it is driving whenever newer ellipses arrive, segment by
segment with the paper's eq. (2) on the continuous segment (`EllipseStack.segment_pairs`). A path that
enters one is not driven: the car brakes, and the reason names the ellipse and where.

What the guard holds the path to is the run's hard floor, not the planner's margins: a grown ellipse
scaled about its centre by `keep_out_scales` still contains its fit grown by `Scenario.keep_out_m`
(half the footprint's diagonal plus half the safety distance), so a path outside it keeps the footprint
half the safety distance clear of the fit in any heading. The planner keeps the full margin wherever
it can and gives it up down to that floor only near a car that newly grown covers have boxed in
(`services.planner.stage.relieved_scales`). The robot may even be deeper than that floor already (a fit
sticks out of a newly seen obstacle): the planner shrinks any ellipse the start is inside just enough to
leave it at level 1.02 (`free_start_scales`), so its path may run no deeper than level(start) / 1.02,
and the guard allows down to level(start) / (1 + START_SLACK) where that is deeper than the floor;
with START_SLACK above the planner's 0.02 it never rejects a path the planner verified, and still
rejects one that goes deeper towards an obstacle than the robot already is.

LEVEL_TOL absorbs the chords between the smoothed curve's samples (0.05 m apart: they stray from the
curve by κ s² / 8 ≈ 1e-4 m, below 2e-4 in level for the paper's car).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

from schemas.messages import Ellipsoids
from services.geometry import EllipseStack, FloatArray, keep_out_scales

START_SLACK = 0.03
LEVEL_TOL = 1e-3


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


class PathGuard:
    """The newest grown ellipses the sim has seen, and the check of a path against them."""

    def __init__(self, *, inflation_m: float, keep_out_m: float) -> None:
        self.inflation_m = inflation_m  # the scenario's: how much the ellipses were grown from their fits
        self.keep_out_m = keep_out_m
        self.stack = EllipseStack.of([])
        self.hard = np.ones(0)  # per ellipse, the scale of its hard floor (level ≥ this)
        self.cluster_ids: list[int] = []
        self.scan_seq = -1  # the scan the known ellipses answer; -1: none yet

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
        """Why the polyline `points`, driven from `start`, is not clear of the known ellipses; None if it is."""
        z = np.asarray(points, dtype=float).reshape(-1, 2)
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
