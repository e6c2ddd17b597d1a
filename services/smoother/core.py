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

Control points on a line (within 1e-9 of it, advancing along it) are smoothed to that line's chord,
which a single exact segment test (eq. 2) proves clear.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.interpolate import BSpline

from services.geometry import Ellipse, EllipseStack, FloatArray, as_complex, distance, norms

SAMPLES_PER_SPAN = 16


@dataclass(frozen=True)
class Verification:
    ok: bool
    min_level: float  # lower bound of ‖A z + b‖ over the curve and all ellipses (> 1: clear)
    max_curvature: float
    reason: str = ""
    sharpest_m: float = 0.0  # how far along the curve its curvature is largest


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
    fraction = np.arange(SAMPLES_PER_SPAN) / SAMPLES_PER_SPAN
    fine = breaks[:-1, None] + np.diff(breaks)[:, None] * fraction[None, :]
    return np.concatenate([fine.ravel(), breaks[-1:]])


def dense_samples(curve: BSpline) -> tuple[FloatArray, FloatArray]:
    """(u, curve(u)) at the parameters `verify` checks and `sample` measures arc length on: a caller that
    does both evaluates the curve there once."""
    u = _parameters(curve)
    return u, curve(u)


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
    dense: tuple[FloatArray, FloatArray] | None = None,
) -> Verification:
    """Check the continuous curve against every ellipse, the curvature bound, start, goals and bounds.
    `dense`: `dense_samples(curve)`, when the caller has them."""
    u, z = dense_samples(curve) if dense is None else dense
    d1 = curve.derivative(1)(u)
    d2 = curve.derivative(2)(u)
    speed = norms(d1)
    if np.any(speed <= 1e-12):
        return Verification(False, 0.0, np.inf, "curve has a cusp (zero tangent)")
    curvature = np.abs(d1[:, 0] * d2[:, 1] - d1[:, 1] * d2[:, 0]) / speed**3
    sharpest = int(np.argmax(curvature))
    max_kappa = float(curvature[sharpest])

    min_level = np.inf
    if ellipses:
        du = np.diff(u)
        acc = norms(d2)
        # B″ is linear on each knot span and the samples include the knots, so the larger end value
        # bounds ‖B″‖ on every sample interval.
        deviation = np.maximum(acc[:-1], acc[1:]) * du**2 / 8.0
        stack = EllipseStack.of(ellipses)
        min_level = float(np.min(stack.min_segment_levels(z[:-1], z[1:], sag_m=deviation, run=SAMPLES_PER_SPAN)))

    return _judge(
        z,
        direction=(d1[0] / speed[0]).tolist(),
        min_level=min_level,
        max_kappa=max_kappa,
        sharpest_m=float(np.sum(norms(np.diff(z[: sharpest + 1], axis=0)))),
        max_curvature=max_curvature,
        start=start,
        heading_rad=heading_rad,
        goals=goals,
        goal_tolerance_m=goal_tolerance_m,
        bounds_min=bounds_min,
        bounds_max=bounds_max,
    )


def _judge(
    z: FloatArray,
    *,
    direction: tuple[float, float] | list[float],
    min_level: float,
    max_kappa: float,
    max_curvature: float,
    sharpest_m: float = 0.0,
    start: FloatArray,
    heading_rad: float | None,
    goals: FloatArray,
    goal_tolerance_m: float,
    bounds_min: FloatArray,
    bounds_max: FloatArray,
    box: tuple[list[float], list[float]] | None = None,
) -> Verification:
    """The verdict from the curve's samples `z` (ordered, the ends included), its unit direction at
    the start, its clearance lower bound and its largest curvature (`sharpest_m` along the curve from its
    start). `box`: the corners (lowest x and y, highest x and y) of a box that holds the whole curve,
    when the caller knows one (a chord's ends span its box); else the bounds are checked on the samples."""

    def fail(reason: str) -> Verification:
        return Verification(False, min_level, max_kappa, reason, sharpest_m)

    if not min_level > 1.0:  # (NaN fails)
        return fail(f"curve enters an ellipse (level {min_level:.4f} <= 1)")
    if not max_kappa <= max_curvature:
        return fail(f"curvature {max_kappa:.3f} exceeds the bound {max_curvature:.3f} 1/m, {sharpest_m:.2f} m along the curve")
    # Plain floats for the few numbers, and one pass per test over the samples: the same tests, but
    # numpy's wrappers (np.linalg.norm, np.any, np.clip) cost more than the arithmetic here.
    (x0, y0), (sx, sy) = z[0].tolist(), np.asarray(start, dtype=float).tolist()
    if not math.hypot(x0 - sx, y0 - sy) <= 1e-6:
        return fail("curve does not start at the start")
    if heading_rad is not None:
        ux, uy = direction
        alignment = ux * math.cos(heading_rad) + uy * math.sin(heading_rad)
        misalignment = math.acos(min(max(alignment, -1.0), 1.0))
        if not misalignment <= 1e-3:
            return fail(f"curve leaves the start {misalignment:.4f} rad off the heading")
    if box is None:
        inside = float((z - bounds_min).min()) >= -1e-9 and float((bounds_max - z).min()) >= -1e-9  # (NaN fails)
    else:
        (lx, ly), (hx, hy) = box
        (bx0, by0), (bx1, by1) = np.asarray(bounds_min, dtype=float).tolist(), np.asarray(bounds_max, dtype=float).tolist()
        inside = lx - bx0 >= -1e-9 and ly - by0 >= -1e-9 and bx1 - hx >= -1e-9 and by1 - hy >= -1e-9
    if not inside:
        return fail("curve leaves the map bounds")
    w = as_complex(z)  # each goal's distances: one subtraction and one |·|
    cursor = 0
    for k, (gx, gy) in enumerate(np.asarray(goals, dtype=float).reshape(-1, 2).tolist()):
        distances = np.abs(w[cursor:] - complex(gx, gy))
        first = int((distances <= goal_tolerance_m).argmax())  # the first sample within tolerance, or 0
        if not distances[first] <= goal_tolerance_m:  # (NaN included)
            return fail(f"curve misses goal {k} by {distances.min():.3f} m")
        cursor += first
    return Verification(True, min_level, max_kappa, sharpest_m=sharpest_m)


