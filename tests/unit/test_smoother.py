"""Smoother: the B-spline's end conditions and the continuous verification it must pass."""

from __future__ import annotations

import numpy as np
import pytest

from services.geometry import Ellipse
from services.smoother.core import bspline, sample, smooth, verify

BOUNDS = dict(bounds_min=np.array([-10.0, -10.0]), bounds_max=np.array([30.0, 30.0]))


def _arc(radius: float, n: int = 60) -> np.ndarray:
    t = np.linspace(0.0, np.pi / 2, n)
    return np.column_stack([radius * np.sin(t), radius * (1 - np.cos(t))])


def _heading(control: np.ndarray) -> float:
    d = control[1] - control[0]
    return float(np.arctan2(d[1], d[0]))


def test_curve_starts_at_start_along_the_first_leg_and_ends_at_the_last_point():
    control = _arc(5.0)
    curve = bspline(control)
    assert np.allclose(curve(0.0), control[0])
    assert np.allclose(curve(1.0), control[-1])
    d = curve.derivative(1)(0.0)
    assert abs(np.arctan2(d[1], d[0]) - _heading(control)) < 1e-9


def test_circle_of_known_radius_verifies_with_its_curvature():
    control = _arc(5.0)
    result = smooth(
        control, ellipses=[], max_curvature=0.25, heading_rad=_heading(control), goals=control[-1:], goal_tolerance_m=0.01, **BOUNDS
    )
    assert result.verification.ok, result.verification.reason
    assert result.verification.max_curvature == pytest.approx(0.2, rel=0.02)
    assert np.linalg.norm(np.diff(result.points, axis=0), axis=1).max() <= 0.05


def test_curvature_over_the_bound_is_rejected():
    control = _arc(2.0)
    result = smooth(
        control, ellipses=[], max_curvature=0.3, heading_rad=_heading(control), goals=control[-1:], goal_tolerance_m=0.01, **BOUNDS
    )
    assert not result.verification.ok
    assert "curvature" in result.verification.reason


def test_a_curvature_rejection_says_how_far_along_the_curve_it_is_broken():
    # 4 m straight, then a quarter circle of radius 1 m (curvature 1 against a bound of 0.5): the curve
    # breaks the bound on the arc, 4 to 5.6 m from its start.
    straight = np.column_stack([np.linspace(0.0, 4.0, 41)[:-1], np.zeros(40)])
    control = np.vstack([straight, _arc(1.0, 20) + [4.0, 0.0]])
    result = smooth(control, ellipses=[], max_curvature=0.5, heading_rad=0.0, goals=control[-1:], goal_tolerance_m=0.01,
                    **BOUNDS)
    assert not result.verification.ok
    where = float(result.verification.reason.split(", ")[-1].split(" m along")[0])
    assert 3.8 <= where <= 4.0 + np.pi / 2 + 0.2, result.verification.reason


def test_curve_entering_an_ellipse_is_rejected_even_between_control_points():
    # The curve cuts the control polygon's corner; a small disc sits in that corner, clear of every
    # control point and of the polygon, but not of the curve.
    control = np.array([[0.0, 0.0], [1.0, 0.0], [2.0, 2.0], [3.0, 0.0], [4.0, 0.0]])
    curve = bspline(control)
    apex = curve(0.5)
    disc = Ellipse.circle(center=apex, radius=0.1)
    assert disc.level(control).min() > 1.0
    check = verify(
        curve,
        ellipses=[disc],
        max_curvature=100.0,
        start=control[0],
        heading_rad=0.0,
        goals=control[-1:],
        goal_tolerance_m=0.01,
        **BOUNDS,
    )
    assert not check.ok
    assert "enters an ellipse" in check.reason
    dense = curve(np.linspace(0, 1, 20001))
    # Long and flat above the apex: its bounding disc overlaps the curve, its body stays ~5 cm clear.
    far = Ellipse.from_axes(center=apex + [0.0, 0.25], semi_axes=[1.0, 0.2])
    bound = verify(curve, ellipses=[far], max_curvature=100.0, start=control[0], heading_rad=0.0,
                   goals=control[-1:], goal_tolerance_m=0.01, **BOUNDS).min_level
    assert 1.0 < bound <= far.level(dense).min() + 1e-12  # clear, and the verified figure is a true lower bound


def test_missed_goal_and_wrong_heading_are_rejected():
    control = _arc(5.0)
    common = dict(ellipses=[], max_curvature=1.0, goal_tolerance_m=0.1, **BOUNDS)
    missed = smooth(control, heading_rad=_heading(control), goals=np.array([[0.0, 5.0]]), **common)
    assert "misses goal" in missed.verification.reason
    wrong = smooth(control, heading_rad=_heading(control) + 0.1, goals=control[-1:], **common)
    assert "heading" in wrong.verification.reason


def test_sample_spacing_is_bounded():
    points = sample(bspline(_arc(5.0)), spacing_m=0.05)
    assert np.linalg.norm(np.diff(points, axis=0), axis=1).max() <= 0.05


