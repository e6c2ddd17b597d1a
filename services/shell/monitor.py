"""The monitor's Zenoh shell: every key under the prefix into the rerun sink (``services.monitor.rerun``).

Its subscriber callback only enqueues (it never slows a publisher that uses congestion control BLOCK),
one worker thread decodes and logs, and a full queue drops samples and counts them.
"""

from __future__ import annotations

import logging
import queue
import threading
import time

import zenoh
from pydantic import BaseModel

from schemas.messages import DecodeError, StageStatus, decode
from schemas.wiring import MONITOR, alive_key, key, model_for, topic_of
from services.monitor.rerun import QUEUE_CAPACITY, MonitorCounts, RerunLogger, RerunTargets, open_recording

logger = logging.getLogger(__name__)


def _message_of(*, prefix: str, key_expr: str, payload: bytes, encoding: str) -> tuple[str | None, str | None,
                                                                                       BaseModel] | None:
    """(topic, stage, message) for a key of the pipeline; None for keys the monitor does not draw."""
    topic = topic_of(prefix, key_expr)
    if topic is not None and topic in MONITOR.subscribes:
        return topic, None, decode(model_for(topic), payload, encoding=encoding)
    status_head = f"{prefix}/status/"
    if key_expr.startswith(status_head):
        stage = key_expr[len(status_head):]
        return None, stage, decode(StageStatus, payload, encoding=encoding)
    return None


def run_monitor(
    *,
    session_config: zenoh.Config,
    prefix: str,
    targets: RerunTargets,
    stop_event: threading.Event,
    ready_event: threading.Event | None = None,
    drain_timeout_s: float = 2.0,
    recording_id: str | None = None,
) -> MonitorCounts:
    """Mirror every key under ``prefix`` into rerun until ``stop_event``; then drain and flush."""
    recording = open_recording(targets=targets, recording_id=recording_id)
    sink = RerunLogger(recording=recording)
    counts = MonitorCounts()
    inbox: queue.Queue[tuple[str, bytes, str]] = queue.Queue(maxsize=QUEUE_CAPACITY)

    def enqueue(sample: zenoh.Sample) -> None:
        if sample.kind != zenoh.SampleKind.PUT:
            return
        try:
            inbox.put_nowait((str(sample.key_expr), sample.payload.to_bytes(), str(sample.encoding)))
        except queue.Full:
            counts.dropped += 1

    def handle(item: tuple[str, bytes, str]) -> None:
        key_expr, payload, encoding = item
        try:
            decoded = _message_of(prefix=prefix, key_expr=key_expr, payload=payload, encoding=encoding)
        except DecodeError as error:
            if key_expr not in counts.rejected:
                logger.warning("monitor: ignoring %s: %s", key_expr, error)
            counts.rejected[key_expr] = counts.rejected.get(key_expr, 0) + 1
            return
        if decoded is None:
            return
        topic, stage, message = decoded
        sink.log(topic=topic, stage=stage, message=message)
        counts.logged[key_expr] = counts.logged.get(key_expr, 0) + 1

    with zenoh.open(session_config) as session:
        subscriber = session.declare_subscriber(f"{prefix}/**", enqueue)
        token = session.liveliness().declare_token(alive_key(prefix, MONITOR.name))
        # A sim that started before us already put the world once: ask its queryable for it.
        for reply in session.get(key(prefix, "world"), timeout=1.0):
            if reply.ok is not None:
                enqueue(reply.ok)
        logger.info("monitor running under %s", prefix)
        if ready_event is not None:
            ready_event.set()
        while not stop_event.is_set():
            try:
                handle(inbox.get(timeout=0.05))
            except queue.Empty:
                continue
        # Drain what already arrived (the sim's last messages), until quiet or the timeout.
        deadline = time.monotonic() + drain_timeout_s
        while time.monotonic() < deadline:
            try:
                handle(inbox.get(timeout=0.2))
            except queue.Empty:
                break
        token.undeclare()
        subscriber.undeclare()
    try:
        recording.flush(timeout_sec=10.0)
    except RuntimeError as error:  # a viewer that never came up or went away; the other sinks have their data
        logger.warning("monitor: %s", str(error).splitlines()[0])
    recording.disconnect()
    total = sum(counts.logged.values())
    logger.info("monitor logged %d messages (%d rejected, %d dropped)", total, sum(counts.rejected.values()),
                counts.dropped)
    return counts
