"""Which implementation runs each pipeline stage: the wiring table's factory, or a swap named in a `stages` file.

A stage is swapped by naming, in a JSON `stages` file, either a Python entry point `"module:factory"`
(called with the scenario, returning a StageCore), or `{"command": ["prog", "arg", ...]}`: any process
that speaks the stage's keys (the supervisor fills in its arguments, `cvxnav.supervisor`).
"""

from __future__ import annotations

import importlib
import json
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from schemas.scenario import read_text
from schemas.wiring import PIPELINE, STAGES
from services.contract import StageCore


STAGES_FILE_BYTES = 1 << 20  # a stages file names a few entry points


class RunError(ValueError):
    """Bad input to `run`/`service` (a stages file, an entry point): one line, exit code 2."""


def load_factory(entry_point: str) -> Callable[..., StageCore]:
    """`module:attr[.attr]` → the callable it names (a factory taking the scenario, and options)."""
    module_name, sep, attr_path = entry_point.partition(":")
    if not sep or not module_name or not attr_path:
        raise RunError(f"entry point {entry_point!r} must look like 'package.module:factory'")
    try:
        target: Any = importlib.import_module(module_name)
    except ImportError as error:
        raise RunError(f"entry point {entry_point!r}: cannot import {module_name}: {error}") from None
    for attr in attr_path.split("."):
        if not hasattr(target, attr):
            raise RunError(f"entry point {entry_point!r}: {module_name} has no {attr_path}")
        target = getattr(target, attr)
    if not callable(target):
        raise RunError(f"entry point {entry_point!r} is not callable")
    return target


@dataclass(frozen=True)
class StageChoice:
    """How one pipeline stage runs: a Python entry point in `cvxnav service`, or an external command."""

    entry_point: str | None = None
    command: tuple[str, ...] | None = None


def load_stages(path: Path | None) -> dict[str, StageChoice]:
    """The stages config (JSON: name → "module:factory" or {"command": [...]}) over the defaults."""
    choices = {name: StageChoice(entry_point=STAGES[name].factory) for name in PIPELINE}
    if path is None:
        return choices
    try:
        doc = json.loads(read_text(path, error=RunError, max_bytes=STAGES_FILE_BYTES)[0])
    except json.JSONDecodeError as error:
        raise RunError(f"{path}: invalid JSON: {error.msg} (line {error.lineno})") from None
    stages = doc.get("stages", doc) if isinstance(doc, dict) else None
    if not isinstance(stages, dict):
        raise RunError(f"{path}: expected an object mapping stage names to entry points")
    for name, spec in stages.items():
        if name not in PIPELINE:
            raise RunError(f"{path}: stages.{name}: unknown stage; swappable: {', '.join(PIPELINE)}")
        if isinstance(spec, str):
            load_factory(spec)  # fail now, in one line, rather than in a child process
            choices[name] = StageChoice(entry_point=spec)
        elif (isinstance(spec, dict) and set(spec) == {"command"} and isinstance(spec["command"], list)
              and spec["command"] and all(isinstance(a, str) for a in spec["command"])):
            choices[name] = StageChoice(command=tuple(spec["command"]))
        else:
            raise RunError(f"{path}: stages.{name}: expected 'module:factory' or {{\"command\": [...]}}")
    return choices
