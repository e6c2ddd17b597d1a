"""The sim as a ticking core (`SimStage`), driven as the shell drives it, with the real stage cores
answering in the same process: what it hears routed by the wiring table, time on a clock we advance."""

from __future__ import annotations

from collections import deque

import pytest
from attacker import FORGED_PLAN, error_status, forge

from cvxnav.bench.closed_loop import run_closed_loop
from cvxnav.stages import load_factory
from schemas.messages import Header, Scan, SmoothPath, StageStatus
from schemas.scenario import bundled_scenario
from schemas.wiring import PIPELINE, SIM, STAGES, subscribers_of
from services.contract import Refusal, StageInputError
from sim.core import SimConfig
from sim.stage import SimStage

SCENARIO = bundled_scenario()


class Bus:
    """Every output handed to the wiring table's readers of its topic, in the order it was published."""

    def __init__(self, sim: SimStage) -> None:
        scenario = sim.core.scenario
        self.cores = {SIM.name: sim, **{name: load_factory(STAGES[name].factory)(scenario) for name in PIPELINE}}
        self.queue: deque = deque()
        self.refusals: list[str] = []

    def publish(self, outputs, *, now_s: float) -> None:
        for topic, message in outputs:
            if isinstance(message, Refusal):
                self.refusals.append(message.reason)
            else:
                self.queue.extend((reader, topic, message) for reader in subscribers_of(topic))

    def deliver(self, *, now_s: float) -> None:
        reader, topic, message = self.queue.popleft()
        self.publish(self.cores[reader].process(topic=topic, message=message, now_s=now_s), now_s=now_s)


def drive(sim: SimStage, *, ticks: int | None = None) -> tuple[Bus, float]:
    """Run the loop as the shell does: every input delivered, then a tick whenever the core asks; the
    bus and the clock's time at the end."""
    bus, now_s = Bus(sim), 0.0
    for name in PIPELINE:
        sim.stage_alive(stage=name, alive=True, now_s=now_s)
    while not sim.done and (ticks is None or ticks > 0):
        if bus.queue:
            bus.deliver(now_s=now_s)
            continue
        due_s = sim.next_tick_s(now_s=now_s)
        now_s = max(now_s, due_s)
        bus.publish(sim.tick(now_s=now_s), now_s=now_s)
        ticks = None if ticks is None else ticks - 1
    return bus, now_s


def test_lockstep_drives_the_same_loop_as_the_closed_loop_bench():
    sim = SimStage.from_scenario(SCENARIO)
    bus, _ = drive(sim)
    result, bench = sim.result(), run_closed_loop(SCENARIO)
    assert result.status == bench.status == "reached"
    assert result.goals_reached == len(SCENARIO.goals)
    assert result.replans == bench.replans
    assert result.min_clearance == pytest.approx(bench.min_clearance_m, abs=1e-6)
    assert len(result.trajectory) - 1 == round(bench.sim_s / sim.config.dt_s)
    assert not bus.refusals
    (_, final), = sim.stop(now_s=0.0)
    assert final.done and final.goals_reached == len(SCENARIO.goals)


def test_a_stage_lost_while_a_scan_waits_brakes_and_stands_on_the_wall_clock():
    sim = SimStage.from_scenario(SCENARIO)
    bus, now_s = drive(sim, ticks=30)  # under way: a few scans answered
    while not any(topic == "scan" for _, topic, _ in bus.queue):
        bus.queue.clear()
        now_s = max(now_s, sim.next_tick_s(now_s=now_s))
        bus.publish(sim.tick(now_s=now_s), now_s=now_s)
    bus.queue.clear()  # the scan just sent is never answered: the planner dies
    waiting = sim.core.scan_seq
    assert sim.core.state.speed_mps > 0.0
    sim.stage_alive(stage="planner", alive=False, now_s=now_s)
    assert sim.next_tick_s(now_s=now_s) == now_s  # heard: it acts at once
    sim.tick(now_s=now_s)
    assert "planner" in sim.core.missing and sim.core.path is None  # no answer will come: it brakes
    period_s = sim.core.steps_per_scan * sim.config.dt_s
    assert sim.next_tick_s(now_s=now_s) == pytest.approx(now_s + period_s)  # and stands a period of wall time
    assert sim.core.scan_seq == waiting + 1


