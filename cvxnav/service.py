"""`cvxnav service NAME`: one process of the wiring table, its core built by the table's factory (or
``--entry``) and run in the one shell until SIGINT/SIGTERM or, for the sim, the end of the run.

The core is built and run in a worker thread, so the main thread keeps the signals: a SIGTERM during
a long solve stops the process within ``STOP_GRACE_S`` (it exits without a worker still busy then).
Under a watchdog (``NOTIFY_SOCKET``, ``WATCHDOG_USEC``: systemd or `cvxnav run`) the process sends
its keep-alives while the worker makes progress (``services.shell.watchdog``).

A warm spare (``standby``) does everything but join the network: the interpreter, the imports and
the core are ready when a line arrives on its standard input, and only then is its state restored
(the checkpoint its predecessor left) and its session opened. End of input dismisses it: it exits 0
without having opened a session. `cvxnav run` keeps one per pipeline stage in a robot run, so a stage
that crashes is replaced by a process that is already up (``cvxnav.supervisor``).
"""

from __future__ import annotations

import logging
import os
import select
import sys
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
from services.shell.stage import STOP_GRACE_S, install_signal_handlers, run_in_worker, run_stage
from services.shell.watchdog import STALL_LIMIT_S, Progress, Watchdog, keep_alive

logger = logging.getLogger(__name__)
EXIT_WORKER_BUSY = 1  # stopped, but its worker was still busy: exited without it


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
    stall_limit_s: float = STALL_LIMIT_S,
    standby: bool = False,
) -> int:
    """Run process `name` until SIGINT/SIGTERM (the sim: until its run ends); the process exit code.

    `options` go to the factory with the scenario (the sim's `SimConfig` fields, the monitor's
    targets); the sim writes its run file to `out_path`. An input payload larger than
    `max_payload_bytes` is rejected before it is decoded. With `state_dir`, a `Stateful` core's state
    is saved there and restored from there. A pass of the worker longer than `stall_limit_s` stops
    the keep-alives (a hang). With `standby`, the process waits, core built, for a line on its standard
    input before it restores its state and opens its session; end of input (or a stop) dismisses it.
    """
    if name not in PROCESSES:
        raise RunError(f"unknown stage {name!r}; known: {', '.join(PROCESSES)}")
    stop = threading.Event()
    install_signal_handlers(stop)
    progress = Progress()
    watchdog = Watchdog.from_environment(os.environ)
    if watchdog is not None:
        keep_alive(watchdog=watchdog, progress=progress, stall_limit_s=stall_limit_s, stop_event=stop)

    # A core computes near the origin, the keys carry world coordinates. A ROS 2 node's other side is the
    # robot's own frame, so the bridge speaks world coordinates on both of its sides.
    frame = LocalFrame() if PROCESSES[name].ros2 else LocalFrame.of(scenario)

    def work():
        core = load_factory(entry_point or PROCESSES[name].factory)(frame.scenario_to_local(scenario),
                                                                     **(options or {}))
        if standby and not _called_up(stop):
            return None  # dismissed
        run_stage(stage=name, core=core, session_config=session_config, prefix=prefix, stop_event=stop,
                  max_payload_bytes=max_payload_bytes, state_dir=state_dir, frame=frame, progress=progress)
        return core

    finished, core = run_in_worker(work, stop_event=stop)
    if not finished:  # the worker may be inside a native solve: only leaving the process ends it
        logger.error("stage %s: its worker was still busy %.1f s after the stop; exiting without it", name,
                     STOP_GRACE_S)
        logging.shutdown()
        sys.stderr.flush()
        os._exit(EXIT_WORKER_BUSY)
    if name != SIM.name or core is None:
        return 0
    result = frame.to_world(core.result())
    if out_path is not None:
        result.write(out_path)
    return EXIT_BY_STATUS[result.status]


def _called_up(stop: threading.Event) -> bool:
    """Wait for a line on standard input: True once it comes, False at its end or when `stop` is set."""
    while not stop.is_set():
        readable, _, _ = select.select([sys.stdin], [], [], STOP_GRACE_S / 4)
        if readable:
            return bool(sys.stdin.readline())
    return False
