"""Multi-host on one machine: stages in separate Linux network namespaces, joined only through `cvxnav router`.

Three namespaces: the router's, and two "hosts" each on its own veth link to it (10.77.1.0/24 and
10.77.2.0/24). The router namespace does not forward IP, so the hosts cannot reach each other at all;
sensing and ellipsoids on one host, planner, smoother and the sim on the other still complete the
paper run, because Zenoh's router relays between them. Made and removed by the test; skipped where
namespaces cannot be made (not root, no `ip`, a container without CAP_SYS_ADMIN).
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pytest

from cvxnav.supervisor import stop_processes
from schemas.files import RunFile

pytestmark = pytest.mark.slow
TAG = f"cx{os.getpid() % 100000}"
ROUTER_NS, HOST_A, HOST_B = f"{TAG}r", f"{TAG}a", f"{TAG}b"
LINKS = {HOST_A: ("10.77.1.1", "10.77.1.2"), HOST_B: ("10.77.2.1", "10.77.2.2")}


def _ip(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(["ip", *args], capture_output=True, text=True)


def _must(*args: str) -> None:
    proc = _ip(*args)
    if proc.returncode != 0:
        raise RuntimeError(f"ip {' '.join(args)}: {proc.stderr.strip()}")


@pytest.fixture
def namespaces():
    if shutil.which("ip") is None:
        pytest.skip("no `ip` command (iproute2) on this machine")
    probe = _ip("netns", "add", ROUTER_NS)
    if probe.returncode != 0:
        pytest.skip(f"cannot create network namespaces here: {probe.stderr.strip()}")
    try:
        for host in (HOST_A, HOST_B):
            _must("netns", "add", host)
        for ns in (ROUTER_NS, HOST_A, HOST_B):
            _must("-n", ns, "link", "set", "lo", "up")
        for index, (host, (router_ip, host_ip)) in enumerate(LINKS.items()):
            outer, inner = f"{TAG}{index}r", f"{TAG}{index}h"
            _must("link", "add", outer, "netns", ROUTER_NS, "type", "veth", "peer", "name", inner, "netns", host)
            _must("-n", ROUTER_NS, "addr", "add", f"{router_ip}/24", "dev", outer)
            _must("-n", host, "addr", "add", f"{host_ip}/24", "dev", inner)
            _must("-n", ROUTER_NS, "link", "set", outer, "up")
            _must("-n", host, "link", "set", inner, "up")
        yield
    finally:
        for ns in (ROUTER_NS, HOST_A, HOST_B):
            _ip("netns", "del", ns)  # removes the veth pairs with them


def _in(ns: str, *args: str, log: Path) -> subprocess.Popen:
    with open(log, "wb") as out:
        return subprocess.Popen(["ip", "netns", "exec", ns, sys.executable, "-m", "cvxnav", *args], stdout=out,
                                stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL, cwd=log.parent)


def test_run_across_namespaces_through_the_router(namespaces, tmp_path):
    # The hosts really are apart: host A has no route to host B.
    reach = subprocess.run(["ip", "netns", "exec", HOST_A, sys.executable, "-c",
                            f"import socket; socket.create_connection(('{LINKS[HOST_B][1]}', 7447), timeout=1)"],
                           capture_output=True, text=True)
    assert reach.returncode != 0 and ("unreachable" in reach.stderr or "timed out" in reach.stderr), reach.stderr
    processes = [_in(ROUTER_NS, "router", "--listen", "tcp/0.0.0.0:7447", log=tmp_path / "router.log")]
    try:
        deadline = time.monotonic() + 30.0  # clients give up if the router is not listening yet
        while "listening" not in (tmp_path / "router.log").read_text() and time.monotonic() < deadline:
            assert processes[0].poll() is None, (tmp_path / "router.log").read_text()
            time.sleep(0.1)
        router_of = {host: f"tcp/{router_ip}:7447" for host, (router_ip, _) in LINKS.items()}
        placement = {"sensing": HOST_A, "ellipsoids": HOST_A, "planner": HOST_B, "smoother": HOST_B}
        for stage, host in placement.items():
            processes.append(_in(host, "service", stage, "--connect", router_of[host], "--mode", "client",
                                 log=tmp_path / f"{stage}.log"))
        sim = _in(HOST_B, "service", "sim", "--connect", router_of[HOST_B], "--mode", "client", "--out",
                  str(tmp_path / "run.json"), log=tmp_path / "sim.log")
        processes.append(sim)
        code = sim.wait(timeout=150)
        logs = {p.name: p.read_text()[-600:] for p in tmp_path.glob("*.log")}
        assert code == 0, logs
        run = RunFile.read(tmp_path / "run.json")
        assert run.status == "reached" and run.goals_reached == 2
    finally:
        stop_processes(processes, grace_s=10.0)