def test_an_answer_to_a_scan_it_never_sent_is_rejected():
    sim = SimStage.from_scenario(SCENARIO)
    forged = SmoothPath(header=Header(stamp_s=0.0, seq=0), scan_seq=10**6, status="ok", goal_index=0,
                        points=[(0.0, 0.0), (1.0, 1.0)], max_curvature=0.0, min_level=2.0, plan_id=1)
    with pytest.raises(StageInputError, match="never sent"):
        sim.process(topic="smooth_path", message=forged, now_s=0.0)


def test_a_status_counts_only_on_the_key_of_the_pipeline_stage_it_names():
    sim = SimStage.from_scenario(SCENARIO)
    sim.hear_status(stage="monitor", status=error_status(stage="monitor", stamp_s=0.0), now_s=0.0)
    sim.hear_status(stage="operator", status=error_status(stage="planner", stamp_s=0.0), now_s=0.0)
    sim.hear_status(stage="smoother", status=error_status(stage="planner", stamp_s=0.0), now_s=0.0)
    sim.hear_status(stage="sim", status=error_status(stage="sim", stamp_s=0.0), now_s=0.0)
    assert sim.rejected == {}
    sim.hear_status(stage="planner", status=error_status(stage="planner", stamp_s=0.0, reason="boom"), now_s=2.5)
    assert sim.rejected == {0.0: ("planner: boom", 2.5)}


# --------------------------------------------------------------------------- forged traffic (issue 27)

def drive_under_attack(sim: SimStage, forge) -> Bus:
    """`drive`, with an attacker who hears every scan and answers it at once with `forge(scan)`: messages
    (delivered to the wiring table's readers, the planner as much as the sim) and statuses (to the sim,
    on the key it names), all before the pipeline's answer, the sim acting on them first as the shell would.
    Each publisher's messages still arrive in the order it sent them, as over Zenoh."""
    bus, now_s = Bus(sim), 0.0
    for name in PIPELINE:
        sim.stage_alive(stage=name, alive=True, now_s=now_s)
    scans: deque[Scan] = deque()

    def tick() -> None:
        outputs = sim.tick(now_s=now_s)
        bus.publish(outputs, now_s=now_s)
        scans.extend(message for topic, message in outputs if topic == "scan")

    while not sim.done:
        if scans:
            messages, statuses = forge(scans.popleft())
            for stage, status in statuses:
                sim.hear_status(stage=stage, status=status, now_s=now_s)
            honest, bus.queue = bus.queue, deque()
            bus.publish(messages, now_s=now_s)
            while bus.queue:  # the forged messages, and what the stages make of them
                bus.deliver(now_s=now_s)
            bus.queue = honest
            if sim.next_tick_s(now_s=now_s) <= now_s:
                tick()
            continue
        if bus.queue:
            bus.deliver(now_s=now_s)
            continue
        now_s = max(now_s, sim.next_tick_s(now_s=now_s))
        tick()
    return bus


def test_forged_empty_ellipses_and_forged_paths_never_move_the_car_into_a_wall_or_off_the_map():
    """Every scan answered at once with no ellipses (to the sim and the planner alike) and a path into the
    nearest thing the car sees, or off the map, in turn: the guard refuses each, and the pipeline's own
    answers still take the car to both goals."""
    sim = SimStage.from_scenario(SCENARIO)
    bus = drive_under_attack(sim, lambda scan: forge(scan, with_status=False))
    result = sim.result()
    assert result.status == "reached" and result.goals_reached == len(SCENARIO.goals)
    assert result.min_clearance >= SCENARIO.robot.safety_distance / 2.0  # the hard floor's promise
    forged = [reason for reason in bus.refusals if f"plan {FORGED_PLAN} " in reason]
    assert any("hit of the car's own scans" in reason for reason in forged)
    assert any("leaves the map" in reason for reason in forged)
    assert all("hit of the car's own scans" in reason or "leaves the map" in reason for reason in forged)


def test_twenty_forged_error_statuses_change_nothing(shared_dir):
    """The issue's 20 errors, one for each of the first 20 scans on the planner's key, naming it, heard
    before the pipeline answers: the run is the honest one, to the sample."""
    from schemas.scenario import load_scenario

    scenario = load_scenario(shared_dir / "scenarios" / "wide-gap.json")
    honest = SimStage.from_scenario(scenario)
    drive(honest)
    sent = []

    def statuses_only(scan: Scan):
        if len(sent) == 20:
            return [], []
        sent.append(scan.header.seq)
        return [], forge(scan, with_status=True)[1]

    attacked = SimStage.from_scenario(scenario)
    drive_under_attack(attacked, statuses_only)
    assert len(sent) == 20
    assert attacked.result().status == honest.result().status == "reached"
    assert attacked.result().trajectory == honest.result().trajectory


