"""Kinematic bicycle for the simulator: the paper's car (width 0.3, length 0.6, wheelbase L 0.6).

The state's (x, y) is the centre of the footprint, because that is what the planner's centre line and
run.json (CONTRACTS §4) talk about. Internally the model is integrated about the rear axle, where the
bicycle is simplest: ẋ_r = v cos θ, ẏ_r = v sin θ, θ̇ = v tan δ / L (v is the rear-axle speed). The axles
are assumed to sit symmetrically about the footprint centre, so centre = rear + (L/2)·(cos θ, sin θ).

Consequence worth knowing: at steering δ the rear axle turns on radius R = L / tan δ (the CONTRACTS'
minimum turn radius), while the footprint centre turns on the slightly larger sqrt(R² + (L/2)²).

The car reverses (negative speed) only when asked to, no faster than `max_reverse_speed_mps`: the sim
backs it out of a dead end along its own tracks (`sim.core`). A change of direction comes to rest
first: a step that would cross zero speed ends at rest.

Within one step the steering angle and the speed ramp linearly from their old to their new (limited)
values (a first-order hold); the step is split into sub-steps, each integrated as the exact arc for the
sub-step's mid values. With constant inputs the result is exact; otherwise the error is O((dt/n)²).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from shapely.geometry import Polygon

_SUBSTEPS = 8


@dataclass(frozen=True)
class VehicleState:
    """Pose of the footprint centre, rear-axle speed and front-wheel steering angle."""

    x_m: float
    y_m: float
    theta_rad: float
    speed_mps: float = 0.0
    steering_rad: float = 0.0

    @classmethod
    def at_start(cls, scenario) -> VehicleState:
        """At rest at the scenario's `start` {x, y, theta}, wheels straight."""
        return cls(x_m=float(scenario.start.x), y_m=float(scenario.start.y), theta_rad=float(scenario.start.theta))


@dataclass(frozen=True)
class VehicleLimits:
    """What the actuators can do. Accelerations are magnitudes (decel applies when slowing)."""

    wheelbase_m: float
    max_speed_mps: float
    max_steering_rad: float
    max_steering_rate_radps: float
    max_accel_mps2: float = 1.0
    max_decel_mps2: float = 2.0
    max_reverse_speed_mps: float = 0.3

    def __post_init__(self) -> None:
        for name in ("wheelbase_m", "max_speed_mps", "max_steering_rad", "max_steering_rate_radps",
                     "max_accel_mps2", "max_decel_mps2", "max_reverse_speed_mps"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0.0):
                raise ValueError(f"{name} must be finite and positive, got {value!r}")
        if self.max_steering_rad >= math.pi / 2:
            raise ValueError("max_steering_rad must be below pi/2")

    @property
    def min_turn_radius_m(self) -> float:
        """Rear-axle turn radius at full lock, L / tan δ_max."""
        return self.wheelbase_m / math.tan(self.max_steering_rad)

    @classmethod
    def from_scenario(cls, scenario) -> VehicleLimits:
        robot = scenario.robot
        return cls(
            wheelbase_m=float(robot.wheelbase),
            max_speed_mps=float(robot.max_speed),
            max_steering_rad=float(robot.max_steering_angle),
            max_steering_rate_radps=float(robot.max_steering_rate),
        )


def _clip(value: float, low: float, high: float) -> float:
    return min(max(value, low), high)


def wrap_angle(angle_rad: float) -> float:
    """The same angle in [-π, π]."""
    return math.remainder(angle_rad, 2.0 * math.pi)


def rear_axle(state: VehicleState, *, wheelbase_m: float) -> tuple[float, float]:
    """Midpoint of the rear axle, L/2 behind the footprint centre."""
    half = 0.5 * wheelbase_m
    return state.x_m - half * math.cos(state.theta_rad), state.y_m - half * math.sin(state.theta_rad)


def step(
    state: VehicleState,
    *,
    limits: VehicleLimits,
    target_speed_mps: float,
    target_steering_rad: float,
    dt_s: float,
) -> VehicleState:
    """Advance `dt_s` seconds towards the targets, within every limit.

    Steering: target clamped to ±max, then the change clamped to ±max_rate·dt. Speed: target clamped to
    [−max_reverse, max], then the change clamped to accel·dt away from rest and decel·dt towards it;
    a change that would cross zero stops at rest (the car changes direction from standstill).
    """
    if not (math.isfinite(dt_s) and dt_s >= 0.0):
        raise ValueError(f"dt_s must be finite and non-negative, got {dt_s!r}")
    if not (math.isfinite(target_speed_mps) and math.isfinite(target_steering_rad)):
        raise ValueError("targets must be finite")
    max_delta = limits.max_steering_rad
    delta0 = _clip(state.steering_rad, -max_delta, max_delta)
    max_change = limits.max_steering_rate_radps * dt_s
    delta_target = _clip(target_steering_rad, -max_delta, max_delta)
    delta1 = _clip(delta0 + _clip(delta_target - delta0, -max_change, max_change), -max_delta, max_delta)

    v0 = _clip(state.speed_mps, -limits.max_reverse_speed_mps, limits.max_speed_mps)
    v_target = _clip(target_speed_mps, -limits.max_reverse_speed_mps, limits.max_speed_mps)
    if v0 * v_target < 0.0:
        v_target = 0.0  # rest first, then the other way
    away = abs(v_target) > abs(v0)
    change = (limits.max_accel_mps2 if away else limits.max_decel_mps2) * dt_s
    v1 = v0 + _clip(v_target - v0, -change, change)

    L = limits.wheelbase_m
    xr, yr = rear_axle(state, wheelbase_m=L)
    theta = state.theta_rad
    h = dt_s / _SUBSTEPS
    for k in range(_SUBSTEPS):
        frac = (k + 0.5) / _SUBSTEPS
        v = v0 + frac * (v1 - v0)
        delta = delta0 + frac * (delta1 - delta0)
        ds = v * h
        dtheta = ds * math.tan(delta) / L
        # Exact arc: chord length ds·sinc(dθ/2) along the mean heading θ + dθ/2.
        half = 0.5 * dtheta
        chord = ds * (math.sin(half) / half if abs(half) > 1e-12 else 1.0 - half * half / 6.0)
        xr += chord * math.cos(theta + half)
        yr += chord * math.sin(theta + half)
        theta += dtheta

    theta = wrap_angle(theta)
    half_l = 0.5 * L
    return VehicleState(
        x_m=xr + half_l * math.cos(theta),
        y_m=yr + half_l * math.sin(theta),
        theta_rad=theta,
        speed_mps=v1,
        steering_rad=delta1,
    )


def footprint(state: VehicleState, *, width_m: float, length_m: float) -> Polygon:
    """The car's rectangle: `length_m` along the heading, `width_m` across, centred on (x, y)."""
    c, s = math.cos(state.theta_rad), math.sin(state.theta_rad)
    hl, hw = 0.5 * length_m, 0.5 * width_m
    corners = [(hl, hw), (-hl, hw), (-hl, -hw), (hl, -hw)]
    return Polygon([(state.x_m + c * a - s * b, state.y_m + s * a + c * b) for a, b in corners])
