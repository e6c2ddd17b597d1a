"""Multi-host on one machine: stages in separate Linux network namespaces, joined only through `cvxnav router`
(the deployment of docs/deploy.md: a router, every stage a client), and the faults of such a network.

The namespaces (`tests/netns.py`) are made and removed by each test; skipped where namespaces cannot be
made. The faults: a stage's link cut for 3 s, the router killed and started again, and the link of a
subscriber that only listens (the monitor) cut for longer than Zenoh's congestion timeout. An observer,
a client of the router on the sim's host, writes what it hears with its arrival time; the run file has
what the car did, on the sim's clock (realtime: the wall clock).
"""

from __future__ import annotations

import json
import math
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import zenoh

from cvxnav.supervisor import stop_processes
from netns import Network, Seen, network
from schemas.files import RunFile
from schemas.scenario import bundled_scenario
from services.drive.vehicle import VehicleLimits

pytestmark = pytest.mark.slow
PAPER = bundled_scenario()
PIPELINE = ("sensing", "ellipsoids", "planner", "smoother")
WAIT_S = 150.0  # a guard against a hung run, not a speed requirement


def start_stages(net: Network, placement: dict[str, str], *, logs: Path) -> list[subprocess.Popen]:
    return [net.cvxnav(host, "service", stage, "--connect", net.router_endpoint(host), "--mode", "client",
                       log=logs / f"{stage}.log") for stage, host in placement.items()]


def start_sim(net: Network, host: str, *args: str, logs: Path) -> subprocess.Popen:
    return net.cvxnav(host, "service", "sim", "--connect", net.router_endpoint(host), "--mode", "client", "--out",
                      str(logs / "run.json"), *args, log=logs / "sim.log")


def wait_for_sim_time(seen_path: Path, sim_s: float) -> None:
    """Block until the observer has seen the sim reach `sim_s`."""
    deadline = time.monotonic() + WAIT_S
    while time.monotonic() < deadline:
        states = Seen.read(seen_path).states if seen_path.exists() else []
        if states and states[-1][1] >= sim_s:
            return
        time.sleep(0.05)
    pytest.fail(f"the sim never reached {sim_s} s")


def driving(seen_path: Path, *, from_s: float) -> tuple[float, float]:
    """Block until the observer sees the car drive forward (0.3 m/s or more) at `from_s` or later; then
    (monotonic time, the sim time it maps to)."""
    deadline = time.monotonic() + WAIT_S
    while time.monotonic() < deadline:
        states = Seen.read(seen_path).states if seen_path.exists() else []
        if states and states[-1][1] >= from_s and states[-1][2] >= 0.3:
            now = time.monotonic()
            return now, states[-1][1] + (now - states[-1][0])
        time.sleep(0.05)
    pytest.fail(f"the car never drove forward after sim {from_s} s")


def stood(run: RunFile, *, from_s: float, to_s: float) -> tuple[float, float] | None:
    """The first stretch of sim time in [from_s, to_s] the car stood still: (start, end); end when it moved on."""
    traj = np.array(run.trajectory)
    t, v = traj[1:, 0], np.linalg.norm(np.diff(traj[:, 1:3], axis=0), axis=1) / np.diff(traj[:, 0])
    still = (t >= from_s) & (t <= to_s) & (v < 1e-3)
    if not still.any():
        return None
    start = int(np.argmax(still))
    moving = np.nonzero((np.arange(len(t)) > start) & (v >= 1e-3))[0]
    return float(t[start]), float(t[moving[0]]) if moving.size else float("inf")


def test_run_across_namespaces_through_the_router(tmp_path):
    with network(hosts=("a", "b")) as net:
        # The hosts really are apart: host A has no route to host B.
        reach = subprocess.run(["ip", "netns", "exec", net.ns("a"), sys.executable, "-c",
                                f"import socket; socket.create_connection(('{net.host_ip('b')}', 7447), timeout=1)"],
                               capture_output=True, text=True)
        assert reach.returncode != 0 and ("unreachable" in reach.stderr or "timed out" in reach.stderr), reach.stderr
        processes = [net.router(log=tmp_path / "router.log")]
        try:
            processes += start_stages(net, {"sensing": "a", "ellipsoids": "a", "planner": "b", "smoother": "b"},
                                      logs=tmp_path)
            sim = start_sim(net, "b", logs=tmp_path)
            processes.append(sim)
            code = sim.wait(timeout=WAIT_S)
            logs = {p.name: p.read_text()[-600:] for p in tmp_path.glob("*.log")}
            assert code == 0, logs
            run = RunFile.read(tmp_path / "run.json")
            assert run.status == "reached" and run.goals_reached == 2
        finally:
            stop_processes(processes, grace_s=10.0)