def _send_until_a_scan(sim: SimStage, bus: Bus, now_s: float) -> tuple[object, float]:
    """Tick until the sim sends a scan; the scan (undelivered) and the clock's time."""
    while bus.queue:
        bus.deliver(now_s=now_s)
    while True:
        now_s = max(now_s, sim.next_tick_s(now_s=now_s))
        outputs = sim.tick(now_s=now_s)
        scans = [message for topic, message in outputs if topic == "scan"]
        if scans:
            return scans[-1], now_s
        bus.publish(outputs, now_s=now_s)
        while bus.queue:
            bus.deliver(now_s=now_s)


def _sensing_ok(scan) -> StageStatus:
    return StageStatus(header=Header(stamp_s=scan.header.stamp_s, seq=0), stage="sensing", state="ok", reason="",
                       input_key="cvxnav/robot1/scan", input_stamp_s=scan.header.stamp_s, processing_ms=5.0)


def test_a_lost_scan_is_sent_again_until_the_sensing_stage_reports_it():
    sim = SimStage.from_scenario(SCENARIO)
    bus, now_s = drive(sim, ticks=30)
    scan, now_s = _send_until_a_scan(sim, bus, now_s)  # dropped on the way: nobody gets it
    now_s = sim.next_tick_s(now_s=now_s)
    again = [message for topic, message in sim.tick(now_s=now_s) if topic == "scan"]
    assert [s.header.seq for s in again] == [scan.header.seq]  # the same scan, once the resend time came
    sim.hear_status(stage="sensing", status=_sensing_ok(scan), now_s=now_s)  # this copy got through
    now_s = sim.next_tick_s(now_s=now_s)
    assert not [message for topic, message in sim.tick(now_s=now_s) if topic == "scan"]  # in the pipeline: no resend


def test_an_unanswered_scan_counts_in_the_latency_until_the_next_answer():
    clock = [0.0]
    sim = SimStage(scenario=SCENARIO, config=SimConfig(), latency_clock=lambda: clock[0])
    bus, now_s = drive(sim, ticks=30)
    lost, now_s = _send_until_a_scan(sim, bus, now_s)
    sim.hear_status(stage="sensing", status=_sensing_ok(lost), now_s=now_s)  # received, never answered
    sent_s = now_s
    while True:  # until the sim gives up on it and sends the next scan
        clock[0] = now_s = max(now_s, sim.next_tick_s(now_s=now_s))
        outputs = sim.tick(now_s=now_s)
        if any(topic == "scan" for topic, _ in outputs):
            break
    assert now_s == pytest.approx(sent_s + sim.config.answer_timeout_s)
    bus.publish(outputs, now_s=now_s)
    while bus.queue:
        bus.deliver(now_s=now_s)  # the next scan answered at once, on the clock of the timeout
    assert sim.result().latency_ms.max == pytest.approx(sim.config.answer_timeout_s * 1e3)


def test_a_run_stopped_before_its_outcome_is_interrupted_and_its_unanswered_scan_counts_until_the_stop():
    clock = [0.0]
    sim = SimStage(scenario=SCENARIO, config=SimConfig(), latency_clock=lambda: clock[0])
    bus, now_s = drive(sim, ticks=30)
    _send_until_a_scan(sim, bus, now_s)  # lost on the way: never answered
    clock[0] += 7.5  # the stall, then the stop
    sim.stop(now_s=now_s)
    clock[0] += 100.0  # the result, read later, still ends at the stop
    result = sim.result()
    assert result.status == "interrupted" and result.format == "cvxnav.run/2"
    assert result.latency_ms.max == pytest.approx(7.5e3)


def test_a_run_whose_goals_are_at_the_start_is_reached_before_the_first_step():
    scenario = bundled_scenario().model_copy(update={"goals": [(0.1, 0.0), (0.0, 0.2)]})
    sim = SimStage.from_scenario(scenario)
    assert sim.core.outcome == "reached" and sim.core.goals.reached_count == 2
    result = sim.result()
    assert result.status == "reached" and len(result.trajectory) == 1
