"""Stopping cleanly: SIGTERM of `cvxnav run` is Ctrl-C, SIGKILL of it leaves no stage behind, a stage in a
long solve honours SIGTERM, and an `--out` nobody can write is refused before anything starts.

Real processes and signals: the run is joined over Zenoh (`--listen`, the `live_run` fixture) to see it
under way, its processes are read from /proc, and its temporary folder is made under a TMPDIR of the
test's own, so the test sees it made and removed.
"""

from __future__ import annotations

import random
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path

import pytest
import zenoh

from cvxnav.exits import EXIT_INTERRUPTED
from cvxnav.service import EXIT_WORKER_BUSY
from cvxnav.supervisor import free_ports
from schemas.files import RUN_FORMAT, RunFile
from schemas.messages import ClusterMsg, Clusters, Header, RobotState, decode
from schemas.scenario import bundled_scenario, load_scenario
from schemas.wiring import default_prefix, key
from services.shell.peers import wait_for_stages
from services.shell.zenoh_config import build_zenoh_config
import stage_processes
from stage_processes import alive, cpu_s

PREFIX = default_prefix()
WAIT_S = 60.0  # a guard against a hung test, not a speed requirement


def wait_for(condition: Callable[[], object], *, what: str) -> object:
    return stage_processes.wait_for(condition, what=what, timeout_s=WAIT_S)


def under_way(session: zenoh.Session, *, sim_s: float = 1.0) -> None:
    """Return once the sim has driven `sim_s` seconds of sim time."""
    reached = threading.Event()

    def on_state(sample: zenoh.Sample) -> None:
        if decode(RobotState, sample.payload.to_bytes()).header.stamp_s >= sim_s:
            reached.set()

    subscriber = session.declare_subscriber(key(PREFIX, "state"), on_state)
    assert reached.wait(WAIT_S), "the run never got under way"
    subscriber.undeclare()


@pytest.fixture
def own_tmpdir(tmp_path, monkeypatch) -> Path:
    """A TMPDIR for the run's temporary folder (inherited by `cvxnav run`)."""
    folder = tmp_path / "tmp"
    folder.mkdir()
    monkeypatch.setenv("TMPDIR", str(folder))
    return folder


@pytest.mark.slow
def test_sigterm_stops_the_run_like_ctrl_c_interrupted_and_nothing_left(live_run, tmp_path, own_tmpdir):
    with live_run("--out", "run.json", cwd=tmp_path) as run:
        under_way(run.session)
        pids = run.stage_pids()
        assert len(list(own_tmpdir.iterdir())) == 1  # the run's folder of logs, configs and checkpoints
        run.process.send_signal(signal.SIGTERM)
        code = run.wait(timeout_s=WAIT_S)
    assert code == EXIT_INTERRUPTED
    result = RunFile.read(tmp_path / "run.json")
    assert result.format == RUN_FORMAT and result.status == "interrupted"
    assert result.trajectory[-1][0] >= 1.0  # what was driven until the stop
    assert not [name for name, pid in pids.items() if alive(pid)]
    assert not list(own_tmpdir.iterdir())  # removed: nothing asked to keep it
    summary = (tmp_path / "run.log").read_text()
    assert f"{result.scenario}: interrupted, goals 0" in summary


@pytest.mark.slow
def test_sigkill_of_the_run_leaves_no_stage_running_and_the_sim_says_interrupted(live_run, tmp_path, own_tmpdir):
    with live_run("--out", "run.json", cwd=tmp_path) as run:
        under_way(run.session)
        pids = run.stage_pids()
        run.process.kill()  # nothing of the supervisor runs: the stages notice their parent is gone
        run.wait(timeout_s=WAIT_S)
        wait_for(lambda: not any(alive(pid) for pid in pids.values()), what="every stage to stop")
    result = RunFile.read(tmp_path / "run.json")  # the sim, stopped, still wrote its run file
    assert result.status == "interrupted"


