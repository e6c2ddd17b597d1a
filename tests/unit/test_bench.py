"""The benchmark's own correctness: on one disc every planner's length matches the analytic optimum
(tangent, arc, tangent) within the tolerance its method allows, and a colliding path is a failure."""

from __future__ import annotations

import dataclasses
import json
import math

import numpy as np
import pytest

from cvxnav.bench import planners
from cvxnav.bench.problem import BenchProblem, check_path
from cvxnav.bench.runner import PlannerSpec, summarise
from schemas.scenario import Scenario, parse_scenario

DISC_CENTRE = (5.0, 0.0)
DISC_RADIUS_M = 1.0
GOAL = (10.0, 0.0)


def _one_disc(*, heading_rad: float) -> Scenario:
    document = {
        "format": "cvxnav.scenario/1",
        "name": "one-disc",
        "bounds": {"min": [-2.0, -5.0], "max": [12.0, 5.0]},
        "robot": {"width": 0.3, "length": 0.6, "wheelbase": 0.6, "safety_distance": 0.5, "max_speed": 1.0,
                  "max_steering_angle": 0.6, "max_steering_rate": 0.5},
        "sensor": {"fov_deg": 180.0, "range": 5.0, "rays": 181, "rate_hz": 10.0},
        "start": {"x": 0.0, "y": 0.0, "theta": heading_rad},
        "goals": [list(GOAL)],
        "goal_tolerance": 0.3,
        "obstacles": [{"type": "circle", "center": list(DISC_CENTRE), "radius": DISC_RADIUS_M}],
        "expect": "reach",
    }
    return parse_scenario(json.dumps(document))


def _tangent_arc_tangent_m(*, distance_m: float, radius_m: float) -> float:
    """Shortest path between two points at `distance_m` either side of a disc's centre, on one line.

    Two tangents of length √(d² − R²) and the arc between their touching points: each tangent turns
    the radius by acos(R / d) away from the line, leaving an arc of π − 2 acos(R / d).
    """
    d, r = distance_m, radius_m
    return 2.0 * math.sqrt(d * d - r * r) + r * (math.pi - 2.0 * math.acos(r / d))


@pytest.fixture(scope="module")
def disc() -> tuple[BenchProblem, float]:
    # Probe the grown model once, then point the start heading along the first tangent so that the
    # curvature-bounded cvxnav path and the point-robot optimum are the same curve.
    probe = BenchProblem.of(_one_disc(heading_rad=0.0))
    (grown,) = probe.grown
    a, b = grown.semi_axes
    assert a == pytest.approx(b, rel=1e-9), "a disc's cover grows into a circle"
    np.testing.assert_allclose(grown.center, DISC_CENTRE, atol=1e-9)
    problem = BenchProblem.of(_one_disc(heading_rad=math.asin(a / 5.0)))
    return problem, _tangent_arc_tangent_m(distance_m=5.0, radius_m=a)


def _length(problem: BenchProblem, attempt: planners.Attempt) -> float:
    assert attempt.path is not None, attempt.reason
    check = check_path(problem, attempt.path)
    assert not check.collides and check.reaches_goals
    return check.length_m


def test_optimum_matches_the_analytic_length(disc):
    problem, analytic_m = disc
    attempt = planners.plan_optimum(problem)
    # The exact tangent graph: tangent, arc, tangent, to rounding.
    assert sum(attempt.extra.values()) == pytest.approx(analytic_m, rel=1e-9)
    # The path drawn round the arc is circumscribed: never shorter, at most 1/cos(π/32) − 1 longer.
    assert analytic_m * (1 - 1e-9) <= _length(problem, attempt) <= analytic_m / np.cos(np.pi / 32)


def test_cvxnav_is_within_one_percent_of_the_analytic_length(disc):
    problem, analytic_m = disc
    length = _length(problem, planners.plan_cvxnav(problem))
    # It keeps ‖A z + b‖ ≥ 1.02 (a margin for the smoothed curve), so it runs a little outside the disc.
    assert analytic_m * (1 - 1e-3) <= length <= analytic_m * 1.01


@pytest.mark.parametrize("algorithm", ["BITstar", "InformedRRTstar"])
def test_ompl_stops_within_its_one_percent_target(disc, algorithm):
    pytest.importorskip("ompl")
    problem, analytic_m = disc
    attempt = planners.plan_ompl(problem, planner=algorithm, budget_s=3.0, leg_optima_m=[analytic_m])
    length = _length(problem, attempt)
    assert attempt.target_s is not None, attempt.reason
    assert attempt.first_solution_s is not None and attempt.first_solution_s <= attempt.target_s
    # Motions are checked exactly against the grown disc: no path can be shorter than the optimum.
    assert analytic_m * (1 - 1e-9) <= length <= analytic_m * 1.01 * (1 + 1e-9)


