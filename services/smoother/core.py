"""Bézier smoothing of the optimised path (paper eq. 5), verified on the continuous curve.

One Bézier curve of degree n through hundreds of points is numerically useless, so the smoothed path is
a uniform cubic B-spline whose control points are the optimised points: a chain of cubic Bézier pieces
(eq. 5 with n = 3 on each span) joined with continuous curvature, each in the convex hull of its four
control points and within ‖Δ²z‖/6 of the control polygon. At every knot its curvature is ‖Δ²z‖/s²,
the very quantity the optimiser bounds. The ends use reflected phantom points 2z₀ − z₁ and 2zₙ − zₙ₋₁
(natural end conditions): the curve starts exactly at z₀, tangent to z₁ − z₀ (the start heading the
optimiser imposes) with zero curvature, and ends exactly at the last goal. (Clamped knots would also
start at z₀, but bend up to twice as sharply on their first span.)

The curve is published only if `verify` passes on the continuous curve:
- clearance: the curve is sampled with the knots among the samples; between two samples it deviates
  from the chord by at most max‖B″‖·Δu²/8, and on a cubic span B″ is linear, so max‖B″‖ over a span is
  at one of its knots. In ellipse j's unit-disc frame that deviation is scaled by at most ‖Aⱼ‖₂, so
  min over the chord of ‖Aⱼ z + bⱼ‖ (exact, eq. 2) minus ‖Aⱼ‖₂ · deviation ≥ 1 proves the whole curve
  clear of ellipse j;
- curvature |B′ × B″| / |B′|³ ≤ tan(δ_max)/L at the dense samples (16 per span, spans ~0.08 m long);
- start point and heading, every goal within tolerance in order, bounds.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.interpolate import BSpline

from cvxnav.geometry import Ellipse, EllipseStack, FloatArray

SAMPLES_PER_SPAN = 16


@dataclass(frozen=True)
class Verification:
    ok: bool
    min_level: float  # lower bound of ‖A z + b‖ over the curve and all ellipses (> 1: clear)
    max_curvature: float
    reason: str = ""


@dataclass(frozen=True)
class Smoothed:
    points: FloatArray  # the curve sampled at most `output_spacing_m` apart
    verification: Verification


def bspline(control: FloatArray) -> BSpline:
    """Uniform cubic B-spline on u ∈ [0, 1] from z₀ to zₙ with natural ends (≥ 3 control points)."""
    control = np.asarray(control, dtype=float)
    if len(control) < 3:
        raise ValueError("the smoother needs at least 3 points")
    extended = np.vstack([2 * control[0] - control[1], control, 2 * control[-1] - control[-2]])
    m = len(extended)
    knots = (np.arange(m + 4) - 3.0) / (m - 3)  # the curve lives on [knots[3], knots[m]] = [0, 1]
    return BSpline(knots, extended, 3, extrapolate=False)


def _parameters(curve: BSpline) -> FloatArray:
    """Parameter samples: SAMPLES_PER_SPAN per knot span, knots included."""
    breaks = curve.t[3:-3]
    fine = [np.linspace(a, b, SAMPLES_PER_SPAN, endpoint=False) for a, b in zip(breaks[:-1], breaks[1:])]
    return np.concatenate([*fine, [breaks[-1]]])


def verify(
    curve: BSpline,
    *,
    ellipses: list[Ellipse],
    max_curvature: float,
    start: FloatArray,
    heading_rad: float | None,
    goals: FloatArray,
    goal_tolerance_m: float,
    bounds_min: FloatArray,
    bounds_max: FloatArray,
) -> Verification:
    """Check the continuous curve against every ellipse, the curvature bound, start, goals and bounds."""
    u = _parameters(curve)
    z = curve(u)
    d1 = curve.derivative(1)(u)
    d2 = curve.derivative(2)(u)
    speed = np.linalg.norm(d1, axis=1)
    if np.any(speed <= 1e-12):
        return Verification(False, 0.0, np.inf, "curve has a cusp (zero tangent)")
    curvature = np.abs(d1[:, 0] * d2[:, 1] - d1[:, 1] * d2[:, 0]) / speed**3
    max_kappa = float(curvature.max())

    min_level = np.inf
    if ellipses:
        du = np.diff(u)
        acc = np.linalg.norm(d2, axis=1)
        # B″ is linear on each knot span and the samples include the knots, so the larger end value
        # bounds ‖B″‖ on every sample interval.
        deviation = np.maximum(acc[:-1], acc[1:]) * du**2 / 8.0
        min_level = float(np.min(EllipseStack.of(ellipses).min_segment_levels(z[:-1], z[1:], sag_m=deviation)))

    def fail(reason: str) -> Verification:
        return Verification(False, min_level, max_kappa, reason)

    if min_level <= 1.0:
        return fail(f"curve enters an ellipse (level {min_level:.4f} <= 1)")
    if max_kappa > max_curvature:
        return fail(f"curvature {max_kappa:.3f} exceeds the bound {max_curvature:.3f} 1/m")
    if np.linalg.norm(z[0] - start) > 1e-6:
        return fail("curve does not start at the start")
    if heading_rad is not None:
        direction = d1[0] / speed[0]
        misalignment = np.arccos(np.clip(direction @ [np.cos(heading_rad), np.sin(heading_rad)], -1.0, 1.0))
        if misalignment > 1e-3:
            return fail(f"curve leaves the start {misalignment:.4f} rad off the heading")
    if np.any(z < np.asarray(bounds_min) - 1e-9) or np.any(z > np.asarray(bounds_max) + 1e-9):
        return fail("curve leaves the map bounds")
    cursor = 0
    for k, goal in enumerate(np.atleast_2d(goals)):
        distances = np.linalg.norm(z[cursor:] - goal, axis=1)
        hits = np.flatnonzero(distances <= goal_tolerance_m)
        if len(hits) == 0:
            return fail(f"curve misses goal {k} by {distances.min():.3f} m")
        cursor += int(hits[0])
    return Verification(True, min_level, max_kappa)


def sample(curve: BSpline, *, spacing_m: float) -> FloatArray:
    """Points on the curve, consecutive ones at most `spacing_m` apart, first and last included."""
    u = np.linspace(0.0, 1.0, 64 * (len(curve.c) + 1))
    z = curve(u)
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(z, axis=0), axis=1))])
    count = max(2, int(np.ceil(s[-1] / (0.95 * spacing_m))) + 1)
    targets = np.linspace(0.0, s[-1], count)
    return curve(np.interp(targets, s, u))


def smooth(
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
    """Smooth the optimised points into a verified curve, sampled for publication."""
    control = np.asarray(control, dtype=float)
    curve = bspline(control)
    verification = verify(
        curve,
        ellipses=ellipses,
        max_curvature=max_curvature,
        start=control[0],
        heading_rad=heading_rad,
        goals=goals,
        goal_tolerance_m=goal_tolerance_m,
        bounds_min=bounds_min,
        bounds_max=bounds_max,
    )
    return Smoothed(points=sample(curve, spacing_m=output_spacing_m), verification=verification)
