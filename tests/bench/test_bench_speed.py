"""pytest-benchmark timings of the fit and the plan. CI runs them once as plain tests
(`--benchmark-disable` in addopts); `pytest tests/bench --benchmark-enable -n 0` times them (pytest-benchmark
times nothing under xdist's workers)."""

from __future__ import annotations

import numpy as np
import pytest

from cvxnav.bench.fitting import _fit_points
from cvxnav.bench.planners import plan_cvxnav
from cvxnav.bench.problem import BenchProblem, check_path
from schemas.scenario import load_scenario
from services.ellipsoids.mvee import mvee, mvee_fast


@pytest.mark.parametrize("count", [20, 100, 1000])
@pytest.mark.parametrize("fit", [mvee, mvee_fast], ids=["cvxpy", "numpy"])
def test_fit(benchmark, fit, count):
    points = _fit_points(count, seed=count)
    ellipse = benchmark(fit, points)
    assert np.max(ellipse.level(points)) <= 1.0 + 1e-9


def test_fit_drake(benchmark):
    optimization = pytest.importorskip("pydrake.geometry.optimization")
    points = np.asfortranarray(_fit_points(100, seed=100).T)
    ellipse = benchmark(optimization.Hyperellipsoid.MinimumVolumeCircumscribedEllipsoid, points)
    assert np.pi / abs(np.linalg.det(ellipse.A())) == pytest.approx(mvee_fast(points.T).area, rel=1e-6)


@pytest.mark.parametrize("name", ["field-8", "paper-two-goals"])
def test_plan(benchmark, scenarios_dir, name):
    problem = BenchProblem.of(load_scenario(scenarios_dir / f"{name}.json"))
    attempt = benchmark.pedantic(plan_cvxnav, args=(problem,), rounds=3, warmup_rounds=1)
    assert attempt.path is not None
    check = check_path(problem, attempt.path)
    assert check.reaches_goals and not check.collides
