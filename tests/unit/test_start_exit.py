"""`services.maps.start`: the proof that no forward path leaves a start hemmed in by walls, tried against a
wall of known distance and, for soundness, against curves actually driven out of random starts on the
depot's map."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from schemas.occupancy import OccupancyGrid, load_map
from services.maps.start import forward_exit, hemmed_in

_RES = 0.05


def _wall_ahead(gap_m: float, *, margin_m: float = 0.3, origin=(0.0, 0.0, 0.0)) -> OccupancyGrid:
    """A 10 × 10 m map, its right half solid from x = 5 + `gap_m` + margin (in the map's frame): the car, at
    (5, 5) facing +x there, has `gap_m` of margin-clear floor ahead of it."""
    mask = np.zeros((200, 200), dtype=bool)
    mask[:, int(round((5.0 + gap_m + margin_m) / _RES)) :] = True
    return OccupancyGrid.from_mask(mask, resolution_m=_RES, origin=origin)


@pytest.mark.parametrize("gap_m, leaves", [(0.6, False), (0.8, False), (1.05, True), (2.0, True)])
@pytest.mark.parametrize("origin", [(0.0, 0.0, 0.0), (4.2e5, 5.6e6, 0.7)])
def test_a_car_facing_a_wall_nearer_than_its_turning_radius_cannot_leave_forward(gap_m, leaves, origin):
    """Radius 1 m: a straight wall 0.8 m ahead (less than √3/2 of the radius) is proved to stop every forward
    path; 1.05 m ahead the car drives straight out of the radius. The same on a map in UTM metres, turned."""
    grid = _wall_ahead(gap_m, origin=origin)
    start = grid.to_world([5.0, 5.0])[0]
    yaw = origin[2]
    assert forward_exit(grid, start=start, heading_rad=yaw, radius_m=1.0, margin_m=0.3) is leaves
    # Along the wall, or facing away from it, the way is open.
    for heading in (math.pi / 2, -math.pi / 2, math.pi):
        assert forward_exit(grid, start=start, heading_rad=yaw + heading, radius_m=1.0, margin_m=0.3)


def test_a_car_turning_wider_than_the_map_is_judged_within_the_map():
    """A turning radius of 10 km (the scenario allows a 100 m wheelbase steering 0.01 rad): the cells looked
    at stop at the map's edges (a window of the radius would not fit in memory)."""
    start = np.array([5.0, 5.0])
    assert not forward_exit(_wall_ahead(0.6), start=start, heading_rad=0.0, radius_m=1e4, margin_m=0.3)
    # Nor does any path come 10 km from the start on a 10 m map, whichever way the car faces.
    for heading in (math.pi, math.pi / 2):
        assert not forward_exit(_wall_ahead(2.0), start=start, heading_rad=heading, radius_m=1e4, margin_m=0.3)


def test_the_reason_names_the_radius_and_the_margin_and_is_given_only_where_proved():
    grid = _wall_ahead(0.6)
    start, behind, ahead = np.array([5.0, 5.0]), np.array([1.0, 5.0]), np.array([5.5, 5.0])
    reason = hemmed_in(grid, start=start, heading_rad=0.0, goal=behind, radius_m=1.0, margin_m=0.3)
    assert "turning radius 1.00 m" in reason and "margin (0.300 m)" in reason and "never reverses" in reason
    assert hemmed_in(grid, start=start, heading_rad=None, goal=behind, radius_m=1.0, margin_m=0.3) == ""
    # A goal within the radius may lie in the room the car has: not this proof's to judge.
    assert hemmed_in(grid, start=start, heading_rad=0.0, goal=ahead, radius_m=1.0, margin_m=0.3) == ""


def _driven_out(grid: OccupancyGrid, start: np.ndarray, heading: float, *, radius_m: float, margin_m: float,
                rng: np.random.Generator, curves: int = 120) -> bool:
    """Whether one of `curves` random forward curves of curvature at most 1 / radius (six pieces of constant
    curvature, the extremes among them) comes `radius_m` from the start keeping the margin all the way."""
    step, pieces = 0.01, 6
    n = int(math.ceil(0.5 * math.pi * radius_m / step))
    kappa = rng.uniform(-1.0, 1.0, size=(curves, pieces))
    extreme = rng.random(kappa.shape) < 0.3
    kappa[extreme] = rng.choice([-1.0, 1.0], size=int(extreme.sum()))
    kappa[:3] = [[-1.0], [0.0], [1.0]]  # hard left, straight, hard right
    turn = np.repeat(kappa / radius_m, -(-n // pieces), axis=1)[:, :n] * step
    psi = heading + np.cumsum(turn, axis=1) - 0.5 * turn  # the heading at each step's middle
    z = start + np.cumsum(step * np.stack([np.cos(psi), np.sin(psi)], axis=-1), axis=1)
    clear = grid.clearance(z.reshape(-1, 2)).reshape(curves, n) >= margin_m + 1e-3
    out = np.linalg.norm(z - start, axis=-1) >= radius_m
    first_out = np.where(out.any(axis=1), out.argmax(axis=1), n)
    return bool(any(first < n and clear[k, : first + 1].all() for k, first in enumerate(first_out)))


def test_no_start_judged_hemmed_in_on_the_depot_is_left_by_a_driven_curve(shared_dir: Path):
    """200 random starts on the depot's free floor, random headings (the depot scenarios' car: turning radius
    0.88 m, margin 0.45 m): wherever one of 120 random curves drives out of the radius keeping the margin,
    the proof must not have said none does. Neither side is vacuous: the proof finds starts hemmed in,
    and the curves drive out of most starts."""
    grid = load_map(shared_dir / "maps" / "depot.yaml")
    radius_m, margin_m = 0.6 / math.tan(0.6), 0.45
    rng = np.random.default_rng(43)
    free = np.argwhere(~grid.blocked)
    picks = free[rng.choice(len(free), size=4000, replace=False)]
    points = grid.to_world((picks[:, ::-1] + rng.random((len(picks), 2))) * grid.resolution_m)
    starts = points[grid.clearance(points) >= margin_m][:200]
    hemmed, driven = 0, 0
    for start in starts:
        heading = float(rng.uniform(-math.pi, math.pi))
        leaves = forward_exit(grid, start=start, heading_rad=heading, radius_m=radius_m, margin_m=margin_m)
        out = _driven_out(grid, start, heading, radius_m=radius_m, margin_m=margin_m, rng=rng)
        assert leaves or not out, (start.tolist(), heading)
        hemmed += not leaves
        driven += out
    assert hemmed >= 8 and driven >= 150, (hemmed, driven)
