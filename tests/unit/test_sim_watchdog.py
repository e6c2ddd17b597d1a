"""The sim's watchdogs: it brakes when a stage's token disappears, never drives a path through a known
obstacle, backs out of a dead end along its tracks, and gives up rather than wait for ever."""

from __future__ import annotations

import json
import math
import re
from dataclasses import replace

import numpy as np
import pytest
from shapely.geometry import LineString, Point

from schemas.messages import Ellipsoids, Header, SmoothPath
from schemas.scenario import Scenario, bundled_scenario
from services.convert import ellipse_to_msg
from services.drive.guard import PathGuard
from services.geometry import Ellipse
from services.sensing.stage import SensingStage
from sim.core import SimConfig, SimCore

PAPER = bundled_scenario()


def open_field() -> Scenario:
    """The paper's car heading east on an empty map, its goal 20 m ahead."""
    doc = json.loads(PAPER.model_dump_json())
    doc.update(name="open", start={"x": 0.0, "y": 0.0, "theta": 0.0}, goals=[[20.0, 0.0]], obstacles=[],
               bounds={"min": [-5.0, -10.0], "max": [25.0, 10.0]})
    return Scenario.model_validate(doc)


def path(core: SimCore, points, *, plan_id: int = 1) -> SmoothPath:
    """An answer to the newest scan the core has sent."""
    return SmoothPath(header=Header(stamp_s=core.t_s, seq=0), scan_seq=core.scan_seq, status="ok", goal_index=0,
                      points=[tuple(p) for p in points], max_curvature=0.0, min_level=2.0, plan_id=plan_id)


def straight(x0: float = 0.0, x1: float = 20.0, *, y: float = 0.0) -> np.ndarray:
    xs = np.linspace(x0, x1, 401)
    return np.column_stack([xs, np.full_like(xs, y)])


def grown(*, center, radius: float, scan_seq: int = 0) -> Ellipsoids:
    msg = ellipse_to_msg(Ellipse.circle(center=center, radius=radius), group=0, cluster_id=7)
    return Ellipsoids(header=Header(stamp_s=0.0, seq=0), scan_seq=scan_seq, inflation_m=PAPER.inflation_m,
                      ellipsoids=[msg])


def drive(core: SimCore, steps: int) -> list[float]:
    speeds = []
    for _ in range(steps):
        core.advance()
        speeds.append(core.state.speed_mps)
    return speeds


def test_a_lost_planner_token_brakes_the_car_to_rest_within_its_limits_until_a_fresh_plan():
    core = SimCore(scenario=open_field(), config=SimConfig(stale_after_s=100.0))
    core.sense()
    assert core.accept(path(core, straight())) is None
    cruising = drive(core, 40)[-1]
    assert cruising > 0.5

    core.stage_lost("planner")
    late = path(core, straight(core.state.x_m), plan_id=2)  # in flight when the stage died
    braking = [cruising] + drive(core, 30)
    dv = np.diff(braking)
    decel = core.limits.max_decel_mps2
    assert np.all(dv <= 1e-12) and np.all(dv >= -decel * core.config.dt_s - 1e-9)  # slowing, within the limit
    steps_to_stop = math.ceil(cruising / (decel * core.config.dt_s))
    assert max(braking[steps_to_stop + 1:]) == 0.0

    assert core.accept(late) is None  # an answer while the stage is down is not driven on
    assert max(drive(core, 10)) == 0.0
    core.stage_back("planner")
    assert core.accept(late) is None  # nor an answer to a scan sent before the loss
    assert max(drive(core, 10)) == 0.0

    core.sense()
    assert core.accept(path(core, straight(core.state.x_m), plan_id=3)) is None  # fresh: answers a new scan
    assert drive(core, 20)[-1] > 0.3


