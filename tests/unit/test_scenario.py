"""The scenario model: public files load, every kind of bad input is one named line, geometry is exact."""

from __future__ import annotations

import copy
import json
import math
from pathlib import Path
from typing import Callable

import numpy as np
import pytest
import shapely
from hypothesis import example, given, settings
from hypothesis import strategies as st

from schemas.scenario import (
    CircleObstacle,
    PointsObstacle,
    PolygonObstacle,
    Scenario,
    ScenarioError,
    bundled_scenario,
    load_scenario,
    parse_scenario,
)

BASE: dict = {
    "format": "cvxnav.scenario/1",
    "name": "unit",
    "description": "small valid scenario the bad-input cases are derived from",
    "bounds": {"min": [-4, -4], "max": [14, 14]},
    "robot": {
        "width": 0.3,
        "length": 0.6,
        "wheelbase": 0.6,
        "safety_distance": 0.5,
        "max_speed": 1.0,
        "max_steering_angle": 0.2,
        "max_steering_rate": 0.5,
    },
    "sensor": {"fov_deg": 180.0, "range": 5.0, "rays": 181, "rate_hz": 10.0},
    "start": {"x": 0, "y": 0, "theta": 0.785},
    "goals": [[10, 10], [12, 2]],
    "goal_tolerance": 0.3,
    "obstacles": [
        {"type": "polygon", "vertices": [[4, 4], [6, 4], [6, 6], [4, 6]]},
        {"type": "circle", "center": [8, 2], "radius": 1.0},
        {"type": "points", "points": [[2, 8], [3, 8], [2.5, 9]]},
    ],
    "expect": "reach",
}


def _write(tmp_path: Path, text: str, name: str = "bad.json") -> Path:
    path = tmp_path / name
    path.write_text(text, encoding="utf-8")
    return path


def _mutated(mutate: Callable[[dict], None]) -> str:
    data = copy.deepcopy(BASE)
    mutate(data)
    return json.dumps(data, indent=1)


def _replace(old: str, new: str) -> Callable[[], str]:
    """Text-level edit of the base file, for things json.dumps will not write (NaN literals, bad syntax)."""

    def make() -> str:
        text = json.dumps(BASE, indent=1)
        assert old in text
        return text.replace(old, new, 1)

    return make


# ---------------------------------------------------------------------------------------------------
# Good files
# ---------------------------------------------------------------------------------------------------


def _public_scenario_files(scenarios_dir: Path) -> list[Path]:
    return sorted(p for p in scenarios_dir.glob("*.json") if p.name != "REFERENCE.json")


def test_every_public_scenario_loads_with_start_and_goals_in_free_space(scenarios_dir: Path) -> None:
    files = _public_scenario_files(scenarios_dir)
    assert files, f"no scenarios in {scenarios_dir}"
    for path in files:
        scenario = load_scenario(path)
        assert scenario.name == path.stem
        points = np.vstack([[scenario.start.x, scenario.start.y], scenario.goals_array])
        assert np.all(scenario.clearance(points) > 0.0), path.name
        assert not scenario.in_collision(points).any()


def test_reference_lengths_cover_exactly_the_public_scenarios(scenarios_dir: Path) -> None:
    reference = json.loads((scenarios_dir / "REFERENCE.json").read_text())
    names = {load_scenario(p).name for p in _public_scenario_files(scenarios_dir)}
    assert set(reference["optimal_length"]) == names


def test_bundled_scenario_is_the_shared_paper_scenario(scenarios_dir: Path) -> None:
    shared = load_scenario(scenarios_dir / "paper-two-goals.json")
    bundled = bundled_scenario()
    assert bundled == shared
    assert bundled.goals == [(10.0, 10.0), (15.0, 15.0)]
    assert bundled.robot.max_steering_angle == 0.2


def test_base_scenario_is_valid(tmp_path: Path) -> None:
    scenario = load_scenario(_write(tmp_path, json.dumps(BASE), "unit.json"))
    assert [o.type for o in scenario.obstacles] == ["polygon", "circle", "points"]
    assert scenario == parse_scenario(json.dumps(BASE))


def test_description_defaults_and_obstacles_may_be_empty() -> None:
    data = copy.deepcopy(BASE)
    del data["description"]
    data["obstacles"] = []
    scenario = parse_scenario(json.dumps(data))
    assert scenario.description == ""
    assert scenario.clearance([[0, 0], [1, 1]]).tolist() == [math.inf, math.inf]
    assert not scenario.in_collision([[0, 0]]).any()


def test_derived_robot_quantities() -> None:
    scenario = parse_scenario(json.dumps(BASE))
    assert scenario.inflation_m == pytest.approx(0.15 + 0.5)
    assert scenario.max_curvature == pytest.approx(math.tan(0.2) / 0.6)


