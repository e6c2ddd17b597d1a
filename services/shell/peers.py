"""Which processes are up under a prefix: their liveliness tokens, asked for once or until all are up."""

from __future__ import annotations

import threading
import time

import zenoh

from schemas.wiring import alive_key, stage_of_alive_key


def alive_stages(session: zenoh.Session, *, prefix: str, timeout_s: float = 2.0) -> set[str]:
    """Names of the processes whose liveliness token is up now."""
    names = set()
    for reply in session.liveliness().get(alive_key(prefix), timeout=timeout_s):
        if reply.ok is not None and (name := stage_of_alive_key(prefix, str(reply.ok.key_expr))) is not None:
            names.add(name)
    return names


def wait_for_stages(session: zenoh.Session, *, prefix: str, stages: tuple[str, ...], timeout_s: float,
                    stop_event: threading.Event | None = None) -> set[str]:
    """Ask the liveliness tokens until every stage is up; the ones still missing after the timeout."""
    deadline = time.monotonic() + timeout_s
    missing = set(stages)
    while missing and time.monotonic() < deadline and not (stop_event and stop_event.is_set()):
        missing -= alive_stages(session, prefix=prefix, timeout_s=1.0)
        if missing:
            time.sleep(0.05)
    return missing