def test_scan_hits_taken_while_sensing_is_down_reach_it_when_it_is_back():
    doc = json.loads(open_field().model_dump_json())
    doc["obstacles"] = [{"type": "circle", "center": [3.0, 0.0], "radius": 0.5},
                        {"type": "circle", "center": [-3.0, 0.0], "radius": 0.5}]
    core = SimCore(scenario=Scenario.model_validate(doc))
    core.stage_lost("sensing")
    _, missed = core.sense()  # facing east: the obstacle at (3, 0)
    assert missed.points
    core.stage_back("sensing")
    core.state = replace(core.state, theta_rad=math.pi)  # facing west: only the one at (-3, 0) is in view
    drive(core, core.steps_per_scan)
    _, resent = core.sense()
    assert set(missed.points) <= set(resent.points)
    drive(core, core.steps_per_scan)
    _, again = core.sense()
    assert set(missed.points) <= set(again.points)  # until the pipeline answers one of the scans that carry them
    core.accept(SmoothPath(header=Header(stamp_s=core.t_s, seq=0), scan_seq=again.header.seq, status="no_path",
                           goal_index=0, points=[], max_curvature=0.0, min_level=0.0))
    drive(core, core.steps_per_scan)
    _, after = core.sense()
    assert after.points and not set(missed.points) & set(after.points)


def test_carried_hits_keep_every_scan_one_the_sensing_stage_accepts():
    """A wall ahead fills most rays; hits missed from poses along 4 m of road do not all fit in one scan
    (one hit per ray at most) nor all lie within the sensor's range of it, as the sensing stage checks."""
    doc = json.loads(open_field().model_dump_json())
    doc["obstacles"] = [{"type": "polygon", "vertices": [[6.0, -4.0], [6.5, -4.0], [6.5, 4.0], [6.0, 4.0]]}]
    scenario = Scenario.model_validate(doc)
    core, sensing = SimCore(scenario=scenario), SensingStage.from_scenario(scenario)
    core.stage_lost("sensing")
    for x_m in np.arange(0.0, 4.01, 0.25):  # the car moved on while the stage was down
        core.state = replace(core.state, x_m=float(x_m))
        core.sense()
    missed = dict(core.unheard)
    assert len(missed) > scenario.sensor.rays
    core.stage_back("sensing")
    core.state = replace(core.state, x_m=1.5)  # far from some of them now
    for _ in range(10):
        _, scan = core.sense()
        assert len(scan.points) <= scenario.sensor.rays
        sensing.process(topic="scan", message=scan, now_s=0.0)  # a scan it accepts: no StageInputError
        core.accept(SmoothPath(header=Header(stamp_s=core.t_s, seq=0), scan_seq=scan.header.seq, status="no_path",
                               goal_index=0, points=[], max_curvature=0.0, min_level=0.0))
        drive(core, core.steps_per_scan)
    in_range = {cell for cell, (x, y) in missed.items() if math.hypot(x - 1.5, y) <= scenario.sensor.range}
    assert in_range and not in_range & set(core.unheard)  # every one in range got through
    assert set(core.unheard) == set(missed) - in_range  # the others wait for the car to come back


def test_a_path_through_a_known_ellipse_is_not_driven_and_says_why():
    core = SimCore(scenario=open_field(), config=SimConfig(stale_after_s=100.0))
    core.sense()
    core.know(grown(center=(8.0, 0.0), radius=1.5))
    reason = core.accept(path(core, straight()))
    assert reason is not None and "cluster 7" in reason
    x, y = map(float, re.search(r"near \(([-\d.]+), ([-\d.]+)\)", reason).groups())
    assert abs(x - 8.0) <= 0.1 and y == 0.0
    assert max(drive(core, 20)) == 0.0  # at rest, short of giving up (`no_path_patience_s`)

    around = [(0.0, 0.0), (4.0, 0.0), (8.0, 3.0), (12.0, 0.0), (20.0, 0.0)]
    core.sense()
    assert core.accept(path(core, around, plan_id=2)) is None
    assert drive(core, 40)[-1] > 0.5