# ---------------------------------------------------------------------------------------------------
# Bad files: one line naming the field
# ---------------------------------------------------------------------------------------------------

BAD_CASES: list[tuple[str, Callable[[], str], str]] = [
    ("unknown field", lambda: _mutated(lambda d: d["robot"].update(foo=1)), "bad.json: unknown field 'foo' at robot"),
    (
        "unknown top-level field",
        lambda: _mutated(lambda d: d.update(colour="red")),
        "bad.json: unknown field 'colour' at top level",
    ),
    ("NaN literal", _replace('"width": 0.3', '"width": NaN'), "bad.json: robot.width: Input should be a finite number"),
    (
        "Infinity literal",
        _replace('"radius": 1.0', '"radius": Infinity'),
        "bad.json: obstacles[1].radius: Input should be a finite number",
    ),
    (
        "-Infinity in a point",
        lambda: _mutated(lambda d: d["goals"].__setitem__(1, [12, "@"])).replace('"@"', "-Infinity"),
        "bad.json: goals[1][1]: Input should be a finite number",
    ),
    (
        "negative width",
        lambda: _mutated(lambda d: d["robot"].update(width=-0.3)),
        "bad.json: robot.width: Input should be greater than or equal to 0.01",
    ),
    (
        "steering at pi/2",
        lambda: _mutated(lambda d: d["robot"].update(max_steering_angle=math.pi / 2)),
        "bad.json: robot.max_steering_angle: Input should be less than or equal to 1.5",
    ),
    (
        "polygon with 2 vertices",
        lambda: _mutated(lambda d: d["obstacles"][0].update(vertices=[[4, 4], [6, 4]])),
        "bad.json: obstacles[0].vertices: polygon needs at least 3 vertices, got 2",
    ),
    (
        "zero-area polygon",
        lambda: _mutated(lambda d: d["obstacles"][0].update(vertices=[[4, 4], [5, 5], [6, 6], [5, 5.0000000001]])),
        "bad.json: obstacles[0].vertices: polygon has zero area",
    ),
    (
        "self-intersecting bow-tie",
        lambda: _mutated(lambda d: d["obstacles"][0].update(vertices=[[4, 4], [6, 6], [6, 4], [4, 6]])),
        "bad.json: obstacles[0].vertices: polygon is self-intersecting",
    ),
    (
        "empty points obstacle",
        lambda: _mutated(lambda d: d["obstacles"][2].update(points=[])),
        "bad.json: obstacles[2].points: List should have at least 1 item",
    ),
    (
        "unknown obstacle type",
        lambda: _mutated(lambda d: d["obstacles"][1].update(type="ellipse")),
        "bad.json: obstacles[1]: Input tag 'ellipse'",
    ),
    (
        "start inside an obstacle",
        lambda: _mutated(lambda d: d["start"].update(x=5, y=5)),
        "bad.json: start: [5.0, 5.0] is inside or on obstacles[0] (polygon)",
    ),
    (
        "start on a circle's boundary",
        lambda: _mutated(lambda d: d["start"].update(x=9, y=2)),
        "bad.json: start: [9.0, 2.0] is inside or on obstacles[1] (circle)",
    ),
    (
        "goal inside an obstacle",
        lambda: _mutated(lambda d: d["goals"].__setitem__(1, [2.5, 8.5])),
        "bad.json: goals[1]: [2.5, 8.5] is inside or on obstacles[2] (points)",
    ),
    (
        "goal outside bounds",
        lambda: _mutated(lambda d: d["goals"].__setitem__(1, [20, 2])),
        "bad.json: goals[1]: [20.0, 2.0] is outside bounds",
    ),
    ("no goals", lambda: _mutated(lambda d: d.update(goals=[])), "bad.json: goals: List should have at least 1 item"),
    (
        "inverted bounds",
        lambda: _mutated(lambda d: d["bounds"].update(max=[-5, 14])),
        "bad.json: bounds.max: must exceed bounds.min",
    ),
    (
        "wrong format string",
        lambda: _mutated(lambda d: d.update(format="cvxnav.scenario/3")),
        "bad.json: format: Input should be 'cvxnav.scenario/1' or 'cvxnav.scenario/2'",
    ),
    ("missing field", lambda: _mutated(lambda d: d.pop("sensor")), "bad.json: sensor: Field required"),
    ("invalid JSON", _replace('"rays": 181,', '"rays": 181,,'), "bad.json: invalid JSON: Expecting property name"),
    ("not an object", lambda: "[1, 2]", "bad.json: Input should be a valid dictionary"),
]


