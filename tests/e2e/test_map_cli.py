"""`cvxnav plan`, `plot` and `bench` on a map scenario as a user runs them: real processes, real files,
and a bad map reported in one line naming the field, exit code 2."""

from __future__ import annotations

import importlib.util
import json
import os
import pty
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from schemas.files import PlanFile


def cvxnav(*args: str, cwd: Path, timeout_s: float = 300) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "cvxnav", *args], cwd=cwd, capture_output=True, text=True,
                          timeout=timeout_s)


@pytest.fixture()
def depot(shared_dir: Path, tmp_path: Path) -> Path:
    """depot-1 with its map copied beside it, to be broken."""
    shutil.copy(shared_dir / "maps" / "depot.yaml", tmp_path / "depot.yaml")
    shutil.copy(shared_dir / "maps" / "depot.pgm", tmp_path / "depot.pgm")
    doc = json.loads((shared_dir / "map-scenarios" / "depot-1.json").read_text())
    doc["obstacles"][0]["map"] = "depot.yaml"
    (tmp_path / "depot-1.json").write_text(json.dumps(doc))
    return tmp_path / "depot-1.json"


def test_plan_on_a_map_writes_a_verified_plan_2_file_timed_from_the_files(depot: Path, tmp_path: Path):
    done = cvxnav("plan", str(depot), "--out", "plan.json", cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    plan = PlanFile.read(tmp_path / "plan.json")
    assert plan.format == "cvxnav.plan/2" and plan.status == "ok"
    assert plan.timings_ms.load > 0.0 and plan.timings_ms.corridor > 0.0 and plan.timings_ms.fit > 0.0
    assert plan.timings_ms.total >= sum(v for k, v in plan.timings_ms.model_dump().items() if k != "total")
    done = cvxnav("plot", "plan.json", "--scenario", str(depot), "--png", "plan.png", cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    assert (tmp_path / "plan.png").stat().st_size > 10_000


def _on_a_terminal(args: list[str], *, cwd: Path, timeout_s: float = 300) -> tuple[int, str]:
    """Run with stdout and stderr on a pseudo-terminal, as in a user's shell: (exit code, all it wrote)."""
    controller, terminal = pty.openpty()
    proc = subprocess.Popen(args, cwd=cwd, stdin=subprocess.DEVNULL, stdout=terminal, stderr=terminal,
                            env={**os.environ, "TERM": "xterm-256color"})
    os.close(terminal)
    out = b""
    while True:
        try:
            data = os.read(controller, 65536)
        except OSError:  # EIO: the process closed its end
            break
        if not data:
            break
        out += data
    os.close(controller)
    return proc.wait(timeout=timeout_s), out.decode(errors="replace")


def test_plan_on_a_terminal_shows_each_plan_while_it_works_and_a_pipe_gets_the_result_alone(depot: Path,
                                                                                            tmp_path: Path):
    """A building's plan may take several plans and a `no_path` seconds: on a terminal a spinner says which
    plan runs among how many ellipses, and is cleared before the result line; piped, stderr stays empty."""
    code, out = _on_a_terminal([sys.executable, "-m", "cvxnav", "plan", str(depot), "--out", "plan.json"],
                               cwd=tmp_path)
    assert code == 0, out
    frames = [line.strip() for line in re.split(r"[\r\n]+", re.sub(r"\x1b\[[0-9;?]*[A-Za-z]", "", out))]
    assert any(re.fullmatch(r"\S cvxnav plan  plan 1 among \d+ ellipses \d+:\d\d:\d\d", f) for f in frames), frames
    assert [f for f in frames if f][-1].startswith("depot-1: path ")
    done = cvxnav("plan", str(depot), "--out", "plan.json", cwd=tmp_path)
    assert done.returncode == 0 and done.stderr == "" and done.stdout.count("\n") == 1


def _break(depot: Path, how: str) -> str:
    folder = depot.parent
    if how == "missing image":
        (folder / "depot.pgm").unlink()
        return "obstacles[0].map: depot.yaml: image: depot.pgm: no such file"
    if how == "wrong size":
        data = (folder / "depot.pgm").read_bytes()
        (folder / "depot.pgm").write_bytes(data[:-1000])
        return "obstacles[0].map: depot.yaml: image: depot.pgm: truncated"
    if how == "unreadable PGM":
        (folder / "depot.pgm").write_bytes(b"P5\n604 307\n255\n")  # a header and no pixels at all
        return "obstacles[0].map: depot.yaml: image: depot.pgm:"
    if how == "thresholds out of order":
        text = (folder / "depot.yaml").read_text().replace("free_thresh: 0.25", "free_thresh: 0.9")
        (folder / "depot.yaml").write_text(text)
        return "obstacles[0].map: depot.yaml: free_thresh: must be below occupied_thresh"
    doc = json.loads(depot.read_text())
    if how == "start in a blocked cell":
        doc["start"].update(x=0.12, y=0.12)
        expected = "start: [0.12, 0.12] is in an"
    else:  # goal in an unknown cell: inside a shelf
        doc["goals"] = [[18.3, 3.0]]
        expected = "goals[0]: [18.3, 3.0] is in an unknown cell"
    depot.write_text(json.dumps(doc))
    return expected


@pytest.mark.parametrize("how", ["missing image", "wrong size", "unreadable PGM", "thresholds out of order",
                                 "start in a blocked cell", "goal in an unknown cell"])
def test_a_bad_map_is_one_line_naming_the_field_and_exit_2(depot: Path, tmp_path: Path, how: str):
    expected = _break(depot, how)
    done = cvxnav("plan", str(depot), cwd=tmp_path)
    assert done.returncode == 2, done.stderr
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in done.stderr
    assert lines[0].startswith(f"cvxnav: error: depot-1.json: {expected}"), lines[0]


@pytest.mark.slow
def test_bench_on_a_map_file_puts_cvxnav_beside_the_grid_planner(shared_dir: Path, tmp_path: Path):
    scenario = shared_dir / "map-scenarios" / "depot-1.json"
    done = cvxnav("bench", str(scenario), "--quick", "--quiet", "--json", "bench.json", "--markdown", "bench.md",
                  "--budget-s", "0.5", cwd=tmp_path, timeout_s=600)
    assert done.returncode == 0, done.stderr[-2000:]
    report = json.loads((tmp_path / "bench.json").read_text())
    assert report["format"] == "cvxnav.bench/6" and report["scenarios"] == []
    rows = {row["planner"]: row for row in report["maps"]["scenarios"][0]["planners"]}
    assert rows["cvxnav"]["success"] and rows["grid (NavFn-like)"]["success"]
    assert rows["cvxnav"]["length_ratio"] <= 1.02
    assert rows["cvxnav"]["stages_ms"]["load"] > 0.0 and rows["grid (NavFn-like)"]["stages_ms"]["inflate"] > 0.0
    assert "depot-1" in report["maps"]["targets"]["time_ratio_vs_grid"]
    kept = {row["planner"]: row for row in report["maps"]["scenarios"][0]["planners_kept_memory"]}
    assert set(kept) == {"cvxnav", "grid (NavFn-like)"} and all(row["success"] for row in kept.values())
    assert "depot-1" in report["maps"]["targets"]["time_ratio_vs_grid_kept_memory"]
    if importlib.util.find_spec("ompl") is not None:  # the bench extra: BIT* for a point and for a Dubins car
        for name in ("BIT* (OMPL, point)", "BIT* (OMPL, Dubins)"):
            assert rows[name]["repeats"] == 1 and (rows[name]["success"] or rows[name]["reason"])
            assert not rows[name]["collision"]
    markdown = (tmp_path / "bench.md").read_text()
    assert "time ÷ grid planner, depot-1" in markdown and "time ÷ grid planner with freed memory kept, depot-1" in markdown
