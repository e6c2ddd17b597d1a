"""`cvxnav plan` as a user runs it: a real process per scenario, real files, the contract's promises."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from schemas.files import PlanFile
from schemas.scenario import load_scenario
from services.convert import ellipse_from_model
from services.drive.controller import menger_curvature
from services.geometry import polyline_length

PUBLIC = [
    "corner-trap",
    "field-8",
    "field-15",
    "field-25",
    "field-60",
    "narrow-gap",
    "paper-two-goals",
    "wide-gap",
]


def cvxnav(*args: str, cwd: Path) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "cvxnav", *args], cwd=cwd, capture_output=True, text=True, timeout=120
    )


@pytest.fixture(scope="module")
def plans(scenarios_dir: Path, tmp_path_factory) -> dict[str, tuple[int, PlanFile]]:
    out = tmp_path_factory.mktemp("plans")
    results = {}
    for name in PUBLIC:
        done = cvxnav("plan", str(scenarios_dir / f"{name}.json"), "--out", str(out / f"{name}.json"), cwd=out)
        results[name] = (done.returncode, PlanFile.read(out / f"{name}.json"))
    return results


@pytest.mark.parametrize("name", PUBLIC)
def test_plan_is_safe_drivable_and_visits_goals_in_order(name, plans, scenarios_dir):
    scenario = load_scenario(scenarios_dir / f"{name}.json")
    code, plan = plans[name]
    assert code == 0 and plan.status == "ok"
    path = np.array(plan.path)
    # Clearance to the TRUE obstacles along the whole polyline (sampled at 1 cm).
    dense = np.concatenate([p + np.linspace(0, 1, 6)[:, None] * (q - p) for p, q in zip(path[:-1], path[1:])])
    assert scenario.clearance(dense).min() >= scenario.inflation_m - 0.02
    assert np.all(dense >= scenario.bounds.min) and np.all(dense <= scenario.bounds.max)
    # Curvature of the published samples (0.05 m apart) within the car's bound (2 % for the sampling).
    assert np.max(np.abs(menger_curvature(path))) <= 1.02 * scenario.max_curvature
    assert np.linalg.norm(np.diff(path, axis=0), axis=1).max() <= 0.05
    assert np.allclose(path[0], scenario.start.xy)
    cursor = 0
    for goal in scenario.goals_array:
        hits = np.flatnonzero(np.linalg.norm(path[cursor:] - goal, axis=1) <= scenario.goal_tolerance)
        assert len(hits), f"goal {goal} missed"
        cursor += hits[0]
    timings = plan.timings_ms.model_dump()
    assert set(timings) == {"load", "corridor", "cluster", "fit", "group", "optimize", "smooth", "total"}
    assert timings["load"] > 0.0 and timings["total"] >= sum(v for k, v in timings.items() if k != "total")
    assert all(ellipse_from_model(e).level(path).min() > 1.0 for e in plan.ellipsoids)


def test_path_length_against_the_reference(plans, scenarios_dir):
    reference = json.loads((scenarios_dir / "REFERENCE.json").read_text())["optimal_length"]
    ratios = {name: polyline_length(np.array(plans[name][1].path)) / reference[name] for name in PUBLIC}
    assert max(ratios.values()) <= 1.25, ratios
    assert np.mean(list(ratios.values())) <= 1.10, ratios


def _write(path: Path, scenario: dict) -> Path:
    path.write_text(json.dumps(scenario))
    return path


@pytest.fixture()
def paper(scenarios_dir: Path) -> dict:
    return json.loads((scenarios_dir / "paper-two-goals.json").read_text())


def test_enclosed_goal_is_reported_as_no_path(paper, tmp_path):
    walls = [
        [[8.0, 8.0], [12.0, 8.0], [12.0, 8.4], [8.0, 8.4]],
        [[8.0, 11.6], [12.0, 11.6], [12.0, 12.0], [8.0, 12.0]],
        [[8.0, 8.0], [8.4, 8.0], [8.4, 12.0], [8.0, 12.0]],
        [[11.6, 8.0], [12.0, 8.0], [12.0, 12.0], [11.6, 12.0]],
    ]
    scenario = dict(paper, name="enclosed", goals=[[10.0, 10.0]], expect="no_path",
                    obstacles=[{"type": "polygon", "vertices": w} for w in walls])
    done = cvxnav("plan", str(_write(tmp_path / "enclosed.json", scenario)), "--out", "plan.json", cwd=tmp_path)
    assert done.returncode == 3, done.stderr
    plan = PlanFile.read(tmp_path / "plan.json")
    assert plan.status == "no_path" and plan.path == []
    assert plan.timings_ms.total < 5000  # the bound: no_path is concluded quickly


def test_a_car_facing_back_down_a_corridor_too_narrow_to_turn_in_is_told_so(paper, tmp_path):
    """A 3 m corridor (1.7 m free of the grown walls) and a turning radius of 2.96 m: the car faces away
    from its goal and cannot turn round without reversing, which a plan never does. Facing the goal, the
    same query plans."""
    walls = [[[-2.0, 1.5], [20.0, 1.5], [20.0, 1.7], [-2.0, 1.7]], [[-2.0, -1.7], [20.0, -1.7], [20.0, -1.5], [-2.0, -1.5]]]
    corridor = dict(paper, goals=[[15.0, 0.0]], bounds={"min": [-3, -3], "max": [21, 3]},
                    obstacles=[{"type": "polygon", "vertices": w} for w in walls])
    back = dict(corridor, name="facing-back", start={"x": 5.0, "y": 0.0, "theta": np.pi}, expect="no_path")
    done = cvxnav("plan", str(_write(tmp_path / "back.json", back)), "--out", "back.json", cwd=tmp_path)
    assert done.returncode == 3, done.stderr
    plan = PlanFile.read(tmp_path / "back.json")
    assert plan.status == "no_path" and plan.path == []
    assert "within a turning radius (2.96 m) of the start" in plan.reason and "never reverses" in plan.reason
    ahead = dict(corridor, name="facing-ahead", start={"x": 5.0, "y": 0.0, "theta": 0.0}, expect="reach")
    done = cvxnav("plan", str(_write(tmp_path / "ahead.json", ahead)), "--out", "ahead.json", cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    assert PlanFile.read(tmp_path / "ahead.json").status == "ok"


@pytest.mark.parametrize(
    "edit, field",
    [
        (lambda s: s["robot"].update(width=-0.3), "robot.width"),
        (lambda s: s.update(colour="red"), "colour"),
        (lambda s: s["obstacles"].append({"type": "polygon", "vertices": [[0, 5], [1, 5]]}), "obstacles[4]"),
        (lambda s: s.update(goals=[[3.2, 3.1]]), "goals[0]"),
    ],
)
def test_bad_scenario_exits_2_with_one_line_naming_the_field(paper, tmp_path, edit, field):
    edit(paper)
    done = cvxnav("plan", str(_write(tmp_path / "bad.json", paper)), cwd=tmp_path)
    assert done.returncode == 2
    assert len(done.stderr.strip().splitlines()) == 1
    assert field in done.stderr and "Traceback" not in done.stderr


def test_default_scenario_is_the_papers(tmp_path):
    done = cvxnav("plan", "--out", "plan.json", cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    assert PlanFile.read(tmp_path / "plan.json").scenario == "paper-two-goals"
