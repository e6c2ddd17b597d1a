"""The inputs a real robot's user gives `cvxnav plan` and `cvxnav run` (issue 26, docs/faults.md "Inputs").

Every bad one is one line and exit 2 before anything runs: through `cvxnav plan` and `cvxnav run` in
this process for the whole table (both load and check the scenario before anything else), and through
real `cvxnav run` and `cvxnav router` processes for a few, which must start no stage: the supervisor
makes its temporary folder before it starts the first stage, and with TMPDIR pointing at an empty
folder that folder stays empty. The valid inputs that used to fail (an empty world, repeated goals, a
goal at the start) plan and run.
"""

from __future__ import annotations

import copy
import json
import os
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from cvxnav.cli import main
from schemas.files import PlanFile, RunFile
from schemas.occupancy import MAX_CELLS
from schemas.scenario import (
    MAX_GOALS,
    MAX_OBSTACLES,
    MAX_RAYS,
    MAX_SCENARIO_BYTES,
    MAX_TOTAL_VERTICES,
    MAX_VERTICES,
    bundled_scenario,
    load_scenario,
)

PAPER = json.loads(bundled_scenario().model_dump_json())
SQUARE = {"type": "polygon", "vertices": [[5.0, -3.0], [5.2, -3.0], [5.2, -2.8], [5.0, -2.8]]}


def _edited(edit: Callable[[dict], object]) -> Callable[[Path], Path]:
    """A maker of the paper scenario with `edit` applied to its document."""

    def make(folder: Path) -> Path:
        doc = copy.deepcopy(PAPER)
        edit(doc)
        (folder / "s.json").write_text(json.dumps(doc))
        return folder / "s.json"

    return make


def _text(text: str) -> Callable[[Path], Path]:
    def make(folder: Path) -> Path:
        (folder / "s.json").write_text(text)
        return folder / "s.json"

    return make


def _fifo(folder: Path) -> Path:
    os.mkfifo(folder / "s.json")  # opening it for reading would block until a writer came
    return folder / "s.json"


def _paper_text_with(old: str, new: str) -> Callable[[Path], Path]:
    text = json.dumps(PAPER)
    assert old in text
    return _text(text.replace(old, new, 1))


def _map_scenario(folder: Path, yaml_name: str) -> Path:
    doc = copy.deepcopy(PAPER)
    doc.update(format="cvxnav.scenario/2", obstacles=[{"type": "occupancy_grid", "map": yaml_name}])
    (folder / "s.json").write_text(json.dumps(doc))
    return folder / "s.json"


def _huge_map(folder: Path) -> Path:
    """A map whose image header says 5000 × 5000 pixels (the pixels are never read)."""
    (folder / "huge.pgm").write_bytes(b"P5\n5000 5000\n255\n" + bytes(1000))
    (folder / "huge.yaml").write_text("image: huge.pgm\nresolution: 0.05\norigin: [0.0, 0.0, 0.0]\n")
    return _map_scenario(folder, "huge.yaml")


def _fifo_image(folder: Path) -> Path:
    os.mkfifo(folder / "m.pgm")
    (folder / "m.yaml").write_text("image: m.pgm\nresolution: 0.05\norigin: [0.0, 0.0, 0.0]\n")
    return _map_scenario(folder, "m.yaml")


def _many_obstacles(doc: dict) -> None:
    doc["obstacles"] = [{"type": "circle", "center": [15.0 + 0.001 * k, -3.0], "radius": 0.001}
                        for k in range(MAX_OBSTACLES + 1)]


