"""The `cvxnav bench` subcommand: arguments and handler, kept here so `cvxnav/cli.py` needs two lines."""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

QUICK_SCENARIOS = ("field-8", "paper-two-goals")


def add_bench_parser(commands: argparse._SubParsersAction) -> None:
    bench = commands.add_parser("bench", help="cvxnav against OMPL, Drake and the paper's method, side by side")
    bench.add_argument("scenarios", nargs="*", type=Path,
                       help="scenario files (default: every public scenario; --quick: field-8 and paper-two-goals)")
    bench.add_argument("--quick", action="store_true", help="CI smoke run: fewer scenarios and repeats, short budgets")
    bench.add_argument("--json", type=Path, default=None, help="write the report as JSON")
    bench.add_argument("--markdown", type=Path, default=None, help="write the tables as Markdown")
    bench.add_argument("--schema", type=Path, default=None, help="write the report's JSON Schema")
    bench.add_argument("--repeats", type=int, default=None,
                       help="timed repeats per planner, exactly (default: at least 5, quick 2, and a fast planner "
                            "again until 1 s, quick 0.05 s, of its time is measured, at most 200 calls)")
    bench.add_argument("--budget-s", type=float, default=None,
                       help="per-leg budget of the sampling planners (default 5, quick 1)")
    bench.add_argument("--maps", action="store_true",
                       help="also (or, with no scenarios, only) the occupancy-grid maps: the depot queries, MovingAI's "
                            "arena, ACES corridor queries, a 30 x 50 m map at 0.03 m; against a NavFn-like grid planner "
                            "and BIT*, timed from reading the map file (scenario/2 files given are benchmarked so too)")
    bench.add_argument("--maps-dir", type=Path, default=None,
                       help="where --maps writes the maps and scenario files it makes (default: a temporary directory)")
    bench.add_argument("--closed-loop", action="store_true",
                       help="instead: drive each scenario's closed loop with the stage cores in this process "
                            "(outcome, length ÷ reference, per-stage latency)")
    bench.add_argument("--deadline", action="store_true",
                       help="with --closed-loop: the planner answers each scan within its budget (the sensor "
                            "period), as in a live run, replanning in the background")
    bench.add_argument("--quiet", action="store_true", help="no progress bar")
    bench.set_defaults(handler=run_command)


def _scenarios(paths: list[Path], *, quick: bool, maps: bool) -> tuple[list, list[Path]]:
    """The scenario/1 scenarios (loaded) and the map scenarios' files (scenario/2 with an occupancy grid)."""
    from cvxnav.bench.runner import default_scenario_dir
    from cvxnav.exits import CliError
    from schemas.scenario import ScenarioError, bundled_scenario, load_scenario

    if not paths:
        if maps:
            return [], []
        folder = default_scenario_dir()
        found = sorted(p for p in folder.glob("*.json") if p.name != "REFERENCE.json") if folder.is_dir() else []
        if quick:
            found = [p for p in found if p.stem in QUICK_SCENARIOS]
        if not found:
            return [bundled_scenario()], []
        paths = found
    try:
        loaded = [(p, load_scenario(p)) for p in paths]
    except ScenarioError as error:
        raise CliError(str(error)) from None
    on_maps = [p for p, s in loaded if any(o.type == "occupancy_grid" for o in s.obstacles)]
    return [s for p, s in loaded if p not in on_maps], on_maps


