"""`cvxnav replay` feeds a stage its inputs in the order the stage handled them (its statuses name each
one), which on a loaded machine is not the order the recorder received them in."""

from __future__ import annotations

from cvxnav.record import Recorded, Recording
from cvxnav.replay import handling_order, replay_stage
from schemas.messages import Ellipsoids, Header, Message, Pose2D, RobotState, StageStatus
from schemas.scenario import bundled_scenario
from schemas.wiring import key, status_key, topic_of
from services.planner.stage import PlannerStage

SCENARIO = bundled_scenario()
PREFIX = "cvxnav/test"


def state(seq: int, x_m: float) -> RobotState:
    return RobotState(header=Header(stamp_s=0.1 * seq, seq=seq), pose=Pose2D(x_m=x_m, y_m=x_m, theta_rad=0.785),
                      speed_mps=0.5, steering_rad=0.0, goal_index=0, goals_reached=0, done=False)


def ellipsoids(seq: int) -> Ellipsoids:
    return Ellipsoids(header=Header(stamp_s=0.1 * seq, seq=seq), scan_seq=seq, inflation_m=SCENARIO.inflation_m,
                      ellipsoids=[])


def recorded(topic_key: str, message: Message, t: int) -> Recorded:
    return Recorded(key=topic_key, encoding=message.encoding(), payload=message.to_json_bytes(), log_time_ns=t)


def test_replay_follows_the_stages_handling_order_not_the_recorders():
    """Live, the planner handled scan 0's ellipsoids before the state of scan 1 existed; the recorder got
    that state first. Fed in receive order, the core would plan scan 0 from scan 1's pose."""
    inputs = [("state", state(0, 0.0)), ("ellipsoids", ellipsoids(0)), ("state", state(1, 0.3)),
              ("ellipsoids", ellipsoids(1))]
    live = PlannerStage.from_scenario(SCENARIO)
    statuses, outputs = [], []
    for seq, (topic, message) in enumerate(inputs):
        outputs += [recorded(key(PREFIX, out_topic), out, seq) for out_topic, out in
                    live.process(topic=topic, message=message, now_s=0.0)]
        statuses.append(recorded(status_key(PREFIX, "planner"), StageStatus(
            header=Header(stamp_s=message.header.stamp_s, seq=seq), stage="planner", state="ok",
            input_key=key(PREFIX, topic), input_stamp_s=message.header.stamp_s, processing_ms=1.0), seq))
    assert [topic_of(PREFIX, m.key) for m in outputs] == ["raw_path", "raw_path"]

    received = [recorded(key(PREFIX, topic), message, k) for k, (topic, message) in enumerate(inputs)]
    received[1], received[2] = received[2], received[1]  # state 1 reached the recorder before ellipsoids 0
    recording = Recording(prefix=PREFIX, scenario=SCENARIO, messages=[*received, *outputs, *statuses])

    order = handling_order(recording, stage="planner", inputs={key(PREFIX, t): t for t in ("state", "ellipsoids")})
    assert [item.payload for item, _ in order] == [message.to_json_bytes() for _, message in inputs]
    assert replay_stage(recording, stage="planner").reproduced

    # Without the statuses there is nothing to go by but the receive order, and scan 0 is planned
    # from where the car was at scan 1.
    report = replay_stage(Recording(prefix=PREFIX, scenario=SCENARIO, messages=[*received, *outputs]), stage="planner")
    assert not report.reproduced
    assert report.differences[0].startswith("raw_path for scan 0")