def sample(curve: BSpline, *, spacing_m: float, dense: tuple[FloatArray, FloatArray] | None = None) -> FloatArray:
    """Points on the curve, consecutive ones at most `spacing_m` apart, first and last included.

    Spaced evenly in arc length, as the chords between `verify`'s samples measure it. A chord h long
    falls short of its arc by a relative (κh)²/24: under 1e-6 on the planner's spans (about 0.08 m, so
    h ≈ 5 mm, and κ ≤ 0.5), far inside the 5 % that `_sample_count` leaves; more samples per span
    measure no better.
    `dense`: `dense_samples(curve)`, when the caller has them.
    """
    u, z = dense_samples(curve) if dense is None else dense
    s = np.concatenate([[0.0], np.cumsum(distance(z[1:], z[:-1]))])
    targets = np.linspace(0.0, s[-1], _sample_count(s[-1], spacing_m=spacing_m))
    return curve(np.interp(targets, s, u))


def _sample_count(length_m: float, *, spacing_m: float) -> int:
    return max(2, math.ceil(length_m / (0.95 * spacing_m)) + 1)


def _chord(control: FloatArray) -> tuple[list[float], list[float]] | None:
    """The ends z₀, zₙ of the control points when they advance strictly along the chord z₀ → zₙ within
    1e-9 of it (relative to its length, at least 1 m), else None.

    Their smoothed curve is then the chord itself, at most that far from their B-spline: each point of
    a B-spline is a convex combination of its control points (the phantom ends mirror z₁ and zₙ₋₁, so
    they keep as close), and its progress along the chord is the B-spline of increasing values,
    increasing from z₀ to zₙ, so it has no cusp and runs the chord once.
    """
    (x0, y0), (x1, y1) = ends = control[0].tolist(), control[-1].tolist()
    length = math.hypot(x1 - x0, y1 - y0)
    if length <= 0.0:
        return None
    # Each point's progress along the chord and its offset from it, in one product: z − z₀ turned by
    # the chord's angle backwards.
    w = as_complex(control)
    turned = (w - w[0]) * complex((x1 - x0) / length, (y0 - y1) / length)
    along = turned.real
    if not (float(np.abs(turned.imag).max()) <= 1e-9 * max(length, 1.0) and float((along[1:] - along[:-1]).min()) > 0.0):
        return None  # (NaN is not straight)
    return ends


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
    chord = _chord(control) if len(control) >= 3 else None
    if chord is not None:
        return _smooth_chord(
            *chord,
            ellipses=ellipses,
            max_curvature=max_curvature,
            heading_rad=heading_rad,
            goals=goals,
            goal_tolerance_m=goal_tolerance_m,
            bounds_min=bounds_min,
            bounds_max=bounds_max,
            output_spacing_m=output_spacing_m,
        )
    curve = bspline(control)
    dense = dense_samples(curve)  # what the verdict is checked on and the published samples are spaced by
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
        dense=dense,
    )
    return Smoothed(points=sample(curve, spacing_m=output_spacing_m, dense=dense), verification=verification)


def _smooth_chord(
    start: list[float],
    end: list[float],
    *,
    ellipses: list[Ellipse],
    max_curvature: float,
    heading_rad: float | None,
    goals: FloatArray,
    goal_tolerance_m: float,
    bounds_min: FloatArray,
    bounds_max: FloatArray,
    output_spacing_m: float,
) -> Smoothed:
    """The chord start → end as the smoothed curve (see `_chord`): one eq. 2 segment test proves it
    clear, its ends' box proves it within the bounds, it does not bend; the other checks run on its
    samples, which are the points published."""
    (x0, y0), (x1, y1) = start, end
    length = math.hypot(x1 - x0, y1 - y0)
    t = np.arange(count := _sample_count(length, spacing_m=output_spacing_m)) * (1.0 / (count - 1))
    t[-1] = 1.0  # t: np.linspace(0, 1, count), without its overhead
    # z₀ + t (zₙ − z₀) for each t, as complex numbers: two numpy calls, each coordinate as before.
    points = (t * complex(x1 - x0, y1 - y0) + complex(x0, y0)).view(float).reshape(-1, 2)
    # One segment against every ellipse: no broad phase needed.
    min_level = EllipseStack.of(ellipses).polyline_level([start, end]) if ellipses else np.inf
    verification = _judge(
        points,
        direction=((x1 - x0) / length, (y1 - y0) / length),
        min_level=min_level,
        max_kappa=0.0,
        max_curvature=max_curvature,
        start=start,
        heading_rad=heading_rad,
        goals=goals,
        goal_tolerance_m=goal_tolerance_m,
        bounds_min=bounds_min,
        bounds_max=bounds_max,
        box=([min(x0, x1), min(y0, y1)], [max(x0, x1), max(y0, y1)]),
    )
    return Smoothed(points=points, verification=verification)
