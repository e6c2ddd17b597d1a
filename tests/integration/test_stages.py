"""Each real stage core over real Zenoh on loopback: it answers a real message on its wired key with
the wired model, and a malformed payload yields an error status naming the problem while the stage
keeps serving the next good message."""

from __future__ import annotations

import json
import threading
import time
import uuid
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass

import numpy as np
import pytest
import zenoh
from pydantic import BaseModel

from cvxnav.supervisor import free_ports
from schemas.messages import (
    ClusterMsg,
    Clusters,
    Ellipsoids,
    Goals,
    Header,
    Message,
    Pose2D,
    RawPath,
    RobotState,
    Scan,
    SmoothPath,
    StageStatus,
    decode,
)
from schemas.scenario import bundled_scenario
from schemas.wiring import STAGES, key, model_for, status_key
from services.ellipsoids.stage import EllipsoidsStage
from services.planner.stage import PlannerStage
from services.sensing.stage import SensingStage
from services.shell.stage import run_stage
from services.shell.zenoh_config import build_zenoh_config
from services.smoother.stage import SmootherStage

WAIT_S = 10.0
SCENARIO = bundled_scenario()
HEADING = float(SCENARIO.start.theta)


def header(seq: int) -> Header:
    return Header(stamp_s=0.1 * seq, seq=seq)


def wall_points() -> list[tuple[float, float]]:
    """Hits on a short wall across the robot's way, 3 m ahead (beyond the start's inflation)."""
    return [(3.0 + 0.05 * k, 1.0 - 0.05 * k) for k in range(21)]


def scan(seq: int) -> Scan:
    return Scan(header=header(seq), pose=Pose2D(x_m=0.0, y_m=0.0, theta_rad=HEADING), points=wall_points())


def clusters(seq: int) -> Clusters:
    return Clusters(header=header(seq), scan_seq=seq, clusters=[ClusterMsg(cluster_id=0, points=wall_points())])


def ellipsoids(seq: int) -> Ellipsoids:
    (_, out), = EllipsoidsStage.from_scenario(SCENARIO).process(topic="clusters", message=clusters(seq), now_s=0.0)
    return out


def state(seq: int) -> RobotState:
    return RobotState(header=header(seq), pose=Pose2D(x_m=0.0, y_m=0.0, theta_rad=HEADING), speed_mps=0.0,
                      steering_rad=0.0, goal_index=0, goals_reached=0, done=False)


def raw_path(seq: int) -> RawPath:
    planner = PlannerStage.from_scenario(SCENARIO)
    planner.process(topic="state", message=state(seq), now_s=0.0)
    (_, out), = planner.process(topic="ellipsoids", message=ellipsoids(seq), now_s=0.0)
    assert out.status == "ok"
    return out


@dataclass
class Case:
    """One stage: its core, the inputs that make it answer, and the model it must answer with."""

    stage: str
    make_core: Callable[[], object]
    inputs: Callable[[int], list[tuple[str, Message]]]  # (topic, message) in publication order
    output: type[Message]


CASES = {
    "sensing": Case("sensing", lambda: SensingStage.from_scenario(SCENARIO), lambda s: [("scan", scan(s))], Clusters),
    "ellipsoids": Case("ellipsoids", lambda: EllipsoidsStage.from_scenario(SCENARIO),
                       lambda s: [("clusters", clusters(s))], Ellipsoids),
    "planner": Case("planner", lambda: PlannerStage.from_scenario(SCENARIO),
                    lambda s: [("state", state(s)), ("ellipsoids", ellipsoids(s))], RawPath),
    "smoother": Case("smoother", lambda: SmootherStage.from_scenario(SCENARIO), lambda s: [("raw_path", raw_path(s))],
                     SmoothPath),
}


