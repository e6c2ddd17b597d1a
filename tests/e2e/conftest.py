"""A live `cvxnav run` that a test joins: the run listens on a free loopback endpoint (`--listen`), the
test opens a Zenoh peer session there, and reads the stage processes' pids and memory from /proc."""

from __future__ import annotations

import subprocess
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import pytest
import zenoh

from cvxnav.supervisor import free_ports, stop_processes
from schemas.wiring import default_prefix
from services.shell.peers import wait_for_stages
from services.shell.zenoh_config import build_zenoh_config
from stage_processes import stage_pids

PREFIX = default_prefix()
ALL_STAGES = ("sensing", "ellipsoids", "planner", "smoother", "sim")


@dataclass
class LiveRun:
    process: subprocess.Popen
    session: zenoh.Session
    cwd: Path
    endpoint: str  # where the run listens (others join its mesh there)

    def stage_pids(self) -> dict[str, int]:
        """The run's child processes by stage name (`python -m cvxnav service NAME ...`)."""
        return stage_pids(self.process.pid)

    @staticmethod
    def memory_kib(pid: int) -> dict[str, int]:
        """VmRSS and VmHWM (peak resident set) of a process, in KiB; empty once it has exited."""
        try:
            lines = Path(f"/proc/{pid}/status").read_text().splitlines()
        except OSError:
            return {}
        fields = dict(line.split(":", 1) for line in lines if ":" in line)
        return {name: int(fields[name].split()[0]) for name in ("VmRSS", "VmHWM") if name in fields}

    def wait(self, *, timeout_s: float) -> int:
        return self.process.wait(timeout=timeout_s)


@contextmanager
def _live_run(*args: str, cwd: Path, startup_s: float = 90.0) -> Iterator[LiveRun]:
    """Start `cvxnav run --listen EP ARGS`, join its mesh, return once every stage and the sim are up."""
    endpoint = f"tcp/127.0.0.1:{free_ports(1)[0]}"
    log = open(cwd / "run.log", "wb")
    process = subprocess.Popen([sys.executable, "-m", "cvxnav", "run", "--quiet", "--listen", endpoint, *args],
                               cwd=cwd, stdout=log, stderr=subprocess.STDOUT)
    try:
        deadline = time.monotonic() + startup_s
        with zenoh.open(build_zenoh_config(connect=[endpoint])) as session:
            missing = set(ALL_STAGES)
            while missing and time.monotonic() < deadline and process.poll() is None:
                missing = wait_for_stages(session, prefix=PREFIX, stages=tuple(missing), timeout_s=1.0)
            if missing:
                pytest.fail(f"stages not up: {sorted(missing)}; {(cwd / 'run.log').read_text()[-2000:]}")
            yield LiveRun(process=process, session=session, cwd=cwd, endpoint=endpoint)
    finally:
        stop_processes([process], grace_s=10.0)
        log.close()


@pytest.fixture(scope="session")
def live_run():
    """`with live_run(*run_args, cwd=DIR) as run:` a joined `cvxnav run` (see `LiveRun`)."""
    return _live_run
