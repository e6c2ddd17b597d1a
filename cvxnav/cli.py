"""The `cvxnav` command line (CONTRACTS §3). Every error is one line; exit codes are the contract's."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from pathlib import Path

EXIT_OK = 0
EXIT_BAD_INPUT = 2
EXIT_NO_PATH = 3
EXIT_TIMEOUT_OR_COLLISION = 4


class CliError(Exception):
    """Bad input: printed as one line, exit code 2."""


def _load(scenario: Path | None):
    from schemas.scenario import ScenarioError, bundled_scenario, load_scenario

    try:
        return bundled_scenario() if scenario is None else load_scenario(scenario)
    except ScenarioError as error:
        raise CliError(str(error)) from None


def _cmd_plan(args: argparse.Namespace) -> int:
    import numpy as np

    from cvxnav.geometry import polyline_length
    from cvxnav.plan import plan_scenario

    scenario = _load(args.scenario)
    plan = plan_scenario(scenario)
    plan.write(args.out)
    if plan.status != "ok":
        print(f"{scenario.name}: no path to the goals ({plan.timings_ms.total:.0f} ms) -> {args.out}")
        return EXIT_NO_PATH
    path = np.array(plan.path)
    clearance = float(np.min(scenario.clearance(path))) if scenario.obstacles else float("inf")
    print(
        f"{scenario.name}: path {polyline_length(path):.2f} m, clearance {clearance:.3f} m "
        f"(needs {scenario.inflation_m:.3f}), planned in {plan.timings_ms.total:.0f} ms -> {args.out}"
    )
    return EXIT_OK


def _cmd_schemas(args: argparse.Namespace) -> int:
    from schemas.export import export_json_schemas

    written = export_json_schemas(args.out)
    print(f"wrote {len(written)} JSON Schemas to {args.out}")
    return EXIT_OK


class _Parser(argparse.ArgumentParser):
    def error(self, message: str) -> None:  # one line, exit 2, like every other bad input
        self.exit(EXIT_BAD_INPUT, f"{self.prog}: error: {message}\n")


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="cvxnav", description="Mobile-robot motion planning by convex optimisation.")
    commands = parser.add_subparsers(dest="command", required=True, parser_class=_Parser)

    plan = commands.add_parser("plan", help="plan once on a known map, in one process")
    plan.add_argument("scenario", nargs="?", type=Path, help="scenario file (default: the paper's)")
    plan.add_argument("--out", type=Path, default=Path("plan.json"), help="plan file to write")
    plan.set_defaults(handler=_cmd_plan)

    schemas = commands.add_parser("schemas", help="write every message model as JSON Schema")
    schemas.add_argument("--out", type=Path, default=Path("schemas-json"), help="directory to write")
    schemas.set_defaults(handler=_cmd_schemas)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return args.handler(args)
    except CliError as error:
        print(f"cvxnav: error: {error}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":
    sys.exit(main())
