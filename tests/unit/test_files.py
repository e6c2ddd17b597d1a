"""Plan and run files: write → read is the identity, and bad files are one named line."""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pytest

from schemas.files import LatencyStats, OutputFileError, PlanFile, PlanTimings, RunFile
from services.convert import ellipse_from_model, ellipse_to_model
from services.geometry import Ellipse


def _plan() -> PlanFile:
    ellipse = Ellipse.from_axes(center=(3.0, 3.1), semi_axes=(1.2, 0.7), angle_rad=0.4).grown(0.65)
    return PlanFile(
        scenario="paper-two-goals",
        status="ok",
        path=[(0.0, 0.0), (0.03, 0.04), (0.1, 0.1)],
        raw_path=[(0.0, 0.0), (0.1, 0.1)],
        ellipsoids=[ellipse_to_model(ellipse)],
        timings_ms=PlanTimings(load=4.0, corridor=0.0, cluster=0.5, fit=1.25, group=0.1, optimize=12.0, smooth=3.0,
                               total=20.85),
    )


def _run() -> RunFile:
    return RunFile(
        scenario="paper-two-goals",
        status="reached",
        goals_reached=2,
        trajectory=[(0.0, 0.0, 0.0, 0.785), (0.05, 0.035, 0.035, 0.79)],
        replans=7,
        latency_ms=LatencyStats(p50=12.5, p99=40.0, max=55.1),
        min_clearance=0.71,
    )


@pytest.mark.parametrize("make", [_plan, _run], ids=["plan", "run"])
def test_write_then_read_is_equal(tmp_path: Path, make) -> None:
    original = make()
    path = tmp_path / "out.json"
    original.write(path)
    loaded = type(original).read(path)
    assert loaded == original
    data = json.loads(path.read_text())
    assert data["format"] == {"PlanFile": "cvxnav.plan/2", "RunFile": "cvxnav.run/2"}[type(original).__name__]
    assert path.read_text().startswith('{\n "format"')  # indent=1


def test_a_plan_1_file_still_reads_and_a_plan_2_file_needs_its_load_time(tmp_path: Path) -> None:
    data = json.loads(_plan().model_dump_json())
    for key in ("load", "corridor"):
        del data["timings_ms"][key]
    del data["reason"]
    (tmp_path / "v1.json").write_text(json.dumps({**data, "format": "cvxnav.plan/1"}))
    assert PlanFile.read(tmp_path / "v1.json").timings_ms.load == 0.0
    (tmp_path / "v2.json").write_text(json.dumps(data))
    with pytest.raises(OutputFileError, match=r"^v2.json: timings_ms.load: missing \(required in cvxnav.plan/2\)$"):
        PlanFile.read(tmp_path / "v2.json")


def test_ellipse_model_round_trips_the_geometry() -> None:
    ellipse = Ellipse.from_axes(center=(-2.0, 5.0), semi_axes=(3.0, 0.5), angle_rad=1.1)
    back = ellipse_from_model(ellipse_to_model(ellipse))
    np.testing.assert_allclose(back.A, ellipse.A)
    np.testing.assert_allclose(back.b, ellipse.b)
    np.testing.assert_allclose(back.center, [-2.0, 5.0])


def _bad_file(tmp_path: Path, model: type, edit) -> str:
    original = _plan() if model is PlanFile else _run()
    data = json.loads(original.model_dump_json())
    text = edit(data)
    path = tmp_path / "bad.json"
    path.write_text(text if isinstance(text, str) else json.dumps(data))
    with pytest.raises(OutputFileError) as info:
        model.read(path)
    message = str(info.value)
    assert "\n" not in message
    return message


def test_plan_rejects_nan(tmp_path: Path) -> None:
    def edit(data: dict) -> str:
        data["path"][1] = [0.03, "@"]
        return json.dumps(data).replace('"@"', "NaN")

    assert _bad_file(tmp_path, PlanFile, edit) == "bad.json: path[1][1]: Input should be a finite number"


def test_run_rejects_infinite_clearance(tmp_path: Path) -> None:
    def edit(data: dict) -> str:
        data["min_clearance"] = "@"
        return json.dumps(data).replace('"@"', "Infinity")

    assert _bad_file(tmp_path, RunFile, edit) == "bad.json: min_clearance: Input should be a finite number"


