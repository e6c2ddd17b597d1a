"""Stage state that survives the stage's process: one file per stage, replaced atomically.

`cvxnav run` restarts a stage that crashes. A core whose output depends on more than its newest input
(the sensing stage's point memory, the planner's current plan) is ``Stateful``: the shell keeps its
``state()`` in ``<state_dir>/state`` (the directory the supervisor passes with ``--state-dir``) and
hands it back to ``restore()`` when the stage starts again. After every input the core accepted, the
state is written, when it changed, to a temporary file beside its target and renamed over it
(``os.replace`` is atomic on POSIX), before the outputs that depend on it are published: a process killed at any instant leaves either the old or the
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

from services.contract import StateError, Stateful


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


class Checkpoint:
    """One stage's state file: restored once at start, saved after each accepted input that changed it."""

    def __init__(self, *, state_dir: Path) -> None:
        self.path = state_dir / "state"
        self._saved: bytes | None = None

    def restore(self, core: Stateful) -> None:
        """Hand `core` the state a previous process of its stage saved, if any."""
        data = read_checkpoint(self.path)
        if data is None:
            return
        try:
            core.restore(data)
        except StateError as error:
            raise CheckpointError(f"{self.path}: {error}") from None
        self._saved = data

    def save(self, core: Stateful) -> None:
        """Write `core`'s state when it differs from the last one written (or restored)."""
        data = core.state()
        if data != self._saved:
            write_atomic(self.path, data)
            self._saved = data