@dataclass
class Harness:
    case: Case
    session: zenoh.Session
    prefix: str
    publishers: dict[str, zenoh.Publisher]
    outputs: zenoh.Subscriber
    statuses: zenoh.Subscriber
    next_seq: int = 0

    def answer(self, *, timeout_s: float = WAIT_S) -> Message:
        """Publish the case's good inputs (a fresh seq) and return the stage's answer for that seq."""
        self.next_seq += 1
        seq = self.next_seq
        deadline = time.monotonic() + timeout_s
        for topic, message in self.case.inputs(seq):
            self.publishers[topic].put(message.model_dump_json())
            time.sleep(0.05)  # the planner must have the state before the ellipsoids
        while time.monotonic() < deadline:
            sample = self.outputs.try_recv()
            if sample is None:
                time.sleep(0.005)
                continue
            assert str(sample.key_expr) == key(self.prefix, STAGES[self.case.stage].publishes[0])
            assert str(sample.encoding) == self.case.output.encoding()
            message = decode(self.case.output, sample.payload.to_bytes(), encoding=str(sample.encoding))
            if message.scan_seq == seq:
                return message
        pytest.fail(f"{self.case.stage} did not answer seq {seq} within {timeout_s} s")

    def error_status(self, *, timeout_s: float = WAIT_S) -> StageStatus:
        return self.status(lambda status: status.state == "error", what="error", timeout_s=timeout_s)

    def status(self, wanted: Callable[[StageStatus], bool], *, what: str, timeout_s: float = WAIT_S) -> StageStatus:
        """The first status `wanted` accepts."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            sample = self.statuses.try_recv()
            if sample is None:
                time.sleep(0.005)
                continue
            status = decode(StageStatus, sample.payload.to_bytes(), encoding=str(sample.encoding))
            if wanted(status):
                return status
        pytest.fail(f"{self.case.stage} reported no {what} within {timeout_s} s")

    def drain(self) -> None:
        for subscriber in (self.outputs, self.statuses):
            while subscriber.try_recv() is not None:
                pass


@contextmanager
def running(case: Case) -> Iterator[Harness]:
    endpoint = f"tcp/127.0.0.1:{free_ports(1)[0]}"
    prefix = f"cvxnav/test-{uuid.uuid4().hex[:8]}"
    stop, ready = threading.Event(), threading.Event()
    thread = threading.Thread(
        target=run_stage, daemon=True,
        kwargs=dict(stage=case.stage, core=case.make_core(), session_config=build_zenoh_config(listen=[endpoint]),
                    prefix=prefix, stop_event=stop, ready_event=ready),
    )
    thread.start()
    try:
        assert ready.wait(WAIT_S)
        with zenoh.open(build_zenoh_config(connect=[endpoint])) as session:
            spec = STAGES[case.stage]
            harness = Harness(
                case=case, session=session, prefix=prefix,
                publishers={
                    topic: session.declare_publisher(key(prefix, topic), encoding=zenoh.Encoding(model_for(topic).encoding()),
                                                     congestion_control=zenoh.CongestionControl.BLOCK)
                    for topic in spec.subscribes
                },
                outputs=session.declare_subscriber(key(prefix, spec.publishes[0])),
                statuses=session.declare_subscriber(status_key(prefix, case.stage)),
            )
            _warm_up(harness)
            yield harness
    finally:
        stop.set()
        thread.join(WAIT_S)
    assert not thread.is_alive()


def _warm_up(harness: Harness) -> None:
    """Declarations propagate asynchronously: re-publish until the first answer comes back."""
    for _ in range(20):
        try:
            harness.answer(timeout_s=1.0)
            return
        except pytest.fail.Exception:
            continue
    pytest.fail("stage never answered")


@pytest.fixture(scope="module")
def stage(request) -> Iterator[Harness]:
    """The stage named by the test's (indirect) parameter, kept running for the module."""
    with running(CASES[request.param]) as harness:
        yield harness


@pytest.mark.parametrize("stage", list(CASES), indirect=True)
def test_stage_answers_on_its_key_with_its_model(stage):
    stage.drain()
    answer = stage.answer()
    assert isinstance(answer, stage.case.output)
    if isinstance(answer, Clusters):
        assert len(answer.clusters) == 1 and len(answer.clusters[0].points) == len(wall_points())
    if isinstance(answer, Ellipsoids):
        assert answer.inflation_m == pytest.approx(SCENARIO.inflation_m)
        assert answer.ellipsoids
    if isinstance(answer, (RawPath, SmoothPath)):
        assert answer.status == "ok"
        assert np.linalg.norm(np.array(answer.points[-1]) - SCENARIO.goals_array[-1]) <= SCENARIO.goal_tolerance
    if isinstance(answer, SmoothPath):
        assert answer.min_level > 1.0
        assert answer.max_curvature <= SCENARIO.max_curvature


def _with_nan(message: BaseModel) -> bytes:
    """The message's JSON with the first float in its header replaced by NaN."""
    doc = json.loads(message.model_dump_json())
    doc["header"]["stamp_s"] = float("nan")
    return json.dumps(doc).encode()


