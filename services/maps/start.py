"""A proof that no forward path leaves a start pose hemmed in by walls closer than the car can turn.

A car that never reverses, set down facing a wall nearer than its turning radius, has no path, and the
planner alone cannot say so quickly: it fails on one route after another, each refined and smoothed in
vain, for seconds. This test settles it in a millisecond, from the grid alone, and only where it can be
proved.

Let the car start at p with heading t, and let γ be any path from there whose curvature is at most 1/R
(arc length s, heading ψ(s) measured from t, so |ψ(s)| ≤ s/R). In the frame of p, t (x along t, y to
its left), while s ≤ πR/2:

  x(s) = ∫ cos ψ ≥ ∫ cos(u/R) du = R sin(s/R)      (|ψ(u)| ≤ u/R ≤ π/2, where cos decreases)
  y(s) = ∫ sin ψ ≤ ∫ sin(u/R) du = R (1 − cos(s/R)) (sin increases on [−π/2, π/2])

and since y (y − 2R) decreases in y below R, x² + (y − R)² − R² = x² + y (y − 2R) ≥ R² sin²(s/R) −
R² sin²(s/R) = 0: γ stays out of the open disc of radius R on the left of p, tangent to t there, and (the
same with −y) out of the one on the right, and it keeps x ≥ 0. At s = πR/2, x ≥ R. So before it has
come R from p, γ runs through the region U of points within R of p, ahead of it (x ≥ 0), outside both
turning discs and at least the margin from every blocked cell (outside the grown walls: the cover's
grown ellipses contain every border cell grown by the margin, and a plan is verified outside them).
When U's part connected to p never comes R from p, no path reaches a goal R or more away.

On the grid, a cell is counted in U when any of its points may be (each test loosened by half the cell's
diagonal, and the margin test as `CoarseGrid` makes it), and cells sharing an edge or a corner are
connected: every cell a path runs through is counted, so the grid's answer errs only towards "it may
leave". A verified curve leaves the start within 1e-3 rad of the heading (`services.smoother.core`),
which moves the discs and the half-plane by at most 1e-3 R: each test is loosened by 2e-3 R more.
"""

from __future__ import annotations

import math

import numpy as np

from schemas.occupancy import OccupancyGrid
from services.geometry import FloatArray
from services.maps.corridor import open_cells, reached_from

_HEADING_SLACK = 2e-3  # radians: a verified curve leaves the start within 1e-3 of the heading


def forward_exit(grid: OccupancyGrid, *, start: FloatArray, heading_rad: float, radius_m: float,
                 margin_m: float) -> bool:
    """Whether a forward path of curvature at most 1 / `radius_m`, keeping `margin_m` from every blocked
    cell, may come `radius_m` from the start (False: proved that none does; see the module docstring)."""
    res = grid.resolution_m
    p = grid.to_grid(start)[0]
    yaw = math.atan2(grid.rotation[1, 0], grid.rotation[0, 0])
    t = np.array([math.cos(heading_rad - yaw), math.sin(heading_rad - yaw)])
    left = np.array([-t[1], t[0]])
    half = res / math.sqrt(2.0)
    slack = half + _HEADING_SLACK * radius_m
    # The cells within the radius of p, and round them the margin's reach, whose blocked cells close them;
    # not beyond the map, where every cell is blocked, as `open_cells` takes everything beyond its mask.
    pc, pr = np.floor(p / res).astype(int)
    if not (0 <= pr < grid.shape[0] and 0 <= pc < grid.shape[1]):
        return True  # a start beyond the map: not this test's to judge
    reach = int(math.ceil((radius_m + margin_m) / res)) + 2
    r0, c0 = max(pr - reach, 0), max(pc - reach, 0)
    r1, c1 = min(pr + reach + 1, grid.shape[0]), min(pc + reach + 1, grid.shape[1])
    open_ = open_cells(grid.padded_blocked(slice(r0, r1), slice(c0, c1)), margin_m=margin_m, resolution_m=res)
    rows, cols = np.mgrid[r0:r1, c0:c1]
    dx, dy = (cols + 0.5) * res - p[0], (rows + 0.5) * res - p[1]
    ahead, side = dx * t[0] + dy * t[1], dx * left[0] + dy * left[1]
    far = np.hypot(dx, dy)
    region = (open_ & (far < radius_m + half) & (ahead >= -slack)
              & (np.hypot(ahead, side - radius_m) >= radius_m - slack)
              & (np.hypot(ahead, side + radius_m) >= radius_m - slack))
    if not region[pr - r0, pc - c0]:
        return True  # the start's own cell is closed: not this test's to judge
    return bool(np.any(far[reached_from(region, pr - r0, pc - c0)] >= radius_m - half))


def hemmed_in(grid: OccupancyGrid, *, start: FloatArray, heading_rad: float | None, goal: FloatArray,
              radius_m: float, margin_m: float) -> str:
    """Why no forward path from the start reaches `goal`, where `forward_exit` proves that none leaves the
    start; "" where it does not (no heading, a goal nearer than the turning radius, or a way out)."""
    if heading_rad is None or float(np.linalg.norm(np.asarray(goal) - start)) < radius_m:
        return ""
    if forward_exit(grid, start=start, heading_rad=heading_rad, radius_m=radius_m, margin_m=margin_m):
        return ""
    return (f"every path the car can drive forward from its heading (turning radius {radius_m:.2f} m) comes "
            f"within the margin ({margin_m:.3f} m) of a blocked cell before it is {radius_m:.2f} m from the start, "
            "and a plan never reverses")
