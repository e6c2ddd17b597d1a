"""Löwner–John ellipses (eq. 1, maximise log det A): reference shapes, both routes, degenerate sets."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from services.ellipsoids.mvee import FitError, mvee, mvee_fast, mvee_fast_support

ROUTES = [mvee, mvee_fast]
CONTAIN_TOL = 1e-9


@pytest.mark.parametrize("fit", ROUTES)
def test_square_corners_give_circumscribed_circle(fit):
    corners = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]])
    e = fit(corners)
    np.testing.assert_allclose(e.center, [0.5, 0.5], atol=1e-5)
    np.testing.assert_allclose(e.semi_axes, [np.sqrt(0.5)] * 2, rtol=1e-5)


@pytest.mark.parametrize("fit", ROUTES)
def test_equilateral_triangle_gives_circumcircle(fit):
    angles = np.pi / 2 + 2 * np.pi * np.arange(3) / 3
    corners = np.array([3.0, -1.0]) + 2.0 * np.column_stack([np.cos(angles), np.sin(angles)])
    e = fit(corners)
    np.testing.assert_allclose(e.center, [3.0, -1.0], atol=1e-5)
    np.testing.assert_allclose(e.semi_axes, [2.0, 2.0], rtol=1e-5)


@pytest.mark.parametrize("fit", ROUTES)
def test_rectangle_gives_sqrt2_scaled_axes(fit):
    corners = np.array([[0.0, 0.0], [4.0, 0.0], [4.0, 2.0], [0.0, 2.0]])
    e = fit(corners)
    np.testing.assert_allclose(e.center, [2.0, 1.0], atol=1e-5)
    np.testing.assert_allclose(e.semi_axes, np.sqrt(2.0) * np.array([2.0, 1.0]), rtol=1e-5)
    assert abs(abs(e.rotation[0, 0]) - 1.0) < 1e-5  # major axis along x


point_sets = arrays(
    np.float64,
    st.tuples(st.integers(3, 40), st.just(2)),
    elements=st.floats(-10.0, 10.0, allow_nan=False, allow_infinity=False),
)


@settings(max_examples=25, deadline=None)
@given(points=point_sets)
def test_routes_agree_in_area(points):
    slow, fast = mvee(points), mvee_fast(points)
    assert abs(slow.area - fast.area) <= 1e-5 * slow.area


@settings(max_examples=40, deadline=None)
@given(points=point_sets)
@pytest.mark.parametrize("fit", ROUTES)
def test_every_point_is_inside(fit, points):
    assert np.max(fit(points).level(points)) <= 1.0 + CONTAIN_TOL


@settings(max_examples=40, deadline=None)
@given(points=point_sets)
def test_the_numpy_support_lies_on_the_ellipse_and_interior_points_change_nothing(points):
    """The numpy route fits every point, not only the hull's vertices: the points it puts weight on lie
    on the ellipse, and points added strictly inside it neither enter the support nor move the ellipse."""
    ellipse, support = mvee_fast_support(points)
    if support is None:  # a degenerate set is fitted to fattened points, not its own
        return
    assert np.all(np.abs(ellipse.level(points[support]) - 1.0) <= 1e-6)
    inner = ellipse.center + 0.5 * (points - ellipse.center)  # level halved: strictly inside
    again, support_again = mvee_fast_support(np.vstack([points, inner]))
    assert np.all(support_again < len(points))
    assert abs(again.area - ellipse.area) <= 1e-8 * ellipse.area


@pytest.mark.parametrize("fit", ROUTES)
@pytest.mark.parametrize(
    "points",
    [
        np.array([[1.0, 2.0]]),
        np.array([[0.0, 0.0], [3.0, 4.0]]),
        np.column_stack([np.linspace(0.0, 9.0, 10), 0.5 * np.linspace(0.0, 9.0, 10) + 1.0]),
        np.repeat([[2.0, -1.0]], 7, axis=0),
        np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 0.0], [0.0, 0.0]]),
    ],
    ids=["one", "two", "collinear", "all-duplicates", "duplicated-segment"],
)
def test_degenerate_sets_give_thin_valid_ellipse(fit, points):
    e = fit(points)
    assert np.max(e.level(points)) <= 1.0 + CONTAIN_TOL
    assert e.semi_axes[1] < 1e-2  # thin: fattened by about 1 mm, not inflated
    extent = np.max(np.linalg.norm(points - points.mean(axis=0), axis=1))
    assert e.semi_axes[0] <= 2.0 * extent + 1e-2


def test_a_diagonal_sliver_thinner_than_the_fattening_is_contained():
    """Three sensed points 0.7 mm off a 45° line (from a closed-loop run of field-25): the fattened
    set must hold the middle one, whatever the line's direction."""
    points = np.array([[8.54116664160529, 9.09906675978574], [8.548365774815917, 9.105636475188584],
                       [8.61118252330341, 9.17641337263159]])
    e = mvee_fast(points)
    assert np.max(e.level(points)) <= 1.0 + CONTAIN_TOL


def test_nearly_collinear_but_wide_enough_is_not_fattened():
    points = np.array([[0.0, 0.0], [4.0, 0.0], [4.0, 0.01], [0.0, 0.01]])
    e = mvee_fast(points)
    np.testing.assert_allclose(e.semi_axes, np.sqrt(2.0) * np.array([2.0, 0.005]), rtol=1e-5)


@pytest.mark.parametrize("fit", ROUTES)
@pytest.mark.parametrize("bad", [np.zeros((0, 2)), np.array([[np.nan, 0.0]]), np.zeros((3, 3))])
def test_bad_input_raises_fit_error(fit, bad):
    with pytest.raises(FitError):
        fit(bad)


def test_unknown_solver_raises_fit_error():
    with pytest.raises(FitError):
        mvee(np.eye(2) * [[1.0], [2.0]] + [[0.0, 1.0], [1.0, 0.0]], solver="NO_SUCH_SOLVER")
