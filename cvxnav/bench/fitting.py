"""Two micro-benchmarks beside the planner table: ellipse fitting, and planning time against obstacle count.

Fitting: the minimum-volume (Löwner–John) ellipse of n random points by the project's two routes
(`services.ellipsoids.mvee`, cvxpy + Clarabel; `mvee_fast`, Todd–Yildirim + Newton in numpy) and by
Drake's `Hyperellipsoid.MinimumVolumeCircumscribedEllipsoid`, on several seeded sets of each size:
`mvee_fast`'s time depends on the set (how many active-set rounds it takes to find the support: on
twenty seeded sets of 20 points it took 0.72 × Drake's time at the median and 1.09 × on the worst,
and 0.62 × on the one set measured before, which needs a single round), so one set would measure
its luck. Each method gets the raw points and one warm-up call per set (cvxpy's compile
is cached per padded size); a set that some method fails on (Drake's solver gives up on one of the
1000-point sets) is reported in that method's row and left out of the timing, so every method is
timed on the same sets. The methods are timed in turns (`cvxnav.bench.turns`), call k on the k-th of
those sets (cyclically); areas are compared with the cvxpy route's, set by set, and the worst
difference is reported.

Scaling: cvxnav's planning time on seeded random fields of 10 … 200 obstacles in one fixed box (the
shape of `field-60`), obstacles drawn like the public `field-*` scenarios (polygons, circles, point
clusters), one of them always across the straight line. The growth exponent is the least-squares slope
of log(time) on log(obstacles).
"""

from __future__ import annotations

import logging
import statistics
import time
from collections.abc import Callable

import numpy as np

from cvxnav.bench.report import FitResult, ScalingPoint, ScalingResult
from cvxnav.bench.turns import in_turns
from schemas.scenario import Scenario, parse_scenario


def _fit_points(count: int, *, seed: int) -> np.ndarray:
    """`count` points of a rotated anisotropic Gaussian cloud: a generic, non-degenerate fitting input."""
    rng = np.random.default_rng(seed)
    z = rng.standard_normal((count, 2)) * np.array([2.0, 0.6])
    c, s = np.cos(0.6), np.sin(0.6)
    return z @ np.array([[c, s], [-s, c]]) + np.array([3.0, -1.0])


def _ms(fn: Callable[[], float]) -> float:
    """One call of `fn`, timed: milliseconds."""
    t0 = time.perf_counter()
    fn()
    return 1e3 * (time.perf_counter() - t0)


def _area_or_error(fn: Callable[[int], float], k: int) -> float | str:
    """The area `fn` fits to set k, or its error in one line."""
    try:
        return fn(k)
    except Exception as error:  # a solver failure is a result, not a crash of the benchmark
        return " ".join(f"{type(error).__name__}: {error}".split())[:200]


def fit_benchmark(
    *, counts: tuple[int, ...], repeats: int, with_drake: bool, sets: int = 10, seed: int = 0
) -> list[FitResult]:
    """Each method's `repeats` timed calls per point count, spread over `sets` seeded point sets."""
    from services.ellipsoids.mvee import mvee, mvee_fast

    results: list[FitResult] = []
    for count in counts:
        clouds = [_fit_points(count, seed=seed + count + 1000 * k) for k in range(sets)]
        methods: list[tuple[str, Callable[[int], float]]] = [
            ("mvee (cvxpy + Clarabel)", lambda k: mvee(clouds[k]).area),
            ("mvee_fast (numpy)", lambda k: mvee_fast(clouds[k]).area),
        ]
        if with_drake:
            from pydrake.geometry.optimization import Hyperellipsoid

            logging.getLogger("drake").setLevel(logging.WARNING)  # its solver's give-ups are reported as errors
            columns = [np.asfortranarray(cloud.T) for cloud in clouds]

            def drake_area(k: int) -> float:
                ellipse = Hyperellipsoid.MinimumVolumeCircumscribedEllipsoid(columns[k])
                return float(np.pi / abs(np.linalg.det(ellipse.A())))

            methods.append(("Drake MinimumVolumeCircumscribedEllipsoid", drake_area))
        # One warm-up call per method and set: its area, or why it failed. A solver failure is a result,
        # not a crash of the benchmark; the methods are timed on the sets that all of them solve.
        outcomes = {method: [_area_or_error(fn, k) for k in range(sets)] for method, fn in methods}
        working = [method for method, _ in methods if any(isinstance(o, float) for o in outcomes[method])]
        common = [k for k in range(sets) if all(isinstance(outcomes[m][k], float) for m in working)]
        timed = working if common else []
        calls = {m: lambda k, fn=fn: _ms(lambda: fn(common[k % len(common)])) for m, fn in methods if m in timed}
        times = in_turns(calls, lambda method, done: len(done) < repeats, seed=seed + count)
        reference = outcomes[timed[0]] if timed else []
        for method, _ in methods:
            errors = [o for o in outcomes[method] if isinstance(o, str)]
            error = f"failed on {len(errors)} of {sets} sets: {errors[0]}" if errors else ""
            if method not in timed:
                results.append(FitResult(method=method, points=count, point_sets=sets, time_median_ms=None,
                                         area_rel_diff=None, error=error or "no set that every method solves"))
                continue
            worst = max(abs(outcomes[method][k] - reference[k]) / reference[k] for k in common)
            results.append(FitResult(method=method, points=count, point_sets=len(common),
                                     time_median_ms=statistics.median(times[method]), times_ms=times[method],
                                     area_rel_diff=worst, error=error))
    return results


