"""Range sensor: exact hits, field of view, range limit, seeded noise."""

from __future__ import annotations

import math

import numpy as np
import shapely

from sim.sensor import Circle, RangeSensor, RayTargets, cast_rays

SENSOR = RangeSensor(fov_deg=180.0, range_m=5.0, rays=181)


def test_square_ahead_is_hit_exactly_on_its_near_face() -> None:
    # Square [3, 4] × [-0.5, 0.5], robot at the origin looking along +x.
    square = shapely.box(3.0, -0.5, 4.0, 0.5)
    hits = SENSOR.scan(x_m=0.0, y_m=0.0, theta_rad=0.0, obstacles=[square])
    assert len(hits) > 0
    np.testing.assert_allclose(hits[:, 0], 3.0, atol=1e-9)
    assert np.all(np.abs(hits[:, 1]) <= 0.5 + 1e-9)
    # The straight-ahead beam measures exactly 3 m.
    ranges = SENSOR.ranges(x_m=0.0, y_m=0.0, theta_rad=0.0, obstacles=[square])
    assert abs(ranges[90] - 3.0) < 1e-9
    # Every hit lies at the beam's exact distance: range = 3 / cos(angle).
    angles = SENSOR.ray_angles_rad(0.0)
    seen = np.isfinite(ranges)
    np.testing.assert_allclose(ranges[seen], 3.0 / np.cos(angles[seen]), atol=1e-9)
    # Beams that miss are exactly the ones whose line passes beside the square's face.
    assert np.array_equal(seen, np.abs(3.0 * np.tan(angles)) <= 0.5 + 1e-12)


def test_box_behind_is_not_seen_with_180_degree_fov() -> None:
    behind = shapely.box(-3.0, -0.5, -2.0, 0.5)
    assert len(SENSOR.scan(x_m=0.0, y_m=0.0, theta_rad=0.0, obstacles=[behind])) == 0
    # Turned around, the same box is seen.
    hits = SENSOR.scan(x_m=0.0, y_m=0.0, theta_rad=math.pi, obstacles=[behind])
    np.testing.assert_allclose(hits[:, 0], -2.0, atol=1e-9)


def test_hits_stay_within_the_field_of_view() -> None:
    narrow = RangeSensor(fov_deg=60.0, range_m=10.0, rays=61)
    ring = shapely.Point(0.0, 0.0).buffer(4.0).difference(shapely.Point(0.0, 0.0).buffer(3.0))
    theta = 0.7
    hits = narrow.scan(x_m=0.0, y_m=0.0, theta_rad=theta, obstacles=[ring])
    assert len(hits) == 61  # the ring surrounds the robot: every beam hits the inner wall
    bearing = np.arctan2(hits[:, 1], hits[:, 0]) - theta
    assert np.all(np.abs(bearing) <= math.radians(30.0) + 1e-12)


def test_obstacle_beyond_range_is_not_seen() -> None:
    far = shapely.box(6.0, -1.0, 7.0, 1.0)
    assert len(SENSOR.scan(x_m=0.0, y_m=0.0, theta_rad=0.0, obstacles=[far])) == 0
    assert len(SENSOR.scan(x_m=1.5, y_m=0.0, theta_rad=0.0, obstacles=[far])) > 0


def test_circle_hit_distance_matches_the_analytic_value() -> None:
    circle = Circle(center=(4.0, 1.0), radius_m=0.75)
    angles = np.linspace(-0.4, 0.6, 41)
    ranges = cast_rays(origin=(0.0, 0.0), angles_rad=angles, targets=RayTargets.of([circle]))
    # Analytic: with ray direction d, t = d·c − sqrt((d·c)² − |c|² + r²) where the root is real.
    d = np.column_stack([np.cos(angles), np.sin(angles)])
    dc = d @ np.array([4.0, 1.0])
    disc = dc**2 - 17.0 + 0.75**2
    expected = np.where(disc >= 0, dc - np.sqrt(np.maximum(disc, 0)), np.inf)
    assert np.isfinite(expected).sum() > 5 and np.isinf(expected).sum() > 5
    np.testing.assert_allclose(ranges[np.isfinite(expected)], expected[np.isfinite(expected)], atol=1e-9)
    assert np.array_equal(np.isfinite(ranges), np.isfinite(expected))
    # Straight at the centre: |c| − r.
    straight = cast_rays(origin=(0.0, 0.0), angles_rad=np.array([math.atan2(1.0, 4.0)]),
                         targets=RayTargets.of([circle]))
    assert abs(straight[0] - (math.sqrt(17.0) - 0.75)) < 1e-12