def test_a_late_answer_it_will_not_drive_brakes_the_car_but_starts_no_back_out():
    """A link cut for longer than a path may be old: the first answer after it is for a scan long gone."""
    core = SimCore(scenario=open_field())
    core.sense()
    core.accept(path(core, straight()))
    drive(core, 20)  # under way: tracks to back out along
    core.sense()
    late = path(core, straight(core.state.x_m), plan_id=2)  # its answer, held up by the cut
    assert drive(core, 60)[-1] == 0.0  # no fresh path: the car braked to rest
    core.know(grown(center=(core.state.x_m + 4.0, 0.0), radius=1.5, scan_seq=core.scan_seq))
    assert core.accept(late) is not None  # crosses newer obstacles: not driven ...
    assert max(drive(core, 40)) == 0.0 and not core.backing_out  # ... and no reason to back out
    core.sense()
    assert core.accept(path(core, straight(core.state.x_m), plan_id=3)) is not None  # the newest scan's verdict
    drive(core, 1)
    assert core.backing_out


def test_newer_obstacles_across_the_path_being_driven_stop_the_car():
    core = SimCore(scenario=open_field(), config=SimConfig(stale_after_s=100.0))
    core.sense()
    core.accept(path(core, straight()))
    drive(core, 40)
    assert core.know(grown(center=(15.0, 0.0), radius=1.0, scan_seq=1)) is not None
    assert drive(core, 40)[-1] == 0.0


def test_the_guard_lets_a_robot_inside_a_grown_ellipse_leave_it_but_not_go_deeper():
    guard = PathGuard(inflation_m=PAPER.inflation_m, keep_out_m=PAPER.keep_out_m)
    guard.know(grown(center=(0.0, 0.0), radius=2.0))
    start = (1.8, 0.0)  # level 0.9: closer to the obstacle than the full margin
    assert guard.check([start, (4.0, 0.0)], start=start) is None
    assert "level" in guard.check([start, (1.0, 0.0), (4.0, 0.0)], start=start)
    assert guard.check([(3.0, 0.0), (3.0, 5.0)], start=(3.0, 0.0)) is None
    assert guard.check([(3.0, -3.0), (3.0, 3.0), (1.9, 3.0)], start=(3.0, -3.0)) is None
    assert guard.check([(-3.0, 0.5), (3.0, 0.5)], start=(-3.0, 0.5)) is not None  # a chord through it


def no_path(core: SimCore) -> SmoothPath:
    """The pipeline's answer to the newest scan: no path."""
    return SmoothPath(header=Header(stamp_s=core.t_s, seq=0), scan_seq=core.scan_seq, status="no_path", goal_index=0,
                      points=[], max_curvature=0.0, min_level=0.0, reason="boxed in")


def until_rest(core: SimCore, limit: int = 400) -> None:
    for _ in range(limit):
        core.advance()
        if core.state.speed_mps == 0.0:
            return
    raise AssertionError("the car did not come to rest")


