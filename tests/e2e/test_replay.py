"""Record a real run's messages (`cvxnav run --record-messages`), then `cvxnav replay` each pipeline stage:
the default cores reproduce their recorded outputs, a swapped smoother is shown to differ, bad input
exits 2."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from cvxnav.record import read_recording
from schemas.messages import StageStatus, decode
from schemas.scenario import bundled_scenario
from schemas.wiring import STAGES, key, status_key

pytestmark = pytest.mark.slow

SCENARIO = bundled_scenario()


def cvxnav(*args: str, cwd: Path, timeout_s: float = 180.0) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "cvxnav", *args], cwd=cwd, capture_output=True, text=True,
                          timeout=timeout_s)


@pytest.fixture(scope="module")
def recorded(tmp_path_factory) -> Path:
    cwd = tmp_path_factory.mktemp("replay")
    proc = cvxnav("run", "--quiet", "--out", "run.json", "--record-messages", "run.mcap", cwd=cwd)
    assert proc.returncode == 0, proc.stderr[-2000:]
    return cwd / "run.mcap"


def test_recording_holds_every_key_with_its_encoding_and_the_scenario(recorded):
    recording = read_recording(recorded)
    assert recording.scenario == SCENARIO
    keys = {m.key for m in recording.messages}
    for topic in ("scan", "state", "clusters", "ellipsoids", "raw_path", "smooth_path", "world"):
        assert key(recording.prefix, topic) in keys
    assert {status_key(recording.prefix, stage) for stage in STAGES if stage != "sim"} <= keys
    times = [m.log_time_ns for m in recording.messages]
    assert times == sorted(times)
    status = next(m for m in recording.messages if m.key == status_key(recording.prefix, "planner"))
    assert status.encoding == StageStatus.encoding()
    assert decode(StageStatus, status.payload, encoding=status.encoding).stage == "planner"


@pytest.mark.parametrize("stage", ["sensing", "ellipsoids", "planner", "smoother"])
def test_each_stage_reproduces_its_recorded_outputs(recorded, stage):
    proc = cvxnav("replay", str(recorded), "--stage", stage, cwd=recorded.parent)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert "reproduced" in proc.stdout
    compared = int(proc.stdout.split(" outputs compared")[0].rsplit(", ", 1)[1])
    assert compared >= 100  # one answer per scan of a ~22 s run at 10 Hz


def test_a_swapped_smoother_is_reported_to_differ(recorded):
    proc = cvxnav("replay", str(recorded), "--stage", "smoother", "--entry", "services.smoother.coarse:factory",
                  cwd=recorded.parent)
    assert proc.returncode == 1, proc.stdout + proc.stderr
    assert "differs: smooth_path for scan " in proc.stdout


@pytest.mark.parametrize(
    "args",
    [["replay", "missing.mcap", "--stage", "planner"], ["replay", "run.json", "--stage", "planner"],
     ["replay", "run.mcap", "--stage", "planner", "--entry", "no.such:factory"],
     ["replay", "run.mcap", "--stage", "nope"]],
    ids=["missing-file", "not-mcap", "bad-entry", "unknown-stage"],
)
def test_bad_input_exits_2_with_one_line(recorded, args):
    proc = cvxnav(*args, cwd=recorded.parent)
    assert proc.returncode == 2
    assert proc.stderr.count("\n") == 1 and "Traceback" not in proc.stderr