@pytest.mark.parametrize(("make_text", "expected"), [c[1:] for c in BAD_CASES], ids=[c[0] for c in BAD_CASES])
def test_bad_scenario_is_one_line_naming_the_field(tmp_path: Path, make_text: Callable[[], str], expected: str) -> None:
    path = _write(tmp_path, make_text())
    with pytest.raises(ScenarioError) as info:
        load_scenario(path)
    message = str(info.value)
    assert "\n" not in message
    assert message.startswith(expected), message
    assert info.value.__cause__ is None and info.value.__suppress_context__


def test_invalid_json_names_line_and_column(tmp_path: Path) -> None:
    path = _write(tmp_path, '{\n "format": "cvxnav.scenario/1",\n "name": \n}\n')
    with pytest.raises(ScenarioError, match=r"^bad\.json: invalid JSON: .* at line 4 column 1$"):
        load_scenario(path)


def test_missing_file_is_one_line(tmp_path: Path) -> None:
    path = tmp_path / "nowhere" / "missing.json"
    with pytest.raises(ScenarioError) as info:
        load_scenario(path)
    assert str(info.value) == f"{path}: no such file"


def test_several_problems_report_the_first_and_count_the_rest() -> None:
    data = copy.deepcopy(BASE)
    data["robot"]["width"] = -1
    data["sensor"]["rays"] = 1
    with pytest.raises(ScenarioError) as info:
        parse_scenario(json.dumps(data), source="two.json")
    assert str(info.value) == "two.json: robot.width: Input should be greater than or equal to 0.01 (and 1 more)"


def test_models_are_frozen() -> None:
    scenario = parse_scenario(json.dumps(BASE))
    with pytest.raises(Exception, match="frozen"):
        scenario.robot.width = 1.0  # type: ignore[misc]


# ---------------------------------------------------------------------------------------------------
# Geometry against hand-computed values
# ---------------------------------------------------------------------------------------------------


def test_circle_distance_is_analytic() -> None:
    circle = CircleObstacle(center=(1.0, 2.0), radius=1.0)
    d = circle.distance([[1, 2], [4, 6], [1.5, 2], [1, 3], [1, 5]])
    np.testing.assert_allclose(d, [0.0, 4.0, 0.0, 0.0, 2.0], atol=1e-15)


def test_polygon_distance_square_in_either_orientation() -> None:
    points = [[1, 1], [3, 1], [5, 6], [2, 2], [-1, -1], [1, -0.5]]
    expected = [0.0, 1.0, 5.0, 0.0, math.sqrt(2.0), 0.5]
    for vertices in ([(0, 0), (2, 0), (2, 2), (0, 2)], [(0, 2), (2, 2), (2, 0), (0, 0)]):
        np.testing.assert_allclose(PolygonObstacle(vertices=vertices).distance(points), expected, atol=1e-12)


def test_concave_polygon_distance_sees_the_notch() -> None:
    u_shape = PolygonObstacle(vertices=[(0, 0), (3, 0), (3, 3), (2, 3), (2, 1), (1, 1), (1, 3), (0, 3)])
    # In the notch of the U the solid is 0.5 away, although the convex hull would contain the point.
    np.testing.assert_allclose(u_shape.distance([[1.5, 2.5], [1.5, 1.0], [0.5, 0.5]]), [0.5, 0.0, 0.0])
    hull = shapely.Polygon(u_shape.cover_vertices())
    assert hull.covers(shapely.Point(1.5, 2.5))


def test_points_distance_for_point_segment_and_hull() -> None:
    np.testing.assert_allclose(PointsObstacle(points=[(1, 1)]).distance([[4, 5], [1, 1]]), [5.0, 0.0])
    segment = PointsObstacle(points=[(0, 0), (4, 0)])
    np.testing.assert_allclose(segment.distance([[2, 3], [6, 0], [2, 0]]), [3.0, 2.0, 0.0])
    # Interior point (1, 1) does not change the hull; (1, 0.5) is inside it, (1, -1) is 1 below.
    triangle = PointsObstacle(points=[(0, 0), (4, 0), (0, 4), (1, 1)])
    np.testing.assert_allclose(triangle.distance([[1, 0.5], [1, -1], [3, 3]]), [0.0, 1.0, math.sqrt(2.0)])


def test_scenario_clearance_is_min_over_obstacles() -> None:
    scenario = parse_scenario(json.dumps(BASE))
    # (7, 4): 1 from the square's right side, sqrt(5) - 1 from the circle at (8, 2) r 1.
    # (8, 3.5): 2 from the square, 0.5 from the circle.
    np.testing.assert_allclose(scenario.clearance([[7, 4], [8, 3.5]]), [1.0, 0.5])
    np.testing.assert_allclose(scenario.clearance([[6.5, 5]]), [0.5])
    assert scenario.in_collision([[5, 5], [8, 2.5], [0, 0]]).tolist() == [True, True, False]
    assert scenario.in_collision([[6.5, 5]], margin_m=scenario.inflation_m).tolist() == [True]