def test_a_car_without_a_drivable_answer_backs_out_along_its_tracks_then_gives_up():
    config = SimConfig(stale_after_s=100.0)
    core = SimCore(scenario=open_field(), config=config)
    core.sense()
    core.accept(path(core, [(0.0, 0.0), (4.0, 0.0), (8.0, 3.0), (12.0, 0.0), (20.0, 0.0)]))
    drive(core, 380)  # past the bend, with tracks for every back-out
    assert core.state.speed_mps > 0.5 and core.backout_m == pytest.approx(0.6 + core.limits.min_turn_radius_m)
    stops = []
    for backout in range(1, config.max_backouts + 1):
        core.sense()
        core.accept(no_path(core))
        until_rest(core)  # brakes ...
        assert core.backing_out
        tracks = LineString([*(p[:2] for p in core.tracks), (core.state.x_m, core.state.y_m)])
        scans, backed_m = 0, 0.0
        while core.backing_out:
            scans += core.scan_due
            before = (core.state.x_m, core.state.y_m)
            core.advance()
            backed_m += math.dist(before, (core.state.x_m, core.state.y_m))
            assert core.state.speed_mps <= 0.0
            # Within 5 cm: pursuit cuts the bends the car drove forward at full lock by a few cm.
            assert tracks.distance(Point(core.state.x_m, core.state.y_m)) < 0.05
        assert scans == 0  # it does not ask the pipeline while it backs out
        # ... backs out its length plus one turning radius along the tracks it drove ...
        assert backed_m == pytest.approx(core.backout_m, abs=0.1)
        assert core.outcome is None and core.backouts == backout
        stops.append(core.state.x_m)
        while not core.scan_due:
            core.advance()
    assert np.all(np.diff(stops) < 0.0)
    core.sense()
    core.accept(no_path(core))
    until_rest(core)
    assert not core.backing_out  # none left for this goal: it waits, then gives up
    drive(core, round(config.no_path_patience_s / config.dt_s) + 1)
    assert core.outcome == "no_path" and core.min_clearance_m > 0.0


def test_a_late_answer_to_a_scan_from_before_a_back_out_is_not_taken():
    core = SimCore(scenario=open_field(), config=SimConfig(stale_after_s=100.0))
    core.sense()
    core.accept(path(core, straight()))
    drive(core, 100)
    core.sense()
    stuck = no_path(core)
    core.accept(stuck)
    until_rest(core)
    while core.backing_out:
        core.advance()
    # Planned from where the car stood before backing out (realtime: the planner was still at it).
    late = path(core, straight(core.state.x_m + 2.0)).model_copy(update={"scan_seq": stuck.scan_seq})
    core.accept(late)
    core.accept(stuck)
    assert core.path is None and core.no_path_since_s is None and core.backouts == 1
    core.sense()
    assert core.accept(path(core, straight(core.state.x_m))) is None and core.path is not None


def test_stage_errors_for_every_scan_of_a_car_at_rest_end_the_run_instead_of_waiting_for_ever():
    config = SimConfig()
    core = SimCore(scenario=open_field(), config=config)
    for _ in range(round(config.no_path_patience_s * 10) + 2):
        core.sense()
        core.no_plan("smoother: smoothed path rejected: curvature 52.1 exceeds the bound 1.079 1/m")
        drive(core, core.steps_per_scan)
        if core.outcome is not None:
            break
    assert core.outcome == "no_path" and "curvature" in core.no_path_reason


def test_a_path_that_starts_against_the_heading_is_not_driven():
    core = SimCore(scenario=open_field(), config=SimConfig(stale_after_s=100.0))
    core.sense()
    reason = core.accept(path(core, straight(0.0, -3.0)))
    assert reason == "the path starts against the car's heading" and core.path is None


def test_a_no_path_while_the_planner_replans_is_no_verdict():
    """The planner's no_path marked `replanning` (its replan still runs in the background): the car goes
    on as if the answer were still to come — on its path while it has one, and at rest without one it
    starts no back-out and does not give up."""
    core = SimCore(scenario=open_field(), config=SimConfig(stale_after_s=100.0))
    core.sense()
    core.accept(path(core, straight()))
    drive(core, 100)  # under way: tracks to back out along
    core.sense()
    replanning = no_path(core).model_copy(update={"reason": "replanning: ...", "replanning": True})
    assert core.accept(replanning) is None and core.path is not None and core.no_path_since_s is None
    assert min(drive(core, 20)) > 0.5
    core.know(grown(center=(core.state.x_m + 4.0, 0.0), radius=1.5, scan_seq=core.scan_seq))  # the path is blocked
    until_rest(core)
    core.sense()
    core.accept(no_path(core).model_copy(update={"reason": "replanning: ...", "replanning": True}))
    drive(core, round(2 * core.config.no_path_patience_s / core.config.dt_s))
    assert not core.backing_out and core.outcome is None and core.state.speed_mps == 0.0
