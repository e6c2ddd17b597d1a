"""Eq. (3) with ellipse constraints: closest points, known gaps, and grouping by the robot's width."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.sparse.csgraph import connected_components

from services.ellipsoids.gap import ellipse_gap, group_ellipses
from services.geometry import Ellipse


def test_gap_between_discs():
    e1 = Ellipse.circle(center=(0.0, 0.0), radius=1.0)
    e2 = Ellipse.circle(center=(3.0, 4.0), radius=1.5)
    gap = ellipse_gap(e1, e2)
    assert gap.distance_m == pytest.approx(5.0 - 2.5, abs=1e-5)
    np.testing.assert_allclose(gap.point_1, [0.6, 0.8], atol=1e-4)
    np.testing.assert_allclose(gap.point_2, [3.0 - 0.9, 4.0 - 1.2], atol=1e-4)


def test_gap_between_axis_aligned_ellipses_on_x_axis():
    e1 = Ellipse.from_axes(center=(0.0, 0.0), semi_axes=(2.0, 0.5))
    e2 = Ellipse.from_axes(center=(5.0, 0.0), semi_axes=(1.0, 3.0))
    gap = ellipse_gap(e1, e2)
    assert gap.distance_m == pytest.approx((5.0 - 1.0) - 2.0, abs=1e-5)


def test_far_apart_ellipses_far_from_origin():
    e1 = Ellipse.from_axes(center=(1000.0, 200.0), semi_axes=(0.3, 0.1), angle_rad=0.4)
    e2 = Ellipse.circle(center=(1010.0, 200.0), radius=0.2)
    gap = ellipse_gap(e1, e2)
    assert np.max(e1.level(gap.point_1)) <= 1.0 + 1e-6
    assert np.max(e2.level(gap.point_2)) <= 1.0 + 1e-6
    assert gap.distance_m == pytest.approx(np.linalg.norm(gap.point_1 - gap.point_2), abs=1e-9)
    assert 10.0 - 0.5 <= gap.distance_m <= 10.0 - 0.3


def test_overlapping_ellipses_have_zero_gap():
    e1 = Ellipse.from_axes(center=(0.0, 0.0), semi_axes=(2.0, 0.5), angle_rad=0.3)
    e2 = Ellipse.from_axes(center=(1.5, 0.5), semi_axes=(1.0, 0.4), angle_rad=-0.7)
    assert ellipse_gap(e1, e2).distance_m == pytest.approx(0.0, abs=1e-6)


def test_group_ellipses_by_min_gap():
    discs = [
        Ellipse.circle(center=(0.0, 0.0), radius=1.0),
        Ellipse.circle(center=(2.5, 0.0), radius=1.0),  # gap 0.5 to the first
        Ellipse.circle(center=(5.7, 0.0), radius=1.0),  # gap 1.2 to the second
    ]
    labels = group_ellipses(discs, min_gap_m=0.8)
    assert labels[0] == labels[1] != labels[2]
    assert len(set(group_ellipses(discs, min_gap_m=1.5))) == 1
    assert len(set(group_ellipses(discs, min_gap_m=0.3))) == 3


def test_group_needs_the_socp_for_elongated_ellipses():
    # Bounding circles overlap but the ellipses are parallel thin bars 1 m apart.
    bars = [
        Ellipse.from_axes(center=(0.0, 0.0), semi_axes=(3.0, 0.1)),
        Ellipse.from_axes(center=(0.0, 1.2), semi_axes=(3.0, 0.1)),
    ]
    assert len(set(group_ellipses(bars, min_gap_m=0.8))) == 2
    assert len(set(group_ellipses(bars, min_gap_m=1.2))) == 1


def test_groups_are_the_components_of_every_pair_closer_than_the_gap():
    # One long bar among small ellipses: the candidate pairs come from a KD-tree of the centres within
    # min_gap + 2 × the largest semi-axis, which must still find a small ellipse beside the bar's middle,
    # far from the bar's centre. Every pair's gap solved: the labels are those components.
    rng = np.random.default_rng(3)
    ellipses = [Ellipse.from_axes(center=(0.0, 0.0), semi_axes=(8.0, 0.2))]
    ellipses += [Ellipse.from_axes(center=rng.uniform(-9, 9, 2), semi_axes=np.sort(rng.uniform(0.05, 0.6, 2))[::-1],
                                   angle_rad=rng.uniform(0, 3)) for _ in range(29)]
    ellipses.append(Ellipse.circle(center=(6.0, 0.9), radius=0.3))  # 0.4 from the bar, 6 m from its centre
    min_gap = 0.5
    m = len(ellipses)
    close = np.zeros((m, m), dtype=bool)
    for a in range(m):
        for b in range(a + 1, m):
            close[a, b] = ellipse_gap(ellipses[a], ellipses[b]).distance_m < min_gap
    _, expected = connected_components(close, directed=False)
    labels = group_ellipses(ellipses, min_gap_m=min_gap)
    assert labels[0] == labels[-1]
    assert len(set(expected)) < m - 1  # some groups form, and some ellipses stay apart
    assert np.array_equal(labels[:, None] == labels[None, :], expected[:, None] == expected[None, :])


def test_group_of_nothing_and_of_one():
    assert group_ellipses([], min_gap_m=1.0).shape == (0,)
    assert list(group_ellipses([Ellipse.circle(center=(0, 0), radius=1.0)], min_gap_m=1.0)) == [0]


def test_direct_clarabel_gap_agrees_with_the_cvxpy_model():
    rng = np.random.default_rng(7)
    for _ in range(10):
        e1 = Ellipse.from_axes(center=rng.uniform(-3, 3, 2), semi_axes=rng.uniform(0.1, 2, 2), angle_rad=rng.uniform(0, 3))
        e2 = Ellipse.from_axes(center=rng.uniform(-3, 3, 2) + 5, semi_axes=rng.uniform(0.1, 2, 2), angle_rad=rng.uniform(0, 3))
        direct = ellipse_gap(e1, e2)
        model = ellipse_gap(e1, e2, method="cvxpy")
        assert direct.distance_m == pytest.approx(model.distance_m, abs=1e-6)
