"""Simulated 2-D range sensor: exact ray casting against polygons, circles and occupancy grids.

Obstacles are shapely geometries (Polygon, MultiPolygon, LineString, ... — every boundary edge is a
target), `Circle`s, or `OccupancyGrid`s (every blocked cell a square, beyond the map blocked). A circle given as a buffered shapely point is a polygon with 4·quad_segs edges
and is hit exactly on that polygon, not on the true circle; pass a `Circle` where the exact curved
surface matters (World.from_scenario does so for the scenario's circle obstacles).

Ray p(t) = o + t d (‖d‖ = 1, t = range). Against a segment a + u e, u ∈ [0, 1]:
    t = ((a − o) × e) / (d × e),  u = ((a − o) × d) / (d × e)          (× is the 2-D cross product)
rays parallel to an edge (d × e = 0) skip it; its end points are hit through the neighbouring edges.
Against a circle |p − c| = r: t² + 2 (f·d) t + (|f|² − r²) = 0 with f = o − c; the nearest
non-negative root is the hit. Everything is evaluated for all rays × all edges at once with numpy.
A grid is traversed cell by cell along every ray at once (Amanatides & Woo's voxel traversal, 1987): the
distance at which a ray enters its first blocked cell is the hit, exact for the square, at a cost that
follows the range in cells, not the map's size.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import numpy as np
import shapely
from numpy.typing import NDArray
from shapely.geometry.base import BaseGeometry

from schemas.occupancy import OccupancyGrid

FloatArray = NDArray[np.float64]
BLOCK_PAIRS = 1 << 20  # ray-target pairs cast at once: about 8 MiB per intermediate array


@dataclass(frozen=True)
class Circle:
    """An exact disc obstacle: `center` (x, y) in metres and `radius_m`."""

    center: tuple[float, float]
    radius_m: float

    def __post_init__(self) -> None:
        cx, cy = (float(v) for v in self.center)
        if not (math.isfinite(cx) and math.isfinite(cy) and math.isfinite(self.radius_m) and self.radius_m > 0):
            raise ValueError("circle needs a finite centre and a finite positive radius")
        object.__setattr__(self, "center", (cx, cy))
        object.__setattr__(self, "radius_m", float(self.radius_m))

    def solid(self, *, quad_segs: int = 32) -> BaseGeometry:
        """A polygonal stand-in for drawing; distances and hits use the exact disc instead."""
        return shapely.Point(self.center).buffer(self.radius_m, quad_segs=quad_segs)

    def distance(self, points: FloatArray) -> FloatArray:
        """Euclidean distance from each point to the disc (0 inside)."""
        z = np.atleast_2d(np.asarray(points, dtype=float))
        return np.maximum(np.hypot(z[:, 0] - self.center[0], z[:, 1] - self.center[1]) - self.radius_m, 0.0)


Obstacle = BaseGeometry | Circle | OccupancyGrid


@dataclass(frozen=True, eq=False)
class RayTargets:
    """Obstacles flattened once into arrays the ray caster sweeps: edges (m, 4) and circles (k, 3), and the
    grids it traverses."""

    edges: FloatArray  # rows: ax, ay, bx, by
    circles: FloatArray  # rows: cx, cy, r
    grids: tuple[OccupancyGrid, ...] = ()

    @classmethod
    def of(cls, obstacles: Iterable[Obstacle]) -> RayTargets:
        edges: list[FloatArray] = []
        circles: list[tuple[float, float, float]] = []
        grids: list[OccupancyGrid] = []
        for obstacle in obstacles:
            if isinstance(obstacle, Circle):
                circles.append((*obstacle.center, obstacle.radius_m))
                continue
            if isinstance(obstacle, OccupancyGrid):
                grids.append(obstacle)
                continue
            for part in shapely.get_parts(obstacle):
                if isinstance(part, shapely.Polygon):
                    rings = [part.exterior, *part.interiors]
                elif isinstance(part, (shapely.LineString, shapely.LinearRing)):
                    rings = [part]
                else:  # points have no extent to hit
                    continue
                for ring in rings:
                    xy = np.asarray(ring.coords, dtype=float)[:, :2]
                    if len(xy) >= 2:
                        edges.append(np.hstack([xy[:-1], xy[1:]]))
        return cls(
            edges=np.concatenate(edges) if edges else np.zeros((0, 4)),
            circles=np.array(circles, dtype=float).reshape(-1, 3),
            grids=tuple(grids),
        )


def cast_rays_grid(grid: OccupancyGrid, *, origin: Sequence[float], angles_rad: FloatArray,
                   max_range_m: float) -> FloatArray:
    """Distance along each ray to the first blocked cell of the grid it enters (inf beyond `max_range_m`;
    0 from inside a blocked cell). In the grid frame, in cells: a ray o + t d crosses the next vertical
    cell boundary at t_x and the next horizontal one at t_y; stepping into the cell across the nearer one
    visits every cell the ray passes, in order."""
    res = grid.resolution_m
    o = grid.to_grid(np.asarray(origin, dtype=float)[None, :])[0] / res
    yaw = np.arctan2(grid.rotation[1, 0], grid.rotation[0, 0])
    d = np.column_stack([np.cos(angles_rad - yaw), np.sin(angles_rad - yaw)])
    n = len(d)
    i = np.full(n, int(math.floor(o[0])))
    j = np.full(n, int(math.floor(o[1])))
    step = np.where(d >= 0.0, 1, -1)
    with np.errstate(divide="ignore"):
        inverse = np.where(d != 0.0, 1.0 / np.abs(d), np.inf)  # t per cell along each axis
    first = np.where(d >= 0.0, np.floor(o) + 1.0 - o, o - np.floor(o))  # cells to the first boundary
    t_next = first * inverse  # (n, 2): t of the next x and y boundary
    t_cell = np.zeros(n)  # t at which the ray entered its current cell
    limit = max_range_m / res
    out = np.full(n, np.inf)
    rows, cols = grid.shape
    blocked = grid.blocked
    active = np.arange(n)
    while len(active):
        ia, ja = i[active], j[active]
        inside = (ia >= 0) & (ja >= 0) & (ia < cols) & (ja < rows)
        hit = ~inside  # beyond the map is blocked
        hit[inside] = blocked[ja[inside], ia[inside]]
        out[active[hit]] = t_cell[active[hit]] * res
        active = active[~hit]
        if not len(active):
            break
        axis = (t_next[active, 1] < t_next[active, 0]).astype(np.intp)  # 0: cross x next, 1: cross y
        t_cell[active] = t_next[active, axis]
        far = t_cell[active] > limit
        active = active[~far]
        axis = axis[~far]
        t_next[active, axis] += inverse[active, axis]
        x_step = axis == 0
        i[active[x_step]] += step[active[x_step], 0]
        j[active[~x_step]] += step[active[~x_step], 1]
    return out


def cast_rays(*, origin: Sequence[float], angles_rad: FloatArray, targets: RayTargets,
              max_range_m: float = math.inf) -> FloatArray:
    """Distance along each ray from `origin` to the first obstacle surface; inf where nothing is hit (a
    grid is traversed up to `max_range_m` only).

    Rays × edges (and rays × circles) are swept in blocks of at most `BLOCK_PAIRS` pairs, so the memory
    of a scan stays bounded whatever the sensor's rays and the world's edges (4096 × 100 000 at once
    would be gigabytes per intermediate array).
    """
    angles = np.asarray(angles_rad, dtype=float)
    per_block = max(1, BLOCK_PAIRS // max(1, len(targets.edges), len(targets.circles)))
    if len(angles) <= per_block:
        return _cast_block(origin=origin, angles=angles, targets=targets, max_range_m=max_range_m)
    return np.concatenate([_cast_block(origin=origin, angles=angles[k : k + per_block], targets=targets,
                                       max_range_m=max_range_m) for k in range(0, len(angles), per_block)])


def _cast_block(*, origin: Sequence[float], angles: FloatArray, targets: RayTargets, max_range_m: float) -> FloatArray:
    ox, oy = float(origin[0]), float(origin[1])
    dx, dy = np.cos(angles)[:, None], np.sin(angles)[:, None]  # (n, 1)
    best = np.full(angles.shape, np.inf)

    if len(targets.edges):
        ax, ay, bx, by = (targets.edges[:, i][None, :] for i in range(4))  # (1, m)
        ex, ey = bx - ax, by - ay
        wx, wy = ax - ox, ay - oy
        denom = dx * ey - dy * ex  # d × e, (n, m)
        parallel = denom == 0.0
        safe = np.where(parallel, 1.0, denom)
        t = (wx * ey - wy * ex) / safe
        u = (wx * dy - wy * dx) / safe
        hit = ~parallel & (t >= 0.0) & (u >= 0.0) & (u <= 1.0)
        best = np.minimum(best, np.where(hit, t, np.inf).min(axis=1))

    if len(targets.circles):
        cx, cy, r = (targets.circles[:, i][None, :] for i in range(3))
        fx, fy = ox - cx, oy - cy
        b = fx * dx + fy * dy  # f·d, (n, k)
        c = fx * fx + fy * fy - r * r  # (1, k)
        disc = b * b - c
        root = np.sqrt(np.where(disc >= 0.0, disc, 0.0))
        near, far = -b - root, -b + root
        t = np.where(near >= 0.0, near, far)  # from inside a disc the far root is the wall
        t = np.where((disc >= 0.0) & (t >= 0.0), t, np.inf)
        best = np.minimum(best, t.min(axis=1))

    for grid in targets.grids:
        best = np.minimum(best, cast_rays_grid(grid, origin=origin, angles_rad=angles, max_range_m=max_range_m))
    return best


@dataclass(frozen=True)
class RangeSensor:
    """A planar range sensor with `rays` beams spread evenly over `fov_deg`, centred on the heading.

    Noise is Gaussian on the measured range (std `noise_std_m`), drawn from the caller's
    numpy Generator so a seeded run repeats exactly; without a generator the scan is noise-free.
    """

    fov_deg: float
    range_m: float
    rays: int
    noise_std_m: float = 0.0

    def __post_init__(self) -> None:
        if not (0.0 < self.fov_deg <= 360.0):
            raise ValueError("fov_deg must be in (0, 360]")
        if not (math.isfinite(self.range_m) and self.range_m > 0.0):
            raise ValueError("range_m must be finite and positive")
        if int(self.rays) != self.rays or self.rays < 1:
            raise ValueError("rays must be a positive integer")
        if not (math.isfinite(self.noise_std_m) and self.noise_std_m >= 0.0):
            raise ValueError("noise_std_m must be finite and non-negative")

    @classmethod
    def from_scenario(cls, scenario, *, noise_std_m: float = 0.0) -> RangeSensor:
        sensor = scenario.sensor
        return cls(fov_deg=float(sensor.fov_deg), range_m=float(sensor.range), rays=int(sensor.rays),
                   noise_std_m=noise_std_m)

    def ray_angles_rad(self, theta_rad: float) -> FloatArray:
        """World-frame beam directions. A full 360° sweep leaves out the duplicate last beam."""
        half = math.radians(self.fov_deg) / 2.0
        if self.rays == 1:
            return np.array([theta_rad])
        full_circle = self.fov_deg >= 360.0
        return theta_rad + np.linspace(-half, half, self.rays, endpoint=not full_circle)

    def ranges(
        self,
        *,
        x_m: float,
        y_m: float,
        theta_rad: float,
        obstacles: Iterable[Obstacle] | RayTargets,
        rng: np.random.Generator | None = None,
    ) -> FloatArray:
        """Measured range per beam (inf where nothing lies within `range_m`)."""
        targets = obstacles if isinstance(obstacles, RayTargets) else RayTargets.of(obstacles)
        true = cast_rays(origin=(x_m, y_m), angles_rad=self.ray_angles_rad(theta_rad), targets=targets,
                         max_range_m=self.range_m)
        seen = true <= self.range_m
        measured = np.where(seen, true, np.inf)
        if rng is not None and self.noise_std_m > 0.0:
            noise = rng.normal(0.0, self.noise_std_m, size=measured.shape)  # one draw per beam, always
            measured = np.where(seen, np.maximum(measured + noise, 0.0), np.inf)
        return measured

    def scan(
        self,
        *,
        x_m: float,
        y_m: float,
        theta_rad: float,
        obstacles: Iterable[Obstacle] | RayTargets,
        rng: np.random.Generator | None = None,
    ) -> FloatArray:
        """World-frame hit points (k, 2) of the beams that hit something within range, in beam order.

        `obstacles` may be a prebuilt `RayTargets` to skip re-flattening a static world every scan.
        """
        measured = self.ranges(x_m=x_m, y_m=y_m, theta_rad=theta_rad, obstacles=obstacles, rng=rng)
        angles = self.ray_angles_rad(theta_rad)
        hit = np.isfinite(measured)
        t, a = measured[hit], angles[hit]
        return np.column_stack([x_m + t * np.cos(a), y_m + t * np.sin(a)]).reshape(-1, 2)