# ---------------------------------------------------------------------------------------------------
# Covers contain the solids
# ---------------------------------------------------------------------------------------------------


def _inside_convex(vertices: np.ndarray, points: np.ndarray, *, tol: float) -> np.ndarray:
    """Point-in-convex-polygon for CCW vertices: on the left of (or on) every edge."""
    edges = np.roll(vertices, -1, axis=0) - vertices
    rel = points[:, None, :] - vertices[None, :, :]
    cross = edges[None, :, 0] * rel[:, :, 1] - edges[None, :, 1] * rel[:, :, 0]
    return np.all(cross >= -tol * np.linalg.norm(edges, axis=1)[None, :], axis=1)


def _signed_area(v: np.ndarray) -> float:
    return 0.5 * float(np.sum(v[:, 0] * np.roll(v[:, 1], -1) - np.roll(v[:, 0], -1) * v[:, 1]))


@settings(max_examples=200, deadline=None)
@given(
    cx=st.floats(-1e3, 1e3),
    cy=st.floats(-1e3, 1e3),
    radius=st.floats(1e-3, 100.0),
    sides=st.integers(3, 64),
    seed=st.integers(0, 2**32 - 1),
)
def test_circle_cover_contains_the_disc(cx: float, cy: float, radius: float, sides: int, seed: int) -> None:
    circle = CircleObstacle(center=(cx, cy), radius=radius)
    cover = circle.cover_vertices(circle_sides=sides)
    assert cover.shape == (sides, 2)
    assert _signed_area(cover) > 0.0  # counter-clockwise
    rng = np.random.default_rng(seed)
    angle = rng.uniform(0.0, 2.0 * np.pi, 500)
    fraction = np.sqrt(rng.uniform(0.0, 1.0, 500))
    fraction[:100] = 1.0  # on the circle itself, where the cover is tightest
    samples = np.array([cx, cy]) + (radius * fraction)[:, None] * np.column_stack([np.cos(angle), np.sin(angle)])
    assert np.all(circle.distance(samples) <= 1e-9 * (radius + abs(cx) + abs(cy)))
    assert np.all(_inside_convex(cover, samples, tol=1e-9 * (radius + abs(cx) + abs(cy))))


def test_circle_cover_is_tangent_at_edge_midpoints() -> None:
    circle = CircleObstacle(center=(2.0, -1.0), radius=3.0)
    cover = circle.cover_vertices(circle_sides=8)
    midpoints = 0.5 * (cover + np.roll(cover, -1, axis=0))
    np.testing.assert_allclose(np.linalg.norm(midpoints - [2.0, -1.0], axis=1), 3.0)
    with pytest.raises(ValueError, match="circle_sides"):
        circle.cover_vertices(circle_sides=2)


@settings(max_examples=100, deadline=None)
@given(st.lists(st.tuples(st.floats(-50, 50), st.floats(-50, 50)), min_size=1, max_size=12))
@example([(0.0, 0.0), (0.0, 1.0), (0.0, 1.1562195742834468e-237), (1.0, 0.0), (-3.993801049433862e-144, -1.0)])
@example([(0.0, 0.0), (0.0, 1.0), (0.0, 1.1562195742834468e-237), (1.0, 0.0), (-3.993801049433862e-144, 0.0)])
def test_points_cover_contains_every_point_and_the_hull(points: list[tuple[float, float]]) -> None:
    obstacle = PointsObstacle(points=points)
    cover = obstacle.cover_vertices()
    if len(points) <= 2:
        np.testing.assert_array_equal(cover, np.asarray(points, dtype=float))
        return
    hull = shapely.MultiPoint(cover).convex_hull
    assert hull.buffer(1e-9).covers(obstacle.solid())
    if len(cover) >= 3:
        assert _signed_area(cover) > 0.0
        assert np.all(_inside_convex(cover, np.asarray(points, dtype=float), tol=1e-9))


def test_polygon_cover_is_the_ccw_hull_and_contains_the_solid() -> None:
    clockwise_u = [(0, 3), (1, 3), (1, 1), (2, 1), (2, 3), (3, 3), (3, 0), (0, 0)]
    obstacle = PolygonObstacle(vertices=clockwise_u)
    cover = obstacle.cover_vertices()
    assert _signed_area(cover) == pytest.approx(9.0)
    assert shapely.Polygon(cover).covers(obstacle.solid())
    assert {tuple(v) for v in cover.tolist()} == {(0, 0), (3, 0), (3, 3), (0, 3)}


def test_scenario_type_annotations_round_trip_through_json() -> None:
    scenario = parse_scenario(json.dumps(BASE))
    assert Scenario.model_validate_json(scenario.model_dump_json()) == scenario
