"""Stages that meet only through `cvxnav router`, a complete run across it, and `cvxnav status` watching."""

from __future__ import annotations

import json
import subprocess
import sys
import time
from pathlib import Path

import pytest
import zenoh

from cvxnav.supervisor import free_ports, stop_processes
from schemas.files import RunFile
from schemas.wiring import default_prefix
from services.shell.peers import alive_stages
from services.shell.zenoh_config import build_zenoh_config

pytestmark = pytest.mark.slow
PIPELINE = ("sensing", "ellipsoids", "planner", "smoother")


def _start(args: list[str], *, log: Path) -> subprocess.Popen:
    with open(log, "wb") as out:
        return subprocess.Popen([sys.executable, "-m", "cvxnav", *args], stdout=out, stderr=subprocess.STDOUT,
                                stdin=subprocess.DEVNULL)


def _open_when_up(endpoint: str, *, timeout_s: float = 30.0) -> zenoh.Session:
    """A client session to the router, once it listens (it is a process still importing)."""
    deadline = time.monotonic() + timeout_s
    while True:
        try:
            return zenoh.open(build_zenoh_config(connect=[endpoint], mode="client"))
        except zenoh.ZError:
            if time.monotonic() > deadline:
                raise
            time.sleep(0.2)


def _wait_alive(session: zenoh.Session, stages: set[str], *, timeout_s: float = 60.0) -> None:
    deadline = time.monotonic() + timeout_s
    while stages - alive_stages(session, prefix=default_prefix()) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert stages <= alive_stages(session, prefix=default_prefix())


def test_run_through_the_router_with_status(tmp_path):
    (port,) = free_ports(1)
    router_ep = f"tcp/127.0.0.1:{port}"
    processes = [_start(["router", "--listen", router_ep], log=tmp_path / "router.log")]
    try:
        # Every stage connects to the router only: no listen endpoint, multicast scouting off.
        processes += [_start(["service", name, "--connect", router_ep], log=tmp_path / f"{name}.log")
                      for name in PIPELINE]
        with _open_when_up(router_ep) as session:
            _wait_alive(session, set(PIPELINE))
            sim = _start(["service", "sim", "--connect", router_ep, "--out", str(tmp_path / "run.json")],
                         log=tmp_path / "sim.log")
            processes.append(sim)
            _wait_alive(session, {"sim"})  # the sim imports, then drives: status looks while it does
        status = subprocess.run([sys.executable, "-m", "cvxnav", "status", "--connect", router_ep, "--mode", "client",
                                 "--window-s", "1.5", "--json"], capture_output=True, text=True, timeout=60)
        assert status.returncode == 0, status.stderr
        report = {stage["name"]: stage for stage in json.loads(status.stdout)["stages"]}
        assert sim.poll() is None, "the sim finished before status looked; the run is too short to watch"
        for name in (*PIPELINE, "sim"):
            assert report[name]["alive"], report
        assert report["sim"]["rates_hz"]["scan"] > 1.0
        assert report["smoother"]["rates_hz"]["smooth_path"] > 1.0
        assert report["planner"]["state"] == "ok"
        assert sim.wait(timeout=120) == 0, (tmp_path / "sim.log").read_text()[-2000:]
        run = RunFile.read(tmp_path / "run.json")
        assert run.status == "reached" and run.goals_reached == 2
    finally:
        stop_processes(processes, grace_s=10.0)
    assert processes[0].returncode == 0  # the router stops cleanly on SIGTERM


def test_status_without_a_reachable_peer_says_so_in_one_line():
    (port,) = free_ports(1)  # nothing listens there
    done = subprocess.run([sys.executable, "-m", "cvxnav", "status", "--connect", f"tcp/127.0.0.1:{port}",
                           "--mode", "client"], capture_output=True, text=True, timeout=60)
    assert done.returncode == 2
    assert done.stderr.startswith("cvxnav: error: cannot open a Zenoh session:") and done.stderr.count("\n") == 1