def test_drake_gcs_is_feasible_and_near_the_analytic_length(disc):
    pytest.importorskip("pydrake")
    problem, analytic_m = disc
    length = _length(problem, planners.plan_drake_gcs(problem, max_regions=12, seed=0))
    # IRIS regions are polytopes inside the free space, so the path cannot hug the circle: a few
    # percent longer, never shorter.
    assert analytic_m * (1 - 1e-6) <= length <= analytic_m * 1.08


def test_the_paper_baseline_detours_round_the_disc(disc):
    problem, analytic_m = disc
    attempt = planners.plan_paper(problem)
    assert attempt.path is not None
    # Straight to the disc, half way round it (the line passes its centre), straight on: 2 (d − R) + πR,
    # then the unverified smoothing cuts the two corners, so a little less.
    (radius_m, _) = problem.grown[0].semi_axes
    detour_m = 2.0 * (5.0 - radius_m) + math.pi * radius_m
    length = check_path(problem, attempt.path).length_m
    assert analytic_m < length <= detour_m * 1.01


def test_a_colliding_planner_is_reported_failed_not_fast(disc):
    problem, analytic_m = disc
    through = np.array([problem.start, problem.goals[0]])  # straight through the disc, instantly
    spec = PlannerSpec("straight line", lambda p, s: planners.Attempt(path=through, time_s=1e-6), 1, "none")
    result = summarise(spec, problem, [spec.call(problem, 0)], optimum_m=analytic_m, cold_s=None, peak_kib=None)
    assert result.collision and not result.success
    assert "collides" in result.reason
    assert result.min_clearance_m is not None and result.min_clearance_m <= 0.0


def test_a_planner_that_returns_nothing_is_reported_failed(disc):
    problem, analytic_m = disc
    spec = PlannerSpec("nothing", lambda p, s: planners.Attempt(path=None, time_s=0.0, reason="gave up"), 1, "none")
    result = summarise(spec, problem, [spec.call(problem, 0)], optimum_m=analytic_m, cold_s=None, peak_kib=None)
    assert not result.success and not result.collision and "gave up" in result.reason
    assert result.length_m is None and result.length_ratio is None


def test_drake_on_circumscribed_polygons_is_feasible_in_the_ellipse_model(disc):
    pytest.importorskip("pydrake")
    problem, analytic_m = disc
    attempt = planners.plan_drake_gcs(problem, max_regions=12, seed=0, obstacle_shape="polygons")
    length = _length(problem, attempt)
    assert check_path(problem, attempt.path).min_model_level >= 1.0 - 1e-6
    assert analytic_m * (1 - 1e-6) <= length <= analytic_m * 1.08


def test_missing_peers_are_skipped_with_a_note_that_says_how_to_install(disc, monkeypatch):
    from rich.console import Console

    from cvxnav.bench import runner

    problem, _ = disc
    why = {"ompl": "ompl not importable (ImportError); install the extra: pip install -e \".[bench]\"",
           "drake": "drake not importable (ImportError); install the extra: pip install -e \".[bench]\""}
    monkeypatch.setattr(runner.planners, "peer_status", lambda: why)
    options = runner.BenchOptions(repeats=1, fit_counts=(), scaling_counts=())
    report = runner.run_bench(scenarios=[problem.scenario], options=options, command="test",
                              console=Console(file=None, quiet=True), show_progress=False)
    names = [p.planner for p in report.scenarios[0].planners]
    assert names == [runner.CVXNAV, runner.PAPER, runner.OPTIMUM]
    assert sum("skipped" in note and "pip install" in note for note in report.notes) == 2
    assert report.targets.time_ratio_vs_bitstar == {} and report.scaling is None


def test_planners_are_timed_in_turns_the_fast_ones_until_enough_time_is_measured(disc):
    from cvxnav.bench import runner

    problem, _ = disc
    order: list[str] = []

    def paper(name: str):
        def call(p: BenchProblem, k: int) -> planners.Attempt:
            order.append(name)
            # The paper's method really plans; its time is set to 10 ms so the count is the machine's load's to
            # decide no more.
            return dataclasses.replace(planners.plan_paper(p), time_s=0.01)
        return call

    specs = [runner.PlannerSpec("exact", paper("exact"), 3, ""),
             runner.PlannerSpec("timed", paper("timed"), 3, "", timed_s=0.045),
             runner.PlannerSpec("capped", paper("capped"), 3, "", timed_s=60.0)]
    attempts = runner._in_turns(specs, problem, max_repeats=7, seed=0)
    assert len(attempts["exact"]) == 3 and len(attempts["capped"]) == 7
    assert len(attempts["timed"]) == 5  # past 3 calls, until their times sum to 45 ms or more
    assert all(a.path is not None for a in attempts["timed"])
    assert sorted(order[:3]) == sorted(order[3:6]) == ["capped", "exact", "timed"]  # one call each per round


@pytest.mark.parametrize("count", [10, 25, 200])
def test_every_scaling_field_blocks_the_straight_line(count):
    """Each point of the scaling run measures planning (a route and its refinement), never the
    straight-line shortcut a sparse field could otherwise leave open."""
    from cvxnav.bench.fitting import random_field
    from services.planner.core import intersected

    scenario = random_field(obstacles=count, seed=7 + count)
    assert len(scenario.obstacles) == count
    problem = BenchProblem.of(scenario)
    assert len(intersected(np.vstack([problem.start, problem.goals]), problem.grown))


