"""Growth of an ellipse by a disc: it must contain the Minkowski sum, thin ellipses included; and a grown
ellipse shrunk to its keep-out scale must still contain its fit grown by the keep-out distance."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from services.geometry import Ellipse, EllipseStack, keep_out_scales


@settings(max_examples=80, deadline=None)
@given(
    axes=st.tuples(st.floats(0.001, 4.0), st.floats(0.001, 4.0)),
    angle=st.floats(0.0, np.pi),
    margin=st.floats(0.01, 2.0),
)
def test_grown_ellipse_contains_the_minkowski_sum_with_a_disc(axes, angle, margin):
    ellipse = Ellipse.from_axes(center=[1.0, -2.0], semi_axes=axes, angle_rad=angle)
    grown = ellipse.grown(margin)
    boundary = ellipse.boundary(720)
    directions = np.linspace(0.0, 2.0 * np.pi, 72, endpoint=False)
    disc = margin * np.column_stack([np.cos(directions), np.sin(directions)])
    minkowski = (boundary[:, None, :] + disc[None, :, :]).reshape(-1, 2)
    assert grown.level(minkowski).max() <= 1.0 + 1e-9


def test_growing_semi_axes_alone_would_miss_the_tip_of_a_thin_ellipse():
    thin = Ellipse.from_axes(center=[0.0, 0.0], semi_axes=[0.48, 0.05])
    tip_offset = np.array([[0.48 + 0.65 * np.cos(np.pi / 4), 0.65 * np.sin(np.pi / 4)]])
    naive = Ellipse.from_axes(center=[0.0, 0.0], semi_axes=[0.48 + 0.65, 0.05 + 0.65])
    assert naive.level(tip_offset)[0] > 1.0
    assert thin.grown(0.65).level(tip_offset)[0] <= 1.0


def test_an_ellipse_s_cached_centre_and_semi_axes_cannot_be_changed_in_place():
    ellipse = Ellipse.from_axes(center=[1.0, 2.0], semi_axes=[3.0, 0.5], angle_rad=0.4)
    assert ellipse.center is ellipse.center  # computed once
    for cached in (ellipse.center, ellipse.semi_axes):
        with pytest.raises(ValueError, match="read-only"):
            cached[0] += 1.0
    assert ellipse.center == pytest.approx([1.0, 2.0]) and ellipse.semi_axes == pytest.approx([3.0, 0.5])


def test_a_stack_is_kept_for_the_same_ellipses_and_neither_can_be_changed_in_place():
    ellipses = [
        Ellipse.circle(center=[0.0, 0.0], radius=1.0),
        Ellipse.from_axes(center=[3.0, 1.0], semi_axes=[2.0, 0.5], angle_rad=0.3),
    ]
    stack = EllipseStack.of(ellipses)
    assert EllipseStack.of(list(ellipses)) is stack  # the same ellipses: the stack (and its caches) again
    assert EllipseStack.of([Ellipse(A=e.A, b=e.b) for e in ellipses]) is not stack  # equal, not the same
    for array in (ellipses[1].A, ellipses[1].b, stack.A, stack.b):
        with pytest.raises(ValueError, match="read-only"):
            array[0] += 1.0
    assert np.array_equal(stack.A[1], ellipses[1].A) and np.array_equal(stack.b[1], ellipses[1].b)


def test_forget_drops_the_kept_stacks():
    ellipses = [Ellipse.circle(center=[0.0, 0.0], radius=1.0)]
    stack = EllipseStack.of(ellipses)
    EllipseStack.forget()
    assert EllipseStack.of(ellipses) is not stack


def test_a_polyline_s_level_is_the_least_segment_level_to_the_bit():
    rng = np.random.default_rng(3)
    stack = EllipseStack.of([
        Ellipse.from_axes(center=c, semi_axes=a, angle_rad=t)
        for c, a, t in zip(rng.uniform(-5, 5, (40, 2)), rng.uniform(0.2, 2.0, (40, 2)), rng.uniform(0, np.pi, 40))
    ])
    polylines = [rng.uniform(-8, 8, (int(rng.integers(2, 5)), 2)) for _ in range(50)]
    for points in polylines + polylines[::-1]:  # asked again, some answers are the kept ones
        assert stack.polyline_level(points) == stack.segment_levels(points[:-1], points[1:]).min()
    assert stack.polyline_level([[1.0, 1.0], [1.0, 1.0]]) == stack.levels([[1.0, 1.0]]).min()  # a point
    assert np.isnan(stack.polyline_level([[0.0, 0.0], [np.nan, 1.0], [3.0, 3.0]]))  # kept, to fail every test
    assert EllipseStack.of([]).polyline_level([[0.0, 0.0], [1.0, 1.0]]) == np.inf


def test_segments_clear_is_the_whole_stack_s_segment_test_for_a_car_s_next_motions():
    """The broad phase leaves out only ellipses the segments pass above the level: the answer is the
    exact test against all of them, also for segments that graze an ellipse at the level (thin walls,
    far from the origin as a map in UTM metres is)."""
    rng = np.random.default_rng(11)
    origin = np.array([4.6e5, 5.3e6])
    ellipses = [
        Ellipse.from_axes(center=origin + c, semi_axes=a, angle_rad=t)
        for c, a, t in zip(rng.uniform(-6, 6, (120, 2)), rng.uniform(0.02, 1.5, (120, 2)), rng.uniform(0, np.pi, 120))
    ]
    stack = EllipseStack.of(ellipses)
    level = 1.01
    found = {True: 0, False: 0}
    for _ in range(300):
        at = origin + rng.uniform(-7, 7, 2)
        starts = at + rng.uniform(-0.4, 0.4, (9, 2))
        ends = starts + rng.uniform(-0.2, 0.2, (9, 2))
        exact = stack.segment_levels(starts, ends).min(axis=1) >= level
        assert np.array_equal(stack.segments_clear(starts, ends, level=level), exact)
        for clear in exact.tolist():
            found[clear] += 1
    assert min(found.values()) > 100  # both answers asked for
    # A segment tangent to an ellipse's boundary scaled to the level (c + level A⁻¹ w) just outside it,
    # and one just inside.
    e = ellipses[0]
    alone = EllipseStack.of([e])
    w, along = np.array([np.cos(0.7), np.sin(0.7)]), np.array([-np.sin(0.7), np.cos(0.7)])
    rim, tangent = e.center + level * np.linalg.solve(e.A, w), np.linalg.solve(e.A, along)
    for scale, clear in ((1.0 + 1e-6, True), (1.0 - 1e-6, False)):
        point = e.center + scale * (rim - e.center)
        starts, ends = (point - 1e-3 * tangent)[None], (point + 1e-3 * tangent)[None]
        assert alone.segments_clear(starts, ends, level=level).tolist() == [clear]
        assert (alone.segment_levels(starts, ends).min() >= level) == clear
    assert EllipseStack.of([]).segments_clear([[0.0, 0.0]], [[1.0, 1.0]], level=level).tolist() == [True]


def test_growing_a_disc_adds_the_margin_to_its_radius():
    grown = Ellipse.circle(center=[3.0, 4.0], radius=0.7).grown(0.65)
    assert grown.semi_axes == pytest.approx([1.35, 1.35], rel=1e-9)
    assert grown.center == pytest.approx([3.0, 4.0])


@settings(max_examples=80, deadline=None)
@given(
    axes=st.tuples(st.floats(0.001, 4.0), st.floats(0.001, 4.0)),
    angle=st.floats(0.0, np.pi),
    inflation=st.floats(0.05, 2.0),
    keep_fraction=st.floats(0.0, 1.0),
)
def test_the_keep_out_scale_keeps_the_fit_plus_the_keep_out_disc_inside(axes, angle, inflation, keep_fraction):
    fit = Ellipse.from_axes(center=[1.0, -2.0], semi_axes=axes, angle_rad=angle)
    grown = fit.grown(inflation)
    keep = keep_fraction * inflation
    scale = keep_out_scales(grown.semi_axes[None, :], inflation_m=inflation, keep_m=keep)[0]
    assert 0.0 < scale <= 1.0
    boundary = fit.boundary(720)
    directions = np.linspace(0.0, 2.0 * np.pi, 72, endpoint=False)
    disc = keep * np.column_stack([np.cos(directions), np.sin(directions)])
    minkowski = (boundary[:, None, :] + disc[None, :, :]).reshape(-1, 2)
    assert grown.level(minkowski).max() <= scale * (1.0 + 1e-9)  # inside the grown ellipse scaled by `scale`


def test_the_keep_out_scale_gives_a_disc_exactly_the_keep_out_radius():
    grown = Ellipse.circle(center=[0.0, 0.0], radius=1.0).grown(0.65)
    assert keep_out_scales(grown.semi_axes[None, :], inflation_m=0.65, keep_m=0.585)[0] == pytest.approx(1.585 / 1.65)
