"""Occupancy grids (CONTRACTS §1b): Nav2 map_server maps read as map_server reads them, built from a ROS
OccupancyGrid's array alike, the true geometry exact, and every bad map one line naming the field."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import shapely
from PIL import Image

from schemas.occupancy import FREE, OCCUPIED, UNKNOWN, MapError, OccupancyGrid, load_map
from schemas.scenario import ScenarioError, load_scenario


def _write_map(folder: Path, pixels: np.ndarray, *, name: str = "map", yaml_extra: str = "", origin=(0.0, 0.0, 0.0),
               resolution: float = 0.05, **fields) -> Path:
    Image.fromarray(np.asarray(pixels, dtype=np.uint8), mode="L").save(folder / f"{name}.pgm")
    doc = {"image": f"{name}.pgm", "mode": "trinary", "resolution": resolution, "origin": list(origin), "negate": 0,
           "occupied_thresh": 0.65, "free_thresh": 0.25, **fields}
    (folder / f"{name}.yaml").write_text("".join(f"{k}: {json.dumps(v)}\n" for k, v in doc.items()) + yaml_extra)
    return folder / f"{name}.yaml"


def _scenario(folder: Path, map_name: str = "map.yaml", **edits) -> Path:
    doc = {"format": "cvxnav.scenario/2", "name": "tiny", "robot": {"width": 0.3, "length": 0.6, "wheelbase": 0.6,
           "safety_distance": 0.1, "max_speed": 1.0, "max_steering_angle": 0.6, "max_steering_rate": 0.5},
           "sensor": {"fov_deg": 180.0, "range": 5.0, "rays": 181, "rate_hz": 10.0}, "goal_tolerance": 0.2,
           "obstacles": [{"type": "occupancy_grid", "map": map_name}], "expect": "reach",
           "start": {"x": 0.3, "y": 0.3, "theta": 0.0}, "goals": [[0.9, 0.3]]}
    doc.update(edits)
    (folder / "tiny.json").write_text(json.dumps(doc))
    return folder / "tiny.json"


def _pixels() -> np.ndarray:
    """A 20 × 24 image (top row first): free, an occupied block, an unknown band on the right."""
    pixels = np.full((20, 24), 254)
    pixels[4:8, 10:14] = 0
    pixels[:, 20:] = 205
    return pixels


def test_a_map_server_map_reads_as_map_server_reads_it(tmp_path):
    grid = load_map(_write_map(tmp_path, _pixels()))
    assert grid.shape == (20, 24) and grid.resolution_m == 0.05
    # Row 0 is the bottom: image row 4..7 (top first) is grid row 12..15.
    assert np.all(grid.state[12:16, 10:14] == OCCUPIED)
    assert np.all(grid.state[:, 20:] == UNKNOWN)  # map_saver's 205: unknown, though p = 0.196 < free_thresh
    assert np.count_nonzero(grid.state == FREE) == 20 * 24 - 16 - 80
    assert grid.state_at([[0.52, 0.67], [0.02, 0.02], [5.0, 5.0]]).tolist() == [OCCUPIED, FREE, UNKNOWN]


def test_shades_thresholds_negate_and_raw_mode(tmp_path):
    pixels = np.array([[0, 80, 100, 150, 180, 191, 254, 255]])  # p = 1, .69, .61, .41, .29, .25, .004, 0
    states = load_map(_write_map(tmp_path, pixels, mode="scale")).state[0].tolist()
    assert states == [OCCUPIED, OCCUPIED, UNKNOWN, UNKNOWN, UNKNOWN, UNKNOWN, FREE, FREE]
    negated = load_map(_write_map(tmp_path, pixels, mode="scale", negate=1)).state[0].tolist()
    assert negated == [FREE, UNKNOWN, UNKNOWN, UNKNOWN, OCCUPIED, OCCUPIED, OCCUPIED, OCCUPIED]  # p = shade
    raw = load_map(_write_map(tmp_path, np.array([[0, 24, 25, 66, 100, 101, 255]]), mode="raw")).state[0].tolist()
    assert raw == [FREE, FREE, UNKNOWN, OCCUPIED, OCCUPIED, UNKNOWN, UNKNOWN]


def test_a_ros_occupancy_grid_array_gives_the_same_grid(tmp_path):
    from_file = load_map(_write_map(tmp_path, _pixels()))
    values = np.select([from_file.state == OCCUPIED, from_file.state == UNKNOWN], [100, -1], 0).astype(np.int8)
    from_array = OccupancyGrid.from_values(values.ravel().tolist(), width=24, height=20, resolution_m=0.05)
    assert np.array_equal(from_array.state, from_file.state)
    with pytest.raises(MapError, match=r"^<OccupancyGrid>: data: 479 values for a 24 × 20 grid \(needs 480\)$"):
        OccupancyGrid.from_values(values.ravel()[:-1], width=24, height=20, resolution_m=0.05)


def _union(grid: OccupancyGrid):
    """The blocked region and everything beyond the map, as shapely geometry (for brute-force checks)."""
    squares = [shapely.Polygon(corners) for corners in grid.rectangles(states=(OCCUPIED, UNKNOWN))]
    outside = shapely.box(-50, -50, 50, 50).difference(shapely.Polygon(grid.extent_corners()))
    return shapely.union_all([*squares, outside])


@pytest.mark.parametrize("yaw", [0.0, 0.7])
def test_clearance_is_the_exact_distance_to_the_blocked_squares(tmp_path, yaw):
    rng = np.random.default_rng(3)
    pixels = np.where(rng.random((30, 40)) < 0.05, 0, 254)
    grid = load_map(_write_map(tmp_path, pixels, origin=(1.5, -2.0, yaw)))
    points = grid.to_world(rng.uniform([-0.2, -0.2], [2.2, 1.7], (400, 2)))
    exact = shapely.distance(_union(grid), shapely.points(points))
    np.testing.assert_allclose(grid.clearance(points), exact, atol=1e-9)


def test_bounds_default_to_the_rotated_maps_extent(tmp_path):
    _write_map(tmp_path, np.full((10, 20), 254), origin=(1.0, 2.0, math.pi / 2))
    scenario = load_scenario(_scenario(tmp_path, start={"x": 0.7, "y": 2.5, "theta": math.pi / 2}, goals=[[0.8, 2.9]]))
    np.testing.assert_allclose(scenario.bounds.min, [0.5, 2.0], atol=1e-12)
    np.testing.assert_allclose(scenario.bounds.max, [1.0, 3.0], atol=1e-12)


def test_border_cells_are_the_blocked_cells_touching_a_free_one():
    blocked = np.zeros((7, 7), dtype=bool)
    blocked[1:6, 1:6] = True  # a 5 × 5 block: its ring of 16 is border, its 3 × 3 inside is not
    blocked[0, 6] = True  # a speck in the corner, touching the ring beyond the map
    grid = OccupancyGrid.from_mask(blocked, resolution_m=0.1)
    cells = {tuple(c) for c in grid.border_cells().tolist()}
    inner = {(i, j) for i in range(2, 5) for j in range(2, 5)}
    ring = {(i, j) for i in range(1, 6) for j in range(1, 6)} - inner
    beyond = {(i, j) for i in range(-1, 8) for j in range(-1, 8)} - {(i, j) for i in range(7) for j in range(7)}
    assert ring | {(6, 0)} <= cells and not cells & inner
    # Of the ring beyond the map, the cells touching a free cell of the map (all but those by the speck).
    assert cells - ring - {(6, 0)} == beyond - {(7, -1)}


# --------------------------------------------------------------------------- bad maps: one line, naming the field


def _bad_maps(tmp_path: Path) -> list[tuple[str, str]]:
    folder = tmp_path
    cases = []
    _write_map(folder, _pixels(), name="missing")
    (folder / "missing.pgm").unlink()
    cases.append(("missing.yaml", "obstacles[0].map: missing.yaml: image: missing.pgm: no such file"))
    _write_map(folder, _pixels(), name="short")
    data = (folder / "short.pgm").read_bytes()
    (folder / "short.pgm").write_bytes(data[: len(data) // 2])
    cases.append(("short.yaml", "obstacles[0].map: short.yaml: image: short.pgm: truncated: the file holds fewer pixels "
                                "than its header's 24 × 20"))
    _write_map(folder, _pixels(), name="garbage")
    (folder / "garbage.pgm").write_bytes(b"not an image at all")
    cases.append(("garbage.yaml", "obstacles[0].map: garbage.yaml: image: garbage.pgm: not an image Pillow can read"))
    _write_map(folder, _pixels(), name="order", free_thresh=0.7)
    cases.append(("order.yaml", "obstacles[0].map: order.yaml: free_thresh: must be below occupied_thresh 0.65, got "
                                "0.7 (thresholds out of order)"))
    _write_map(folder, _pixels(), name="origin", origin=[0.0, 0.0])
    cases.append(("origin.yaml", "obstacles[0].map: origin.yaml: origin: must be [x, y, yaw], got [0.0, 0.0]"))
    _write_map(folder, _pixels(), name="mode", mode="fancy")
    cases.append(("mode.yaml", "obstacles[0].map: mode.yaml: mode: must be trinary, scale or raw, got 'fancy'"))
    (folder / "nomap.yaml").write_text("image: x.pgm\nresolution: [0.05]\norigin: [0, 0, 0]\n")
    cases.append(("nomap.yaml", "obstacles[0].map: nomap.yaml: resolution: must be a finite number, got [0.05]"))
    (folder / "broken.yaml").write_text("image: [x.pgm\nresolution: 0.05\n")
    cases.append(("broken.yaml", "obstacles[0].map: broken.yaml: invalid YAML at line 2 column 11: did not find "
                                 "expected ',' or ']'"))
    cases.append(("absent.yaml", "obstacles[0].map: "))
    return cases


def test_every_bad_map_is_one_line_naming_the_field(tmp_path):
    for map_name, expected in _bad_maps(tmp_path):
        with pytest.raises(ScenarioError) as info:
            load_scenario(_scenario(tmp_path, map_name=map_name))
        message = str(info.value)
        assert "\n" not in message and message.startswith(f"tiny.json: {expected}"), message
    assert "no such map file" in str(pytest.raises(ScenarioError, load_scenario,
                                                   _scenario(tmp_path, map_name="absent.yaml")).value)


@pytest.mark.parametrize("where, expected", [
    ({"start": {"x": 0.52, "y": 0.67, "theta": 0.0}}, "start: [0.52, 0.67] is in an occupied cell of obstacles[0]'s map"),
    ({"goals": [[1.02, 0.3]]}, "goals[0]: [1.02, 0.3] is in an unknown cell of obstacles[0]'s map"),
    ({"goals": [[0.5, 0.6]]}, "goals[0]: [0.5, 0.6] is on the edge of a blocked cell of obstacles[0]'s map"),
    # The bounds, the map's extent, shown to a nanometre: 24 cells of 0.05 m are 1.2000000000000002 m.
    ({"start": {"x": -0.1, "y": 0.3, "theta": 0.0}}, "start: [-0.1, 0.3] is outside bounds [0.0, 0.0]..[1.2, 1.0]$"),
    ({"start": {"x": 0.1, "y": 0.5, "theta": 0.0}},
     "start: the robot's 0.6 × 0.3 m footprint leaves bounds [0.0, 0.0]..[1.2, 1.0]$"),
])
def test_a_start_or_goal_in_a_blocked_or_unknown_cell_is_refused(tmp_path, where, expected):
    _write_map(tmp_path, _pixels())
    with pytest.raises(ScenarioError, match="^tiny.json: " + expected.replace("[", r"\[").replace("]", r"\]")):
        load_scenario(_scenario(tmp_path, **where))


def test_a_rotated_map_places_its_cells_by_the_yaw(tmp_path):
    # The occupied block (grid columns 10..13, rows 12..15) under a quarter turn about the origin (1, 1):
    # grid (x, y) lands at (1 − y, 1 + x).
    _write_map(tmp_path, _pixels(), origin=(1.0, 1.0, math.pi / 2))
    grid = load_scenario(_scenario(tmp_path, start={"x": 0.5, "y": 1.2, "theta": 0.0}, goals=[[0.5, 1.9]])).obstacles[0].grid
    assert grid.state_at([[1.0 - 0.67, 1.0 + 0.52]])[0] == OCCUPIED
    assert grid.state_at([[1.0 - 0.52, 1.0 + 0.67]])[0] == FREE
    with pytest.raises(ScenarioError, match=r"start: \[0.33, 1.52\] is in an occupied cell"):
        load_scenario(_scenario(tmp_path, start={"x": 0.33, "y": 1.52, "theta": 0.0}, goals=[[0.5, 1.9]]))


def test_a_map_in_a_version_1_scenario_is_refused(tmp_path):
    _write_map(tmp_path, _pixels())
    with pytest.raises(ScenarioError, match=r"^tiny.json: obstacles\[0\].type: occupancy_grid needs format "
                                            r"cvxnav.scenario/2, got cvxnav.scenario/1$"):
        load_scenario(_scenario(tmp_path, format="cvxnav.scenario/1", bounds={"min": [0, 0], "max": [1, 1]}))


def test_one_map_per_scenario(tmp_path):
    _write_map(tmp_path, _pixels())
    doc = json.loads(_scenario(tmp_path).read_text())
    doc["obstacles"].append({"type": "occupancy_grid", "map": "map.yaml"})
    (tmp_path / "two.json").write_text(json.dumps(doc))
    with pytest.raises(ScenarioError, match=r"^two.json: obstacles\[1\].type: one occupancy_grid per scenario"):
        load_scenario(tmp_path / "two.json")


def test_a_scenario_written_out_reads_its_map_back_from_anywhere(tmp_path, monkeypatch):
    from schemas.scenario import parse_scenario

    _write_map(tmp_path, _pixels())
    scenario = load_scenario(_scenario(tmp_path))
    monkeypatch.chdir(Path("/"))
    again = parse_scenario(scenario.model_dump_json(), source="recording")  # as a recording's attachment
    assert np.array_equal(again.obstacles[0].grid.state, scenario.obstacles[0].grid.state)