def run_command(args: argparse.Namespace) -> int:
    from dataclasses import replace

    from rich.console import Console

    from cvxnav.bench.report import BenchReport
    from cvxnav.bench.runner import BenchOptions, command_line, print_report, run_bench, to_markdown
    from cvxnav.exits import CliError

    if args.repeats is not None and args.repeats < 1:
        raise CliError(f"--repeats must be at least 1, got {args.repeats}")
    if args.deadline and not args.closed_loop:
        raise CliError("--deadline is an option of --closed-loop")
    if args.budget_s is not None and not args.budget_s > 0:
        raise CliError(f"--budget-s must be positive, got {args.budget_s}")
    options = BenchOptions.quick_defaults(repeats=args.repeats) if args.quick else BenchOptions()
    if args.repeats is not None:  # exactly that many
        options = replace(options, repeats=args.repeats, min_timed_s=0.0)
    if args.budget_s is not None:
        options = replace(options, sampling_budget_s=args.budget_s)
    scenarios, map_files = _scenarios(list(args.scenarios), quick=args.quick, maps=args.maps)
    if args.closed_loop:
        from schemas.scenario import load_scenario

        return _closed_loop(scenarios + [load_scenario(p) for p in map_files], args, map_files=map_files)
    console = Console() if sys.stdout.isatty() else Console(width=160)
    with tempfile.TemporaryDirectory(prefix="cvxnav-maps-") as scratch:
        maps = None
        if args.maps or map_files:
            maps = _map_cases(map_files, args=args, work_dir=args.maps_dir or Path(scratch))
        report = run_bench(scenarios=scenarios, options=options, command=command_line(),
                           console=Console(stderr=True), show_progress=not args.quiet, maps=maps)
    print_report(report, console=console)
    if args.json is not None:
        args.json.write_text(report.model_dump_json(indent=1) + "\n", encoding="utf-8")
    if args.markdown is not None:
        args.markdown.write_text(to_markdown(report), encoding="utf-8")
    if args.schema is not None:
        args.schema.write_text(json.dumps(BenchReport.model_json_schema(), indent=1) + "\n", encoding="utf-8")
    return 0


def _map_cases(files: list[Path], *, args: argparse.Namespace, work_dir: Path):
    """The map suite (with --maps) and the scenario/2 files given, with their REFERENCE optimum if the file
    beside them has one; what `run_bench` needs to run them."""
    from cvxnav.bench.maps import MapBenchOptions, MapCase, write_map_suite
    from cvxnav.bench.problem import reference_lengths
    from cvxnav.bench.runner import MapRun, default_scenario_dir

    shared = default_scenario_dir().parent
    cases = write_map_suite(work_dir, shared=shared, quick=args.quick) if args.maps else []
    for path in files:
        reference = reference_lengths(path.parent / "REFERENCE.json").get(path.stem)
        cases.append(MapCase(path, "given", reference))
    options = (MapBenchOptions(repeats=1, min_timed_s=0.0, sampling_budget_s=args.budget_s or 1.0, growth_tiles=(1, 2),
                               growth_repeats=1, memory=False) if args.quick else
               MapBenchOptions(sampling_budget_s=args.budget_s or 5.0))
    if args.repeats is not None:
        options = MapBenchOptions(**{**options.__dict__, "repeats": args.repeats, "min_timed_s": 0.0})
    return MapRun(cases=cases, options=options, work_dir=work_dir, shared=shared if args.maps else None)


def _closed_loop(scenarios: list, args: argparse.Namespace, *, map_files: list[Path] = ()) -> int:
    from rich.console import Console
    from rich.markdown import Markdown
    from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

    from cvxnav.bench.closed_loop import ClosedLoopReport, closed_loop_markdown, run_closed_loop
    from cvxnav.bench.problem import reference_lengths
    from cvxnav.bench.runner import default_scenario_dir
    from sim.core import default_time_limit_s

    references = reference_lengths(default_scenario_dir() / "REFERENCE.json")
    for path in map_files:  # a map scenario's REFERENCE.json sits beside it
        references.update(reference_lengths(path.parent / "REFERENCE.json"))
    rows = []
    columns = (TextColumn("[bold]{task.description}"), BarColumn(), TextColumn("sim {task.completed:5.1f} s"),
               TimeElapsedColumn())
    with Progress(*columns, console=Console(stderr=True), disable=args.quiet) as bar:
        for scenario in scenarios:
            task = bar.add_task(scenario.name, total=default_time_limit_s(scenario))
            rows.append(run_closed_loop(scenario, reference_m=references.get(scenario.name), deadline=args.deadline,
                                        on_step=lambda sim_s, task=task: bar.update(task, completed=sim_s)))
    report = ClosedLoopReport(rows=rows, deadline=args.deadline)
    table = closed_loop_markdown(report)
    Console(width=200).print(Markdown(table))
    if args.json is not None:
        args.json.write_text(report.model_dump_json(indent=1) + "\n", encoding="utf-8")
    if args.markdown is not None:
        args.markdown.write_text(table, encoding="utf-8")
    if args.schema is not None:
        args.schema.write_text(json.dumps(ClosedLoopReport.model_json_schema(), indent=1) + "\n", encoding="utf-8")
    return 0