def test_a_run_2_file_says_null_for_no_obstacle_or_interrupted_and_a_run_1_file_still_reads(tmp_path: Path) -> None:
    empty = _run().model_copy(update={"min_clearance": None})
    empty.write(tmp_path / "empty.json")
    assert json.loads((tmp_path / "empty.json").read_text())["min_clearance"] is None
    assert RunFile.read(tmp_path / "empty.json") == empty
    interrupted = _run().model_copy(update=dict(status="interrupted"))
    interrupted.write(tmp_path / "interrupted.json")
    assert RunFile.read(tmp_path / "interrupted.json") == interrupted
    data = json.loads(_run().model_dump_json())
    (tmp_path / "v1.json").write_text(json.dumps({**data, "format": "cvxnav.run/1"}))
    old = RunFile.read(tmp_path / "v1.json")
    assert (old.min_clearance, old.status) == (0.71, "reached")
    assert (_bad_file(tmp_path, RunFile, lambda d: d.update(format="cvxnav.run/1", min_clearance=None))
            == "bad.json: min_clearance: null is new in cvxnav.run/2")
    assert (_bad_file(tmp_path, RunFile, lambda d: d.update(format="cvxnav.run/1", status="interrupted"))
            == "bad.json: status: interrupted is new in cvxnav.run/2")


def test_a_fifo_or_a_device_is_refused_unread(tmp_path: Path) -> None:
    fifo = tmp_path / "run.json"
    os.mkfifo(fifo)  # reading it would block until a writer came
    with pytest.raises(OutputFileError, match=r"not a regular file"):
        RunFile.read(fifo)
    with pytest.raises(OutputFileError, match=r"^/dev/zero: not a regular file"):
        RunFile.read("/dev/zero")


def test_unknown_fields_are_rejected(tmp_path: Path) -> None:
    assert (
        _bad_file(tmp_path, PlanFile, lambda d: d["timings_ms"].update(io=1.0))
        == "bad.json: unknown field 'io' at timings_ms"
    )
    assert _bad_file(tmp_path, RunFile, lambda d: d.update(seed=3)) == "bad.json: unknown field 'seed' at top level"


def test_wrong_format_status_and_shapes_are_named(tmp_path: Path) -> None:
    assert _bad_file(tmp_path, PlanFile, lambda d: d.update(format="cvxnav.run/1")).startswith("bad.json: format:")
    assert _bad_file(tmp_path, RunFile, lambda d: d.update(status="ok")).startswith("bad.json: status:")
    short_row = _bad_file(tmp_path, RunFile, lambda d: d["trajectory"][0].pop())
    assert short_row == "bad.json: trajectory[0][3]: Field required"
    assert _bad_file(tmp_path, RunFile, lambda d: d.update(replans=-1)).startswith("bad.json: replans:")
    assert _bad_file(tmp_path, RunFile, lambda d: d["latency_ms"].update(p99=-1)).startswith(
        "bad.json: latency_ms.p99:"
    )


def test_ellipse_must_be_positive_definite(tmp_path: Path) -> None:
    message = _bad_file(tmp_path, PlanFile, lambda d: d["ellipsoids"][0].update(A=[[1, 0], [0, -1]]))
    assert message == "bad.json: ellipsoids[0].A: must be positive definite"
    message = _bad_file(tmp_path, PlanFile, lambda d: d["ellipsoids"][0].update(A=[[1, 0.5], [0, 1]]))
    assert message.startswith("bad.json: ellipsoids[0].A: must be symmetric")


def test_invalid_json_and_missing_file_are_one_line(tmp_path: Path) -> None:
    assert _bad_file(tmp_path, PlanFile, lambda d: "{not json").startswith("bad.json: invalid JSON:")
    with pytest.raises(OutputFileError, match=r"missing\.json: no such file$"):
        RunFile.read(tmp_path / "missing.json")


def test_models_are_frozen() -> None:
    with pytest.raises(Exception, match="frozen"):
        _run().replans = 3  # type: ignore[misc]


def test_a_run_says_how_often_and_how_far_the_car_backed_out() -> None:
    """Heading east throughout: 1 m forward, 0.5 m back, 0.4 m forward, 0.3 m back, 0.2 m forward."""
    xs = np.concatenate([np.linspace(0.0, 1.0, 11), np.linspace(0.95, 0.5, 10), np.linspace(0.6, 0.9, 4),
                         np.linspace(0.8, 0.6, 3), np.linspace(0.7, 0.8, 2)])
    run = _run().model_copy(update={"trajectory": [(0.05 * k, float(x), 0.0, 0.0) for k, x in enumerate(xs)]})
    times, metres = run.backed_out()
    assert times == 2 and metres == pytest.approx(0.8)
    assert _run().backed_out() == (0, 0.0)
