"""A `cvxnav run`'s stage processes as /proc shows them: the children running `python -m cvxnav service NAME`."""

from __future__ import annotations

from pathlib import Path


def stage_pids(parent_pid: int) -> dict[str, int]:
    """The child processes of ``parent_pid`` that run a stage, by stage name."""
    pids = {}
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            parent = int(stat.read_text().rsplit(")", 1)[1].split()[1])
            argv = (stat.parent / "cmdline").read_bytes().split(b"\0")
        except (OSError, IndexError, ValueError):
            continue
        if parent == parent_pid and b"service" in argv:
            pids[argv[argv.index(b"service") + 1].decode()] = int(stat.parent.name)
    return pids
