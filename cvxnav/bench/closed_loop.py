"""`cvxnav bench --closed-loop`: the pipeline's stage cores driving the sim in one process.

`cvxnav run` measures what a user sees (processes, Zenoh, the machine's load). This measures what the
stages themselves cost and what the closed loop achieves: the sim's `SimCore` senses, the default cores
of sensing → ellipsoids → planner → smoother answer each scan in turn (lockstep, like a run's default
mode), and the sim takes the answer exactly as `sim.stage.SimStage` does — the ellipsoids to its path guard, the
path to `accept`, a stage's rejection to `reject`. Same scenario, same trajectory as a lockstep run;
no IPC, so the latency is each stage's compute time per scan and their sum.

With `deadline` (`--deadline`) the planner answers within its budget, as in a live run (`cvxnav service
planner --deadline`), its repairs and replans going on in the background (`services.planner.stage`);
while one runs, the next scan waits for the rest of the sensor period in wall time, as a live sensor
would, so the replan has the time it would have had. Other scans follow at once.

For each scenario: the outcome, the closed-loop path length ÷ REFERENCE.json's known-map optimum
(the issue's ≤ 1.3 on average), the smallest footprint clearance, replans, and per-stage p50/p99/max.
"""

from __future__ import annotations

import time
from collections.abc import Callable

import numpy as np
from pydantic import BaseModel

from cvxnav.stages import load_factory
from schemas.messages import Ellipsoids, SmoothPath
from schemas.scenario import Scenario
from schemas.wiring import PIPELINE, STAGES
from services.contract import StageInputError
from services.shell.stage import freeze_startup_objects
from sim.core import SimCore

STAGE_ORDER = PIPELINE  # sensing -> ellipsoids -> planner -> smoother


class StageLatency(BaseModel):
    p50_ms: float
    p99_ms: float
    max_ms: float

    @classmethod
    def of(cls, samples_ms: list[float]) -> StageLatency:
        values = np.asarray(samples_ms or [0.0])
        return cls(p50_ms=float(np.percentile(values, 50)), p99_ms=float(np.percentile(values, 99)),
                   max_ms=float(values.max()))


class ClosedLoopRow(BaseModel):
    scenario: str
    status: str  # reached | no_path | timeout | collision (as run.json)
    goals_reached: int
    goals: int
    sim_s: float
    wall_s: float
    length_m: float
    reference_m: float | None  # REFERENCE.json's known-map optimum
    min_clearance_m: float
    replans: int
    latency: dict[str, StageLatency]  # per stage, and "total": scan -> verified path


class ClosedLoopReport(BaseModel):
    format: str = "cvxnav.closed_loop/1"
    rows: list[ClosedLoopRow]
    deadline: bool = False  # the planner answered within its budget, replanning in the background

    @property
    def mean_length_ratio(self) -> float | None:
        ratios = [r.length_m / r.reference_m for r in self.rows if r.reference_m and r.status == "reached"]
        return float(np.mean(ratios)) if ratios else None


def run_closed_loop(scenario: Scenario, *, reference_m: float | None = None, deadline: bool = False,
                    on_step: Callable[[float], None] | None = None) -> ClosedLoopRow:
    """Drive `scenario` to its outcome with the default stage cores (the planner's `deadline` on or off);
    `on_step(sim_s)` after each scan."""
    core = SimCore(scenario)
    stages = {name: load_factory(STAGES[name].factory)(scenario, **({"deadline": True} if deadline and
                                                                    name == "planner" else {}))
              for name in STAGE_ORDER}
    period_s = 1.0 / float(scenario.sensor.rate_hz)
    freeze_startup_objects()  # as every stage process does before its first message
    samples: dict[str, list[float]] = {name: [] for name in (*STAGE_ORDER, "total")}
    started = time.perf_counter()
    while core.outcome is None:
        if core.scan_due:
            state, scan = core.sense()
            stages["planner"].process(topic="state", message=state, now_s=state.header.stamp_s)
            topic, message = "scan", scan
            scan_started = time.perf_counter()
            for name in STAGE_ORDER:
                stage_started = time.perf_counter()
                try:
                    outputs = stages[name].process(topic=topic, message=message, now_s=state.header.stamp_s)
                except StageInputError as error:
                    core.no_plan(f"{name}: {error}")
                    outputs = []
                samples[name].append((time.perf_counter() - stage_started) * 1e3)
                if not outputs:
                    break
                topic, message = outputs[0]
                if isinstance(message, Ellipsoids):
                    core.know(message)
            else:
                assert isinstance(message, SmoothPath)
                core.accept(message)
            samples["total"].append((time.perf_counter() - scan_started) * 1e3)
            if stages["planner"].replanning:
                time.sleep(max(0.0, scan_started + period_s - time.perf_counter()))
            if on_step is not None:
                on_step(core.t_s)
        core.advance()
    stages["planner"].stop(now_s=core.t_s)
    trajectory = np.asarray(core.trajectory)
    return ClosedLoopRow(
        scenario=scenario.name, status=core.outcome, goals_reached=core.goals.reached_count,
        goals=len(scenario.goals), sim_s=core.t_s, wall_s=time.perf_counter() - started,
        length_m=float(np.sum(np.linalg.norm(np.diff(trajectory[:, 1:3], axis=0), axis=1))),
        reference_m=reference_m, min_clearance_m=float(core.min_clearance_m), replans=core.replans,
        latency={name: StageLatency.of(values) for name, values in samples.items()},
    )


def closed_loop_markdown(report: ClosedLoopReport) -> str:
    """The report as one Markdown table, with the mean length ratio under it."""
    head = ("| scenario | outcome | goals | sim s | length ÷ ref | min clearance m | replans | "
            + " | ".join(f"{name} p50/p99/max ms" for name in (*STAGE_ORDER, "total")) + " |")
    lines = [head, "|" + "---|" * (7 + len(STAGE_ORDER) + 1)]
    for row in report.rows:
        ratio = f"{row.length_m / row.reference_m:.3f}" if row.reference_m else "—"
        cells = [row.scenario, row.status, f"{row.goals_reached}/{row.goals}", f"{row.sim_s:.1f}", ratio,
                 f"{row.min_clearance_m:.3f}", str(row.replans)]
        cells += [f"{row.latency[name].p50_ms:.0f} / {row.latency[name].p99_ms:.0f} / {row.latency[name].max_ms:.0f}"
                  for name in (*STAGE_ORDER, "total")]
        lines.append("| " + " | ".join(cells) + " |")
    mean = report.mean_length_ratio
    lines.append("")
    if report.deadline:
        lines.append("The planner answered within its budget (`--deadline`), replanning in the background.")
        lines.append("")
    lines.append(f"Mean closed-loop length ÷ reference over the reached scenarios: {mean:.3f}" if mean is not None
                 else "No scenario with a reference was reached.")
    return "\n".join(lines) + "\n"
