"""The planner on a map nobody here drew: MovingAI's `arena` (`shared/external/movingai`), walls and
pillars of 1 m cells, with the benchmark's own queries.

Its walls are long thin rectangles (45 of them), which the known-map fit covers with 2092 ellipses.
Every query the paper's car can start and end in is planned on that one fitted model: the path keeps
the car's margin from the true walls and is within 1 % of the exact optimum on the grown covers. A query that starts or ends half a
cell from a wall, closer than the car's margin, is no path, and says why.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from cvxnav.bench import planners
from cvxnav.bench.problem import BenchProblem, check_path
from cvxnav.plan import plan_on_model
from schemas.scenario import Scenario, bundled_scenario
from services.geometry import polyline_length

PAPER = bundled_scenario()  # the paper's car and sensor


def _rectangles(rows: list[str]) -> list[tuple[int, int, int, int]]:
    """The blocked cells as rectangles (x₀, y₀, x₁, y₁): runs along each row, joined down the rows while
    the same run continues. Cell (x, y) is column x of row y and covers [x, x + 1] × [y, y + 1]."""
    rectangles, open_runs = [], {}
    for y, row in enumerate(rows):
        runs, x = [], 0
        while x < len(row):
            if row[x] in ".G":
                x += 1
                continue
            start = x
            while x < len(row) and row[x] not in ".G":
                x += 1
            runs.append((start, x))
        rectangles += [(x0, y0, x1, y) for (x0, x1), y0 in open_runs.items() if (x0, x1) not in runs]
        open_runs = {run: open_runs.get(run, y) for run in runs}
    rectangles += [(x0, y0, x1, len(rows)) for (x0, x1), y0 in open_runs.items()]
    return rectangles


def _scenario(rows: list[str], query: list[str]) -> Scenario:
    """One line of the `.scen` file (bucket, map, width, height, start x, y, goal x, y, optimal length) as
    a scenario: start and goal at their cells' centres, the car heading for the goal."""
    (sx, sy), (gx, gy) = [(int(query[k]) + 0.5, int(query[k + 1]) + 0.5) for k in (4, 6)]
    return Scenario.model_validate({
        "format": "cvxnav.scenario/1",
        "name": f"arena-{query[4]}-{query[5]}-{query[6]}-{query[7]}",
        "bounds": {"min": [0, 0], "max": [len(rows[0]), len(rows)]},
        "robot": PAPER.robot.model_dump(),
        "sensor": PAPER.sensor.model_dump(),
        "start": {"x": sx, "y": sy, "theta": math.atan2(gy - sy, gx - sx)},
        "goals": [[gx, gy]],
        "goal_tolerance": 0.3,
        "expect": "reach",
        "obstacles": [{"type": "polygon", "vertices": [[x0, y0], [x1, y0], [x1, y1], [x0, y1]]}
                      for x0, y0, x1, y1 in _rectangles(rows)],
    })


@pytest.fixture(scope="module")
def arena(shared_dir: Path) -> tuple[list[str], list[list[str]], list]:
    """The map's rows, its queries, and the grown covers of its walls, fitted once."""
    folder = shared_dir / "external" / "movingai"
    if not (folder / "arena.map").is_file():
        pytest.skip(f"{folder / 'arena.map'} is absent")
    rows = (folder / "arena.map").read_text().split("map\n", 1)[1].split()
    queries = [line.split("\t") for line in (folder / "arena.map.scen").read_text().splitlines()[1:] if line]
    return rows, queries, BenchProblem.of(_scenario(rows, queries[0])).grown


def test_the_wall_runs_make_up_the_map_exactly(arena):
    rows, _, _ = arena
    covered = np.zeros((len(rows), len(rows[0])), dtype=int)
    for x0, y0, x1, y1 in _rectangles(rows):
        covered[y0:y1, x0:x1] += 1
    assert np.array_equal(covered, [[c not in ".G" for c in row] for row in rows])  # each blocked cell once


@pytest.mark.parametrize("index", [0, 1, 2, 3, 5, 6])
def test_a_query_is_planned_clear_of_the_true_walls_within_1_percent_of_the_optimum(arena, index):
    rows, queries, grown = arena
    problem = BenchProblem(scenario=_scenario(rows, queries[index]), grown=grown)
    plan, smoothed = plan_on_model(problem.scenario, grown)
    assert plan.status == "ok" and smoothed is not None and smoothed.verification.ok
    check = check_path(problem, smoothed.points)
    assert check.reaches_goals and not check.collides
    assert check.min_clearance_m >= problem.scenario.inflation_m - 0.02
    optimum = planners.plan_optimum(problem)
    assert polyline_length(smoothed.points) <= 1.01 * sum(optimum.extra.values())


@pytest.mark.parametrize("index, which", [(4, "a goal"), (7, "start")])
def test_a_query_half_a_cell_from_a_wall_is_no_path_with_the_reason(arena, index, which):
    rows, queries, grown = arena
    plan, smoothed = plan_on_model(_scenario(rows, queries[index]), grown)
    assert plan.status == "no_path" and smoothed is None
    assert plan.reason == f"{which} lies inside an obstacle's grown ellipse"
