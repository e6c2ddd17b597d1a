"""The attacker of issue 27, for the tests that replay it: forged answers to every scan the car sends.

The moment a scan is heard: an empty ellipse set answering it, a path (plan `FORGED_PLAN`) into the
nearest thing the car sees or off the map, in turn, and, for the first `statuses` scans, an error status
on the planner's key naming the planner. `forge` builds them from a scan (tests/unit/test_sim_stage.py
hands them to the stage cores in one process); `Attacker` puts them on a live run's keys from a Zenoh
session (tests/e2e/test_attacks.py, tests/e2e/test_secure_run.py).
"""

from __future__ import annotations

import threading

import numpy as np
import zenoh
from pydantic import BaseModel

from schemas.messages import DecodeError, Ellipsoids, Header, Scan, SmoothPath, StageStatus, decode
from schemas.wiring import key, status_key

FORGED_PLAN = 999_999
INFLATION_M = 0.65  # what an ellipse set claims to be grown by (the paper's car; the sim does not check it)


def through_the_nearest_wall(scan: Scan) -> list[tuple[float, float]]:
    """From the car to the hit nearest it ahead and 1 m beyond: into what it sees (straight on with none)."""
    pose = np.array([scan.pose.x_m, scan.pose.y_m])
    heading = np.array([np.cos(scan.pose.theta_rad), np.sin(scan.pose.theta_rad)])
    hits = np.array(scan.points, dtype=float).reshape(-1, 2)
    ahead = hits[(hits - pose) @ heading > 0.3]
    if not len(ahead):
        return [tuple(pose), tuple(pose + 5.0 * heading)]
    hit = ahead[np.argmin(np.linalg.norm(ahead - pose, axis=1))]
    beyond = hit + (hit - pose) / np.linalg.norm(hit - pose)
    return [tuple(pose + 0.05 * k * (beyond - pose)) for k in range(21)]


def off_the_map(scan: Scan) -> list[tuple[float, float]]:
    """A metre along the heading, then 60 m south: off any of the test maps."""
    pose = np.array([scan.pose.x_m, scan.pose.y_m])
    heading = np.array([np.cos(scan.pose.theta_rad), np.sin(scan.pose.theta_rad)])
    return [tuple(pose), tuple(pose + heading), tuple(pose + heading + (0.0, -60.0))]


def forged_path(scan: Scan) -> SmoothPath:
    route = (through_the_nearest_wall, off_the_map)[scan.header.seq % 2](scan)
    return SmoothPath(header=Header(stamp_s=scan.header.stamp_s, seq=0), scan_seq=scan.header.seq, status="ok",
                      goal_index=0, points=[tuple(map(float, p)) for p in route], max_curvature=0.0, min_level=2.0,
                      plan_id=FORGED_PLAN)


def empty_ellipsoids(scan: Scan) -> Ellipsoids:
    return Ellipsoids(header=Header(stamp_s=scan.header.stamp_s, seq=0), scan_seq=scan.header.seq,
                      inflation_m=INFLATION_M, ellipsoids=[])


def error_status(*, stage: str, stamp_s: float, reason: str = "no path: every route is blocked") -> StageStatus:
    return StageStatus(header=Header(stamp_s=stamp_s, seq=0), stage=stage, state="error", reason=reason,
                       input_key="forged", input_stamp_s=stamp_s, processing_ms=1.0)


def forge(scan: Scan, *, with_status: bool) -> tuple[list[tuple[str, BaseModel]], list[tuple[str, StageStatus]]]:
    """The forged messages answering `scan` (topic, message), and the forged statuses (stage key, status)."""
    messages = [("ellipsoids", empty_ellipsoids(scan)), ("smooth_path", forged_path(scan))]
    statuses = [("planner", error_status(stage="planner", stamp_s=scan.header.stamp_s))] if with_status else []
    return messages, statuses


class Attacker:
    """Hears a live run's scans through `session` and answers each with `forge`'s messages on their keys."""

    def __init__(self, session: zenoh.Session, *, prefix: str, statuses: int = 20) -> None:
        self.session = session
        self.prefix = prefix
        self.statuses_left = statuses
        self.scans = 0  # answered
        self.lock = threading.Lock()
        self.subscriber = session.declare_subscriber(key(prefix, "scan"), self._on_scan)

    def _on_scan(self, sample: zenoh.Sample) -> None:
        try:
            scan = decode(Scan, sample.payload.to_bytes())
        except DecodeError:
            return
        with self.lock:
            with_status = self.statuses_left > 0
            self.statuses_left -= with_status
            self.scans += 1
        messages, statuses = forge(scan, with_status=with_status)
        for topic, message in messages:
            self.session.put(key(self.prefix, topic), message.model_dump_json())
        for stage, status in statuses:
            self.session.put(status_key(self.prefix, stage), status.model_dump_json())