def test_nearest_surface_wins_among_several_obstacles() -> None:
    obstacles = [shapely.box(4.0, -1.0, 5.0, 1.0), Circle(center=(2.5, 0.0), radius_m=0.5)]
    ranges = cast_rays(origin=(0.0, 0.0), angles_rad=np.array([0.0]), targets=RayTargets.of(obstacles))
    assert abs(ranges[0] - 2.0) < 1e-12


def test_noise_is_reproducible_with_the_same_seed() -> None:
    noisy = RangeSensor(fov_deg=180.0, range_m=5.0, rays=181, noise_std_m=0.02)
    square = shapely.box(3.0, -1.0, 4.0, 1.0)
    kwargs = dict(x_m=0.0, y_m=0.0, theta_rad=0.0, obstacles=[square])
    a = noisy.scan(**kwargs, rng=np.random.default_rng(7))
    b = noisy.scan(**kwargs, rng=np.random.default_rng(7))
    c = noisy.scan(**kwargs, rng=np.random.default_rng(8))
    clean = noisy.scan(**kwargs)
    assert np.array_equal(a, b)
    assert not np.array_equal(a, c)
    assert not np.array_equal(a, clean)
    assert np.max(np.abs(a[:, 0] - 3.0)) < 0.2


# --- World: the sim's ground truth ------------------------------------------------------------------

from pathlib import Path  # noqa: E402

import pytest  # noqa: E402

from services.drive.vehicle import VehicleState  # noqa: E402
from sim.world import World  # noqa: E402

SCENARIOS = Path("/work/shared/scenarios")


def test_world_clearance_is_the_distance_to_the_nearest_obstacle() -> None:
    world = World(obstacles=[shapely.box(2.0, -1.0, 3.0, 1.0), Circle(center=(0.0, 5.0), radius_m=1.0)],
                  robot_width_m=0.3, robot_length_m=0.6)
    clearance = world.clearance([[0.0, 0.0], [2.5, 0.0], [0.0, 3.0], [5.0, 0.5]])
    np.testing.assert_allclose(clearance, [2.0, 0.0, 1.0, 2.0], atol=1e-12)


def test_footprint_collision_and_clearance() -> None:
    world = World(obstacles=[shapely.box(2.0, -1.0, 3.0, 1.0), Circle(center=(0.0, 5.0), radius_m=1.0)],
                  robot_width_m=0.3, robot_length_m=0.6, bounds_min=(-1.0, -1.0), bounds_max=(10.0, 10.0))
    free = VehicleState(x_m=1.0, y_m=0.0, theta_rad=0.0)
    assert abs(world.footprint_clearance(free) - 0.7) < 1e-12  # front edge at x = 1.3
    assert not world.footprint_collides(free)
    assert world.footprint_collides(VehicleState(x_m=1.75, y_m=0.0, theta_rad=0.0))
    # Heading +x under the circle: the rectangle's top edge (y = 3.4 + 0.15) is 0.45 below the disc.
    assert abs(world.footprint_clearance(VehicleState(x_m=0.0, y_m=3.4, theta_rad=0.0)) - 0.45) < 1e-12
    assert world.footprint_collides(VehicleState(x_m=0.0, y_m=3.8, theta_rad=math.pi / 2))
    assert world.footprint_in_bounds(free)
    assert not world.footprint_in_bounds(VehicleState(x_m=-0.8, y_m=0.0, theta_rad=0.0))


@pytest.mark.parametrize("name", ["paper-two-goals", "field-25", "corner-trap"])
def test_world_from_scenario_scan_hits_lie_on_the_true_obstacles(name: str) -> None:
    scenario_module = pytest.importorskip("schemas.scenario")
    path = SCENARIOS / f"{name}.json"
    if not path.exists():
        pytest.skip(f"{path} not present")
    scenario = scenario_module.load_scenario(path)
    world = World.from_scenario(scenario)
    sensor = RangeSensor.from_scenario(scenario)
    start = scenario.start
    hits = sensor.scan(x_m=start.x, y_m=start.y, theta_rad=start.theta, obstacles=world.ray_targets)
    if len(hits):
        assert np.max(world.clearance(hits)) < 1e-9
        assert np.max(np.hypot(hits[:, 0] - start.x, hits[:, 1] - start.y)) <= sensor.range_m + 1e-12
    assert not world.footprint_collides(VehicleState(x_m=start.x, y_m=start.y, theta_rad=start.theta))


from hypothesis import given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402


