"""Issue 27's attacks on an open network (`cvxnav run --listen`, no TLS), replayed on a real run.

While the car drives, a session joined to the run's mesh answers every scan at once with an empty
ellipse set, a path into the nearest thing the car sees or off the map (in turn), and for 20 scans an
error status on the planner's key naming the planner. Nothing authenticates them here: the sim must
refuse every forged path with its reason, and the pipeline's own answers must still take the car to
its goals, never closer to an obstacle than the hard floor and never off the map. Meanwhile a second
run under the same robot id is refused at start, and one under another id runs beside it.
"""

from __future__ import annotations

import subprocess
import sys

import pytest
from attacker import FORGED_PLAN, Attacker
from tls_clients import Inbox

from schemas.files import RunFile
from schemas.messages import StageStatus, decode
from schemas.scenario import bundled_scenario
from schemas.wiring import default_prefix, status_key

pytestmark = pytest.mark.slow
PREFIX = default_prefix()
RUN_S = 600.0  # only a guard against a hung run: a lockstep run's wall time follows the machine's load


def test_forged_traffic_on_an_open_network_never_moves_the_car_and_a_second_id_is_refused(live_run, tmp_path):
    sim_statuses = Inbox()
    with live_run("--out", "run.json", cwd=tmp_path) as run:
        run.session.declare_subscriber(status_key(PREFIX, "sim"), sim_statuses)
        attacker = Attacker(run.session, prefix=PREFIX)
        same = subprocess.run([sys.executable, "-m", "cvxnav", "run", "--quiet", "--connect", run.endpoint,
                               "--out", "same.json"], cwd=tmp_path, capture_output=True, text=True, timeout=RUN_S)
        other = subprocess.Popen([sys.executable, "-m", "cvxnav", "run", "--quiet", "--robot-id", "robot2",
                                  "--connect", run.endpoint, "--out", "robot2.json"], cwd=tmp_path,
                                 stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        try:
            assert run.wait(timeout_s=RUN_S) == 0, (tmp_path / "run.log").read_text()[-2000:]
            log, _ = other.communicate(timeout=RUN_S)
        finally:
            other.kill()
        assert other.returncode == 0, log[-2000:]

    assert same.returncode == 2 and not (tmp_path / "same.json").exists()
    assert same.stderr.count("\n") == 1 and "robot id 'robot1' is already up at" in same.stderr, same.stderr
    scenario = bundled_scenario()
    for out in ("run.json", "robot2.json"):
        result = RunFile.read(tmp_path / out)
        assert result.status == "reached" and result.goals_reached == len(scenario.goals), out
        assert result.min_clearance >= scenario.robot.safety_distance / 2.0, out  # the hard floor's promise
    assert attacker.scans > 20 and attacker.statuses_left == 0
    refused = [decode(StageStatus, payload).reason for _, payload in sim_statuses.samples]
    forged = [reason for reason in refused if f"plan {FORGED_PLAN} " in reason]
    assert any("hit of the car's own scans" in reason for reason in forged), refused[:5]
    assert any("leaves the map" in reason for reason in forged), refused[:5]
