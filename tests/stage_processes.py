"""A `cvxnav run`'s stage processes as /proc shows them: the children running `python -m cvxnav service NAME`,
and what /proc says of a process, for the e2e tests that signal them."""

from __future__ import annotations

import os
import time
from collections.abc import Callable
from pathlib import Path

import pytest


def _stat_fields(pid: int) -> list[str]:
    """The fields of /proc/PID/stat after the command name (which may hold spaces and parentheses)."""
    return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()


def argv(pid: int) -> list[str]:
    """The command line of a process."""
    return [arg.decode() for arg in Path(f"/proc/{pid}/cmdline").read_bytes().split(b"\0") if arg]


def _stage_processes(parent_pid: int) -> dict[str, list[tuple[int, int]]]:
    """The live child processes of ``parent_pid`` that run a stage: by stage name, (start time, pid), oldest first."""
    found: dict[str, list[tuple[int, int]]] = {}
    for stat in Path("/proc").glob("[0-9]*/stat"):
        pid = int(stat.parent.name)
        try:
            fields = _stat_fields(pid)
            args = argv(pid)
        except (OSError, IndexError, ValueError):
            continue  # exited while we looked
        if int(fields[1]) == parent_pid and fields[0] != "Z" and "service" in args:
            found.setdefault(args[args.index("service") + 1], []).append((int(fields[19]), pid))
    return {name: sorted(processes) for name, processes in found.items()}


def stage_pids(parent_pid: int) -> dict[str, int]:
    """The stage processes of a run, by stage name: of two, the older (a warm spare is started after its stage,
    and the one that took a stage's place is older than the spare started behind it)."""
    return {name: processes[0][1] for name, processes in _stage_processes(parent_pid).items()}


def spare_pids(parent_pid: int) -> dict[str, int]:
    """A run's warm spares (`cvxnav run --warm-spares`), by the name of the stage each stands by for."""
    return {name: processes[-1][1] for name, processes in _stage_processes(parent_pid).items() if len(processes) > 1}


def alive(pid: int) -> bool:
    """Whether `pid` is a process that has not exited (a zombie has)."""
    try:
        return _stat_fields(pid)[0] != "Z"
    except OSError:
        return False


def cpu_s(pid: int) -> float:
    """User + system CPU time of a process, in seconds."""
    fields = _stat_fields(pid)
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def wait_for(condition: Callable[[], object], *, what: str, timeout_s: float) -> object:
    """`condition()`'s first truthy value, polled; the test fails naming `what` after `timeout_s` (a guard
    against a hung test, not a speed requirement)."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if value := condition():
            return value
        time.sleep(0.02)
    pytest.fail(f"gave up waiting for {what}")
