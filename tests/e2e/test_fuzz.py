"""Hostile payloads on every key of a live `cvxnav run`: no stage dies, every rejection is reported on
its status key, and the run still reaches its goals without a collision.

The test joins the run's Zenoh mesh (`cvxnav run --listen`) and hypothesis generates, for each key of
the wiring table: random bytes, truncated JSON, NaN/inf numbers, fields of the wrong shape, messages of
another schema, wrong encodings and schema versions, payloads above `max_payload_bytes`, and messages
that are well-formed but absurd (more hits than rays, hits out of range, a robot off the map, needle
ellipses, 10^4-point paths, answers to scans never sent). Each is published once (again if the stage's ring let a newer real message
supersede it), until the run ends; the stage that reads
the key (the sim for smooth_path; none for world, which only the monitor reads) must answer with an
error status naming the key, the next good message on the key is served as before.

Deliberately absent: well-formed messages with plausible content — a scan of an obstacle that is not
there, a path answering the current scan. No check on the content can tell them from the truth; that
defence is access control (docs/security.md), which keeps foreign publishers off the keys.
"""

from __future__ import annotations

import json
import re
import time
from collections import Counter
from collections.abc import Callable

import pytest
import zenoh
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from schemas.messages import (
    CircleMsg,
    ClusterMsg,
    Clusters,
    EllipsoidMsg,
    Ellipsoids,
    Goals,
    Header,
    Map,
    Message,
    Pose2D,
    RawPath,
    RobotState,
    Scan,
    SmoothPath,
    StageStatus,
    World,
    decode,
)
from schemas.scenario import bundled_scenario
from schemas.wiring import TOPICS, default_prefix, key, model_for, status_key, subscribers_of
from services.limits import DEFAULT_MAX_PAYLOAD_BYTES, MAX_ELLIPSES, MAX_GOALS, MAX_PATH_POINTS

pytestmark = pytest.mark.slow

SCENARIO = bundled_scenario()
PREFIX = default_prefix()
FUZZ_STAMP_S = 1e6  # every decodable fuzz message carries a stamp at or above this; real ones never do
OFF_MAP = 1e4
ATTEMPTS = 3  # a payload is published again when its status does not come (the ring keeps the newest)
STATUS_WAIT_S = 5.0


def header(i: int = 0, *, frame_id: str = "map") -> Header:
    return Header(stamp_s=FUZZ_STAMP_S + i, frame_id=frame_id, seq=10**6 + i)


def pose(x_m: float = 0.0) -> Pose2D:
    return Pose2D(x_m=x_m, y_m=0.0, theta_rad=0.0)


def needle() -> EllipsoidMsg:
    return EllipsoidMsg(A=((1e9, 0.0), (0.0, 1.0)), b=(-4e9, -4.0), group=0, cluster_id=0)


def state(**changes) -> RobotState:
    fields = dict(header=header(), pose=pose(), speed_mps=0.0, steering_rad=0.0, goal_index=0, goals_reached=0,
                  done=False)
    return RobotState(**(fields | changes))


def raw_path(**changes) -> RawPath:
    fields = dict(header=header(), scan_seq=10**6, status="ok", goal_index=0, points=[(0.0, 0.0), (1.0, 1.0)],
                  ellipsoids=[])
    return RawPath(**(fields | changes))


# Well-formed but absurd: every one must be rejected by the stage that reads its key.
ABSURD: dict[str, list[Message]] = {
    "scan": [
        Scan(header=header(), pose=pose(OFF_MAP), points=[(OFF_MAP + 1.0, 0.0)]),
        Scan(header=header(), pose=pose(), points=[(1.0, 1.0)] * (SCENARIO.sensor.rays + 1)),
        Scan(header=header(), pose=pose(), points=[(0.5, 0.5), (60.0, 0.0)]),
        Scan(header=header(frame_id="odom"), pose=pose(), points=[(1.0, 1.0)]),
    ],
    "state": [state(pose=pose(OFF_MAP)), state(goals_reached=99), state(goal_index=7)],
    "clusters": [
        Clusters(header=header(), scan_seq=10**6, clusters=[ClusterMsg(cluster_id=0, points=[(1e9, 1e9)])]),
        Clusters(header=header(), scan_seq=10**6,
                 clusters=[ClusterMsg(cluster_id=k, points=[(OFF_MAP, k)]) for k in range(5)]),
    ],
    "ellipsoids": [
        Ellipsoids(header=header(), scan_seq=10**6, inflation_m=0.65, ellipsoids=[needle()]),
        Ellipsoids(header=header(), scan_seq=10**6, inflation_m=0.65,
                   ellipsoids=[EllipsoidMsg(A=((1.0, 0.0), (0.0, 1.0)), b=(-3.0, -3.0), group=0, cluster_id=0)]
                   * (MAX_ELLIPSES + 1)),
    ],
    "raw_path": [
        raw_path(points=[(0.0, 0.0), (OFF_MAP, 0.0)]),
        raw_path(points=[(0.0, 1e-3 * k) for k in range(MAX_PATH_POINTS + 1)]),
        raw_path(goal_index=9),
        raw_path(ellipsoids=[needle()]),
    ],
    "smooth_path": [
        SmoothPath(header=header(), scan_seq=10**6, status="ok", goal_index=0, points=[(0.0, 0.0), (OFF_MAP, 0.0)],
                   max_curvature=0.0, min_level=2.0),
        SmoothPath(header=header(), scan_seq=10**7, status="no_path", goal_index=0, points=[], max_curvature=0.0,
                   min_level=0.0, reason="fuzz"),
    ],
    "world": [
        World(header=header(), scenario="fuzz", bounds_min=(0.0, 0.0), bounds_max=(1.0, 1.0), robot_width_m=0.3,
              robot_length_m=0.6, start=pose(), goals=[(OFF_MAP, 0.0)], goal_tolerance_m=0.3,
              polygons=[[(1e9, 1e9)]], circles=[CircleMsg(center=(0.0, 0.0), radius_m=1e9)]),
    ],
    "goals": [
        Goals(header=header(), goals=[(1.0, 1.0), (OFF_MAP, 0.0)]),
        Goals(header=header(), goals=[(1.0, 1.0)] * (MAX_GOALS + 1)),
    ],
    "map": [
        Map(header=header(), width=2, height=2, resolution_m=0.5, origin=pose(OFF_MAP), cells=Map.pack_cells(bytes(4))),
    ],
}
assert set(ABSURD) == set(TOPICS)