def test_a_cut_link_and_a_dead_router_brake_the_car_which_drives_on_once_they_are_back(tmp_path):
    """Realtime: the planner alone on host P, its link cut for 3 s; later the router SIGKILLed and started
    again 1 s after, each while the car drives forward. The car stands while it has no fresh plan, within
    its braking limits, and the run reaches both goals."""
    seen_path = tmp_path / "seen.jsonl"
    with network(hosts=("a", "p")) as net:
        router = net.router(log=tmp_path / "router.log")
        processes = start_stages(net, {"sensing": "a", "ellipsoids": "a", "planner": "p", "smoother": "a"},
                                 logs=tmp_path)
        try:
            processes.append(net.observe("a", log=tmp_path / "observer.log", out=seen_path))
            sim = start_sim(net, "a", "--realtime", logs=tmp_path)
            processes.append(sim)
            cut_at, cut_s = driving(seen_path, from_s=3.0)
            net.cut("p")
            time.sleep(3.0)
            net.restore("p")
            back_at = time.monotonic()
            killed_at, kill_s = driving(seen_path, from_s=cut_s + 8.0)
            router.kill()
            router.wait()
            time.sleep(1.0)
            router = net.router(log=tmp_path / "router.log")
            listening_at = time.monotonic()
            code = sim.wait(timeout=WAIT_S)
        finally:
            stop_processes([*processes, router], grace_s=10.0)
    logs = {p.name: p.read_text()[-600:] for p in tmp_path.glob("*.log")}
    assert code == 0, logs
    run = RunFile.read(tmp_path / "run.json")
    assert run.status == "reached" and run.goals_reached == len(PAPER.goals)
    assert run.min_clearance >= 0.5 * PAPER.robot.safety_distance
    # Realtime: sim time runs with the wall clock, so the wall times of the faults map onto it.
    back_s, listening_s = cut_s + (back_at - cut_at), kill_s + (listening_at - killed_at)
    cut_stand = stood(run, from_s=cut_s, to_s=back_s)
    router_stand = stood(run, from_s=kill_s, to_s=listening_s)
    assert cut_stand is not None, "the car did not stop while the planner was cut off"
    assert router_stand is not None, "the car did not stop while the router was down"
    heard_again_at = min((t for t, _, _ in Seen.read(seen_path).states if t > listening_at), default=math.nan)
    print(f"planner link cut for 3 s: the car was at rest {cut_stand[0] - cut_s:.2f} s after the cut and moved "
          f"again {cut_stand[1] - back_s:.2f} s after the link was back; router killed: the car was at rest "
          f"{router_stand[0] - kill_s:.2f} s after the kill and stood {router_stand[1] - router_stand[0]:.2f} s; "
          f"the new router said it listened {listening_at - killed_at:.2f} s after the kill, the sim was heard "
          f"again {heard_again_at - listening_at:.2f} s after that")
    traj = np.array(run.trajectory)
    v = np.linalg.norm(np.diff(traj[:, 1:3], axis=0), axis=1) / np.diff(traj[:, 0])
    decel = VehicleLimits.from_scenario(PAPER).max_decel_mps2
    assert np.all(np.diff(v) / np.diff(traj[1:, 0]) >= -decel * 1.05 - 1e-6)  # braking within its limits
    for _, moved_s in (cut_stand, router_stand):
        assert moved_s < float("inf")  # and it drove on


def test_a_dead_link_to_a_passive_subscriber_stalls_nothing(tmp_path):
    """Lockstep, the monitor alone on host M, its link cut for longer than Zenoh's congestion timeout: no
    publisher of the loop waits for it (every topic is dropped on a congested link), so the states keep
    coming; a publisher that blocked would stall the router's forwarding for that timeout."""
    seen_path = tmp_path / "seen.jsonl"
    block_s = json.loads(zenoh.Config().get_json("transport/link/tx/queue/congestion_control"))["block"][
        "wait_before_close"] / 1e6
    with network(hosts=("a", "m")) as net:
        router = net.router(log=tmp_path / "router.log")
        processes = start_stages(net, dict.fromkeys(PIPELINE, "a"), logs=tmp_path)
        try:
            processes.append(net.cvxnav("m", "service", "monitor", "--connect", net.router_endpoint("m"), "--mode",
                                        "client", "--record", str(tmp_path / "run.rrd"), log=tmp_path / "monitor.log"))
            processes.append(net.observe("a", log=tmp_path / "observer.log", out=seen_path))
            time.sleep(2.0)  # the monitor joins before the run starts
            sim = start_sim(net, "a", logs=tmp_path)
            processes.append(sim)
            wait_for_sim_time(seen_path, 2.0)
            cut_at = time.monotonic()
            net.cut("m")
            time.sleep(block_s + 3.0)
            net.restore("m")
            back_at = time.monotonic()
            code = sim.wait(timeout=WAIT_S)
        finally:
            stop_processes([*processes, router], grace_s=10.0)
    assert code == 0, {p.name: p.read_text()[-600:] for p in tmp_path.glob("*.log")}
    seen = Seen.read(seen_path)
    end = min(back_at, seen.states[-1][0])  # the run may end before the link is back
    gap_s = seen.longest_gap_s(start_s=cut_at, end_s=end)
    before_s = seen.longest_gap_s(start_s=seen.states[0][0], end_s=cut_at)
    print(f"monitor link cut for {block_s + 3.0:.0f} s: longest wait for a state {gap_s:.2f} s while cut "
          f"({before_s:.2f} s before the cut; the run went on {end - cut_at:.1f} s of it)")
    assert gap_s < block_s / 2, f"the loop stalled {gap_s:.1f} s behind a subscriber that stopped reading"
    assert RunFile.read(tmp_path / "run.json").status == "reached"