def _bad_inputs(case: Case) -> dict[str, tuple[str, bytes, str | None, str]]:
    topic, good = case.inputs(0)[-1]
    model = model_for(topic)
    other = Scan if model is not Scan else Clusters
    bad = {
        "bad-json": (topic, b'{"header": {', model.encoding(), "invalid JSON"),
        "wrong-schema": (topic, good.model_dump_json().encode(), other.encoding(), "wrong schema"),
        "nan": (topic, _with_nan(good), model.encoding(), "header.stamp_s: Input should be a finite number"),
    }
    if case.stage == "ellipsoids":
        empty = json.loads(good.model_dump_json())
        empty["clusters"][0]["points"] = []
        bad["empty-cluster"] = (topic, json.dumps(empty).encode(), model.encoding(), "clusters.0.points")
    return bad


BAD = [(name, label) for name, case in CASES.items() for label in _bad_inputs(case)]


@pytest.mark.parametrize(("stage", "label"), BAD, indirect=["stage"], ids=[f"{n}-{label}" for n, label in BAD])
def test_malformed_input_reports_error_and_stage_serves_the_next(stage, label):
    topic, payload, encoding, reason = _bad_inputs(stage.case)[label]
    stage.drain()
    stage.publishers[topic].put(payload, encoding=zenoh.Encoding(encoding))
    status = stage.error_status()
    assert reason in status.reason
    assert status.input_key == key(stage.prefix, topic)
    assert "\n" not in status.reason
    assert isinstance(stage.answer(), stage.case.output)


def test_smoother_never_publishes_a_curve_that_fails_verification():
    """A raw path straight through an obstacle's ellipse: rejected with the reason, nothing published."""
    with running(CASES["smoother"]) as harness:
        harness.drain()
        good = raw_path(999)
        through = good.model_copy(update=dict(points=[(0.0, 0.0), (1.5, 0.3), (3.5, 0.5), (10.0, 10.0), (15.0, 15.0)],
                                              scan_seq=999))
        harness.publishers["raw_path"].put(through.model_dump_json())
        status = harness.error_status()
        assert "smoothed path rejected" in status.reason and "enters an ellipse" in status.reason
        time.sleep(0.2)
        assert harness.outputs.try_recv() is None
        assert isinstance(harness.answer(), SmoothPath)


def test_a_planner_past_its_budget_answers_while_it_replans_and_its_ok_status_says_why():
    """A planner whose budget no replan meets answers the scan that needs one with no_path while the
    replan runs in the background, and the shell puts the core's reason on that input's ok status; a
    later scan gets the replan's plan (its status: answered over the budget). New goals start another
    replan, and the stage stops with it running (`running` joins the stage's thread)."""
    from dataclasses import replace

    from services.planner.stage import PlannerConfig

    config = replace(PlannerConfig.from_scenario(SCENARIO), budget_s=1e-9)
    case = Case("planner", lambda: PlannerStage(config=config), CASES["planner"].inputs, RawPath)
    with running(case) as harness:
        # The warm-up's answers started a replan, but their statuses may have gone before the harness's
        # subscription reached the stage: goals (the scenario's own) drop the plan and start another,
        # until a scan is answered while it runs (one may finish before the scan's second input).
        for _ in range(20):
            harness.publishers["goals"].put(Goals(header=header(0), goals=[
                (float(x), float(y)) for x, y in SCENARIO.goals_array]).model_dump_json())
            time.sleep(0.2)
            harness.drain()
            first = harness.answer()
            if first.status == "no_path":
                break
        assert first.status == "no_path" and first.reason.startswith("replanning: no verified path")
        status = harness.status(lambda status: status.reason.startswith("replanning: no verified path"),
                                what="status of an answer while replanning")
        assert status.state == "ok" and status.input_key == key(harness.prefix, "ellipsoids")
        for _ in range(50):
            answer = harness.answer()
            if answer.status == "ok":
                break
            assert answer.reason.startswith("replanning:") and answer.points == []
        assert answer.status == "ok" and len(answer.points) >= 2
        harness.status(lambda status: status.reason.startswith("deadline: answered in")
                       and status.reason.endswith("over the 0 ms budget"), what="status of the late answer")
        goals = Goals(header=header(0), goals=[(float(x), float(y)) for x, y in SCENARIO.goals_array[::-1]])
        harness.publishers["goals"].put(goals.model_dump_json())
        time.sleep(0.2)
        replanning = harness.answer()
        assert replanning.status == "no_path" and replanning.reason.startswith("replanning:")
