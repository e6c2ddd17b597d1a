"""State that survives a stage's process: the sensing memory and the planner's plan, saved and reloaded by the
shell's checkpoint as it does around every input."""

from __future__ import annotations

import re

import numpy as np
import pytest

from schemas.messages import Ellipsoids, Header, Pose2D, RobotState, Scan
from schemas.scenario import bundled_scenario
from services.planner.stage import PlannerStage
from services.sensing.stage import SensingStage
from services.shell.checkpoint import Checkpoint, CheckpointError, write_atomic

SCENARIO = bundled_scenario()


def scan(seq: int, points: list[tuple[float, float]]) -> Scan:
    return Scan(header=Header(stamp_s=0.1 * seq, seq=seq), pose=Pose2D(x_m=0.0, y_m=0.0, theta_rad=0.0),
                points=points)


def started(core, state_dir):
    """`core` as the shell starts it with a state directory: its saved state restored, if any."""
    checkpoint = Checkpoint(state_dir=state_dir)
    checkpoint.restore(core)
    return core, checkpoint


def processed(core, checkpoint, **input_):
    """One input as the shell handles it: processed, then the state saved before the outputs go out."""
    outputs = core.process(**input_, now_s=0.0)
    checkpoint.save(core)
    return outputs


def test_a_restarted_sensing_stage_remembers_every_point_in_the_same_order(tmp_path):
    first, checkpoint = started(SensingStage.from_scenario(SCENARIO), tmp_path)
    processed(first, checkpoint, topic="scan", message=scan(0, [(3.0, 1.0), (3.02, 1.0), (3.3, 1.2)]))
    processed(first, checkpoint, topic="scan", message=scan(1, [(-2.0, 4.0), (3.0, 1.0)]))  # (3, 1) seen again
    (_, before), = processed(first, checkpoint, topic="scan", message=scan(2, [(4.0, -1.0)]))

    restarted, _ = started(SensingStage.from_scenario(SCENARIO), tmp_path)  # a new process: its memory starts empty
    np.testing.assert_array_equal(restarted.memory.points(), first.memory.points())
    (_, after), = restarted.process(topic="scan", message=scan(3, []), now_s=0.0)
    assert after.clusters == before.clusters  # the obstacles out of view are still there


def test_an_unreadable_sensing_checkpoint_stops_the_stage_rather_than_forgetting(tmp_path):
    write_atomic(tmp_path / "state", b"not numpy")
    with pytest.raises(CheckpointError, match=re.escape(str(tmp_path / "state"))):
        started(SensingStage.from_scenario(SCENARIO), tmp_path)


def _state(seq: int, *, x_m: float, y_m: float) -> RobotState:
    return RobotState(header=Header(stamp_s=0.1 * seq, seq=seq), pose=Pose2D(x_m=x_m, y_m=y_m, theta_rad=0.785),
                      speed_mps=0.5, steering_rad=0.0, goal_index=0, goals_reached=0, done=False)


def _empty_map(seq: int) -> Ellipsoids:
    return Ellipsoids(header=Header(stamp_s=0.1 * seq, seq=seq), scan_seq=seq, inflation_m=SCENARIO.inflation_m,
                      ellipsoids=[])


def _answer(planner: PlannerStage, checkpoint: Checkpoint, seq: int, *, x_m: float, y_m: float):
    processed(planner, checkpoint, topic="state", message=_state(seq, x_m=x_m, y_m=y_m))
    (_, raw), = processed(planner, checkpoint, topic="ellipsoids", message=_empty_map(seq))
    return raw


def test_a_restarted_planner_resumes_its_plan_under_the_same_id(tmp_path):
    first, checkpoint = started(PlannerStage.from_scenario(SCENARIO), tmp_path)
    made = _answer(first, checkpoint, 0, x_m=0.0, y_m=0.0)
    assert made.status == "ok"

    restarted, checkpoint = started(PlannerStage.from_scenario(SCENARIO), tmp_path)
    x_m, y_m = made.points[len(made.points) // 4]  # the car drove on a little
    resumed = _answer(restarted, checkpoint, 1, x_m=x_m, y_m=y_m)
    assert resumed.plan_id == made.plan_id  # the same plan, re-checked and re-published, not a new one
    assert resumed.points == made.points[-len(resumed.points):]

    fresh, checkpoint = started(PlannerStage.from_scenario(SCENARIO), tmp_path / "fresh")  # no checkpoint there
    assert _answer(fresh, checkpoint, 1, x_m=x_m, y_m=y_m).points != resumed.points  # a new plan from the car


def test_an_unreadable_plan_checkpoint_stops_the_stage(tmp_path):
    write_atomic(tmp_path / "state", b'{"plan": [[0, 0]], "goal_base": 0}')
    with pytest.raises(CheckpointError, match=re.escape(str(tmp_path / "state"))):
        started(PlannerStage.from_scenario(SCENARIO), tmp_path)
