"""`cvxnav service NAME`: one process of the wiring table, its core built by the table's factory (or
``--entry``) and run in the one shell until SIGINT/SIGTERM or, for the sim, the end of the run."""

from __future__ import annotations

import threading
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import zenoh

from cvxnav.exits import EXIT_BY_STATUS
from cvxnav.stages import RunError, load_factory
from schemas.scenario import Scenario
from schemas.wiring import PROCESSES, SIM
from services.convert import LocalFrame
from services.limits import DEFAULT_MAX_PAYLOAD_BYTES
from services.shell.stage import install_signal_handlers, run_stage


def serve(
    *,
    name: str,
    scenario: Scenario,
    session_config: zenoh.Config,
    prefix: str,
    entry_point: str | None = None,
    options: Mapping[str, Any] | None = None,
    out_path: Path | None = None,
    max_payload_bytes: int = DEFAULT_MAX_PAYLOAD_BYTES,
    state_dir: Path | None = None,
) -> int:
    """Run process `name` until SIGINT/SIGTERM (the sim: until its run ends); the process exit code.

    `options` go to the factory with the scenario (the sim's `SimConfig` fields, the monitor's
    targets); the sim writes its run file to `out_path`. An input payload larger than
    `max_payload_bytes` is rejected before it is decoded. With `state_dir`, a `Stateful` core's state
    is saved there and restored from there.
    """
    if name not in PROCESSES:
        raise RunError(f"unknown stage {name!r}; known: {', '.join(PROCESSES)}")
    stop = threading.Event()
    install_signal_handlers(stop)
    # A core computes near the origin, the keys carry world coordinates. A ROS 2 node's other side is the
    # robot's own frame, so the bridge speaks world coordinates on both of its sides.
    frame = LocalFrame() if PROCESSES[name].ros2 else LocalFrame.of(scenario)
    core = load_factory(entry_point or PROCESSES[name].factory)(frame.scenario_to_local(scenario), **(options or {}))
    run_stage(stage=name, core=core, session_config=session_config, prefix=prefix, stop_event=stop,
              max_payload_bytes=max_payload_bytes, state_dir=state_dir, frame=frame)
    if name != SIM.name:
        return 0
    result = frame.to_world(core.result())
    if out_path is not None:
        result.write(out_path)
    return EXIT_BY_STATUS[result.status]
