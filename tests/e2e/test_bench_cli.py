"""`cvxnav bench --quick` as CI runs it: a real process, its JSON valid against the schema it writes."""

from __future__ import annotations

import json
import math
import statistics
import subprocess
import sys
from pathlib import Path

import jsonschema
import pytest

from cvxnav.bench.report import BenchReport


@pytest.mark.slow
def test_quick_bench_writes_json_that_validates_against_its_schema(tmp_path: Path, scenarios_dir: Path):
    out, schema, markdown = tmp_path / "out.json", tmp_path / "schema.json", tmp_path / "out.md"
    done = subprocess.run(
        [sys.executable, "-m", "cvxnav", "bench", "--quick", "--quiet", "--repeats", "1",
         str(scenarios_dir / "field-8.json"),
         "--json", str(out), "--schema", str(schema), "--markdown", str(markdown)],
        capture_output=True, text=True, timeout=120,
    )
    assert done.returncode == 0, done.stderr[-2000:]
    document = json.loads(out.read_text())
    jsonschema.validate(document, json.loads(schema.read_text()))
    report = BenchReport.model_validate(document)

    (scenario,) = report.scenarios
    rows = {p.planner: p for p in scenario.planners}
    assert rows["cvxnav"].success and rows["cvxnav"].length_ratio is not None
    assert rows["optimum (tangent graph)"].length_ratio == 1.0
    for row in scenario.planners:  # every timed call is in the report, and the median is theirs
        assert len(row.times_ms) == row.repeats
        assert row.time_median_ms == (pytest.approx(statistics.median(row.times_ms)) if row.times_ms else None)
    for fit in report.fit:  # quick: 5 calls over 5 seeded point sets, each area within 1e-6 of cvxpy's
        assert fit.error or fit.time_median_ms == pytest.approx(statistics.median(fit.times_ms))
        assert fit.error or (fit.point_sets == len(fit.times_ms) == 5 and fit.area_rel_diff <= 1e-6)
    peers = {"BIT* (OMPL)", "Informed RRT* (OMPL)", "IRIS + GCS (Drake)"}
    for name in peers:
        # Either measured, or skipped with a note that says how to get it.
        assert name in rows or any("pip install" in note for note in report.notes)
    # The quick scaling run: two fields, the second's local exponent is the slope from the first.
    first, second = report.scaling.points
    assert first.success and second.success and first.local_exponent is None
    assert second.local_exponent == pytest.approx(
        math.log(second.time_median_ms / first.time_median_ms) / math.log(second.obstacles / first.obstacles))
    assert "cvxnav" in done.stdout and "length ÷ grown-ellipse optimum" in done.stdout
    assert "| scenario | planner |" in markdown.read_text()


def test_a_bad_scenario_is_one_line_and_exit_2(tmp_path: Path):
    bad = tmp_path / "bad.json"
    bad.write_text('{"format": "cvxnav.scenario/1"}')
    done = subprocess.run([sys.executable, "-m", "cvxnav", "bench", "--quick", str(bad)],
                          capture_output=True, text=True, timeout=60)
    assert done.returncode == 2
    assert len(done.stderr.strip().splitlines()) == 1 and "bad.json" in done.stderr


@pytest.mark.slow
def test_closed_loop_bench_drives_a_scenario_to_its_goal_and_reports_it(tmp_path: Path, scenarios_dir: Path):
    """`cvxnav bench --closed-loop`: the stage cores close the loop; the row is what the run would show."""
    from cvxnav.bench.closed_loop import STAGE_ORDER, ClosedLoopReport
    from schemas.scenario import load_scenario

    out, markdown = tmp_path / "loop.json", tmp_path / "loop.md"
    done = subprocess.run(
        [sys.executable, "-m", "cvxnav", "bench", "--closed-loop", "--quiet", str(scenarios_dir / "field-8.json"),
         "--json", str(out), "--markdown", str(markdown)],
        capture_output=True, text=True, timeout=300,
    )
    assert done.returncode == 0, done.stderr[-2000:]
    (row,) = ClosedLoopReport.model_validate_json(out.read_text()).rows
    scenario = load_scenario(scenarios_dir / "field-8.json")
    assert row.status == "reached" and row.goals_reached == row.goals == len(scenario.goals)
    assert row.min_clearance_m >= 0.5 * scenario.robot.safety_distance
    assert row.reference_m is not None and 0.9 <= row.length_m / row.reference_m <= 1.3  # goal tolerance: may end short
    assert set(row.latency) == {*STAGE_ORDER, "total"}
    assert row.latency["total"].p50_ms <= row.latency["total"].p99_ms <= row.latency["total"].max_ms
    assert "| field-8 | reached | 1/1 |" in markdown.read_text()
