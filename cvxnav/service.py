"""`cvxnav service NAME`: one stage of the wiring table as a process, in the one shell."""

from __future__ import annotations

import threading
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import zenoh

from cvxnav.exits import EXIT_BY_STATUS
from cvxnav.stages import DEFAULT_FACTORIES, RunError, load_factory
from schemas.scenario import Scenario
from schemas.wiring import STAGES
from services.limits import DEFAULT_MAX_PAYLOAD_BYTES
from services.shell.stage import install_signal_handlers, run_stage


def serve(
    *,
    name: str,
    scenario: Scenario,
    session_config: zenoh.Config,
    prefix: str,
    entry_point: str | None = None,
    sim_options: Mapping[str, Any] | None = None,
    max_payload_bytes: int = DEFAULT_MAX_PAYLOAD_BYTES,
    state_dir: Path | None = None,
) -> int:
    """Run stage `name` until SIGINT/SIGTERM (the sim: until its run ends); the process exit code.

    An input payload larger than `max_payload_bytes` is rejected before it is decoded. With
    `state_dir`, a `Stateful` core's state is saved there and restored from there.
    """
    stop = threading.Event()
    install_signal_handlers(stop)
    if name == "sim":
        from services.shell.sim import run_sim
        from sim.core import SimConfig

        options = dict(sim_options or {})
        out_path = options.pop("out_path", None)
        result = run_sim(scenario=scenario, config=SimConfig(**options, max_payload_bytes=max_payload_bytes),
                         session_config=session_config,
                         prefix=prefix, stop_event=stop, out_path=out_path)
        return EXIT_BY_STATUS[result.status]
    if name not in STAGES:
        raise RunError(f"unknown stage {name!r}; known: {', '.join(STAGES)}")
    core = load_factory(entry_point or DEFAULT_FACTORIES[name])(scenario)
    run_stage(stage=name, core=core, session_config=session_config, prefix=prefix, stop_event=stop,
              max_payload_bytes=max_payload_bytes, state_dir=state_dir)
    return 0
