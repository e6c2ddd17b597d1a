"""Kinematic bicycle: the properties the simulator's truth rests on."""

from __future__ import annotations

import math

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from services.drive.vehicle import VehicleLimits, VehicleState, footprint, rear_axle, step

PAPER = VehicleLimits(wheelbase_m=0.6, max_speed_mps=1.0, max_steering_rad=0.2, max_steering_rate_radps=0.5)


def _fit_circle(points: np.ndarray) -> tuple[np.ndarray, float]:
    """Least-squares circle (Kåsa): x² + y² = 2 a x + 2 b y + c."""
    A = np.column_stack([2 * points[:, 0], 2 * points[:, 1], np.ones(len(points))])
    rhs = np.sum(points**2, axis=1)
    (a, b, c), *_ = np.linalg.lstsq(A, rhs, rcond=None)
    return np.array([a, b]), float(np.sqrt(c + a * a + b * b))


def test_straight_driving_covers_speed_times_time() -> None:
    state = VehicleState(x_m=1.0, y_m=2.0, theta_rad=math.pi / 6, speed_mps=0.8)
    for _ in range(100):
        state = step(state, limits=PAPER, target_speed_mps=0.8, target_steering_rad=0.0, dt_s=0.05)
    travelled = math.hypot(state.x_m - 1.0, state.y_m - 2.0)
    assert abs(travelled - 0.8 * 5.0) < 1e-12
    assert abs(state.theta_rad - math.pi / 6) < 1e-12
    assert abs(math.atan2(state.y_m - 2.0, state.x_m - 1.0) - math.pi / 6) < 1e-12


def test_full_lock_traces_circle_of_radius_wheelbase_over_tan_delta() -> None:
    delta = PAPER.max_steering_rad
    state = VehicleState(x_m=0.0, y_m=0.0, theta_rad=0.0, speed_mps=1.0, steering_rad=delta)
    rear, centre = [], []
    for _ in range(200):
        state = step(state, limits=PAPER, target_speed_mps=1.0, target_steering_rad=10.0, dt_s=0.05)
        rear.append(rear_axle(state, wheelbase_m=PAPER.wheelbase_m))
        centre.append((state.x_m, state.y_m))
    R = PAPER.wheelbase_m / math.tan(delta)
    _, r_rear = _fit_circle(np.array(rear))
    _, r_centre = _fit_circle(np.array(centre))
    assert abs(r_rear - R) / R < 0.01
    assert abs(r_rear - R) < 1e-9  # constant inputs: the arc integration is exact
    # The footprint centre sits L/2 ahead of the rear axle, so it rides on a slightly larger circle.
    assert abs(r_centre - math.hypot(R, PAPER.wheelbase_m / 2)) < 1e-9
    # Curvature 1/R of the rear-axle trajectory from three consecutive samples, within 1 %.
    p = np.array(rear)
    a, b, c = p[:-2], p[1:-1], p[2:]
    cross = np.abs((b - a)[:, 0] * (c - a)[:, 1] - (b - a)[:, 1] * (c - a)[:, 0])
    menger = 2 * cross / (np.linalg.norm(b - a, axis=1) * np.linalg.norm(c - b, axis=1) * np.linalg.norm(c - a, axis=1))
    assert np.all(np.abs(menger * R - 1.0) < 0.01)


@settings(max_examples=60, deadline=None)
@given(
    targets=st.lists(
        st.tuples(st.floats(-3.0, 3.0), st.floats(-2.0, 5.0)), min_size=5, max_size=60
    ),
    dt_s=st.floats(0.005, 0.2),
)
def test_limits_hold_every_step(targets: list[tuple[float, float]], dt_s: float) -> None:
    state = VehicleState(x_m=0.0, y_m=0.0, theta_rad=0.0)
    for steer, speed in targets:
        new = step(state, limits=PAPER, target_speed_mps=speed, target_steering_rad=steer, dt_s=dt_s)
        assert abs(new.steering_rad - state.steering_rad) <= PAPER.max_steering_rate_radps * dt_s + 1e-12
        assert abs(new.steering_rad) <= PAPER.max_steering_rad + 1e-12
        assert -PAPER.max_reverse_speed_mps <= new.speed_mps <= PAPER.max_speed_mps
        assert new.speed_mps * state.speed_mps >= 0.0  # a change of direction passes through rest
        assert abs(new.speed_mps) - abs(state.speed_mps) <= PAPER.max_accel_mps2 * dt_s + 1e-12
        assert abs(state.speed_mps) - abs(new.speed_mps) <= PAPER.max_decel_mps2 * dt_s + 1e-12
        # Distance covered never exceeds max speed × time. The speed is the rear axle's; while
        # steering at δ the footprint centre, L/2 ahead of it, moves √(1 + (tan δ / 2)²) faster.
        centre_factor = math.hypot(1.0, math.tan(PAPER.max_steering_rad) / 2.0)
        step_m = math.hypot(new.x_m - state.x_m, new.y_m - state.y_m)
        assert step_m <= PAPER.max_speed_mps * dt_s * centre_factor + 1e-9
        assert -math.pi <= new.theta_rad <= math.pi
        state = new


def test_footprint_is_the_rotated_rectangle_centred_on_the_pose() -> None:
    state = VehicleState(x_m=3.0, y_m=-1.0, theta_rad=math.pi / 2)
    shape = footprint(state, width_m=0.3, length_m=0.6)
    assert abs(shape.area - 0.18) < 1e-12
    assert abs(shape.centroid.x - 3.0) < 1e-12 and abs(shape.centroid.y + 1.0) < 1e-12
    minx, miny, maxx, maxy = shape.bounds
    assert abs((maxx - minx) - 0.3) < 1e-12 and abs((maxy - miny) - 0.6) < 1e-12


def test_reversing_at_the_same_steering_runs_back_along_the_same_circle() -> None:
    delta = PAPER.max_steering_rad
    state = VehicleState(x_m=0.0, y_m=0.0, theta_rad=0.0, steering_rad=delta)
    rear = []
    for target in (0.5,) * 60 + (-0.3,) * 80:
        state = step(state, limits=PAPER, target_speed_mps=target, target_steering_rad=delta, dt_s=0.05)
        rear.append(rear_axle(state, wheelbase_m=PAPER.wheelbase_m))
    assert state.speed_mps == -PAPER.max_reverse_speed_mps
    centre, radius = _fit_circle(np.array(rear))
    R = PAPER.wheelbase_m / math.tan(delta)
    assert abs(radius - R) < 1e-9 and np.allclose(centre, [-0.5 * PAPER.wheelbase_m, R], atol=1e-9)
