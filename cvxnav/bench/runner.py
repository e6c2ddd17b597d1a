"""`cvxnav bench`: every planner on the same scenarios and the same grown ellipses, in one process.

For each scenario: the grown-ellipse model (`BenchProblem`), its exact optimum (the tangent graph of the ellipses), then
each planner at least `repeats` times, the planners in turns (cvxnav once more first, cold), each answer
judged on the true geometry;
peak memory from one extra untimed call under tracemalloc (Python allocations, numpy's included;
C++ allocations inside OMPL, Drake and Clarabel are not seen). Then the fitting micro-benchmark and
the scaling run. Progress goes to a rich bar; the result is a `BenchReport`, printed as a rich table
and written as JSON and Markdown.
"""

from __future__ import annotations

import platform
import statistics
import sys
import time
import tracemalloc
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from functools import partial
from importlib import metadata
from pathlib import Path

import numpy as np
from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn
from rich.table import Table

from cvxnav.bench import planners
from cvxnav.bench.planners import Attempt
from cvxnav.bench.problem import COLLISION_TOLERANCE_M, BenchProblem, check_path, reference_lengths
from cvxnav.bench.report import (
    BenchReport,
    FitResult,
    Machine,
    PlannerResult,
    ScalingResult,
    ScenarioResult,
    TargetRatios,
)
from cvxnav.bench.turns import in_turns, ratio_interval
from schemas.scenario import Scenario

CVXNAV = "cvxnav"
BITSTAR = "BIT* (OMPL)"
INFORMED = "Informed RRT* (OMPL)"
DRAKE = "IRIS + GCS (Drake)"
DRAKE_POLYGONS = "IRIS + GCS (Drake, 32-gons)"
PAPER = "paper, as written"
OPTIMUM = "optimum (tangent graph)"


@dataclass(frozen=True)
class BenchOptions:
    quick: bool = False
    repeats: int = 5  # at least; a fast planner is repeated until min_timed_s is timed (at most max_repeats)
    # A median of 5 moves with every hiccup of the machine (sub-millisecond times) and with a sampling
    # planner's draws (BIT* on corner-trap: 17 to 72 ms between the deciles of 40 runs).
    min_timed_s: float = 1.0
    max_repeats: int = 200
    sampling_budget_s: float = 5.0  # per leg, for BIT* and Informed RRT*
    drake_regions: int = 16
    drake_repeats: int = 2  # IRIS + GCS is slow and deterministic given its seed
    fit_counts: tuple[int, ...] = (20, 100, 1000)
    fit_repeats: int = 50  # mvee_fast and Drake take under 1 ms at 20 points
    fit_sets: int = 10  # point sets per size: mvee_fast's time depends on the set
    scaling_counts: tuple[int, ...] = (10, 25, 50, 100, 200)
    scaling_repeats: int = 5  # plans per field, median taken: a median of 2 moved with one slow moment (all five: ~2.5 s)
    seed: int = 0

    @classmethod
    def quick_defaults(cls, *, repeats: int | None = None) -> BenchOptions:
        """Under two minutes on two cores: one repeat fewer everywhere, short budgets, a small scaling run."""
        return cls(quick=True, repeats=repeats or 2, min_timed_s=0.05, sampling_budget_s=1.0, drake_regions=8,
                   drake_repeats=1, fit_counts=(20, 100), fit_repeats=5, fit_sets=5, scaling_counts=(10, 25),
                   scaling_repeats=1)


@dataclass(frozen=True)
class MapRun:
    """The map part of a run (`cvxnav.bench.maps`): the cases, their options, where generated files go, and
    the shared folder for the growth run (None: no growth run)."""

    cases: list
    options: object
    work_dir: Path
    shared: Path | None


@dataclass(frozen=True)
class PlannerSpec:
    name: str
    call: Callable[[BenchProblem, int], Attempt]
    repeats: int
    time_meaning: str
    cold: bool = False
    timed_s: float = 0.0  # repeat beyond `repeats` until this much time is measured (0: exactly `repeats`)


def _wants_more(spec: PlannerSpec, done: list[Attempt], *, max_repeats: int) -> bool:
    """Fewer than `spec.repeats` calls, or fewer than `max_repeats` whose times sum to under `spec.timed_s`
    (like timeit's autorange: a sub-millisecond median then rests on many calls)."""
    return len(done) < spec.repeats or (len(done) < max_repeats and sum(a.time_s for a in done) < spec.timed_s)


