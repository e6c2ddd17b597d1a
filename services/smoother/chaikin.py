"""An alternative smoother: Chaikin corner cutting, then the same clamped cubic B-spline and `verify`.

Chaikin's scheme (1974) replaces every control edge PQ by the points ¾P + ¼Q and ¼P + ¾Q, keeping the
two end points. Repeated, it converges to the quadratic B-spline of the polygon; here a few rounds
round the control polygon's corners before the cubic B-spline of `services.smoother.core` is built, so
the curve is rounder and lies farther inside the corners than the default smoother's. It is shipped to
show a stage being swapped (`cvxnav run` with `stages: {"smoother": "services.smoother.chaikin:factory"}`):
the curve it publishes passes exactly the same verification (`verify`) as the default one.
"""

from __future__ import annotations

import numpy as np

from cvxnav.geometry import Ellipse, FloatArray
from schemas.scenario import Scenario
from services.smoother.core import Smoothed, bspline, sample, verify
from services.smoother.stage import SmootherConfig, SmootherStage

ROUNDS = 2


def chaikin(points: FloatArray, *, rounds: int = ROUNDS) -> FloatArray:
    """Corner-cut the polyline `rounds` times; the first and last points stay where they are."""
    z = np.asarray(points, dtype=float)
    for _ in range(rounds):
        if len(z) < 3:
            break
        p, q = z[:-1], z[1:]
        cut = np.empty((2 * len(p), 2))
        cut[0::2] = 0.75 * p + 0.25 * q
        cut[1::2] = 0.25 * p + 0.75 * q
        z = np.vstack([z[:1], cut[1:-1], z[-1:]])
    return z


def smooth_chaikin(
    control: FloatArray,
    *,
    ellipses: list[Ellipse],
    max_curvature: float,
    heading_rad: float | None,
    goals: FloatArray,
    goal_tolerance_m: float,
    bounds_min: FloatArray,
    bounds_max: FloatArray,
    output_spacing_m: float = 0.05,
) -> Smoothed:
    """Same contract as `services.smoother.core.smooth`, with a Chaikin-rounded control polygon."""
    control = np.asarray(control, dtype=float)
    curve = bspline(chaikin(control))
    verification = verify(curve, ellipses=ellipses, max_curvature=max_curvature, start=control[0],
                          heading_rad=heading_rad, goals=goals, goal_tolerance_m=goal_tolerance_m,
                          bounds_min=bounds_min, bounds_max=bounds_max)
    return Smoothed(points=sample(curve, spacing_m=output_spacing_m), verification=verification)


def factory(scenario: Scenario) -> SmootherStage:
    """Entry point named in a `stages` config: the smoother stage with Chaikin smoothing."""
    return SmootherStage(config=SmootherConfig.from_scenario(scenario), smooth_fn=smooth_chaikin)
