"""Shared fixtures: where the public scenarios live (the `shared/` directory next to the repository); and
how many xdist workers `-n auto` (addopts) starts."""

from __future__ import annotations

import math
import os
from pathlib import Path

import pytest


def pytest_xdist_auto_num_workers(config: pytest.Config) -> int:
    """A worker per CPU this process may use: the CPUs it may run on (a container's cpuset), fewer under a
    cgroup's CPU quota (`docker run --cpus`); not the host's count, which xdist reads through psutil.
    PYTEST_XDIST_AUTO_NUM_WORKERS, as for xdist itself, overrides it."""
    if named := os.environ.get("PYTEST_XDIST_AUTO_NUM_WORKERS"):
        return int(named)
    cpus = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1
    try:
        quota, period = Path("/sys/fs/cgroup/cpu.max").read_text().split()
        if quota != "max":
            cpus = min(cpus, max(1, math.ceil(int(quota) / int(period))))
    except (OSError, ValueError):
        pass  # no cgroup v2 CPU controller here
    return cpus


@pytest.fixture(scope="session")
def shared_dir() -> Path:
    path = Path(__file__).resolve().parents[2] / "shared"
    if not path.is_dir():
        pytest.skip(f"shared directory {path} is absent (it sits next to the repository checkout)")
    return path


@pytest.fixture(scope="session")
def scenarios_dir(shared_dir: Path) -> Path:
    path = shared_dir / "scenarios"
    if not path.is_dir():
        pytest.skip(f"public scenarios directory {path} is absent")
    return path