@pytest.mark.slow
def test_a_stage_in_a_long_solve_honours_sigterm_without_finishing_it(tmp_path):
    """The ellipsoid stage fits 400 clusters (well over ten seconds of Clarabel solves here); SIGTERM
    once it is computing ends the process with the solve unfinished: no ellipses ever come out."""
    endpoint = f"tcp/127.0.0.1:{free_ports(1)[0]}"
    log = tmp_path / "ellipsoids.log"
    with open(log, "wb") as out:
        proc = subprocess.Popen([sys.executable, "-m", "cvxnav", "service", "ellipsoids", "--listen", endpoint],
                                stdout=out, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL)
    rng = random.Random(7)
    clusters = []
    for index in range(400):
        cx, cy = rng.uniform(-3.0, 18.0), rng.uniform(-3.0, 18.0)
        clusters.append(ClusterMsg(cluster_id=index, points=[(cx + rng.gauss(0.0, 0.2), cy + rng.gauss(0.0, 0.2))
                                                            for _ in range(50)]))
    message = Clusters(header=Header(stamp_s=0.0, seq=0), scan_seq=0, clusters=clusters).model_dump_json()
    try:
        with zenoh.open(build_zenoh_config(connect=[endpoint])) as session:
            assert not wait_for_stages(session, prefix=PREFIX, stages=("ellipsoids",), timeout_s=WAIT_S)
            answers = session.declare_subscriber(key(PREFIX, "ellipsoids"))
            publisher = session.declare_publisher(key(PREFIX, "clusters"))
            idle_s = cpu_s(proc.pid)
            publisher.put(message)
            wait_for(lambda: cpu_s(proc.pid) > idle_s + 1.0 or publisher.put(message), what="the solve to start")
            signalled = time.monotonic()
            proc.send_signal(signal.SIGTERM)
            code = proc.wait(timeout=WAIT_S)
            print(f"ellipsoids in a solve: exited {time.monotonic() - signalled:.2f} s after SIGTERM")
            assert answers.try_recv() is None  # it left the solve unfinished
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert code == EXIT_WORKER_BUSY
    assert "its worker was still busy" in log.read_text()


@pytest.mark.parametrize("dismissal", ["end of input", "SIGTERM"])
def test_a_standby_stage_stays_off_the_network_until_called_and_leaves_when_dismissed(tmp_path, dismissal):
    """`cvxnav service NAME --standby` (a warm spare) builds its core but opens no session: it listens
    nowhere, and no token of it is seen; end of its input or SIGTERM ends it with exit 0."""
    port = free_ports(1)[0]
    proc = subprocess.Popen([sys.executable, "-m", "cvxnav", "service", "smoother", "--standby",
                             "--listen", f"tcp/127.0.0.1:{port}"], stdin=subprocess.PIPE,
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    try:
        def settled() -> bool:  # its imports done and its core built: it waits, spending nothing
            before = cpu_s(proc.pid)
            time.sleep(0.5)
            return before > 0.3 and cpu_s(proc.pid) == before

        wait_for(settled, what="the spare to stand by")
        with zenoh.open(build_zenoh_config(connect=[f"tcp/127.0.0.1:{port}"])) as session:
            assert wait_for_stages(session, prefix=PREFIX, stages=("smoother",), timeout_s=1.0) == {"smoother"}
        assert proc.poll() is None  # waiting for its cue
        if dismissal == "SIGTERM":
            proc.send_signal(signal.SIGTERM)
        else:
            proc.stdin.close()
        assert proc.wait(timeout=WAIT_S) == 0, proc.stderr.read().decode()[-2000:]
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


def test_an_out_file_in_a_missing_folder_is_refused_before_anything_starts(tmp_path, own_tmpdir):
    out = tmp_path / "nowhere" / "run.json"
    proc = subprocess.run([sys.executable, "-m", "cvxnav", "run", "--quiet", "--out", str(out)], cwd=tmp_path,
                          capture_output=True, text=True, timeout=WAIT_S)
    assert proc.returncode == 2
    assert proc.stderr.splitlines() == [f"cvxnav: error: --out {out}: folder {out.parent} does not exist"]
    assert not list(own_tmpdir.iterdir())  # no run folder: no process was started


def test_an_out_file_that_is_the_scenario_is_refused_before_anything_starts(tmp_path, own_tmpdir):
    scenario = tmp_path / "field.json"
    scenario.write_text(bundled_scenario().model_dump_json())
    proc = subprocess.run([sys.executable, "-m", "cvxnav", "run", "--quiet", "field.json", "--out", "./field.json"],
                          cwd=tmp_path, capture_output=True, text=True, timeout=WAIT_S)
    assert proc.returncode == 2
    assert proc.stderr.splitlines() == ["cvxnav: error: --out field.json: is the scenario file"]
    assert load_scenario(scenario) == bundled_scenario()  # untouched
    assert not list(own_tmpdir.iterdir())
