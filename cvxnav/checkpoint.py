"""Stage state that survives the stage's process: one file per piece of state, replaced atomically.

`cvxnav run` restarts a stage that crashes. A stage whose output depends on more than its newest input
(the sensing stage's point memory, the planner's current plan) keeps that state in a directory the
supervisor passes with ``--state-dir`` and reloads it when it starts. A checkpoint is written to a
temporary file beside its target and renamed over it (``os.replace`` is atomic on POSIX), before the
outputs that depend on it are published: a process killed at any instant leaves either the old or the
new checkpoint, never a torn one, and never an output ahead of its checkpoint. There is no fsync: the
page cache outlives a killed process; surviving a power cut is not the goal.

A checkpoint that exists but cannot be read is an error, not an empty state: a stage that silently
forgot the obstacles behind the robot would plan through them. The stage then fails to start, and the
supervisor ends the run once the restarts are used up, naming the file.
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path


class CheckpointError(RuntimeError):
    """A checkpoint file exists but is unreadable: one line naming the file."""


def write_atomic(path: Path, data: bytes) -> None:
    """Replace `path` with `data`: a reader sees the old content or the new one, never a mix."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as file:
            file.write(data)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def read_checkpoint(path: Path) -> bytes | None:
    """The checkpoint's bytes; None when there is none yet (the stage's first start)."""
    try:
        return path.read_bytes()
    except FileNotFoundError:
        return None
    except OSError as error:
        raise CheckpointError(f"{path}: cannot read checkpoint: {error.strerror}") from None
