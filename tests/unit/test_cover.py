"""Tight covers: the union contains the obstacle and sticks out of it by at most the tolerance."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

from services.ellipsoids.cover import (
    _boundary_samples,
    cover_points,
    cover_polygon,
    excess_over_points,
    excess_over_polygon,
    tiled_cover,
    tiles,
)
from depot_car import depot_car_scenario
from schemas.messages import ClusterMsg, Clusters, Goals, Header, Pose2D, RobotState
from services.ellipsoids.mvee import mvee, mvee_fast
from services.ellipsoids.stage import EllipsoidsStage
from services.geometry import EllipseStack

BOX = np.array([[0.0, 0.0], [4.0, 0.0], [4.0, 2.0], [0.0, 2.0]])


def _covered(ellipses, points):
    return np.min(EllipseStack.of(ellipses).levels(points), axis=1) <= 1.0 + 1e-9


def _box_samples():
    xs, ys = np.meshgrid(np.linspace(0.0, 4.0, 81), np.linspace(0.0, 2.0, 41))
    return np.column_stack([xs.ravel(), ys.ravel()])


@pytest.mark.parametrize("max_pieces", [8, 64, 128])
def test_box_union_contains_box_whatever_the_budget(max_pieces):
    ellipses = cover_polygon(BOX, tolerance_m=0.1, max_pieces=max_pieces)
    assert len(ellipses) <= max_pieces
    assert np.all(_covered(ellipses, _box_samples()))


def test_box_cover_sticks_out_by_at_most_the_tolerance():
    # A single MVEE sticks out by (√2 − 1) · 2 m; reaching 0.1 m takes 82 pieces (more than the default 64).
    ellipses = cover_polygon(BOX, tolerance_m=0.1, max_pieces=128)
    assert max(excess_over_polygon(e, BOX, tolerance_m=0.01) for e in ellipses) <= 0.1 + 1e-3


def test_single_mvee_of_box_over_covers():
    assert excess_over_polygon(mvee(BOX), BOX) == pytest.approx(2.0 * (np.sqrt(2.0) - 1.0), abs=1e-3)  # past the 4 m sides


def test_circle_needs_one_ellipse():
    angles = 2 * np.pi * np.arange(16) / 16
    ellipses = cover_polygon(np.column_stack([np.cos(angles), np.sin(angles)]), tolerance_m=0.1)
    assert len(ellipses) == 1


@pytest.mark.parametrize("vertices", [[[1.0, 2.0]], [[0.0, 0.0], [3.0, 1.0]]], ids=["point", "segment"])
def test_degenerate_polygon_is_covered_thinly(vertices):
    ellipses = cover_polygon(vertices, tolerance_m=0.1)
    v = np.asarray(vertices)
    on = v[0] + np.linspace(0.0, 1.0, 50)[:, None] * (v[-1] - v[0])
    assert np.all(_covered(ellipses, on))
    assert max(excess_over_polygon(e, v) for e in ellipses) <= 0.1 + 1e-3


def _l_wall():
    t = np.arange(0.0, 4.0 + 1e-9, 0.05)
    return np.vstack([np.column_stack([t, 0.0 * t]), np.column_stack([0.0 * t[1:], t[1:]])])


def test_l_wall_points_covered_tightly_and_corner_left_free():
    points = _l_wall()
    ellipses = cover_points(points, tolerance_m=0.1)
    assert np.all(_covered(ellipses, points))
    assert max(excess_over_points(e, points, tolerance_m=0.1) for e in ellipses) <= 0.1 + 1e-9
    assert not np.any(_covered(ellipses, np.array([[1.0, 1.0]])))


def test_ring_of_wall_samples_does_not_swallow_the_room():
    angles = 2 * np.pi * np.arange(400) / 400
    ring = 3.0 * np.column_stack([np.cos(angles), np.sin(angles)])
    ellipses = cover_points(ring, tolerance_m=0.1, max_pieces=200)
    assert np.all(_covered(ellipses, ring))
    assert not np.any(_covered(ellipses, np.array([[0.0, 0.0], [2.0, 0.0]])))


def test_duplicated_points_stop_splitting():
    ellipses = cover_points(np.repeat([[1.0, 1.0]], 5, axis=0), tolerance_m=0.1)
    assert len(ellipses) == 1


def _excess_over_every_sample(ellipse, points, *, tolerance_m):
    """The definition excess_over_points computes: the largest distance over all of its region samples."""
    boundary = _boundary_samples(ellipse, tolerance_m=tolerance_m)
    rings = int(np.clip(np.ceil(ellipse.semi_axes[0] / (0.5 * tolerance_m)), 1, 16))
    levels = np.arange(rings + 1)[:, None, None] / rings
    samples = (ellipse.center + levels * (boundary - ellipse.center)[None, :, :]).reshape(-1, 2)
    return float(np.max(cKDTree(points).query(samples)[0]))


@pytest.mark.parametrize("shape", ["l-wall", "ring", "blob", "few"])
def test_excess_over_points_prunes_samples_but_not_the_maximum(shape):
    rng = np.random.default_rng(3)
    points = {"l-wall": _l_wall(), "ring": 3.0 * np.column_stack([np.cos(a := np.linspace(0, 6.0, 300)), np.sin(a)]),
              "blob": rng.normal(size=(200, 2)), "few": rng.uniform(0.0, 0.3, size=(6, 2))}[shape]
    for part in (points, points[: len(points) // 3], points[::7]):
        e = mvee_fast(part)
        assert excess_over_points(e, part, tolerance_m=0.1) == _excess_over_every_sample(e, part, tolerance_m=0.1)


def _revealed_obstacle():
    """A round obstacle with a straight wall, sensed as a car passes: 5 cm voxels, revealed in order."""
    rng = np.random.default_rng(11)
    arc = np.linspace(np.pi, 0.0, 120)
    round_side = np.column_stack([3.0 + 1.5 * np.cos(arc), 1.5 * np.sin(arc)]) + rng.normal(0.0, 0.004, (120, 2))
    wall = np.column_stack([np.arange(4.55, 9.0, 0.05), np.zeros(89)])
    return np.vstack([round_side, wall])


def _lexsorted(points):
    return points[np.lexsort((points[:, 1], points[:, 0]))]  # as the sensing stage sends a cluster


def _nodes(root):
    return [root] + [node for child in root.children for node in _nodes(child)]


def _leaves_by_cell(covers):
    return {piece.cell: piece for cover in covers for piece in cover.pieces}


def test_a_tiled_cover_of_a_growing_cluster_refits_only_the_cells_new_points_fall_in():
    """Each scan adds 10-30 points. Every tile's cover contains its points and sticks out by at most the
    tolerance; built on the previous scan's pieces it is the cover built
    afresh; and a leaf whose cell gained no point keeps its ellipse, the same object."""
    obstacle = _revealed_obstacle()
    rng = np.random.default_rng(5)
    seen, previous, before, kept = 40, {}, {}, 0
    while seen < len(obstacle):
        points = _lexsorted(obstacle[:seen])
        covers = []
        for cell, part in tiles(points, tile_m=2.0):
            x0, y0, x1, y1 = cell
            assert np.all((part >= (x0, y0)) & (part < (x1, y1)))
            cover = tiled_cover(part, cell=cell, previous=previous, tolerance_m=0.1, max_pieces=32)
            fresh = tiled_cover(part, cell=cell, tolerance_m=0.1, max_pieces=32)
            assert [p.cell for p in cover.pieces] == [p.cell for p in fresh.pieces]
            for piece, again in zip(cover.pieces, fresh.pieces):
                np.testing.assert_allclose(piece.ellipse.A, again.ellipse.A, rtol=1e-9, atol=1e-9 * np.abs(again.ellipse.A).max())
                assert np.all(piece.ellipse.level(piece.points) <= 1.0 + 1e-12)
                assert piece.excess_m == excess_over_points(piece.ellipse, piece.points, tolerance_m=0.1) <= 0.1
            covers.append(cover)
        leaves = _leaves_by_cell(covers)
        assert sum(len(p.points) for p in leaves.values()) == len(points)
        for cell, piece in leaves.items():
            old = before.get(cell)
            if old is not None and np.array_equal(old.points, piece.points):
                assert piece.ellipse is old.ellipse
                kept += 1
        previous = {}
        for cover in covers:
            for node in _nodes(cover.root):
                previous.setdefault(node.cell, []).append(node)
        before = leaves
        seen += int(rng.integers(10, 31))
    assert kept > 0


def _door_clusters(door_m: float) -> Clusters:
    """A wall's face at x = 6 m as the car sees it from (1.5, 3) (5 cm apart, from 0.8 to 5.2 m), with a door
    of `door_m` centred at y = 3 m: its two sides are two clusters."""
    y = np.arange(0.8, 5.2 + 1e-9, 0.05)
    sides = [y[y <= 3.0 - door_m / 2], y[y >= 3.0 + door_m / 2]]
    clusters = [ClusterMsg(cluster_id=k, points=[(6.0, float(v)) for v in side]) for k, side in enumerate(sides)]
    return Clusters(header=Header(stamp_s=0.0, seq=0), scan_seq=0, clusters=clusters)


def test_sensed_door_jambs_leave_a_door_the_robot_fits_through_open():
    """A door 0.2 m wider than the depot car's passage (twice its 0.45 m margin): twice the cover's
    tolerance. The least-area growth of the jambs' fits ran their tips more than 0.1 m into the doorway,
    and the two closed it (level 0.986 at its middle); grown to stray at most the tolerance beyond the
    margin from the wall's points (`grown_cover`), the way through the door's middle is outside every
    grown ellipse. Every point within the margin of a sensed point is still inside one."""
    scenario = depot_car_scenario(bounds=((0.0, 0.0), (12.0, 6.0)), start=(1.5, 3.0, 0.0), goals=[(11.0, 3.0)])
    margin = scenario.inflation_m
    clusters = _door_clusters(2 * margin + 0.2)
    (_, out), = EllipsoidsStage.from_scenario(scenario).process(topic="clusters", message=clusters, now_s=0.0)
    grown = EllipseStack(A=np.array([e.A for e in out.ellipsoids]), b=np.array([e.b for e in out.ellipsoids]))
    through = np.column_stack([np.linspace(4.0, 8.0, 401), np.full(401, 3.0)])
    assert grown.levels(through).min() > 1.0
    assert len({e.group for e in out.ellipsoids}) == 2  # the jambs are not grouped across the door
    sensed = np.array([p for c in clusters.clusters for p in c.points])
    angle = np.linspace(0.0, 2.0 * np.pi, 32, endpoint=False)
    within = (sensed[:, None, :] + margin * np.stack([np.cos(angle), np.sin(angle)], axis=1)[None]).reshape(-1, 2)
    assert np.all(grown.levels(within).min(axis=1) <= 1.0 + 1e-9)


def test_a_sensed_wall_lets_out_a_goal_just_beyond_the_margin_and_holds_one_within_it():
    """A wall's face at y = 0 seen 5 cm apart; goals 1.5 cm beyond the 0.45 m margin and 5 cm within it.
    The growths may stray up to the tolerance (0.1 m) beyond the margin and held the first; the pieces
    holding a goal ahead are fitted tighter until none does, and the second stays inside at every
    tolerance. The goals are the scenario's until a `Goals` message replaces them, and those the robot
    has reached no longer count."""
    scenario = depot_car_scenario(bounds=((-1.0, -1.0), (12.0, 6.0)), start=(4.0, 3.0, 0.0), goals=[(4.2, 0.465)])
    wall = Clusters(header=Header(stamp_s=0.0, seq=0), scan_seq=0,
                    clusters=[ClusterMsg(cluster_id=0, points=[(float(x), 0.0) for x in np.arange(1.0, 8.0, 0.05)])])

    def levels(stage: EllipsoidsStage, points) -> np.ndarray:
        (_, out), = stage.process(topic="clusters", message=wall, now_s=0.0)
        grown = EllipseStack(A=np.array([e.A for e in out.ellipsoids]), b=np.array([e.b for e in out.ellipsoids]))
        return grown.levels(np.array(points)).min(axis=1)

    beyond, within = (4.2, 0.465), (5.0, 0.4)
    untightened = EllipsoidsStage.from_scenario(scenario.model_copy(update={"goals": [(9.0, 3.0)]}))
    assert levels(untightened, [beyond])[0] <= 1.0  # held by the cover grown to the tolerance
    stage = EllipsoidsStage.from_scenario(scenario)
    assert levels(stage, [beyond])[0] > 1.0
    stage.process(topic="goals", message=Goals(header=Header(stamp_s=0.0, seq=0), goals=[within, beyond]), now_s=0.0)
    assert levels(stage, [within])[0] <= 1.0
    state = RobotState(header=Header(stamp_s=0.0, seq=0), pose=Pose2D(x_m=4.0, y_m=3.0, theta_rad=0.0),
                       speed_mps=0.0, steering_rad=0.0, goal_index=1, goals_reached=1, done=False)
    stage.process(topic="state", message=state, now_s=0.0)
    assert levels(stage, [beyond])[0] > 1.0


def test_a_cluster_across_a_tile_edge_is_covered_in_both_tiles_message_after_message():
    """A short wall across the edge of two of the stage's tiles (x = 4 m), within each other's halo: the
    tiles' covers are cached apart (each by its cell and the points near it), so every sensed point is
    inside a grown ellipse with the margin round it, as a fresh stage covers it, however often the same
    or a grown cluster comes again."""
    scenario = depot_car_scenario(bounds=((0.0, -2.0), (12.0, 6.0)), start=(1.0, 3.0, 0.0), goals=[(11.0, 3.0)])
    stage = EllipsoidsStage.from_scenario(scenario)
    margin = scenario.inflation_m
    angle = np.linspace(0.0, 2.0 * np.pi, 32, endpoint=False)
    ring = margin * np.stack([np.cos(angle), np.sin(angle)], axis=1)
    for end in (4.3, 4.3, 4.35, 4.4):
        wall = [(float(x), 1.0) for x in np.arange(3.7, end + 1e-9, 0.05)]
        message = Clusters(header=Header(stamp_s=0.0, seq=0), scan_seq=0,
                           clusters=[ClusterMsg(cluster_id=0, points=wall)])
        (_, out), = stage.process(topic="clusters", message=message, now_s=0.0)
        (_, fresh), = EllipsoidsStage.from_scenario(scenario).process(topic="clusters", message=message, now_s=0.0)
        grown = EllipseStack(A=np.array([e.A for e in out.ellipsoids]), b=np.array([e.b for e in out.ellipsoids]))
        within = (np.array(wall)[:, None, :] + ring[None]).reshape(-1, 2)
        assert np.all(grown.levels(within).min(axis=1) <= 1.0 + 1e-9)
        assert len(out.ellipsoids) == len(fresh.ellipsoids)