NUMBER = re.compile(rb"-?\d+(?:\.\d+)?(?:[eE][-+]?\d+)?")
BAD_SHAPES = ([[1.0, 2.0, 3.0]], [[[]]], {"x": 1}, None, "x" * 3, [[1.0, 2.0]] * 3 + [1.0])
BAD_ENCODINGS = ("text/plain", "image/png", "application/cbor", "application/json;cvxnav.Nope/1")
Payload = tuple[str, bytes, str | None]  # kind, bytes, Zenoh encoding (None: the default)


def _leaves(doc, path=()) -> list[tuple]:
    """Paths to every value of a JSON document (containers included)."""
    out = [path] if path else []
    if isinstance(doc, dict):
        for name, value in doc.items():
            out += _leaves(value, path + (name,))
    elif isinstance(doc, list):
        for index, value in enumerate(doc[:3]):
            out += _leaves(value, path + (index,))
    return out


def _replaced(doc, path: tuple, value):
    if not path:
        return value
    head, rest = path[0], path[1:]
    copy = dict(doc) if isinstance(doc, dict) else list(doc)
    copy[head] = _replaced(doc[head], rest, value)
    return copy


@st.composite
def payloads(draw, topic: str) -> Payload:
    """One hostile payload for `topic`'s key."""
    template = draw(st.sampled_from(ABSURD[topic]))
    raw = template.model_dump_json().encode()
    encoding = model_for(topic).encoding()
    kind = draw(st.sampled_from(["absurd", "bytes", "truncated", "non-finite", "shape", "other-schema",
                                 "other-schema-unlabelled", "encoding", "newer-version", "oversize"]))
    if kind == "absurd":
        return kind, raw, encoding
    if kind == "bytes":
        return kind, draw(st.binary(max_size=300)), draw(st.sampled_from([encoding, None]))
    if kind == "truncated":
        return kind, raw[: draw(st.integers(0, len(raw) - 1))], encoding
    if kind == "non-finite":
        numbers = list(NUMBER.finditer(raw))
        hit = numbers[draw(st.integers(0, len(numbers) - 1))]
        token = draw(st.sampled_from([b"NaN", b"Infinity", b"-Infinity", b"1e999"]))
        return kind, raw[: hit.start()] + token + raw[hit.end():], encoding
    if kind == "shape":
        doc = json.loads(raw)
        path = draw(st.sampled_from(_leaves(doc)))
        return kind, json.dumps(_replaced(doc, path, draw(st.sampled_from(BAD_SHAPES)))).encode(), encoding
    if kind in ("other-schema", "other-schema-unlabelled"):
        other = draw(st.sampled_from([t for t in TOPICS if t != topic and model_for(t) is not model_for(topic)]))
        message = ABSURD[other][0]
        return kind, message.model_dump_json().encode(), (message.encoding() if kind == "other-schema" else None)
    if kind == "encoding":
        return kind, raw, draw(st.sampled_from(BAD_ENCODINGS))
    if kind == "newer-version":
        model = model_for(topic)
        return kind, raw, f"application/json;{model.SCHEMA}/{model.VERSION + 1}"
    size = draw(st.integers(DEFAULT_MAX_PAYLOAD_BYTES + 1, 3 * DEFAULT_MAX_PAYLOAD_BYTES))
    return kind, (b"[" + b"[1.0,2.0]," * (size // 10) + b"[1.0,2.0]]")[:max(size, 1)], encoding


def readers(topic: str, kind: str = "", data: bytes = b"") -> tuple[str, ...]:
    """The stages that must report a rejected payload on `topic` (the sim reads smooth_path itself). A
    state absurd only in its goal counts is the planner's to judge: the ellipsoid stage reads only the pose."""
    if topic == "state" and kind == "absurd" and RobotState.model_validate_json(data).pose == pose():
        return ("planner",)
    return ("sim",) if topic == "smooth_path" else subscribers_of(topic)


class Fuzzer:
    """Publishes one payload at a time into the live run and waits for each reader's error status."""

    def __init__(self, session: zenoh.Session, *, running: Callable[[], bool]) -> None:
        self.session = session
        self.running = running  # a payload sent as the run ends may find no stage left to answer
        self.statuses = session.declare_subscriber(status_key(PREFIX, "*"), zenoh.handlers.RingChannel(4096))
        self.published: Counter[str] = Counter()
        self.kinds: Counter[str] = Counter()
        self.reported: Counter[tuple[str, str]] = Counter()  # (stage, key) -> fuzz rejections seen
        self.unreported: list[str] = []

    def _fuzz_rejections(self) -> list[StageStatus]:
        out = []
        while (sample := self.statuses.try_recv()) is not None:
            status = decode(StageStatus, sample.payload.to_bytes(), encoding=str(sample.encoding))
            if status.state == "error" and (status.input_stamp_s is None or status.input_stamp_s >= FUZZ_STAMP_S):
                out.append(status)
        return out

    def send(self, topic: str, payload: Payload) -> None:
        kind, data, encoding = payload
        target = key(PREFIX, topic)
        waiting = set(readers(topic, kind, data))
        self._fuzz_rejections()  # forget stale ones
        for _ in range(ATTEMPTS):
            self.session.put(target, data, encoding=zenoh.Encoding(encoding) if encoding else None)
            self.published[topic] += 1
            self.kinds[kind] += 1
            deadline = time.monotonic() + STATUS_WAIT_S
            while waiting and time.monotonic() < deadline:
                for status in self._fuzz_rejections():
                    if status.input_key == target and status.stage in waiting:
                        assert "\n" not in status.reason and status.reason
                        waiting.discard(status.stage)
                        self.reported[(status.stage, topic)] += 1
                time.sleep(0.002)
            if not waiting:
                return
        if self.running():
            self.unreported.append(f"{topic}/{kind}: no error status from {sorted(waiting)}")


@pytest.fixture(scope="module")
def fuzzed(tmp_path_factory, live_run):
    cwd = tmp_path_factory.mktemp("fuzz")
    # Realtime: the run lasts its sim time (about 25 s) however fast the machine plans, time for every example.
    with live_run("--out", "run.json", "--realtime", cwd=cwd) as run:
        pids = run.stage_pids()
        assert set(pids) == {"sensing", "ellipsoids", "planner", "smoother", "sim"}
        yield run, Fuzzer(run.session, running=lambda: run.process.poll() is None), pids


@settings(max_examples=140, deadline=None, database=None, derandomize=True,
          suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow,
                                 HealthCheck.data_too_large])
@given(data=st.data())
def test_hostile_payloads_are_rejected_and_reported(fuzzed, data):
    """Each example is sent while the run is in progress; those drawn after it ended are not sent.

    Every example draws its payload either way: hypothesis requires the same draws on a replay.
    """
    run, fuzzer, pids = fuzzed
    topic = data.draw(st.sampled_from(sorted(TOPICS)))
    payload = data.draw(payloads(topic))
    if run.process.poll() is not None:
        return
    assert set(run.stage_pids().values()) <= set(pids.values())
    fuzzer.send(topic, payload)


def test_no_stage_died_every_rejection_was_reported_and_the_run_reached_its_goals(fuzzed):
    from schemas.files import RunFile

    run, fuzzer, pids = fuzzed
    if run.process.poll() is None:  # still running (each example checked the pids while it was)
        assert run.stage_pids() == pids, "a stage process died or was replaced"
    print(f"\nfuzz: published {dict(fuzzer.published)}; kinds {dict(fuzzer.kinds)}; "
          f"rejections reported {dict(fuzzer.reported)}")
    assert fuzzer.unreported == []
    assert set(fuzzer.published) == set(TOPICS) and sum(fuzzer.published.values()) >= 50
    for topic in TOPICS:
        for stage in readers(topic):
            assert fuzzer.reported[(stage, topic)] >= 1
    assert run.wait(timeout_s=300.0) == 0, (run.cwd / "run.log").read_text()[-2000:]
    assert "stage restarts 0," in (run.cwd / "run.log").read_text()  # the supervisor restarted no stage
    result = RunFile.read(run.cwd / "run.json")
    assert result.status == "reached" and result.goals_reached == len(SCENARIO.goals)
    assert result.min_clearance > 0.0
