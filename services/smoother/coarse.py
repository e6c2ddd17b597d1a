"""An alternative smoother: the same cubic B-spline over every other optimised point, same `verify`.

Halving the control points halves the spline's knots: the curve averages over twice the span, so it is
cheaper to build and check and rounds off the optimiser's small zig-zags, at the price of cutting
corners slightly more (which `verify` bounds against every ellipse). The first and last points (start
and final goal) are kept; the spacing stays uniform, because the spline's knots are.

Shipped to show a stage being swapped without the rest of the pipeline knowing:
`cvxnav run --stages stages.json` with `{"stages": {"smoother": "services.smoother.coarse:factory"}}`.
(A Chaikin corner-cutting variant was tried first: its denser polygon made the spline follow the
planned turns more tightly and broke the curvature bound by ~1 %, so every curve was rejected.)
"""

from __future__ import annotations

import numpy as np

from schemas.scenario import Scenario
from services.geometry import FloatArray
from services.smoother.core import Smoothed, smooth
from services.smoother.stage import SmootherConfig, SmootherStage

STRIDE = 2


def decimate(points: FloatArray, *, stride: int = STRIDE) -> FloatArray:
    """Every `stride`-th point and the last (uniform spacing: the spline's knots are uniform)."""
    z = np.asarray(points, dtype=float)
    if len(z) <= 4:
        return z
    return np.vstack([z[:-1:stride], z[-1:]])


def smooth_coarse(control: FloatArray, **verification: object) -> Smoothed:
    """Same contract as `services.smoother.core.smooth`, over the decimated control polygon.

    Decimation keeps the first point, so the curve still starts at the start, along the heading.
    """
    return smooth(decimate(control), **verification)


def factory(scenario: Scenario) -> SmootherStage:
    """Entry point named in a `stages` config: the smoother stage with the coarse spline."""
    return SmootherStage(config=SmootherConfig.from_scenario(scenario), smooth_fn=smooth_coarse)