@settings(max_examples=40, deadline=None)
@given(
    cloud=st.lists(st.tuples(st.floats(1.0, 4.0), st.floats(-3.0, 3.0)), min_size=3, max_size=12),
    theta=st.floats(-np.pi, np.pi),
)
def test_ray_hits_agree_with_shapely_on_random_convex_polygons(cloud, theta: float) -> None:
    hull = shapely.MultiPoint(cloud).convex_hull
    if not isinstance(hull, shapely.Polygon) or hull.area < 1e-3:
        return
    angles = theta + np.linspace(-np.pi / 2, np.pi / 2, 37)
    ranges = cast_rays(origin=(0.0, 0.0), angles_rad=angles, targets=RayTargets.of([hull]))
    vertices = np.asarray(hull.exterior.coords)[:-1]
    for angle, r in zip(angles, ranges):
        ray = shapely.LineString([(0.0, 0.0), (20.0 * np.cos(angle), 20.0 * np.sin(angle))])
        crossing = ray.intersection(hull.boundary)
        on_boundary = np.isinf(r) or shapely.distance(hull.boundary, shapely.Point(r * np.cos(angle), r * np.sin(angle))) < 1e-9
        # A ray passing within 1e-9 m of a vertex ahead grazes it: shapely and we may round it to either side
        # (a miss, the vertex's edges, or the edge beyond), so only the hit's being on the boundary is checked.
        ahead = vertices @ [np.cos(angle), np.sin(angle)] > 0.0
        grazes = np.any(ahead & (np.abs(vertices @ [-np.sin(angle), np.cos(angle)]) < 1e-9))
        if crossing.is_empty or grazes:
            assert on_boundary
            continue
        # The crossing is points, or a piece of an edge along the ray, whose nearer end is its nearest point:
        # the nearest of its coordinates (shapely.distance divides by a piece's squared length, which a piece
        # 1e-277 m long underflows to zero: it said inf).
        expected = float(np.min(np.hypot(*shapely.get_coordinates(crossing).T)))
        assert abs(r - expected) < 1e-9


@pytest.mark.parametrize("yaw", [0.0, 0.4])
def test_rays_through_an_occupancy_grid_stop_where_they_enter_its_first_blocked_cell(yaw):
    """The cell-by-cell traversal against the same cells cast exactly as polygons (and the map's edge:
    beyond it is blocked)."""
    from schemas.occupancy import OCCUPIED, UNKNOWN, OccupancyGrid
    from sim.sensor import cast_rays_grid

    rng = np.random.default_rng(11)
    grid = OccupancyGrid.from_mask(rng.random((40, 50)) < 0.06, resolution_m=0.05, origin=(-1.0, 2.0, yaw))
    boxes = [shapely.Polygon(c) for c in grid.rectangles(states=(OCCUPIED, UNKNOWN))]
    edge = shapely.Polygon(grid.extent_corners()).exterior
    targets = RayTargets.of([*boxes, edge])
    free = np.argwhere(~grid.blocked)
    angles = np.linspace(-np.pi, np.pi, 181)
    for j, i in free[rng.choice(len(free), 12, replace=False)]:
        origin = grid.to_world([[(i + 0.3) * 0.05, (j + 0.6) * 0.05]])[0]
        exact = cast_rays(origin=origin, angles_rad=angles, targets=targets)
        traversed = cast_rays_grid(grid, origin=origin, angles_rad=angles, max_range_m=10.0)
        np.testing.assert_allclose(traversed, exact, atol=1e-9)
        short = cast_rays_grid(grid, origin=origin, angles_rad=angles, max_range_m=0.5)
        np.testing.assert_allclose(short, np.where(exact <= 0.5, exact, np.inf), atol=1e-9)


def test_rays_cast_in_blocks_measure_what_one_sweep_measures(monkeypatch) -> None:
    import sim.sensor

    targets = RayTargets.of([shapely.box(3.0, -0.5, 4.0, 0.5), shapely.box(-2.0, 1.0, -1.0, 3.0),
                             Circle(center=(0.0, -3.0), radius_m=0.7)])
    angles = np.linspace(-math.pi, math.pi, 4096, endpoint=False)
    whole = cast_rays(origin=(0.2, 0.1), angles_rad=angles, targets=targets)
    monkeypatch.setattr(sim.sensor, "BLOCK_PAIRS", 50)  # 50 // 8 edges: blocks of 6 rays
    blocks = cast_rays(origin=(0.2, 0.1), angles_rad=angles, targets=targets)
    assert np.isfinite(whole).sum() > 1000
    np.testing.assert_array_equal(blocks, whole)