# (id, scenario maker, the start of the error after "cvxnav: error: s.json: ")
BAD: list[tuple[str, Callable[[Path], Path], str]] = [
    ("width 1e200", _edited(lambda d: d["robot"].update(width=1e200)),
     "robot.width: Input should be less than or equal to 100"),
    ("safety distance 1e308", _edited(lambda d: d["robot"].update(safety_distance=1e308)),
     "robot.safety_distance: Input should be less than or equal to 100"),
    ("JSON nested 100 000 deep", _text("[" * 100_000 + "]" * 100_000), "invalid JSON: arrays or objects nested too deeply"),
    ("rays of 10 000 digits", _paper_text_with('"rays": 181', '"rays": ' + "9" * 10_000),
     "invalid JSON: an integer of 10000 digits at line 1 column "),
    ("rays of 400 digits", _paper_text_with('"rays": 181', '"rays": ' + "9" * 400),
     f"sensor.rays: Input should be less than or equal to {MAX_RAYS}"),
    ("width of 400 digits", _paper_text_with('"width": 0.3', '"width": ' + "9" * 400),
     "robot.width: Input should be a valid number"),
    ("1e9 rays", _edited(lambda d: d["sensor"].update(rays=10**9)),
     f"sensor.rays: Input should be less than or equal to {MAX_RAYS}"),
    ("width as a string", _edited(lambda d: d["robot"].update(width="0.3")), "robot.width: Input should be a valid number"),
    ("width true", _edited(lambda d: d["robot"].update(width=True)), "robot.width: Input should be a valid number"),
    ("rays as a string", _edited(lambda d: d["sensor"].update(rays="181")), "sensor.rays: Input should be a valid integer"),
    ("rays as a float", _edited(lambda d: d["sensor"].update(rays=181.0)), "sensor.rays: Input should be a valid integer"),
    ("goal as strings", _edited(lambda d: d.update(goals=[["10", "10"]])), "goals[0][0]: Input should be a valid number"),
    ("start footprint on an obstacle",
     _edited(lambda d: d["obstacles"].append({"type": "circle", "center": [0.45, 0.0], "radius": 0.2})),
     "start: the robot's 0.6 × 0.3 m footprint overlaps or touches obstacles[4] (circle)"),
    ("start footprint beyond the bounds", _edited(lambda d: d["start"].update(x=-3.9, y=-3.9)),
     "start: the robot's 0.6 × 0.3 m footprint leaves bounds"),
    ("coordinate 1e11", _edited(lambda d: d["goals"].append([1e11, 0.0])),
     "goals[2][0]: Input should be less than or equal to 10000000000"),
    ("bounds 20 km across", _edited(lambda d: d["bounds"].update(max=[20_000.0, 19.0])),
     "bounds: span 20004 m, more than the 10000 m a side may have"),
    ("too many goals", _edited(lambda d: d.update(goals=[[10.0, 10.0]] * (MAX_GOALS + 1))),
     f"goals: List should have at most {MAX_GOALS} items"),
    ("too many obstacles", _edited(_many_obstacles),
     f"obstacles: an array of {MAX_OBSTACLES + 1} items, more than any field holds ({MAX_OBSTACLES})"),
    ("a polygon of too many vertices",
     _edited(lambda d: d["obstacles"].append({"type": "polygon", "vertices": [
         [15 + np.cos(t), -2 + np.sin(t)] for t in np.linspace(0, 6.28, MAX_VERTICES + 1, endpoint=False)]})),
     f"obstacles[4].vertices: an array of {MAX_VERTICES + 1} items, more than any field holds ({MAX_VERTICES})"),
    ("too many vertices in all",
     _edited(lambda d: d["obstacles"].extend({"type": "points", "points": [[15.0 + 1e-5 * k, -3.0 + 1e-3 * j]
                                                                          for k in range(MAX_VERTICES)]}
                                             for j in range(MAX_TOTAL_VERTICES // MAX_VERTICES))),
     f"obstacles: {MAX_TOTAL_VERTICES + 17} vertices and points in all, more than {MAX_TOTAL_VERTICES}"),
    ("a file over the size bound", _text(json.dumps(PAPER) + " " * MAX_SCENARIO_BYTES),
     f"larger than the {MAX_SCENARIO_BYTES} bytes such a file may have"),
    ("a name of two lines", _edited(lambda d: d.update(name="two\nlines")), "name: String should match pattern"),
    ("a rate of 0 Hz", _edited(lambda d: d["sensor"].update(rate_hz=0)), "sensor.rate_hz: Input should be greater than or equal to 0.1"),
    ("a FIFO", _fifo, "not a regular file (a FIFO, socket or device)"),
    ("a FIFO as the map's image", _fifo_image,
     "obstacles[0].map: m.yaml: image: m.pgm: not a regular file (a FIFO, socket, device or directory)"),
    ("/dev/zero as the map", lambda folder: _map_scenario(folder, "/dev/zero"),
     "obstacles[0].map: /dev/zero: cannot read the map file: not a regular file"),
    ("a map of 25 million cells", _huge_map,
     f"obstacles[0].map: huge.yaml: image: huge.pgm: 5000 × 5000 pixels is more than the {MAX_CELLS} cells a map may have"),
]

# Valid, and they used to fail: (id, maker, what plan's file must say)
VALID: list[tuple[str, Callable[[Path], Path]]] = [
    ("no obstacle", _edited(lambda d: d.update(obstacles=[]))),
    ("no obstacles field", _edited(lambda d: d.pop("obstacles"))),
    ("a goal twice in a row", _edited(lambda d: d.update(goals=[[10.0, 10.0], [10.0, 10.0], [15.0, 15.0]]))),
    ("200 identical goals", _edited(lambda d: d.update(goals=[[10.0, 10.0]] * 200))),
    ("the goal at the start", _edited(lambda d: d.update(goals=[[0.0, 0.0]]))),
    ("the first goal at the start", _edited(lambda d: d.update(goals=[[0.1, 0.0], [10.0, 10.0]]))),
    ("integers for every float", _edited(lambda d: d["robot"].update(width=1, safety_distance=1))),
]


def _one_error_line(stderr: str) -> str:
    assert stderr.count("\n") == 1 and "Traceback" not in stderr, stderr[-2000:]
    assert stderr.startswith("cvxnav: error: ")
    return stderr.strip()[len("cvxnav: error: "):]


@pytest.mark.parametrize("command", ["plan", "run"])
@pytest.mark.parametrize(("make", "expected"), [case[1:] for case in BAD], ids=[case[0] for case in BAD])
def test_a_bad_scenario_is_one_line_naming_the_field_and_exit_2(command, make, expected, tmp_path, capsys,
                                                              monkeypatch):
    monkeypatch.chdir(tmp_path)
    path = make(tmp_path)
    assert main([command, str(path), "--out", "out.json", *(["--quiet"] if command == "run" else [])]) == 2
    captured = capsys.readouterr()
    line = _one_error_line(captured.err)
    assert line.startswith(f"{path.name}: {expected}") or line.startswith(f"{path}: {expected}"), line
    assert captured.out == "" and not (tmp_path / "out.json").exists()


def test_dev_zero_is_refused_unread(tmp_path, capsys):
    assert main(["plan", "/dev/zero", "--out", str(tmp_path / "out.json")]) == 2
    assert _one_error_line(capsys.readouterr().err) == "/dev/zero: not a regular file (a FIFO, socket or device)"


@pytest.mark.parametrize(("make",), [case[1:] for case in VALID], ids=[case[0] for case in VALID])
def test_an_input_that_used_to_fail_plans(make, tmp_path, capsys):
    path = make(tmp_path)
    scenario = load_scenario(path)
    assert main(["plan", str(path), "--out", str(tmp_path / "plan.json")]) == 0, capsys.readouterr().err
    plan = PlanFile.read(tmp_path / "plan.json")
    path_xy = np.array(plan.path)
    assert plan.status == "ok" and np.allclose(path_xy[0], (scenario.start.x, scenario.start.y))
    cursor = 0  # every goal, in order, within tolerance of the path
    for goal in scenario.goals_array:
        near = np.flatnonzero(np.linalg.norm(path_xy[cursor:] - goal, axis=1) <= scenario.goal_tolerance)
        assert len(near), goal
        cursor += int(near[0])
    if scenario.obstacles:
        assert np.min(scenario.clearance(path_xy)) >= scenario.inflation_m - 0.02


def test_a_goal_at_the_start_is_a_plan_of_one_point(tmp_path, capsys):
    path = VALID[4][1](tmp_path)
    assert main(["plan", str(path), "--out", str(tmp_path / "plan.json")]) == 0
    assert "path 0.00 m" in capsys.readouterr().out
    assert PlanFile.read(tmp_path / "plan.json").path == [(0.0, 0.0)]


def _cvxnav(*args: str, cwd: Path, tmp: Path) -> tuple[subprocess.CompletedProcess, float]:
    started = time.monotonic()
    proc = subprocess.run([sys.executable, "-m", "cvxnav", *args], cwd=cwd, capture_output=True, text=True,
                          timeout=60, env={**os.environ, "TMPDIR": str(tmp)})
    return proc, time.monotonic() - started


MAKE = {name: make for name, make, _ in BAD}


@pytest.mark.parametrize(
    ("make", "args", "expected"),
    [(MAKE["width 1e200"], [], "s.json: robot.width: Input should be less than or equal to 100"),
     (MAKE["JSON nested 100 000 deep"], [], "s.json: invalid JSON: arrays or objects nested too deeply"),
     (MAKE["1e9 rays"], [], f"s.json: sensor.rays: Input should be less than or equal to {MAX_RAYS}"),
     (_fifo, [], "not a regular file (a FIFO, socket or device)"),
     (None, ["/dev/zero"], "/dev/zero: not a regular file (a FIFO, socket or device)"),
     (None, ["--listen", "tcp/8.8.8.8:7447"], "cannot open the run's Zenoh session: Can not create a new TCP listener")],
    ids=["width-1e200", "nested-100000-deep", "1e9-rays", "fifo", "dev-zero", "listen-on-an-address-not-ours"],
)
def test_cvxnav_run_refuses_before_any_stage_starts(make, args, expected, tmp_path):
    tmp = tmp_path / "tmp"
    tmp.mkdir()
    target = [str(make(tmp_path))] if make is not None else []
    proc, wall_s = _cvxnav("run", "--quiet", *target, *args, "--out", "run.json", cwd=tmp_path, tmp=tmp)
    assert proc.returncode == 2, proc.stderr[-2000:]
    assert expected in _one_error_line(proc.stderr)
    assert list(tmp.iterdir()) == [] and not (tmp_path / "run.json").exists()  # no supervisor, no stage
    print(f"refused in {wall_s:.2f} s")


@pytest.mark.parametrize(
    "args",
    [["run", "--listen", "tcp/notanendpoint"], ["run", "--connect", "foo/127.0.0.1:7447"],
     ["router", "--listen", "tcp/999.1.1.1:7447"], ["router", "--listen", "tcp/127.0.0.1:99999"],
     ["status", "--connect", "tcp/[::1:7447"]],
    ids=["listen-without-a-port", "unknown-protocol", "octet-999", "port-99999", "unclosed-ipv6"],
)
def test_a_malformed_endpoint_is_a_usage_error(args, tmp_path):
    proc, _ = _cvxnav(*args, cwd=tmp_path, tmp=tmp_path)
    assert proc.returncode == 2 and proc.stderr.count("\n") == 1 and "Traceback" not in proc.stderr
    assert proc.stderr.startswith(f"cvxnav {args[0]}: error: argument ")


@pytest.mark.parametrize(
    ("args", "option"),
    [(["run", "--robot-id", "*"], "--robot-id"), (["run", "--robot-id", "robot1/**"], "--robot-id"),
     (["service", "sim", "--robot-id", "a b"], "--robot-id"), (["status", "--robot-id", ""], "--robot-id"),
     (["status", "--prefix", "cvxnav/*"], "--prefix"), (["service", "planner", "--prefix", "cvxnav//r"], "--prefix")],
    ids=["star", "slash-wildcard", "space", "empty", "prefix-star", "prefix-empty-chunk"],
)
def test_a_robot_id_is_a_name_not_a_key_pattern(args, option, capsys):
    """`*` in a robot id was a wildcard whose stages read and answered every robot's keys."""
    with pytest.raises(SystemExit) as exited:
        main(args)
    stderr = capsys.readouterr().err
    assert exited.value.code == 2 and stderr.count("\n") == 1, stderr
    assert stderr.startswith(f"cvxnav {args[0]}: error: argument {option}: must be ")


def test_a_router_that_cannot_listen_is_one_line(tmp_path):
    proc, _ = _cvxnav("router", "--listen", "tcp/8.8.8.8:7447", cwd=tmp_path, tmp=tmp_path)
    assert proc.returncode == 2
    assert _one_error_line(proc.stderr).startswith("the router cannot listen: Can not create a new TCP listener "
                                                   "bound to tcp/8.8.8.8:7447")


@pytest.mark.slow
@pytest.mark.parametrize("index", [0, 2, 4], ids=[VALID[k][0] for k in (0, 2, 4)])
def test_a_run_that_used_to_fail_reaches_its_goals(index, tmp_path):
    path = VALID[index][1](tmp_path)
    scenario = load_scenario(path)
    proc, _ = _cvxnav("run", "--quiet", str(path), "--out", "run.json", cwd=tmp_path, tmp=tmp_path)
    assert proc.returncode == 0, proc.stderr[-2000:]
    run = RunFile.read(tmp_path / "run.json")
    assert run.status == "reached" and run.goals_reached == len(scenario.goals)
    if not scenario.obstacles:
        assert run.min_clearance is None and '"min_clearance": null' in (tmp_path / "run.json").read_text()
    if np.allclose(scenario.goals_array, [[0.0, 0.0]]):
        assert len(run.trajectory) == 1  # reached at once, before the first step


@pytest.mark.slow
def test_a_run_far_from_the_origin_drives_as_at_home(tmp_path):
    """The paper's run moved by 10⁷ m (a map in UTM metres): the same trajectory, moved, within 1 mm.
    Lockstep runs repeat exactly, and every core works in the scenario's local frame, so only the
    rounding of the world coordinates on the keys (2 nm at 10⁷ m) separates the two."""
    offset = 1e7
    doc = copy.deepcopy(PAPER)
    move = lambda p: [p[0] + offset, p[1] + offset]  # noqa: E731
    doc["bounds"] = {"min": move(doc["bounds"]["min"]), "max": move(doc["bounds"]["max"])}
    doc["start"].update(x=doc["start"]["x"] + offset, y=doc["start"]["y"] + offset)
    doc["goals"] = [move(g) for g in doc["goals"]]
    for obstacle in doc["obstacles"]:
        obstacle["points"] = [move(p) for p in obstacle["points"]]
    (tmp_path / "far.json").write_text(json.dumps(doc))
    runs = {}
    for name, target in (("home", []), ("far", ["far.json"])):
        proc, _ = _cvxnav("run", "--quiet", *target, "--out", f"{name}-run.json", cwd=tmp_path, tmp=tmp_path)
        assert proc.returncode == 0, proc.stderr[-2000:]
        runs[name] = RunFile.read(tmp_path / f"{name}-run.json")
    home, far = runs["home"], runs["far"]
    assert far.status == "reached" and far.goals_reached == 2 and far.replans == home.replans
    assert far.min_clearance == pytest.approx(home.min_clearance, abs=1e-3)
    moved = np.array(far.trajectory) - [0.0, offset, offset, 0.0]
    np.testing.assert_allclose(moved, home.trajectory, rtol=0, atol=1e-3)
