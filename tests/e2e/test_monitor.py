"""The monitor stage mirrors a real pipeline run into rerun: a recording (`cvxnav run --record`, with a
`--viewer` that cannot open a window), and a rerun server elsewhere (`cvxnav run --viewer-url`) while
`cvxnav status` watches the same run through a router the run joined with `--connect`. Both are read
back with rerun's own reader.
"""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import rerun_cli

from cvxnav.supervisor import free_ports, stop_processes
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
    """One lockstep run of the paper scenario with the monitor recording (the process, its directory).

    It also asks for a viewer, with no display: the viewer exits at once, and the recording must still
    be whole (the monitor once hung on flushing to the missing viewer and was killed mid-file).
    """
    cwd = tmp_path_factory.mktemp("recorded")
    env = {name: value for name, value in os.environ.items() if name not in ("DISPLAY", "WAYLAND_DISPLAY")}
    proc = subprocess.run([sys.executable, "-m", "cvxnav", "run", "--quiet", "--record", "run.rrd", "--viewer",
                           "--out", "run.json"], cwd=cwd, capture_output=True, text=True, timeout=180, env=env)
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


def _wait_listening(port: int, process: subprocess.Popen, *, timeout_s: float = 30.0) -> None:
    deadline = time.monotonic() + timeout_s
    while True:
        try:
            socket.create_connection(("127.0.0.1", port), timeout=0.5).close()
            return
        except OSError:
            assert process.poll() is None and time.monotonic() < deadline, f"nothing listens on {port}"
            time.sleep(0.2)


def _status(router_ep: str) -> dict:
    proc = subprocess.run([sys.executable, "-m", "cvxnav", "status", "--connect", router_ep, "--mode", "client",
                           "--window-s", "1.5", "--json"], capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0, proc.stderr
    return {stage["name"]: stage for stage in json.loads(proc.stdout)["stages"]}


@pytest.mark.filterwarnings("ignore:RRD file has no footer")  # `rerun --save` writes a stream without one
def test_run_streams_to_a_rerun_server_and_status_watches_through_the_router(tmp_path):
    """A headless rerun server (`rerun --save`, the binary of rerun-sdk) receives the run over gRPC."""
    # The server binary itself (the `rerun` script beside the interpreter runs it as a child and does not
    # pass signals on), with SIGINT's default restored: a test run started in the background of a shell
    # inherits SIGINT ignored, and the server would never close its file.
    rerun_bin = Path(rerun_cli.__file__).with_name("rerun")
    router_port, rerun_port = free_ports(2)
    router_ep = f"tcp/127.0.0.1:{router_port}"
    env = {**os.environ, "CI": "1"}  # no analytics from the rerun server either
    with open(tmp_path / "rerun.log", "wb") as log:
        server = subprocess.Popen([str(rerun_bin), "--save", str(tmp_path / "live.rrd"), "--bind", "127.0.0.1",
                                   "--port", str(rerun_port)], stdout=log, stderr=subprocess.STDOUT, env=env,
                                  preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    with open(tmp_path / "router.log", "wb") as log:
        router = subprocess.Popen([sys.executable, "-m", "cvxnav", "router", "--listen", router_ep], stdout=log,
                                  stderr=subprocess.STDOUT)
    processes = [server, router]
    try:
        _wait_listening(rerun_port, server)
        _wait_listening(router_port, router)
        # On the wall clock (--realtime) the run lasts its tour's half minute of sim, so that each poll of
        # `cvxnav status` (a process start and a 1.5 s window) can find it going; in lockstep, on a machine
        # busy with other tests, the run once ended between two polls that each missed it.
        with open(tmp_path / "run.log", "wb") as log:
            run = subprocess.Popen([sys.executable, "-m", "cvxnav", "run", "--quiet", "--realtime", "--out", "run.json",
                                    "--connect", router_ep,
                                    "--viewer-url", f"rerun+http://127.0.0.1:{rerun_port}/proxy"],
                                   cwd=tmp_path, stdout=log, stderr=subprocess.STDOUT)
        processes.append(run)
        report: dict = {}
        while run.poll() is None and not all(report.get(name, {}).get("alive") for name in ("sim", "monitor")):
            report = _status(router_ep)  # from outside the run's mesh: only through the router
        assert run.wait(timeout=180) == 0, (tmp_path / "run.log").read_text()[-2000:]
        assert report["sim"]["alive"] and report["monitor"]["alive"], report
        for name in ("sensing", "ellipsoids", "planner", "smoother"):
            assert report[name]["alive"], report
        assert report["sim"]["rates_hz"]["scan"] > 0.0
        server.send_signal(signal.SIGINT)  # the server has written everything it received; let it close the file
        server.wait(timeout=30)
    finally:
        stop_processes(processes, grace_s=10.0)
    run_file = RunFile.read(tmp_path / "run.json")
    assert run_file.status == "reached"
    chunks = _chunks_by_entity(tmp_path / "live.rrd")
    for entity in (*EXPECTED_STATIC, *EXPECTED_OVER_TIME):
        assert entity in chunks, f"{entity} missing; have {sorted(chunks)}"
    assert sum(chunk.num_rows for chunk in chunks["/sim/robot"]) >= 10
    times_s = _sim_times_s(chunks["/smoother/path"])
    assert times_s[-1] >= 0.8 * run_file.trajectory[-1][0]  # streamed to the end of the run