def test_straight_control_points_are_judged_as_the_chord_they_are():
    # Evenly spaced points on a line: the B-spline is the chord, so one exact segment test decides.
    control = np.linspace([0.0, 0.0], [10.0, 10.0], 158)
    near = Ellipse.from_axes(center=[5.0, 3.0], semi_axes=[2.0, 1.0], angle_rad=0.3)
    common = dict(max_curvature=1.0, heading_rad=np.pi / 4, goals=np.array([[10.0, 10.0]]), goal_tolerance_m=0.3, **BOUNDS)
    fast = smooth(control, ellipses=[near], **common)
    general = verify(bspline(control), ellipses=[near], start=control[0], **common)
    assert fast.verification.ok and general.ok
    assert fast.verification.min_level == pytest.approx(general.min_level, rel=1e-9)
    assert fast.verification.max_curvature <= 1e-6
    assert np.linalg.norm(np.diff(fast.points, axis=0), axis=1).max() <= 0.05
    assert np.allclose(fast.points[[0, -1]], control[[0, -1]])
    blocking = Ellipse.circle(center=[5.0, 5.2], radius=0.5)
    assert "enters an ellipse" in smooth(control, ellipses=[near, blocking], **common).verification.reason
    turned = dict(common, heading_rad=0.0)
    assert "heading" in smooth(control, ellipses=[near], **turned).verification.reason


def test_points_within_1e_9_of_their_chord_are_smoothed_to_it_and_points_further_off_are_not():
    # A 14.14 m chord: a zigzag of 1e-8 m across it (under 1e-9 of its length) is smoothed to the chord
    # itself, published as its samples, with no curvature; one of 1e-6 m is a B-spline, judged as one.
    along = np.linspace([0.0, 0.0], [10.0, 10.0], 158)
    across = np.array([-1.0, 1.0]) / np.sqrt(2.0) * np.resize([0.0, 1.0], 158)[:, None]
    across[-1] = 0.0  # the ends stay put: the chord runs (0, 0) → (10, 10)
    common = dict(ellipses=[Ellipse.circle(center=[5.0, 0.0], radius=1.0)], max_curvature=1.0,
                  heading_rad=np.pi / 4, goals=np.array([[10.0, 10.0]]), goal_tolerance_m=0.3, **BOUNDS)
    chord = smooth(along + 1e-8 * across, **common)
    assert chord.verification.ok and chord.verification.max_curvature == 0.0
    t = np.linspace(0.0, 1.0, len(chord.points))[:, None]
    assert np.allclose(chord.points, t * [10.0, 10.0], rtol=0.0, atol=1e-12)  # on the chord, not the zigzag
    assert np.linalg.norm(np.diff(chord.points, axis=0), axis=1).max() <= 0.05
    curve = smooth(along + 1e-6 * across, **common)
    assert curve.verification.max_curvature > 0.0  # the B-spline's own curvature, measured
    backwards = smooth(along[::-1].copy(), **dict(common, heading_rad=-3 * np.pi / 4, goals=np.array([[0.0, 0.0]])))
    assert backwards.verification.ok and backwards.verification.max_curvature == 0.0


def test_the_verdict_does_not_depend_on_the_control_points_layout():
    # The straight test and the verdict read the points as complex numbers: a Fortran-ordered, float32
    # or strided array must give the same answer as a C-ordered float64 one.
    control = np.linspace([0.0, 0.0], [10.0, 10.0], 158)
    common = dict(ellipses=[Ellipse.circle(center=[5.0, 0.0], radius=1.0)], max_curvature=1.0, heading_rad=np.pi / 4,
                  goals=np.array([[10.0, 10.0]]), goal_tolerance_m=0.3, **BOUNDS)
    expected = smooth(control, **common).verification
    strided = np.repeat(control, 2, axis=0)[::2]  # every other row of a larger array
    assert not strided.flags.c_contiguous
    for layout in (np.asfortranarray(control), control.astype(np.float32), strided):
        got = smooth(layout, **common).verification
        assert got.ok == expected.ok and got.min_level == pytest.approx(expected.min_level, rel=1e-6)
    missed = dict(common, goals=np.array([[10.0, 12.0]]))
    assert "misses goal 0 by 2.000 m" in smooth(np.asfortranarray(control), **missed).verification.reason


def test_a_nan_is_refused_and_a_curve_off_the_map_is_not_verified():
    control = np.linspace([0.0, 0.0], [10.0, 10.0], 158)
    common = dict(ellipses=[Ellipse.circle(center=[5.0, 0.0], radius=1.0)], max_curvature=1.0, heading_rad=np.pi / 4,
                  goals=np.array([[10.0, 10.0]]), goal_tolerance_m=0.3)
    assert smooth(control, **common, **BOUNDS).verification.ok
    broken = control.copy()
    broken[80, 1] = np.nan  # not taken for a straight chord (which would hide it): the curve check refuses it
    with pytest.raises(ValueError, match="finite"):
        smooth(broken, **common, **BOUNDS)
    small = dict(bounds_min=np.array([-1.0, -1.0]), bounds_max=np.array([9.0, 11.0]))
    assert smooth(control, **common, **small).verification.reason == "curve leaves the map bounds"
