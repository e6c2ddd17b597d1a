"""The `cvxnav bench` subcommand: arguments and handler, kept here so `cvxnav/cli.py` needs two lines."""

from __future__ import annotations

import argparse
import json
import sys
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
    bench.add_argument("--closed-loop", action="store_true",
                       help="instead: drive each scenario's closed loop with the stage cores in this process "
                            "(outcome, length ÷ reference, per-stage latency)")
    bench.add_argument("--quiet", action="store_true", help="no progress bar")
    bench.set_defaults(handler=run_command)


def _scenarios(paths: list[Path], *, quick: bool) -> list:
    from cvxnav.bench.runner import default_scenario_dir
    from cvxnav.exits import CliError
    from schemas.scenario import ScenarioError, bundled_scenario, load_scenario

    if not paths:
        folder = default_scenario_dir()
        found = sorted(p for p in folder.glob("*.json") if p.name != "REFERENCE.json") if folder.is_dir() else []
        if quick:
            found = [p for p in found if p.stem in QUICK_SCENARIOS]
        if not found:
            return [bundled_scenario()]
        paths = found
    try:
        return [load_scenario(p) for p in paths]
    except ScenarioError as error:
        raise CliError(str(error)) from None


def run_command(args: argparse.Namespace) -> int:
    from dataclasses import replace

    from rich.console import Console

    from cvxnav.bench.report import BenchReport
    from cvxnav.bench.runner import BenchOptions, command_line, print_report, run_bench, to_markdown
    from cvxnav.exits import CliError

    if args.repeats is not None and args.repeats < 1:
        raise CliError(f"--repeats must be at least 1, got {args.repeats}")
    if args.budget_s is not None and not args.budget_s > 0:
        raise CliError(f"--budget-s must be positive, got {args.budget_s}")
    options = BenchOptions.quick_defaults(repeats=args.repeats) if args.quick else BenchOptions()
    if args.repeats is not None:  # exactly that many
        options = replace(options, repeats=args.repeats, min_timed_s=0.0)
    if args.budget_s is not None:
        options = replace(options, sampling_budget_s=args.budget_s)
    scenarios = _scenarios(list(args.scenarios), quick=args.quick)
    if args.closed_loop:
        return _closed_loop(scenarios, args)
    console = Console() if sys.stdout.isatty() else Console(width=160)
    report = run_bench(scenarios=scenarios, options=options, command=command_line(),
                       console=Console(stderr=True), show_progress=not args.quiet)
    print_report(report, console=console)
    if args.json is not None:
        args.json.write_text(report.model_dump_json(indent=1) + "\n", encoding="utf-8")
    if args.markdown is not None:
        args.markdown.write_text(to_markdown(report), encoding="utf-8")
    if args.schema is not None:
        args.schema.write_text(json.dumps(BenchReport.model_json_schema(), indent=1) + "\n", encoding="utf-8")
    return 0


def _closed_loop(scenarios: list, args: argparse.Namespace) -> int:
    from rich.console import Console
    from rich.markdown import Markdown
    from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

    from cvxnav.bench.closed_loop import ClosedLoopReport, closed_loop_markdown, run_closed_loop
    from cvxnav.bench.problem import reference_lengths
    from cvxnav.bench.runner import default_scenario_dir
    from sim.core import default_time_limit_s

    references = reference_lengths(default_scenario_dir() / "REFERENCE.json")
    rows = []
    columns = (TextColumn("[bold]{task.description}"), BarColumn(), TextColumn("sim {task.completed:5.1f} s"),
               TimeElapsedColumn())
    with Progress(*columns, console=Console(stderr=True), disable=args.quiet) as bar:
        for scenario in scenarios:
            task = bar.add_task(scenario.name, total=default_time_limit_s(scenario))
            rows.append(run_closed_loop(scenario, reference_m=references.get(scenario.name),
                                        on_step=lambda sim_s, task=task: bar.update(task, completed=sim_s)))
    report = ClosedLoopReport(rows=rows)
    table = closed_loop_markdown(report)
    Console(width=200).print(Markdown(table))
    if args.json is not None:
        args.json.write_text(report.model_dump_json(indent=1) + "\n", encoding="utf-8")
    if args.markdown is not None:
        args.markdown.write_text(table, encoding="utf-8")
    if args.schema is not None:
        args.schema.write_text(json.dumps(ClosedLoopReport.model_json_schema(), indent=1) + "\n", encoding="utf-8")
    return 0
