"""The planner stage pairs each scan's ellipsoids with the robot state of that same scan."""

from __future__ import annotations

from schemas.messages import Ellipsoids, Header, Pose2D, RawPath, RobotState
from schemas.scenario import bundled_scenario
from services.planner.stage import PlannerStage

SCENARIO = bundled_scenario()


def state(seq: int) -> RobotState:
    return RobotState(header=Header(stamp_s=0.1 * seq, seq=seq), pose=Pose2D(x_m=0.0, y_m=0.0, theta_rad=0.785),
                      speed_mps=0.0, steering_rad=0.0, goal_index=0, goals_reached=0, done=False)


def ellipsoids(seq: int) -> Ellipsoids:
    return Ellipsoids(header=Header(stamp_s=0.1 * seq, seq=seq), scan_seq=seq, inflation_m=SCENARIO.inflation_m,
                      ellipsoids=[])


def test_ellipsoids_arriving_before_their_state_wait_for_it():
    planner = PlannerStage.from_scenario(SCENARIO)
    planner.process(topic="state", message=state(2), now_s=0.0)
    assert planner.process(topic="ellipsoids", message=ellipsoids(3), now_s=0.0) == []  # state 3 not here yet
    (topic, out), = planner.process(topic="state", message=state(3), now_s=0.0)
    assert topic == "raw_path" and isinstance(out, RawPath)
    assert out.scan_seq == 3 and out.status == "ok"


def test_state_first_answers_at_once():
    planner = PlannerStage.from_scenario(SCENARIO)
    planner.process(topic="state", message=state(5), now_s=0.0)
    (_, out), = planner.process(topic="ellipsoids", message=ellipsoids(5), now_s=0.0)
    assert out.scan_seq == 5