def test_the_time_ratio_interval_holds_the_ratio_and_narrows_with_more_calls():
    from cvxnav.bench.turns import ratio_interval

    rng = np.random.default_rng(3)
    ours, theirs = rng.gamma(4.0, 1.0, 400), rng.gamma(4.0, 1.25, 400)  # medians' ratio about 0.8
    few, many = ratio_interval(ours[:30], theirs[:30]), ratio_interval(ours, theirs)
    assert many[0] < np.median(ours) / np.median(theirs) < many[1]
    assert few[0] < np.median(ours[:30]) / np.median(theirs[:30]) < few[1]
    assert many[1] - many[0] < 0.5 * (few[1] - few[0])  # about 1/sqrt(400/30) as wide
    assert ratio_interval(ours, theirs) == many  # seeded: the same report from the same times
    assert ratio_interval(ours[:1], theirs) is None  # one call has no spread to resample


def test_the_fit_is_timed_on_the_sets_every_method_solves_and_a_failure_is_reported():
    """Drake's solver gives up on one of the ten 1000-point sets (Clarabel: InsufficientProgress); every
    method is then timed on the other nine, and Drake's row says where it failed."""
    pytest.importorskip("pydrake")
    from cvxnav.bench.fitting import fit_benchmark

    rows = {r.method.split()[0]: r for r in fit_benchmark(counts=(1000,), repeats=3, with_drake=True)}
    assert rows["Drake"].error.startswith("failed on 1 of 10 sets: RuntimeError")
    for row in rows.values():
        assert row.point_sets == 9 and len(row.times_ms) == 3
        assert row.area_rel_diff <= 1e-6  # against the cvxpy route, on each of the nine sets
    assert not rows["mvee_fast"].error and not rows["mvee"].error


@pytest.mark.parametrize("dubins", [False, True])
def test_bitstar_on_a_map_plans_through_every_goal_in_order(tmp_path, dubins: bool):
    """A waypoint file: BIT* (point and Dubins car) goes leg by leg through both goals, clear of the walls."""
    pytest.importorskip("ompl")
    from cvxnav.bench.maps import _scenario_doc, _write_map, call_bitstar, judge
    from schemas.scenario import load_scenario

    pixels = np.full((160, 160), 254)  # an 8 m room at 0.05 m, a wall round it
    pixels[[0, -1], :] = pixels[:, [0, -1]] = 0
    doc = _scenario_doc("two-goals", map_path=_write_map(tmp_path, "room", pixels, resolution_m=0.05),
                        start=(1.5, 1.5, 0.0), goal=(6.5, 1.5), description="")
    doc["goals"].append([1.5, 6.5])
    (tmp_path / "two-goals.json").write_text(json.dumps(doc))
    attempt = call_bitstar(tmp_path / "two-goals.json", dubins=dubins, budget_s=0.5, target_m=None)
    assert attempt.path is not None, attempt.reason
    judged = judge(load_scenario(tmp_path / "two-goals.json"), attempt.path)
    assert judged.reaches and not judged.collides


def test_a_map_case_is_timed_in_a_process_of_its_own_its_progress_and_failure_relayed(tmp_path):
    """`cvxnav bench` on maps runs each case in a spawned process (what ran before in a process moves the
    grid planner's time): the child's progress reaches the caller, its result comes back, and a case that
    fails there fails here with the child's traceback."""
    from cvxnav.bench.maps import MapBenchOptions, MapCase, _isolated, _scenario_doc, _write_map, bench_case

    pixels = np.full((80, 120), 254)  # a 6 × 4 m room at 0.05 m, walled
    pixels[[0, -1], :] = pixels[:, [0, -1]] = 0
    doc = _scenario_doc("room", map_path=_write_map(tmp_path, "room", pixels, resolution_m=0.05),
                        start=(1.0, 2.0, 0.0), goal=(5.0, 2.0), description="")
    (tmp_path / "room.json").write_text(json.dumps(doc))
    options = MapBenchOptions(repeats=1, min_timed_s=0.0)
    steps: list[str] = []
    result = _isolated(bench_case, MapCase(tmp_path / "room.json", "a room"), options, with_ompl=False,
                       on_step=steps.append)
    assert steps[0] == "room: cold calls" and "room: in turns, round 1" in steps
    rows = {row.planner: row for row in result.planners}
    assert set(rows) == {"cvxnav", "grid (NavFn-like)"} and all(row.success for row in rows.values())
    assert rows["cvxnav"].length_m == pytest.approx(4.0, abs=1e-3)  # straight along the heading

    with pytest.raises(RuntimeError, match=r"(?s)failed in its process.*ScenarioError.*missing\.json"):
        _isolated(bench_case, MapCase(tmp_path / "missing.json", "none"), options, with_ompl=False,
                  on_step=steps.append)