# --------------------------------------------------------------------------- scaling


def random_field(*, obstacles: int, seed: int, side_m: float = 24.0) -> Scenario:
    """A `field-*`-style scenario: start (0, 0) heading 45°, goal (side, side), `obstacles` shapes.

    The first is a disc of radius 0.5 m at the centre of the box, across the straight line, so that
    every field needs a route and its refinement: without it a sparse field can leave the straight
    line clear (10 obstacles, seed 17, did), and its time would measure the straight-line shortcut
    (under 1 ms) rather than planning. The others are random: centres uniform in the box between
    start and goal, at least 1.5 m from both; triangles to hexagons, circles and point clusters of
    0.15–0.5 m radius, so the field stays passable up to 200 obstacles in a 28 m box.
    """
    rng = np.random.default_rng(seed)
    items: list[dict] = [{"type": "circle", "center": [side_m / 2, side_m / 2], "radius": 0.5}]
    ends = np.array([[0.0, 0.0], [side_m, side_m]])
    while len(items) < obstacles:
        centre = rng.uniform(0.5, side_m - 0.5, size=2)
        if np.min(np.linalg.norm(ends - centre, axis=1)) < 1.5:
            continue
        radius = rng.uniform(0.15, 0.5)
        kind = rng.choice(["polygon", "circle", "points"])
        if kind == "circle":
            items.append({"type": "circle", "center": centre.round(4).tolist(), "radius": round(radius, 4)})
            continue
        count = int(rng.integers(3, 7)) if kind == "polygon" else int(rng.integers(5, 11))
        angles = np.sort(rng.uniform(0.0, 2.0 * np.pi, count)) if kind == "polygon" else rng.uniform(0, 2 * np.pi, count)
        radii = radius * (np.ones(count) if kind == "polygon" else np.sqrt(rng.uniform(0.2, 1.0, count)))
        pts = centre + radii[:, None] * np.column_stack([np.cos(angles), np.sin(angles)])
        key = "vertices" if kind == "polygon" else "points"
        (ax, ay), (bx, by) = pts[1] - pts[0], pts[2] - pts[0]
        if kind == "polygon" and abs(ax * by - ay * bx) < 1e-3:  # the first three vertices nearly collinear
            continue
        items.append({"type": kind, key: pts.round(4).tolist()})
    document = {
        "format": "cvxnav.scenario/1",
        "name": f"random-{obstacles}",
        "description": f"random field, seed {seed}, {obstacles} obstacles (generated by cvxnav bench)",
        "bounds": {"min": [-4.0, -4.0], "max": [side_m + 4.0, side_m + 4.0]},
        "robot": {"width": 0.3, "length": 0.6, "wheelbase": 0.6, "safety_distance": 0.5, "max_speed": 1.0,
                  "max_steering_angle": 0.6, "max_steering_rate": 0.5},
        "sensor": {"fov_deg": 180.0, "range": 5.0, "rays": 181, "rate_hz": 10.0},
        "start": {"x": 0.0, "y": 0.0, "theta": float(np.pi / 4)},
        "goals": [[side_m, side_m]],
        "goal_tolerance": 0.3,
        "obstacles": items,
        "expect": "reach",
    }
    import json

    return parse_scenario(json.dumps(document), source=document["name"])


def scaling_benchmark(*, counts: tuple[int, ...], repeats: int, seed: int = 7,
                      on_step: Callable[[], None] | None = None) -> ScalingResult:
    """cvxnav's planning time (optimise + smooth, as in the main table) against obstacle count."""
    from cvxnav.bench.planners import plan_cvxnav
    from cvxnav.bench.problem import BenchProblem

    points: list[ScalingPoint] = []
    for count in counts:
        problem = BenchProblem.of(random_field(obstacles=count, seed=seed + count))
        plan_cvxnav(problem)  # warm: the table compares warm times
        attempts = [plan_cvxnav(problem) for _ in range(repeats)]
        ok = all(a.path is not None for a in attempts)
        points.append(ScalingPoint(obstacles=count, grown_ellipses=len(problem.grown),
                                   time_median_ms=1e3 * statistics.median(a.time_s for a in attempts), success=ok))
        if on_step is not None:
            on_step()
    usable = [(p.obstacles, p.time_median_ms) for p in points if p.success and p.time_median_ms]
    # A fit over the whole range can hide a steep end behind a flat start (the refinement's cost
    # depends on the path's length more than on the obstacles): each point also gets its local slope.
    slopes = {b[0]: float(np.log(b[1] / a[1]) / np.log(b[0] / a[0])) for a, b in zip(usable, usable[1:])}
    points = [p.model_copy(update={"local_exponent": slopes.get(p.obstacles)}) if p.success else p for p in points]
    exponent = None
    if len(usable) >= 2:
        x, y = np.log([u[0] for u in usable]), np.log([u[1] for u in usable])
        exponent = float(np.polyfit(x, y, 1)[0])
    return ScalingResult(points=points, growth_exponent=exponent,
                         time_meaning="cvxnav warm optimise + smooth, median; exponent over successful points")
