"""The local frame: every message and file moves between the world and a core's frame exactly, and a far
scenario plans exactly as at home.

The public scenarios are first put on the grid of float64 at 10⁷ m (multiples of 2⁻²⁹ m, a move of at
most 1 nm): moved by 10⁶ or 10⁷ m they then lose no digit, so any difference between the plans is the
planner's dependence on where the map lies, which the local frame removes. Without that step the moved
file itself holds other numbers (rounded to 2 nm at 10⁷ m), and two public scenarios turn on such digits
even at the origin: corner-trap and narrow-gap are mirror-symmetric about y = x, with two equally short
ways round, and a rigid move of 1e-12 m at the origin already takes corner-trap the other way round
(`test_mirror_symmetric_scenarios_turn_on_the_last_digit_at_the_origin_too`). For the files as they
are, the moved plans must still be found, as clear, and as long within 0.1 % (narrow-gap moved by 10⁷ m
goes round the other wall, 2 mm longer).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from cvxnav.plan import plan_scenario
from schemas.files import EllipseModel, LatencyStats, PlanFile, PlanTimings, RunFile
from schemas.messages import (
    MESSAGE_MODELS,
    CircleMsg,
    ClusterMsg,
    Clusters,
    EllipsoidMsg,
    Ellipsoids,
    Goals,
    Header,
    Map,
    Pose2D,
    RawPath,
    RobotState,
    Scan,
    SmoothPath,
    StageStatus,
    World,
)
from schemas.scenario import MAX_COORDINATE_M, Scenario, ScenarioError, load_scenario
from services.convert import _MOVERS, LocalFrame
from services.geometry import Ellipse, EllipseStack, polyline_length

PUBLIC = ["corner-trap", "field-8", "field-15", "field-25", "field-60", "narrow-gap", "paper-two-goals", "wide-gap"]
MAP_SCENARIO = "depot-1"  # in map-scenarios/
GRID_M = 2.0**-29  # float64's spacing in [2²³, 2²⁴) m, which holds everything moved by 10⁷ m
FAR = (1e6, 1e7)


def _header() -> Header:
    return Header(stamp_s=1.5, seq=3)


def _ellipse(center: tuple[float, float]) -> EllipsoidMsg:
    e = Ellipse.from_axes(center=center, semi_axes=(1.2, 0.4), angle_rad=0.3)
    (a11, a12), (_, a22) = e.A.tolist()
    return EllipsoidMsg(A=((a11, a12), (a12, a22)), b=tuple(e.b.tolist()), group=0, cluster_id=2)


def _messages(at: float) -> list:
    """One of every message, with its coordinates near (at, at)."""
    p = lambda dx, dy: (at + dx, at + dy)  # noqa: E731
    pose = Pose2D(x_m=at + 1.0, y_m=at - 2.0, theta_rad=0.7)
    return [
        Scan(header=_header(), pose=pose, points=[p(1.0, 2.0), p(-3.0, 0.5)]),
        Clusters(header=_header(), scan_seq=3, clusters=[ClusterMsg(cluster_id=0, points=[p(1.0, 1.0), p(1.5, 1.0)])]),
        Ellipsoids(header=_header(), scan_seq=3, inflation_m=0.65, ellipsoids=[_ellipse(p(4.0, 3.0))]),
        RawPath(header=_header(), scan_seq=3, status="ok", goal_index=0, points=[p(0.0, 0.0), p(1.0, 1.0)],
                ellipsoids=[_ellipse(p(-2.0, 5.0))], plan_id=4),
        SmoothPath(header=_header(), scan_seq=3, status="ok", goal_index=0, points=[p(0.0, 0.0), p(0.05, 0.0)],
                   max_curvature=0.1, min_level=1.2),
        RobotState(header=_header(), pose=pose, speed_mps=0.5, steering_rad=0.1, goal_index=0, goals_reached=0,
                   done=False),
        Goals(header=_header(), goals=[p(10.0, 10.0), p(15.0, 15.0)]),
        StageStatus(header=_header(), stage="planner", state="ok", processing_ms=3.0),
        World(header=_header(), scenario="w", bounds_min=p(-4.0, -4.0), bounds_max=p(19.0, 19.0), robot_width_m=0.3,
              robot_length_m=0.6, start=pose, goals=[p(10.0, 10.0)], goal_tolerance_m=0.3,
              polygons=[[p(3.0, 2.6), p(3.6, 2.9), p(3.3, 3.6)]], circles=[CircleMsg(center=p(8.0, 2.0), radius_m=1.0)]),
        Map(header=_header(), width=2, height=2, resolution_m=0.5, origin=pose, cells=Map.pack_cells(bytes([0, 1, 2, 0]))),
    ]


def _coordinates(message) -> np.ndarray:
    """Every position a message holds (ellipse centres for ellipses), in one array."""
    out: list = []
    for name in ("points", "goals", "path", "raw_path"):
        out += list(getattr(message, name, []))
    for pose in (getattr(message, "pose", None), getattr(message, "start", None), getattr(message, "origin", None)):
        if pose is not None:
            out.append((pose.x_m, pose.y_m))
    out += [pt for c in getattr(message, "clusters", []) for pt in c.points]
    out += [pt for poly in getattr(message, "polygons", []) for pt in poly] + [c.center for c in getattr(message, "circles", [])]
    if hasattr(message, "bounds_min"):
        out += [message.bounds_min, message.bounds_max]
    out += [tuple(Ellipse(A=e.A, b=e.b).center) for e in getattr(message, "ellipsoids", [])]
    out += [(x, y) for _, x, y, _ in getattr(message, "trajectory", [])]
    return np.asarray(out, dtype=float).reshape(-1, 2)


def test_every_message_model_and_output_file_has_a_conversion() -> None:
    assert set(MESSAGE_MODELS) | {PlanFile, RunFile} <= set(_MOVERS)
    with pytest.raises(TypeError, match=r"no local-frame conversion for Header"):
        LocalFrame(origin=(1e6, 0.0)).to_local(_header())


@pytest.mark.parametrize("message", _messages(1e7 + 0.25), ids=lambda m: type(m).__name__)
def test_a_message_moves_into_the_local_frame_and_back_exactly(message) -> None:
    frame = LocalFrame(origin=(1e7, 1e7))
    local = frame.to_local(message)
    assert type(local) is type(message)
    np.testing.assert_allclose(_coordinates(local), _coordinates(message) - 1e7, rtol=0, atol=1e-8)
    assert np.all(np.abs(_coordinates(local)) < 30.0)
    back = frame.to_world(local)
    np.testing.assert_allclose(_coordinates(back), _coordinates(message), rtol=0, atol=1e-8)
    type(message).model_validate_json(local.model_dump_json())  # still a valid message, as the shell publishes it
    assert local.header == message.header


def test_an_ellipse_moved_holds_the_same_points_at_the_same_level() -> None:
    frame = LocalFrame(origin=(1e6, -2e6))
    world = Ellipsoids(header=_header(), scan_seq=0, inflation_m=0.65, ellipsoids=[_ellipse((1e6 + 3.0, -2e6 + 1.0))])
    local = frame.to_local(world)
    probes = np.array([[3.0, 1.0], [3.9, 1.2], [2.0, 0.0], [5.0, 5.0]])
    level = lambda m, z: EllipseStack.of([Ellipse(A=e.A, b=e.b) for e in m.ellipsoids]).levels(z)  # noqa: E731
    np.testing.assert_allclose(level(local, probes), level(world, probes + frame.origin), rtol=0, atol=1e-7)


def _path(shared_dir: Path, name: str) -> Path:
    return shared_dir / ("map-scenarios" if name == MAP_SCENARIO else "scenarios") / f"{name}.json"


def test_the_frame_of_a_scenario_near_the_origin_is_the_identity(shared_dir) -> None:
    for name in [*PUBLIC, MAP_SCENARIO]:
        scenario = load_scenario(_path(shared_dir, name))
        frame = LocalFrame.of(scenario)
        assert frame.identity and frame.scenario_to_local(scenario) is scenario
        message = _messages(0.0)[0]
        assert frame.to_local(message) is message and frame.to_world(message) is message


def _moved_file(path: Path, offset: float, out: Path) -> Path:
    """The scenario file moved by `offset` on both axes, as a user's tool would write it (a map: a copy of
    its YAML with the origin moved, naming the same image)."""
    import yaml

    doc = json.loads(path.read_text())
    move = lambda p: [p[0] + offset, p[1] + offset]  # noqa: E731
    if "bounds" in doc:
        doc["bounds"] = {"min": move(doc["bounds"]["min"]), "max": move(doc["bounds"]["max"])}
    doc["start"].update(x=doc["start"]["x"] + offset, y=doc["start"]["y"] + offset)
    doc["goals"] = [move(g) for g in doc["goals"]]
    for obstacle in doc.get("obstacles", []):
        if obstacle["type"] == "polygon":
            obstacle["vertices"] = [move(v) for v in obstacle["vertices"]]
        elif obstacle["type"] == "points":
            obstacle["points"] = [move(v) for v in obstacle["points"]]
        elif obstacle["type"] == "circle":
            obstacle["center"] = move(obstacle["center"])
        else:
            source = (path.parent / obstacle["map"]).resolve()
            meta = yaml.safe_load(source.read_text())
            meta["image"] = str((source.parent / meta["image"]).resolve())
            meta["origin"] = [meta["origin"][0] + offset, meta["origin"][1] + offset, meta["origin"][2]]
            (out.parent / f"{out.stem}.yaml").write_text(yaml.safe_dump(meta))
            obstacle["map"] = f"{out.stem}.yaml"
    out.write_text(json.dumps(doc, indent=1))
    return out


def _on_grid(path: Path, out: Path) -> Path:
    """The scenario with every number of a coordinate rounded to a multiple of `GRID_M`."""
    doc = json.loads(path.read_text())
    snap = lambda p: [round(v / GRID_M) * GRID_M for v in p]  # noqa: E731
    if "bounds" in doc:
        doc["bounds"] = {k: snap(v) for k, v in doc["bounds"].items()}
    doc["start"].update(x=snap([doc["start"]["x"]])[0], y=snap([doc["start"]["y"]])[0])
    doc["goals"] = [snap(g) for g in doc["goals"]]
    for obstacle in doc.get("obstacles", []):
        for key in ("vertices", "points"):
            if key in obstacle:
                obstacle[key] = [snap(v) for v in obstacle[key]]
        if "center" in obstacle:
            obstacle["center"] = snap(obstacle["center"])
        if "map" in obstacle:
            obstacle["map"] = str((path.parent / obstacle["map"]).resolve())
    out.write_text(json.dumps(doc, indent=1))
    return out


@pytest.fixture(scope="module")
def home_plans(shared_dir, tmp_path_factory) -> dict[str, tuple[Path, PlanFile]]:
    folder = tmp_path_factory.mktemp("home")
    plans = {}
    for name in [*PUBLIC, MAP_SCENARIO]:
        snapped = _on_grid(_path(shared_dir, name), folder / f"{name}.json")
        plans[name] = (snapped, plan_scenario(load_scenario(snapped)))
    return plans


@pytest.mark.parametrize("offset", FAR, ids=lambda d: f"{d:g} m")
@pytest.mark.parametrize("name", [*PUBLIC, MAP_SCENARIO])
def test_a_scenario_moved_far_away_plans_exactly_as_at_home(name, offset, home_plans, tmp_path) -> None:
    snapped, home = home_plans[name]
    far = plan_scenario(load_scenario(_moved_file(snapped, offset, tmp_path / f"{name}.json")))
    assert home.status == far.status == "ok"
    assert len(far.path) == len(home.path) and len(far.raw_path) == len(home.raw_path)
    np.testing.assert_allclose(np.array(far.path) - offset, home.path, rtol=0, atol=1e-3)
    np.testing.assert_allclose(np.array(far.raw_path) - offset, home.raw_path, rtol=0, atol=1e-3)
    moved = [Ellipse(A=e.A, b=e.b).center for e in far.ellipsoids]
    np.testing.assert_allclose(np.array(moved) - offset, [Ellipse(A=e.A, b=e.b).center for e in home.ellipsoids],
                               rtol=0, atol=1e-3)


@pytest.fixture(scope="module")
def public_plans(scenarios_dir) -> dict[str, PlanFile]:
    return {name: plan_scenario(load_scenario(scenarios_dir / f"{name}.json")) for name in PUBLIC}


@pytest.mark.parametrize("offset", (1e7, 1e9), ids=lambda d: f"{d:g} m")
def test_the_public_files_moved_far_away_are_planned_as_long_and_as_clear(offset, scenarios_dir, public_plans,
                                                                          tmp_path) -> None:
    for name in PUBLIC:
        path = scenarios_dir / f"{name}.json"
        home = public_plans[name]
        moved = load_scenario(_moved_file(path, offset, tmp_path / path.name))
        far = plan_scenario(moved)
        assert far.status == home.status == "ok", name
        # Within 0.1 %: where a plan turns on the last digit, the other way round converges to its own length.
        assert polyline_length(np.array(far.path)) == pytest.approx(polyline_length(np.array(home.path)), rel=1e-3)
        assert np.min(moved.clearance(np.array(far.path))) >= moved.inflation_m - 0.02, name


def test_mirror_symmetric_scenarios_turn_on_the_last_digit_at_the_origin_too(scenarios_dir) -> None:
    """corner-trap's two ways round are equally long: a rigid move by 1e-12 m takes the other one (so
    the exact comparison above needs moves that lose no digit)."""
    scenario = load_scenario(scenarios_dir / "corner-trap.json")
    home = np.array(plan_scenario(scenario).path)
    sides = set()
    for d in np.random.default_rng(1).normal(0.0, 1e-12, (5, 2)):
        moved = np.array(plan_scenario(scenario.translated(d)).path) - d
        sides.add(bool(np.abs(moved - home).max() < 1e-3))
    assert sides == {True, False}


def test_coordinates_beyond_the_bound_are_one_line(scenarios_dir, tmp_path) -> None:
    path = _moved_file(scenarios_dir / "field-8.json", 2 * MAX_COORDINATE_M, tmp_path / "beyond.json")
    with pytest.raises(ScenarioError, match=r"^beyond.json: bounds.min\[0\]: Input should be less than or equal to "):
        load_scenario(path)


def test_a_scenario_moves_exactly_and_keeps_what_validation_checked(scenarios_dir) -> None:
    scenario = load_scenario(scenarios_dir / "field-8.json")
    far = scenario.translated((1e7, 1e7))
    back = far.translated((-1e7, -1e7))
    for a, b in [(scenario.goals, back.goals), ([scenario.bounds.min], [back.bounds.min]),
                 ([(scenario.start.x, scenario.start.y)], [(back.start.x, back.start.y)])]:
        np.testing.assert_allclose(a, b, rtol=0, atol=2e-9)
    probes = np.array([[1.0, 2.0], [5.0, 5.0], [8.0, 1.0]])
    np.testing.assert_allclose(far.clearance(probes + 1e7), scenario.clearance(probes), atol=1e-8)
    assert isinstance(far, Scenario) and far.start.theta == scenario.start.theta


def test_a_plan_and_a_run_file_move_back_into_the_world() -> None:
    frame = LocalFrame(origin=(1e6, 2e6))
    e = Ellipse.from_axes(center=(3.0, 4.0), semi_axes=(1.0, 0.5))
    plan = PlanFile(scenario="s", status="ok", path=[(0.0, 0.0), (1.0, 1.0)], raw_path=[(0.0, 0.0)],
                    ellipsoids=[EllipseModel(A=tuple(map(tuple, e.A.tolist())), b=tuple(e.b.tolist()))],
                    timings_ms=PlanTimings(load=0, corridor=0, cluster=0, fit=0, group=0, optimize=0, smooth=0, total=0))
    world = frame.to_world(plan)
    assert world.path == [(1e6, 2e6), (1e6 + 1.0, 2e6 + 1.0)]
    np.testing.assert_allclose(Ellipse(A=world.ellipsoids[0].A, b=world.ellipsoids[0].b).center, (1e6 + 3.0, 2e6 + 4.0))
    run = RunFile(scenario="s", status="reached", goals_reached=1, trajectory=[(0.0, 1.0, 2.0, 0.5)], replans=0,
                  latency_ms=LatencyStats(p50=0, p99=0, max=0), min_clearance=None)
    assert frame.to_world(run).trajectory == [(0.0, 1e6 + 1.0, 2e6 + 2.0, 0.5)]

