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
Backing out of a dead end along its own tracks (`reverse_command`), the car tracks its rear axle
instead, with the classic law: in reverse the rear axle leads.

Speed is the largest value from which the car can still slow down, at `max_decel_mps2`, to each path
vertex's limit v_j and to rest at the path end:
    v = min_j sqrt(v_j² + 2 a_dec (s_j − s)),  over vertices j ahead of the projection s.
The limit v_j is the lower of two. Lateral acceleration: sqrt(a_lat / κ_j). Steering rate: over
the window of `steering_window_m` of path ahead of vertex j the wheels must swing through the largest
change Δδ_j of the steering angle that the path's curvature asks for, and they turn at δ̇_max at most,
so v_j ≤ ρ·δ̇_max·window / Δδ_j. Without it the car reaches a bend whose curvature climbs to the bound
faster than its wheels can follow and runs wide of it (0.4 m in a closed-loop run of field-15). The
window lets the short wiggles of a refined path, which average out, pass at speed.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

from services.drive.vehicle import VehicleLimits, VehicleState, rear_axle

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class Command:
    """What the controller asks of the vehicle, plus where it found itself on the path."""

    target_speed_mps: float
    target_steering_rad: float
    progress_m: float = 0.0  # arc length of the footprint centre's projection onto the path
    remaining_m: float = 0.0  # path length left after the projection
    cross_track_m: float = 0.0  # distance from the footprint centre to the path


def signed_curvature(points: ArrayLike, *, stride: int = 1) -> FloatArray:
    """Curvature of the circle through each vertex and the vertices `stride` before and after it.

    Signed: positive where the path turns left. A stride longer than one averages the curvature over
    the arc between the three points. The first and last `stride` vertices have no such circle: 0.
    """
    z = np.asarray(points, dtype=float)
    kappa = np.zeros(len(z))
    h = max(1, int(stride))
    if len(z) < 2 * h + 1:
        return kappa
    a, b, c = z[: -2 * h], z[h:-h], z[2 * h :]
    ab, bc, ac = b - a, c - b, c - a
    cross = ab[:, 0] * ac[:, 1] - ab[:, 1] * ac[:, 0]
    lengths = np.linalg.norm(ab, axis=1) * np.linalg.norm(bc, axis=1) * np.linalg.norm(ac, axis=1)
    kappa[h:-h] = np.where(lengths > 0.0, 2.0 * cross / np.where(lengths > 0.0, lengths, 1.0), 0.0)
    return kappa


def menger_curvature(points: ArrayLike) -> FloatArray:
    """Unsigned curvature at each vertex from the circle through it and its two neighbours (0 at the ends)."""
    return np.abs(signed_curvature(points))


