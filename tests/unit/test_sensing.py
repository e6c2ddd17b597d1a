"""Sensing core: single-linkage clustering and the voxel point memory."""

from __future__ import annotations

import numpy as np
import shapely

from services.geometry import PointMemory
from services.sensing.core import cluster_points
from sim.sensor import RangeSensor


def _blob(center: tuple[float, float], *, n: int, rng: np.random.Generator) -> np.ndarray:
    return np.asarray(center) + rng.uniform(-0.2, 0.2, size=(n, 2))


def test_two_blobs_2m_apart_split_at_small_link_and_merge_at_large() -> None:
    rng = np.random.default_rng(0)
    a, b = _blob((0.0, 0.0), n=40, rng=rng), _blob((2.0, 0.0), n=30, rng=rng)
    points = np.vstack([a, b])
    split = cluster_points(points, link_m=0.5)
    assert len(split) == 2
    assert np.array_equal(split[0], a) and np.array_equal(split[1], b)
    merged = cluster_points(points, link_m=3.0)
    assert len(merged) == 1 and len(merged[0]) == 70


def test_clusters_follow_chains_and_partition_the_input() -> None:
    # A chain of points 0.3 apart is one cluster at link 0.35 even though its ends are 3 m apart.
    chain = np.column_stack([np.arange(11) * 0.3, np.zeros(11)])
    lone = np.array([[10.0, 10.0]])
    points = np.vstack([lone, chain])
    clusters = cluster_points(points, link_m=0.35)
    assert [len(c) for c in clusters] == [1, 11]  # ordered by first appearance
    assert sorted(map(tuple, np.vstack(clusters))) == sorted(map(tuple, points))
    assert len(cluster_points(chain, link_m=0.25)) == 11
    assert cluster_points(np.zeros((0, 2)), link_m=1.0) == []


def test_memory_deduplicates_on_the_voxel_grid() -> None:
    memory = PointMemory(voxel_m=0.1)
    assert memory.add([[0.01, 0.01], [0.02, 0.03], [0.15, 0.0]]) == 2
    assert memory.add([[0.05, 0.05]]) == 0  # same voxel as the first point
    np.testing.assert_array_equal(memory.points(), [[0.15, 0.0], [0.01, 0.01]])  # first kept; refreshed last
    assert len(memory) == 2


def test_memory_keeps_points_out_of_view() -> None:
    sensor = RangeSensor(fov_deg=180.0, range_m=5.0, rays=181)
    box = shapely.box(2.0, -0.5, 3.0, 0.5)
    memory = PointMemory(voxel_m=0.05)
    memory.add(sensor.scan(x_m=0.0, y_m=0.0, theta_rad=0.0, obstacles=[box]))
    seen = memory.points().copy()
    assert len(seen) > 0
    # Turned away, the scan is empty, yet the box is remembered.
    away = sensor.scan(x_m=0.0, y_m=0.0, theta_rad=np.pi, obstacles=[box])
    assert len(away) == 0
    memory.add(away)
    np.testing.assert_array_equal(memory.points(), seen)


def test_memory_is_bounded_and_drops_the_least_recently_seen() -> None:
    memory = PointMemory(voxel_m=0.1, max_points=100)
    old = np.column_stack([np.arange(80) * 0.5, np.zeros(80)])
    new = np.column_stack([np.arange(80) * 0.5, np.full(80, 10.0)])
    memory.add(old)
    memory.add(old[:10])  # these ten are seen again: now the freshest of the old ones
    memory.add(new)
    kept = memory.points()
    assert len(kept) == 100
    kept_set = set(map(tuple, kept))
    assert all(tuple(p) in kept_set for p in new)
    assert all(tuple(p) in kept_set for p in old[:10])
    assert sum(tuple(p) in kept_set for p in old[10:]) == 10  # the other 60 oldest were dropped
    assert all(tuple(p) in kept_set for p in old[70:])


def test_memory_ignores_non_finite_rows() -> None:
    memory = PointMemory()
    assert memory.add([[np.inf, 0.0], [1.0, np.nan], [1.0, 1.0]]) == 1
    assert len(memory) == 1
