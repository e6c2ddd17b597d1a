"""`cvxnav run --record`: the monitor stage mirrors a real pipeline run into an .rrd, read back with rerun."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from schemas.files import RunFile

pytestmark = pytest.mark.slow

EXPECTED_OVER_TIME = (
    "/sensing/scan", "/sensing/clusters", "/ellipsoids/grown", "/planner/raw_path", "/smoother/path",
    "/sim/robot", "/sim/trail", "/latency/scan_to_path_ms", "/status/planner/processing_ms",
    "/status/smoother/processing_ms", "/status/sim/speed_mps",
)
EXPECTED_STATIC = ("/world/obstacles", "/world/bounds", "/goals")


@pytest.fixture(scope="module")
def recorded_run(tmp_path_factory) -> tuple[subprocess.CompletedProcess, Path]:
    """One lockstep run of the paper scenario with the monitor recording (the process, its directory)."""
    cwd = tmp_path_factory.mktemp("recorded")
    proc = subprocess.run([sys.executable, "-m", "cvxnav", "run", "--quiet", "--record", "run.rrd", "--out", "run.json"],
                          cwd=cwd, capture_output=True, text=True, timeout=180)
    return proc, cwd


def _chunks_by_entity(path: Path) -> dict[str, list]:
    from rerun.chunk import RrdReader

    reader = RrdReader(path)
    (entry,) = reader.recordings()
    assert entry.application_id == "cvxnav"
    chunks: dict[str, list] = {}
    for chunk in reader.stream():
        chunks.setdefault(chunk.entity_path, []).append(chunk)
    return chunks


def _sim_times_s(chunks: list) -> np.ndarray:
    """Every row's sim_time in seconds (rerun stores durations in nanoseconds)."""
    times = []
    for chunk in chunks:
        batch = chunk.to_record_batch()
        column = batch.column(batch.schema.get_field_index("sim_time"))
        times.extend(value.value / 1e9 if hasattr(value, "value") else value.as_py().total_seconds()
                     for value in column)
    return np.asarray(sorted(times), dtype=float)


def test_recording_mirrors_the_pipeline_on_sim_time(recorded_run):
    proc, cwd = recorded_run
    assert proc.returncode == 0, proc.stderr[-2000:]
    run = RunFile.read(cwd / "run.json")
    t_end_s = run.trajectory[-1][0]
    chunks = _chunks_by_entity(cwd / "run.rrd")
    for entity in EXPECTED_STATIC:
        assert entity in chunks, f"{entity} missing; have {sorted(chunks)}"
        assert all(chunk.is_static for chunk in chunks[entity])
    for entity in EXPECTED_OVER_TIME:
        assert entity in chunks, f"{entity} missing; have {sorted(chunks)}"
        rows = sum(chunk.num_rows for chunk in chunks[entity])
        times_s = _sim_times_s(chunks[entity])
        assert rows >= 10, f"{entity}: only {rows} rows"
        # Rows spread over the run's sim time, not bunched at one instant.
        assert times_s[0] <= 1.0 and times_s[-1] >= 0.8 * t_end_s, (entity, times_s[0], times_s[-1], t_end_s)
    # The robot's rows follow the trajectory: one per sensor tick, as many as the run's scans.
    robot_rows = sum(chunk.num_rows for chunk in chunks["/sim/robot"])
    scans = sum(chunk.num_rows for chunk in chunks["/sensing/scan"])
    assert robot_rows >= scans
