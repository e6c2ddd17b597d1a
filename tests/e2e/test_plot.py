"""`cvxnav plot`: a real plan and a run file drawn to PNG at the asked size, and not blank."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from cvxnav.cli import main
from schemas.files import LatencyStats, RunFile
from schemas.scenario import bundled_scenario


def cvxnav(*args: str, cwd: Path) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "cvxnav", *args], cwd=cwd, capture_output=True, text=True,
                          timeout=120)


def _assert_drawn(png: Path, *, width_px: int, height_px: int) -> None:
    image = Image.open(png)
    assert image.size == (width_px, height_px)
    gray = np.asarray(image.convert("L"), dtype=float)
    assert gray.std() > 10.0  # not a blank canvas
    colours = np.asarray(image.convert("RGB")).reshape(-1, 3)
    assert len(np.unique(colours, axis=0)) > 50  # paths, ellipses, obstacles in several colours


def test_plot_of_a_plan(tmp_path):
    assert cvxnav("plan", "--out", "plan.json", cwd=tmp_path).returncode == 0
    proc = cvxnav("plot", "plan.json", "--png", "plan.png", cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    _assert_drawn(tmp_path / "plan.png", width_px=1200, height_px=900)


def test_plot_of_a_run_at_a_chosen_size(tmp_path):
    paper = bundled_scenario()
    t = np.linspace(0.0, 10.0, 201)
    rows = [(float(ti), float(ti), float(ti), 0.785) for ti in t]
    RunFile(scenario=paper.name, status="reached", goals_reached=2, trajectory=rows, replans=0,
            latency_ms=LatencyStats(p50=1.0, p99=2.0, max=3.0), min_clearance=0.6).write(tmp_path / "run.json")
    proc = cvxnav("plot", "run.json", "--png", "run.png", "--width-px", "640", "--height-px", "480", cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    _assert_drawn(tmp_path / "run.png", width_px=640, height_px=480)


@pytest.mark.parametrize("content, message", [
    ('{"format": "cvxnav.other/1"}', "format: expected cvxnav.plan/2 (or /1) or cvxnav.run/2 (or /1)"),
    ("{", "invalid JSON"),
])
def test_plot_rejects_bad_files_in_one_line(tmp_path, capsys, content, message):
    (tmp_path / "bad.json").write_text(content)
    assert main(["plot", str(tmp_path / "bad.json")]) == 2
    err = capsys.readouterr().err
    assert message in err and len(err.strip().splitlines()) == 1


def test_plot_needs_the_scenario_of_a_foreign_file(tmp_path, capsys):
    paper = bundled_scenario()
    RunFile(scenario="elsewhere", status="timeout", goals_reached=0, trajectory=[(0.0, 0.0, 0.0, 0.0)], replans=0,
            latency_ms=LatencyStats(p50=0.0, p99=0.0, max=0.0), min_clearance=1.0).write(tmp_path / "run.json")
    assert main(["plot", str(tmp_path / "run.json")]) == 2
    assert "--scenario" in capsys.readouterr().err
    assert paper.name != "elsewhere"
