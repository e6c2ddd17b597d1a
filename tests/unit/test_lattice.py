"""`services.planner.lattice`: a lead-in over the car's turns onto a route it faces away from; a search to a point."""

from __future__ import annotations

import math

import numpy as np

from services.drive.controller import menger_curvature
from services.geometry import Ellipse, EllipseStack, polyline_length
from services.planner.lattice import lead_in, search

_LO, _HI = np.array([-20.0, -20.0]), np.array([20.0, 20.0])


def _lead(ellipses: list[Ellipse], *, heading_rad: float = 0.0):
    """The car at the origin, a route due west to (−10, 0), radius 1 m, joined 3 m along."""
    route = np.array([[0.0, 0.0], [-10.0, 0.0]])
    return lead_in(start=np.zeros(2), heading_rad=heading_rad, route=route, stack=EllipseStack.of(ellipses),
                   bounds_min=_LO, bounds_max=_HI, radius=1.0, level=1.0, spacing_m=0.1, ahead_m=3.0)


def _assert_drivable_onto_the_route(lead: np.ndarray, ellipses: list[Ellipse]) -> None:
    assert np.allclose(lead[0], 0.0) and lead[1, 0] > 0.0 and abs(lead[1, 1]) < 0.01  # off along the heading
    assert np.allclose(lead[-1], [-3.0, 0.0])  # onto the route, 3 m along it
    # Arcs of radius 1 m and straight stretches up to the last pose, then a straight run in to the route.
    assert np.max(menger_curvature(lead[:-1])) <= 1.0 + 1e-9
    if ellipses:
        assert EllipseStack.of(ellipses).segment_levels(lead[:-1], lead[1:]).min() >= 1.0


def test_a_car_facing_away_from_its_route_is_led_round_onto_it():
    lead = _lead([])
    _assert_drivable_onto_the_route(lead, [])
    assert polyline_length(lead) < 3.0 + math.pi * 1.0 + 3.0  # a U-turn, not a wander


def test_the_lead_in_goes_round_the_side_left_open():
    """A wall mass to the car's left (north) closes the left-hand U-turn: the lead-in turns right."""
    wall = [Ellipse.from_axes(center=(0.0, 2.2), semi_axes=(6.0, 1.0))]
    lead = _lead(wall)
    _assert_drivable_onto_the_route(lead, wall)
    assert lead[:, 1].min() < -1.0 and lead[:, 1].max() < 1.2


def test_no_lead_in_where_the_car_is_boxed_in():
    box = [Ellipse.from_axes(center=(1.6, 0.0), semi_axes=(0.5, 3.0)),
           Ellipse.from_axes(center=(0.0, 1.6), semi_axes=(3.0, 0.5)),
           Ellipse.from_axes(center=(0.0, -1.6), semi_axes=(3.0, 0.5))]
    assert _lead(box) is None


def test_a_search_to_a_point_behind_the_car_loops_round_to_it_any_way_round():
    """No direction to arrive in: the car at the origin facing east reaches a point 0.5 m behind it."""
    def clear(starts, ends):
        return np.ones(len(starts), dtype=bool)

    path = search(start=np.zeros(2), heading_rad=0.0, target=np.array([-0.5, 0.0]), facing=None, clear=clear,
                  bounds_min=_LO, bounds_max=_HI, radius=1.0, spacing_m=0.1, reach_m=math.inf, max_nodes=3000)
    assert path is not None and np.allclose(path[-1], [-0.5, 0.0])
    assert path[1, 0] > 0.0 and abs(path[1, 1]) < 0.01  # off along the heading
    # Arcs of radius 1 m and straight runs to its end: the last turns until it faces the point and runs in.
    assert np.max(menger_curvature(path)) <= 1.0 + 1e-6
    assert polyline_length(path) < 2.0 * math.pi * 1.0 + 1.0  # about one loop of the turning circle, not a wander


def test_a_search_stays_within_its_reach():
    def clear(starts, ends):
        return np.ones(len(starts), dtype=bool)

    assert search(start=np.zeros(2), heading_rad=0.0, target=np.array([-0.5, 0.0]), facing=None, clear=clear,
                  bounds_min=_LO, bounds_max=_HI, radius=1.0, spacing_m=0.1, reach_m=1.0, max_nodes=3000) is None