def steering_for_curvature(kappa: ArrayLike, *, wheelbase_m: float) -> FloatArray:
    """Steering angle that drives the footprint centre (L/2 ahead of the rear axle) on curvature κ.

    The centre turns on radius sqrt(R² + L²/4) when the rear axle turns on R = L / tan δ, so
    tan δ = L κ / sqrt(1 − (L κ / 2)²); curvatures at or beyond 2/L (unreachable) map to ±π/2.
    """
    k = np.asarray(kappa, dtype=float)
    half = np.clip(0.5 * wheelbase_m * np.abs(k), 0.0, 1.0)
    return np.sign(k) * np.arctan2(wheelbase_m * np.abs(k), np.sqrt(1.0 - half**2))


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
    max_steering_rate_radps: float
    steering_rate_share: float = 0.8  # ρ: the share of the steering rate the speed profile may use
    steering_window_m: float = 0.5
    lookahead_gain_s: float = 1.0
    min_lookahead_m: float = 0.35
    max_lateral_accel_mps2: float = 0.5
    max_decel_mps2: float = 1.0
    stop_tolerance_m: float = 0.05
    search_window_m: float = 2.0
    reverse_speed_mps: float = 0.3  # backing out (`reverse_command`)
    reverse_lookahead_m: float = 0.2  # short: the tracks bend at full lock where the car turned hard
    reverse_swing_m: float = 0.05

    @classmethod
    def from_limits(cls, limits: VehicleLimits, **overrides: float) -> PurePursuit:
        return cls(wheelbase_m=limits.wheelbase_m, max_speed_mps=limits.max_speed_mps,
                   max_steering_rad=limits.max_steering_rad,
                   max_steering_rate_radps=limits.max_steering_rate_radps,
                   **{"reverse_speed_mps": limits.max_reverse_speed_mps, **overrides})

    def command(self, state: VehicleState, *, path: ArrayLike, progress_m: float | None = None) -> Command:
        """Steering and speed targets to follow `path` ((n, 2), centre line) from `state`."""
        z = np.asarray(path, dtype=float).reshape(-1, 2)
        if len(z) == 0:
            return Command(target_speed_mps=0.0, target_steering_rad=state.steering_rad)
        if len(z) == 1:
            z = np.vstack([z, z])
        centre = np.array([state.x_m, state.y_m])
        s_start, seg_len, s_here, cross_track = self._project(z, centre, progress_m=progress_m)
        remaining = max(float(s_start[-1]) - s_here, 0.0)

        speed = self._speed(z=z, s_vertices=s_start, seg_len=seg_len, s_here=s_here, remaining_m=remaining,
                            steering_rad=state.steering_rad)
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

    def reverse_command(self, state: VehicleState, *, path: ArrayLike, progress_m: float | None = None) -> Command:
        """Steering and speed (negative) targets to back the rear axle along `path` ((n, 2), rear-axle
        points in the order to drive them), at most `reverse_speed_mps`, coming to rest at its end.

        In reverse the rear axle leads, and it moves along the heading whichever way the car goes, so
        it is the point to track: the arc through it, tangent to the heading, through the lookahead
        point g behind it (rear-axle frame) has curvature 2 g_y / |g|², and tan δ = L κ, as forward.
        """
        z = np.asarray(path, dtype=float).reshape(-1, 2)
        rear = np.array(rear_axle(state, wheelbase_m=self.wheelbase_m))
        if len(z) < 2:
            return Command(target_speed_mps=0.0, target_steering_rad=state.steering_rad)
        s_start, seg_len, s_here, cross_track = self._project(z, rear, progress_m=progress_m)
        remaining = max(float(s_start[-1]) - s_here, 0.0)
        speed = 0.0
        if remaining > self.stop_tolerance_m:
            speed = min(self.reverse_speed_mps, math.sqrt(2.0 * self.max_decel_mps2 * remaining))
        goal = self._point_at(z=z, s_vertices=s_start, seg_len=seg_len, s_m=s_here + self.reverse_lookahead_m)
        gx, gy = _in_frame(goal, origin=rear, theta_rad=state.theta_rad)
        g2 = gx * gx + gy * gy
        steering = math.atan(2.0 * self.wheelbase_m * gy / g2) if g2 > 1e-12 else 0.0
        steering = max(-self.max_steering_rad, min(self.max_steering_rad, steering))
        # Slow while the wheels swing (they start where the car stopped): cover at most
        # `reverse_swing_m` before they reach the angle asked for.
        swing = abs(steering - state.steering_rad)
        if swing > 0.0:
            speed = min(speed, self.max_steering_rate_radps * self.reverse_swing_m / swing)
        return Command(target_speed_mps=-speed, target_steering_rad=steering, progress_m=s_here,
                       remaining_m=remaining, cross_track_m=cross_track)

    def _project(self, z: FloatArray, point: FloatArray, *, progress_m: float | None
                 ) -> tuple[FloatArray, FloatArray, float, float]:
        """Arc length at each vertex, segment lengths, and the arc length of and distance to the point's
        projection onto the path: the nearest foot, within the search window of `progress_m` if given."""
        a, b = z[:-1], z[1:]
        e = b - a
        seg_len = np.linalg.norm(e, axis=1)
        s_start = np.concatenate([[0.0], np.cumsum(seg_len)])
        ee = np.where(seg_len > 0.0, seg_len**2, 1.0)
        u = np.clip(np.einsum("ij,ij->i", point - a, e) / ee, 0.0, 1.0)
        foot = a + u[:, None] * e
        dist = np.linalg.norm(foot - point, axis=1)
        if progress_m is not None:
            in_window = (s_start[1:] >= progress_m - self.search_window_m) & (
                s_start[:-1] <= progress_m + self.search_window_m)
            dist = np.where(in_window, dist, np.inf) if in_window.any() else dist
        k = int(np.argmin(dist))
        return s_start, seg_len, float(s_start[k] + u[k] * seg_len[k]), float(dist[k])

    def _speed(self, *, z: FloatArray, s_vertices: FloatArray, seg_len: FloatArray, s_here: float,
               remaining_m: float, steering_rad: float) -> float:
        if remaining_m <= self.stop_tolerance_m:
            return 0.0
        spacing = float(np.median(seg_len)) if len(seg_len) else 0.0
        stride = max(1, round(0.1 / spacing)) if spacing > 0.0 else 1  # curvature over ±0.1 m of path
        kappa = signed_curvature(z, stride=stride)
        if len(kappa) > 2 * stride:  # the end vertices have no circle: carry their neighbours' curvature
            kappa[:stride], kappa[-stride:] = kappa[stride], kappa[-stride - 1]
        steering = steering_for_curvature(kappa, wheelbase_m=self.wheelbase_m)
        v_limit = np.sqrt(self.max_lateral_accel_mps2 / np.maximum(np.abs(kappa), 1e-12))
        v_limit = np.minimum(v_limit, self._steering_rate_limit(steering, spacing_m=spacing))
        # The wheels, from where they are now, must also reach what the path asks for just ahead
        # (the car lags a fast curvature change): v ≤ ρ·δ̇_max·(distance + lookahead) / Δδ.
        near = (s_vertices > s_here) & (s_vertices <= s_here + self.steering_window_m)
        catch_up = (self.steering_rate_share * self.max_steering_rate_radps
                    * (s_vertices[near] - s_here + self.min_lookahead_m)
                    / np.maximum(np.abs(steering[near] - steering_rad), 1e-12))
        v_now = float(catch_up.min()) if catch_up.size else np.inf
        v_limit = np.minimum(v_limit, self.max_speed_mps)
        v_limit[-1] = 0.0  # come to rest at the end
        ahead = s_vertices > s_here
        reachable = np.sqrt(v_limit[ahead] ** 2 + 2.0 * self.max_decel_mps2 * (s_vertices[ahead] - s_here))
        return float(min(self.max_speed_mps, v_now, reachable.min() if reachable.size else 0.0))

    def _steering_rate_limit(self, steering: FloatArray, *, spacing_m: float) -> FloatArray:
        """Per vertex: the speed at which the wheels keep up with the path's steering over the window."""
        window = max(1, round(self.steering_window_m / spacing_m)) if spacing_m > 0.0 else 1
        swing = np.zeros(len(steering))
        for m in range(1, min(window, len(steering) - 1) + 1):
            change = np.abs(steering[m:] - steering[:-m])
            swing[:-m] = np.maximum(swing[:-m], change)
        return self.steering_rate_share * self.max_steering_rate_radps * window * spacing_m / np.maximum(swing, 1e-12)

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
        gx, gy = _in_frame(goal, origin=rear_axle(state, wheelbase_m=L), theta_rad=state.theta_rad)
        denom = gx * gx + gy * gy - 0.25 * L * L
        if denom <= 1e-9:  # goal no farther from the rear axle than the centre is: turn hard towards it
            return math.copysign(self.max_steering_rad, gy) if gy != 0.0 else 0.0
        delta = math.atan(2.0 * L * gy / denom)
        return max(-self.max_steering_rad, min(self.max_steering_rad, delta))


def _in_frame(point: ArrayLike, *, origin: ArrayLike, theta_rad: float) -> tuple[float, float]:
    """`point` in the frame at `origin` whose x axis points along `theta_rad` (y to its left)."""
    c, s = math.cos(theta_rad), math.sin(theta_rad)
    dx, dy = float(point[0]) - float(origin[0]), float(point[1]) - float(origin[1])
    return c * dx + s * dy, -s * dx + c * dy


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