def _in_turns(specs: list[PlannerSpec], problem: BenchProblem, *, max_repeats: int, seed: int,
              on_round: Callable[[int], None] = lambda k: None) -> dict[str, list[Attempt]]:
    """Each planner's timed calls, the planners in turns (`cvxnav.bench.turns`) while they want more
    (`_wants_more`)."""
    by_name = {spec.name: spec for spec in specs}
    return in_turns(
        {spec.name: partial(spec.call, problem) for spec in specs},
        lambda name, done: _wants_more(by_name[name], done, max_repeats=max_repeats),
        seed=seed,
        on_round=on_round,
    )


def default_scenario_dir() -> Path:
    """The public scenarios: `shared/scenarios` beside the checkout (as the test suite finds them)."""
    return Path(__file__).resolve().parents[3] / "shared" / "scenarios"


def _machine() -> Machine:
    import os

    packages = {}
    for name in ("cvxnav", "cvxpy", "clarabel", "numpy", "ompl", "drake"):
        try:
            packages[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            packages[name] = "not installed"
    cpu = platform.processor() or ""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return Machine(platform=platform.platform(), processor=cpu or "unknown", cpus=os.cpu_count() or 1,
                   python=platform.python_version(), packages=packages)


def _peak_kib(call: Callable[[], object]) -> float:
    tracemalloc.start()
    try:
        call()
        return tracemalloc.get_traced_memory()[1] / 1024.0
    finally:
        tracemalloc.stop()


def summarise(spec: PlannerSpec, problem: BenchProblem, attempts: list[Attempt], *, optimum_m: float | None,
               cold_s: float | None, peak_kib: float | None) -> PlannerResult:
    """Success only if every repeat returned a path that reaches the goals and never collides."""
    checks = [check_path(problem, a.path) if a.path is not None else None for a in attempts]
    failed = [a.reason or "no path" for a, c in zip(attempts, checks) if c is None]
    collides = any(c is not None and c.collides for c in checks)
    misses = any(c is not None and not c.reaches_goals for c in checks)
    lengths = [c.length_m for c in checks if c is not None]
    times = [1e3 * a.time_s for a in attempts]
    reasons = []
    if failed:
        reasons.append(f"{len(failed)}/{len(attempts)} failed: {failed[0]}")
    if collides:
        worst = min(c.min_clearance_m for c in checks if c is not None)
        reasons.append(f"collides: true clearance {worst:.3f} m < {problem.scenario.inflation_m - COLLISION_TOLERANCE_M:.3f} m")
    if misses:
        reasons.append("misses a goal")
    other = sorted({a.reason for a in attempts if a.path is not None and a.reason})
    reasons += other
    length = statistics.median(lengths) if lengths else None
    firsts = [1e3 * a.first_solution_s for a in attempts if a.first_solution_s is not None]
    is_sampling = spec.name in (BITSTAR, INFORMED)
    return PlannerResult(
        planner=spec.name,
        success=not failed and not collides and not misses,
        collision=collides,
        reason="; ".join(reasons),
        repeats=len(attempts),
        length_m=length,
        length_ratio=length / optimum_m if length is not None and optimum_m else None,
        min_clearance_m=min((c.min_clearance_m for c in checks if c is not None), default=None),
        time_median_ms=statistics.median(times) if times else None,
        time_p90_ms=float(np.percentile(times, 90)) if times else None,
        times_ms=times,
        time_meaning=spec.time_meaning,
        cold_ms=1e3 * cold_s if cold_s is not None else None,
        first_solution_ms=statistics.median(firsts) if firsts else None,
        target_reached=sum(a.target_s is not None for a in attempts) if is_sampling else None,
        peak_memory_kib=peak_kib,
    )


def _specs(options: BenchOptions, peers: dict[str, str], leg_optima: list[float]) -> list[PlannerSpec]:
    specs = [
        PlannerSpec(CVXNAV, lambda p, s: planners.plan_cvxnav(p), options.repeats,
              "optimise + smooth on the grown ellipses (fit excluded, as for every planner; its EllipseStack rebuilt each call); heading + curvature honoured",
              cold=True, timed_s=options.min_timed_s),
        PlannerSpec(PAPER, lambda p, s: planners.plan_paper(p), options.repeats, "straight line, detours, Bézier; nothing verified",
                    timed_s=options.min_timed_s),
    ]
    if not peers["ompl"]:
        budget = options.sampling_budget_s
        for name, algorithm in ((BITSTAR, "BITstar"), (INFORMED, "InformedRRTstar")):
            specs.append(PlannerSpec(
                name,
                lambda p, s, algorithm=algorithm: planners.plan_ompl(p, planner=algorithm, budget_s=budget, leg_optima_m=leg_optima),
                options.repeats,
                f"time to within 1 % of the optimum (stops there), else the {budget:g} s budget per leg; point robot",
                timed_s=options.min_timed_s,
            ))
    if not peers["drake"]:
        for name, shape in ((DRAKE, "ellipses"), (DRAKE_POLYGONS, "polygons")):
            specs.append(PlannerSpec(
                name,
                lambda p, s, shape=shape: planners.plan_drake_gcs(
                    p, max_regions=options.drake_regions, seed=options.seed + s, obstacle_shape=shape),
                options.drake_repeats,
                f"IRIS (≤ {options.drake_regions} regions, obstacles as {shape}) + GCS per leg; point robot",
            ))
    return specs


def run_bench(*, scenarios: Sequence[Scenario], options: BenchOptions, command: str,
              console: Console | None = None, show_progress: bool = True, maps: MapRun | None = None) -> BenchReport:
    console = console or Console(stderr=True)
    started = time.perf_counter()
    peers = planners.peer_status()
    map_result = None
    if maps is not None:
        from cvxnav.bench.maps import run_map_bench

        with Progress(TextColumn("{task.description}"), TimeElapsedColumn(), console=console,
                      disable=not show_progress) as bar:
            task = bar.add_task("maps")
            map_result = run_map_bench(maps.cases, options=maps.options, work_dir=maps.work_dir, shared=maps.shared,
                                       with_ompl=not peers["ompl"],
                                       on_step=lambda text: bar.update(task, description=f"maps: {text}"))
    if not scenarios:
        return BenchReport(command=command, machine=_machine(), quick=options.quick, repeats=options.repeats,
                           sampling_budget_s=options.sampling_budget_s, collision_tolerance_m=COLLISION_TOLERANCE_M,
                           notes=[f"skipped {name}: {why}" for name, why in peers.items() if why], scenarios=[], fit=[],
                           scaling=None, targets=_targets([], [], None), maps=map_result,
                           wall_s=time.perf_counter() - started)
    if not peers["ompl"]:
        from ompl import util as ou

        ou.RNG.setSeed(options.seed + 1)  # OMPL's global seed: set once, before any planner samples
    notes = [f"skipped {name}: {why}" for name, why in peers.items() if why]
    notes += [
        "All planners get the same grown ellipses (cvxnav's known-map fit grown by width/2 + safety); "
        "only cvxnav honours the start heading and the curvature bound, the peers plan for a point robot.",
        f"Collision = true-geometry clearance (Scenario.clearance, path resampled at 0.02 m) below "
        f"width/2 + safety − {COLLISION_TOLERANCE_M} m; a colliding planner counts as failed.",
        "Optimum = the exact tangent graph of the grown ellipses (common tangents, tangents from start and goals, "
        "free boundary arcs; services/planner/route.py at level 1): its length is the model's exact optimum.",
        "OMPL validity: outside every grown ellipse; motions checked exactly (EllipseStack's segment test, as "
        "cvxnav checks its straight line) in a Python MotionValidator, so OMPL's times include Python callback "
        "overhead. Its times, like cvxnav's, include building its arrays of the ellipses from the model and end "
        "with its path read out into an array.",
        "Drake: IRIS on the grown ellipses themselves, and on 32-gons circumscribing them (≤ 0.5 % larger) because "
        "Clarabel, the solver Drake has here (MOSEK unlicensed), often fails IRIS's ellipse SOCP.",
        "Peak memory: tracemalloc over one extra untimed call (Python and numpy allocations; not C++ inside OMPL/Drake/Clarabel).",
    ]
    more = (f"; a faster planner is called again until {options.min_timed_s:g} s of its time is measured, at most "
            f"{options.max_repeats} calls" if options.min_timed_s > 0 else "")
    notes.append(f"Timing: the planners are called in turns, one call each per round in an order shuffled per round "
                 f"(seeded), so that the machine's slow and fast spells fall on all of them alike. At least "
                 f"{options.repeats} timed calls per planner (Drake {options.drake_repeats}){more}. Each row's repeats "
                 f"are its count.")
    references = reference_lengths(default_scenario_dir() / "REFERENCE.json")
    n_steps = len(scenarios) * (2 + (0 if peers["ompl"] else 2) + (0 if peers["drake"] else 2)) + 2
    progress = Progress(TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
                        console=console, disable=not show_progress, transient=False)
    results: list[ScenarioResult] = []
    with progress:
        task = progress.add_task("bench", total=n_steps)
        for scenario in scenarios:
            progress.update(task, description=f"{scenario.name}: fitting the model")
            problem = BenchProblem.of(scenario)
            progress.update(task, description=f"{scenario.name}: optimum")
            optimum = planners.plan_optimum(problem)
            leg_optima = [v for k, v in optimum.extra.items() if k.startswith("leg")]
            optimum_m = float(sum(leg_optima)) if optimum.path is not None else None
            specs = _specs(options, peers, leg_optima)
            aimless = {BITSTAR, INFORMED} if optimum_m is None else set()
            timed = [spec for spec in specs if spec.name not in aimless]
            cold_s = {spec.name: spec.call(problem, 0).time_s for spec in timed if spec.cold}
            attempts = _in_turns(timed, problem, max_repeats=options.max_repeats, seed=options.seed, on_round=lambda k, name=scenario.name:
                                 progress.update(task, description=f"{name}: timing the planners in turns, round {k + 1}"))
            rows: list[PlannerResult] = []
            for spec in specs:
                progress.update(task, description=f"{scenario.name}: {spec.name}, peak memory")
                if spec.name in aimless:
                    rows.append(PlannerResult(planner=spec.name, success=False, collision=False, repeats=0,
                                              reason="no optimum to aim at: the model has no route"))
                else:
                    done = attempts[spec.name]
                    peak = _peak_kib(lambda: spec.call(problem, len(done)))
                    rows.append(summarise(spec, problem, done, optimum_m=optimum_m, cold_s=cold_s.get(spec.name), peak_kib=peak))
                progress.advance(task)
            rows.append(PlannerResult(
                planner=OPTIMUM, success=optimum.path is not None, collision=False, repeats=1,
                reason=optimum.reason, length_m=optimum_m, length_ratio=1.0 if optimum_m else None,
                min_clearance_m=check_path(problem, optimum.path).min_clearance_m if optimum.path is not None else None,
                time_median_ms=1e3 * optimum.time_s, time_p90_ms=1e3 * optimum.time_s, times_ms=[1e3 * optimum.time_s],
                time_meaning="one exact tangent-graph search",
            ))
            results.append(ScenarioResult(
                name=scenario.name, obstacles=len(scenario.obstacles), grown_ellipses=len(problem.grown),
                optimum_m=optimum_m, optimum_note="exact tangent graph of the grown ellipses",
                reference_m=references.get(scenario.name), planners=rows,
            ))
        progress.update(task, description="fitting micro-benchmark")
        from cvxnav.bench.fitting import fit_benchmark, scaling_benchmark

        fit = fit_benchmark(counts=options.fit_counts, repeats=options.fit_repeats, sets=options.fit_sets,
                            with_drake=not peers["drake"])
        progress.advance(task)
        progress.update(task, description="scaling: random fields")
        scaling = (
            scaling_benchmark(counts=options.scaling_counts, repeats=options.scaling_repeats)
            if options.scaling_counts
            else None
        )
        progress.advance(task)
        progress.update(task, description="done")
    return BenchReport(
        command=command, machine=_machine(), quick=options.quick, repeats=options.repeats,
        sampling_budget_s=options.sampling_budget_s, collision_tolerance_m=COLLISION_TOLERANCE_M, notes=notes,
        scenarios=results, fit=fit, scaling=scaling, targets=_targets(results, fit, scaling), maps=map_result,
        wall_s=time.perf_counter() - started,
    )


def _targets(results: list[ScenarioResult], fit: list[FitResult], scaling: ScalingResult | None) -> TargetRatios:
    """The issue's three targets as ratios measured in this run."""
    ratios, time_ratios, lower, intervals = [], {}, {}, {}
    for scenario in results:
        by_name = {p.planner: p for p in scenario.planners}
        ours, bit = by_name.get(CVXNAV), by_name.get(BITSTAR)
        if ours is not None and ours.success and ours.length_ratio is not None:
            ratios.append(ours.length_ratio)
        if ours is not None and bit is not None and ours.time_median_ms and bit.time_median_ms and ours.success:
            time_ratios[scenario.name] = ours.time_median_ms / bit.time_median_ms
            lower[scenario.name] = bit.target_reached != bit.repeats
            if (interval := ratio_interval(ours.times_ms, bit.times_ms)) is not None:
                intervals[scenario.name] = interval
    fit_ratio: dict[str, float | None] = {}
    fit_intervals: dict[str, tuple[float, float]] = {}
    for count in sorted({f.points for f in fit}):
        fast = next((f for f in fit if f.points == count and f.method.startswith("mvee_fast")), None)
        drake = next((f for f in fit if f.points == count and f.method.startswith("Drake")), None)
        if fast and drake and fast.time_median_ms and drake.time_median_ms:
            fit_ratio[str(count)] = fast.time_median_ms / drake.time_median_ms
            if (interval := ratio_interval(fast.times_ms, drake.times_ms)) is not None:
                fit_intervals[str(count)] = interval
    return TargetRatios(length_ratio_worst=max(ratios) if ratios else None, time_ratio_vs_bitstar=time_ratios,
                        time_ratio_vs_bitstar_is_lower_bound=lower, time_ratio_vs_bitstar_interval=intervals,
                        fit_ratio_vs_drake=fit_ratio, fit_ratio_vs_drake_interval=fit_intervals,
                        growth_exponent=scaling.growth_exponent if scaling else None)


# --------------------------------------------------------------------------- rendering


def _num(value: float | None, fmt: str) -> str:
    return "—" if value is None else format(value, fmt)


_HEADER = ("scenario", "planner", "ok", "length m", "÷ optimum", "median ms", "p90 ms", "cold ms",
           "1st sol ms", "to 1 %", "peak KiB", "note")


def _rows(report: BenchReport) -> list[tuple[str, ...]]:
    rows = []
    for scenario in report.scenarios:
        ref = f" (ref {scenario.reference_m:.3f})" if scenario.reference_m else ""
        for k, p in enumerate(scenario.planners):
            rows.append((
                f"{scenario.name}{ref}" if k == 0 else "",
                p.planner,
                "yes" if p.success else ("COLLIDES" if p.collision else "no"),
                _num(p.length_m, ".3f"),
                _num(p.length_ratio, ".4f"),
                _num(p.time_median_ms, ".1f"),
                _num(p.time_p90_ms, ".1f"),
                _num(p.cold_ms, ".0f"),
                _num(p.first_solution_ms, ".1f"),
                "—" if p.target_reached is None else f"{p.target_reached}/{p.repeats}",
                _num(p.peak_memory_kib, ".0f"),
                p.reason[:160],
            ))
    return rows


def _target_lines(report: BenchReport) -> list[str]:
    t = report.targets
    lines = [f"length ÷ grown-ellipse optimum, worst over scenarios (target ≤ 1.01): {_num(t.length_ratio_worst, '.4f')}"]
    for name, ratio in t.time_ratio_vs_bitstar.items():
        bound = " (BIT* missed 1 % in budget: ratio vs budget)" if t.time_ratio_vs_bitstar_is_lower_bound.get(name) else ""
        spread = _spread(t.time_ratio_vs_bitstar_interval.get(name))
        lines.append(f"time ÷ BIT* time to 1 %, {name} (target ≤ 1): {_num(ratio, '.2f')}{spread}{bound}")
    for count, ratio in t.fit_ratio_vs_drake.items():
        lines.append(f"fit time mvee_fast ÷ Drake, {count} points (target ≤ 1): {_num(ratio, '.2f')}"
                     f"{_spread(t.fit_ratio_vs_drake_interval.get(count))}")
    lines.append(f"planning-time growth exponent in obstacles (target ≤ 1): {_num(t.growth_exponent, '.2f')}")
    if report.scaling and (steep := _steepest(report.scaling)):
        lines.append(f"steepest local growth exponent: {steep[1]:.2f} ({steep[0]} obstacles)")
    return lines


def _spread(interval: tuple[float, float] | None) -> str:
    return f" (95 % interval {interval[0]:.2f}–{interval[1]:.2f})" if interval else ""


def _steepest(scaling: ScalingResult) -> tuple[str, float] | None:
    """(obstacle counts, exponent) of the steepest step between successive successful scaling points."""
    usable = [p for p in scaling.points if p.success and p.time_median_ms]
    steps = [(f"{a.obstacles} → {b.obstacles}", b.local_exponent) for a, b in zip(usable, usable[1:])]
    return max(steps, key=lambda step: step[1], default=None)


_FIT_HEADER = ("points", "sets", "method", "median ms", "worst area rel. diff", "error")


def _fit_rows(report: BenchReport) -> list[tuple[str, ...]]:
    return [(str(f.points), str(f.point_sets), f.method, _num(f.time_median_ms, ".3f"), _num(f.area_rel_diff, ".1e"),
             f.error) for f in report.fit]


def print_report(report: BenchReport, *, console: Console) -> None:
    if report.maps is not None:
        from cvxnav.bench.maps import map_tables, map_target_lines

        for title, header, rows in map_tables(report.maps):
            table = Table(title=title)
            for column in header:
                table.add_column(column)
            for row in rows:
                table.add_row(*row)
            console.print(table)
        for line in map_target_lines(report.maps):
            console.print(f"• {line}")
    if not report.scenarios:
        return
    table = Table(title=f"cvxnav bench ({'quick' if report.quick else 'full'}, {report.repeats} repeats)")
    for column in _HEADER[:-1]:
        table.add_column(column, no_wrap=True)
    notes = []
    for row in _rows(report):
        # Notes are long: numbered under the table so the numbers stay readable in 120 columns.
        if row[-1]:
            notes.append(row[-1])
        table.add_row(*row[:-2], row[-2] + (f" [{len(notes)}]" if row[-1] else ""))
    console.print(table)
    for k, note in enumerate(notes, start=1):
        console.print(f"[{k}] {note}", markup=False, highlight=False)
    fit = Table(title="minimum-volume ellipse fit")
    for column in _FIT_HEADER:
        fit.add_column(column)
    for row in _fit_rows(report):
        fit.add_row(*row)
    console.print(fit)
    if report.scaling:
        scale = Table(title=f"scaling (growth exponent {_num(report.scaling.growth_exponent, '.2f')})")
        for column in ("obstacles", "grown ellipses", "median ms", "local exponent", "ok"):
            scale.add_column(column)
        for s in report.scaling.points:
            scale.add_row(str(s.obstacles), str(s.grown_ellipses), _num(s.time_median_ms, ".0f"),
                          _num(s.local_exponent, ".2f"), "yes" if s.success else "no")
        console.print(scale)
    for line in _target_lines(report) + report.notes:
        console.print(f"• {line}")


def to_markdown(report: BenchReport) -> str:
    """The same tables as GitHub Markdown."""
    def table(header: Sequence[str], rows: list[Sequence[str]]) -> list[str]:
        clean = [[str(c).replace("|", "\\|") for c in row] for row in rows]
        return ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)] + ["| " + " | ".join(r) + " |" for r in clean]

    m = report.machine
    out = [f"Machine: {m.processor}, {m.cpus} CPUs, {m.platform}, Python {m.python}; "
           + ", ".join(f"{k} {v}" for k, v in m.packages.items()) + ".",
           f"Command: `{report.command}` ({report.wall_s:.0f} s wall).", ""]
    if report.maps is not None:
        from cvxnav.bench.maps import map_tables, map_target_lines

        for title, header, rows in map_tables(report.maps):
            out += [f"**{title}**", ""] + table(header, rows) + [""]
        out += [f"- {line}" for line in map_target_lines(report.maps)] + [""]
    if not report.scenarios:
        return "\n".join(out) + "\n"
    out += table(_HEADER, _rows(report)) + [""]
    out += table(_FIT_HEADER, _fit_rows(report)) + [""]
    if report.scaling:
        out += table(("obstacles", "grown ellipses", "cvxnav median ms", "local exponent", "ok"),
                     [(str(s.obstacles), str(s.grown_ellipses), _num(s.time_median_ms, ".0f"),
                       _num(s.local_exponent, ".2f"), "yes" if s.success else "no")
                      for s in report.scaling.points]) + [""]
    out += [f"- {line}" for line in _target_lines(report) + report.notes]
    return "\n".join(out) + "\n"


def command_line(argv: Sequence[str] | None = None) -> str:
    return "cvxnav " + " ".join(sys.argv[1:] if argv is None else argv)
