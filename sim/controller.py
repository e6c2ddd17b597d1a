"""Path tracking for the car: pure pursuit on the footprint centre, speed scheduled for curvature and stopping.

Pure pursuit (Coulter 1992, CMU-RI-TR-92-01) steers onto the circular arc that joins the vehicle to a
lookahead point on the path. The classic form places the arc through the rear axle. Here the tracked
point is the footprint centre (what the planner's path and run.json describe), which sits L/2 ahead of
the rear axle. For a bicycle every body point turns about the instantaneous centre of rotation on the
rear-axle line, at (0, s) in the rear-axle frame (x forward, y left). Asking the centre (L/2, 0) and
the lookahead point g = (gx, gy) to lie on one circle about it gives

    s = (gx² + gy² − L²/4) / (2 gy),      tan δ = L / s = 2 L gy / (|g|² − L²/4),

the classic law with |g|² replaced by |g|² − L²/4. On a circular path the centre then has zero
steady-state cross-track error: the lookahead point and the centre share the turning circle.

Speed is the largest value from which the car can still slow down, at `max_decel_mps2`, to each path
vertex's curvature limit sqrt(a_lat / κ) and to rest at the path end:
    v = min_j sqrt(v_j² + 2 a_dec (s_j − s)),  over vertices j ahead of the projection s.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

from sim.vehicle import VehicleLimits, VehicleState

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class Command:
    """What the controller asks of the vehicle, plus where it found itself on the path."""

    target_speed_mps: float
    target_steering_rad: float
    progress_m: float = 0.0  # arc length of the footprint centre's projection onto the path
    remaining_m: float = 0.0  # path length left after the projection
    cross_track_m: float = 0.0  # distance from the footprint centre to the path


def menger_curvature(points: ArrayLike) -> FloatArray:
    """Unsigned curvature at each vertex from the circle through it and its two neighbours (0 at the ends)."""
    z = np.asarray(points, dtype=float)
    kappa = np.zeros(len(z))
    if len(z) < 3:
        return kappa
    a, b, c = z[:-2], z[1:-1], z[2:]
    ab, bc, ac = b - a, c - b, c - a
    cross = np.abs(ab[:, 0] * ac[:, 1] - ab[:, 1] * ac[:, 0])
    lengths = np.linalg.norm(ab, axis=1) * np.linalg.norm(bc, axis=1) * np.linalg.norm(ac, axis=1)
    kappa[1:-1] = np.where(lengths > 0.0, 2.0 * cross / np.where(lengths > 0.0, lengths, 1.0), 0.0)
    return kappa


@dataclass(frozen=True)
class PurePursuit:
    """Pure pursuit on the footprint centre with a speed profile; holds configuration only (no state).

    Lookahead = max(min_lookahead_m, lookahead_gain_s · speed). `search_window_m` bounds where the
    projection is looked for when the caller passes back the last `progress_m`, so a path that comes
    back near itself (a loop, a U-turn) is followed in order rather than short-cut.
    """

    wheelbase_m: float
    max_speed_mps: float
    max_steering_rad: float
    lookahead_gain_s: float = 1.0
    min_lookahead_m: float = 0.6
    max_lateral_accel_mps2: float = 0.5
    max_decel_mps2: float = 1.0
    stop_tolerance_m: float = 0.05
    search_window_m: float = 2.0

    @classmethod
    def from_limits(cls, limits: VehicleLimits, **overrides: float) -> PurePursuit:
        return cls(wheelbase_m=limits.wheelbase_m, max_speed_mps=limits.max_speed_mps,
                   max_steering_rad=limits.max_steering_rad, **overrides)

    def command(self, state: VehicleState, *, path: ArrayLike, progress_m: float | None = None) -> Command:
        """Steering and speed targets to follow `path` ((n, 2), centre line) from `state`."""
        z = np.asarray(path, dtype=float).reshape(-1, 2)
        if len(z) == 0:
            return Command(target_speed_mps=0.0, target_steering_rad=state.steering_rad)
        if len(z) == 1:
            z = np.vstack([z, z])
        centre = np.array([state.x_m, state.y_m])

        # Project the centre onto every segment; keep the nearest (within the search window if given).
        a, b = z[:-1], z[1:]
        e = b - a
        seg_len = np.linalg.norm(e, axis=1)
        s_start = np.concatenate([[0.0], np.cumsum(seg_len)])
        total = float(s_start[-1])
        ee = np.where(seg_len > 0.0, seg_len**2, 1.0)
        u = np.clip(np.einsum("ij,ij->i", centre - a, e) / ee, 0.0, 1.0)
        foot = a + u[:, None] * e
        dist = np.linalg.norm(foot - centre, axis=1)
        if progress_m is not None:
            in_window = (s_start[1:] >= progress_m - self.search_window_m) & (
                s_start[:-1] <= progress_m + self.search_window_m)
            dist = np.where(in_window, dist, np.inf) if in_window.any() else dist
        k = int(np.argmin(dist))
        s_here = float(s_start[k] + u[k] * seg_len[k])
        cross_track = float(np.linalg.norm(foot[k] - centre))
        remaining = max(total - s_here, 0.0)

        speed = self._speed(z=z, s_vertices=s_start, s_here=s_here, remaining_m=remaining)
        lookahead = max(self.min_lookahead_m, self.lookahead_gain_s * state.speed_mps)
        goal = self._point_at(z=z, s_vertices=s_start, seg_len=seg_len, s_m=s_here + lookahead)
        steering = self._steer(state, goal=goal)

        # Do not ask for more speed than the commanded turn allows (lateral acceleration limit).
        beta = math.atan(0.5 * math.tan(steering))
        kappa_cmd = 2.0 * abs(math.sin(beta)) / self.wheelbase_m
        if kappa_cmd > 0.0:
            speed = min(speed, math.sqrt(self.max_lateral_accel_mps2 / kappa_cmd))
        return Command(target_speed_mps=speed, target_steering_rad=steering, progress_m=s_here,
                       remaining_m=remaining, cross_track_m=cross_track)

    def _speed(self, *, z: FloatArray, s_vertices: FloatArray, s_here: float, remaining_m: float) -> float:
        if remaining_m <= self.stop_tolerance_m:
            return 0.0
        kappa = menger_curvature(z)
        v_limit = np.sqrt(self.max_lateral_accel_mps2 / np.maximum(kappa, 1e-12))
        v_limit = np.minimum(v_limit, self.max_speed_mps)
        v_limit[-1] = 0.0  # come to rest at the end
        ahead = s_vertices > s_here
        reachable = np.sqrt(v_limit[ahead] ** 2 + 2.0 * self.max_decel_mps2 * (s_vertices[ahead] - s_here))
        return float(min(self.max_speed_mps, reachable.min() if reachable.size else 0.0))

    @staticmethod
    def _point_at(*, z: FloatArray, s_vertices: FloatArray, seg_len: FloatArray, s_m: float) -> FloatArray:
        """The path point at arc length `s_m`; past the end, continue straight along the last segment."""
        total = s_vertices[-1]
        if s_m <= total:
            k = int(np.clip(np.searchsorted(s_vertices, s_m, side="right") - 1, 0, len(seg_len) - 1))
            t = (s_m - s_vertices[k]) / seg_len[k] if seg_len[k] > 0.0 else 0.0
            return z[k] + t * (z[k + 1] - z[k])
        nonzero = np.flatnonzero(seg_len > 0.0)
        if nonzero.size == 0:
            return z[-1]
        last = int(nonzero[-1])
        direction = (z[last + 1] - z[last]) / seg_len[last]
        return z[-1] + (s_m - total) * direction

    def _steer(self, state: VehicleState, *, goal: FloatArray) -> float:
        L = self.wheelbase_m
        c, s = math.cos(state.theta_rad), math.sin(state.theta_rad)
        rx, ry = state.x_m - 0.5 * L * c, state.y_m - 0.5 * L * s  # rear axle
        dx, dy = float(goal[0]) - rx, float(goal[1]) - ry
        gx, gy = c * dx + s * dy, -s * dx + c * dy
        denom = gx * gx + gy * gy - 0.25 * L * L
        if denom <= 1e-9:  # goal no farther from the rear axle than the centre is: turn hard towards it
            return math.copysign(self.max_steering_rad, gy) if gy != 0.0 else 0.0
        delta = math.atan(2.0 * L * gy / denom)
        return max(-self.max_steering_rad, min(self.max_steering_rad, delta))


@dataclass
class GoalTracker:
    """Visits goals in order: the current goal counts as reached within `tolerance_m` of the centre.

    Mutable on purpose (it is the sim's record of progress); `update` is the only mutator.
    """

    goals: Sequence[Sequence[float]]
    tolerance_m: float
    reached_count: int = field(default=0)

    def __post_init__(self) -> None:
        self.goals = [(float(g[0]), float(g[1])) for g in self.goals]
        if not (math.isfinite(self.tolerance_m) and self.tolerance_m >= 0.0):
            raise ValueError("tolerance_m must be finite and non-negative")

    @classmethod
    def from_scenario(cls, scenario) -> GoalTracker:
        return cls(goals=scenario.goals, tolerance_m=float(scenario.goal_tolerance))

    @property
    def done(self) -> bool:
        return self.reached_count >= len(self.goals)

    @property
    def current(self) -> tuple[float, float] | None:
        """The goal being driven to, None once all are reached."""
        return None if self.done else self.goals[self.reached_count]

    @property
    def remaining(self) -> list[tuple[float, float]]:
        return list(self.goals[self.reached_count:])

    def update(self, *, x_m: float, y_m: float) -> int:
        """Advance past every goal in order that lies within tolerance; returns how many were reached now."""
        before = self.reached_count
        while not self.done:
            gx, gy = self.goals[self.reached_count]
            if math.hypot(x_m - gx, y_m - gy) > self.tolerance_m:
                break
            self.reached_count += 1
        return self.reached_count - before
