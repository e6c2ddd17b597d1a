"""`cvxnav status` and `cvxnav router`: what is running under a prefix, and the Zenoh router stages meet at.

Status asks the liveliness tokens (which processes are up), then listens to every key under the
prefix for a short window: message rate per key, each stage's last ``StageStatus``, and
the scan → smoothed-path latency as seen from here (scan and path matched by ``scan_seq``).
"""

from __future__ import annotations

import json
import threading
import time
from collections import defaultdict
from dataclasses import asdict, dataclass, field

import numpy as np
import zenoh

from schemas.messages import DecodeError, Scan, SmoothPath, StageStatus, decode
from schemas.wiring import PROCESSES, TOPICS, every_key, stage_of_status_key, topic_of
from services.shell.peers import alive_stages


@dataclass
class StageReport:
    name: str
    alive: bool
    state: str | None = None  # the last StageStatus: "ok" | "error"; None when none was heard
    reason: str = ""
    processing_ms: float | None = None
    rates_hz: dict[str, float] = field(default_factory=dict)  # topic -> messages per second


@dataclass
class PipelineReport:
    prefix: str
    window_s: float
    stages: list[StageReport]
    latency_ms_p50: float | None = None
    latency_ms_max: float | None = None

    def to_json(self) -> str:
        return json.dumps(asdict(self), indent=1)

    def table(self) -> str:
        """A fixed-width table, one stage per line, then the latency line."""
        lines = [f"{'stage':<11} {'alive':<5} {'status':<6} {'proc ms':>8}  rates (Hz)"]
        for stage in self.stages:
            rates = ", ".join(f"{topic} {hz:.1f}" for topic, hz in stage.rates_hz.items()) or "-"
            proc = f"{stage.processing_ms:8.1f}" if stage.processing_ms is not None else f"{'-':>8}"
            state = stage.state or "-"
            line = f"{stage.name:<11} {'yes' if stage.alive else 'no':<5} {state:<6} {proc}  {rates}"
            lines.append(line + (f"  ({stage.reason})" if stage.state == "error" else ""))
        if self.latency_ms_p50 is not None:
            lines.append(f"scan->path latency here: p50 {self.latency_ms_p50:.0f} ms, max {self.latency_ms_max:.0f} ms")
        else:
            lines.append(f"scan->path latency: no scan answered within {self.window_s:.1f} s")
        return "\n".join(lines)


def observe(session: zenoh.Session, *, prefix: str, window_s: float) -> PipelineReport:
    """Liveliness now, then rates, statuses and latency over ``window_s`` seconds of traffic."""
    counts: dict[str, int] = defaultdict(int)
    statuses: dict[str, StageStatus] = {}
    scans_seen: dict[int, float] = {}
    latencies_ms: list[float] = []
    lock = threading.Lock()

    def on_sample(sample: zenoh.Sample) -> None:
        key_expr, now = str(sample.key_expr), time.monotonic()
        with lock:
            topic = topic_of(prefix, key_expr)
            if topic is not None:
                counts[topic] += 1
                try:
                    if topic == "scan":
                        scans_seen[decode(Scan, sample.payload.to_bytes()).header.seq] = now
                    elif topic == "smooth_path":
                        sent = scans_seen.pop(decode(SmoothPath, sample.payload.to_bytes()).scan_seq, None)
                        if sent is not None:
                            latencies_ms.append((now - sent) * 1e3)
                except DecodeError:
                    pass
            elif (stage := stage_of_status_key(prefix, key_expr)) is not None:
                try:
                    statuses[stage] = decode(StageStatus, sample.payload.to_bytes())
                except DecodeError:
                    pass

    subscriber = session.declare_subscriber(every_key(prefix), on_sample)
    try:
        alive = alive_stages(session, prefix=prefix)
        time.sleep(window_s)
    finally:
        subscriber.undeclare()
    with lock:
        names = [*PROCESSES] + sorted((alive | set(statuses)) - set(PROCESSES))
        stages = []
        for name in names:
            status = statuses.get(name)
            publishes = PROCESSES[name].publishes if name in PROCESSES else ()
            stages.append(StageReport(
                name=name, alive=name in alive, state=status.state if status else None,
                reason=status.reason if status else "", processing_ms=status.processing_ms if status else None,
                rates_hz={topic: counts[topic] / window_s for topic in publishes if topic in TOPICS},
            ))
        lat = np.asarray(latencies_ms)
        return PipelineReport(prefix=prefix, window_s=window_s, stages=stages,
                              latency_ms_p50=float(np.median(lat)) if lat.size else None,
                              latency_ms_max=float(lat.max()) if lat.size else None)


def run_router(*, session_config: zenoh.Config, stop_event: threading.Event,
               ready_event: threading.Event | None = None) -> None:
    """Zenoh's own router mode, in this process, until ``stop_event`` (SIGINT/SIGTERM in the CLI).

    Stages on other machines connect to it (``--connect tcp/<host>:7447``) and it routes between
    them; multicast scouting does not cross networks or Docker bridges, a router does.
    """
    session_config.insert_json5("mode", json.dumps("router"))
    with zenoh.open(session_config):
        if ready_event is not None:
            ready_event.set()
        stop_event.wait()
