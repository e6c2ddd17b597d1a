"""The planner stage's pure core: check the straight reference (eq. 2), choose the way round globally,
refine by convex optimisation, and check the refined path exactly before anyone smooths it.

A straight reference that is clear (eq. 2 at the planning level) and drivable (every leg along the
start heading, so no turn at all) is already the shortest drivable path: it is returned as it is,
sampled like a refined path, without running the refinement.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from contextlib import AbstractContextManager, nullcontext
from dataclasses import dataclass, replace
from itertools import accumulate
from typing import Literal

import numpy as np

from services.geometry import Ellipse, EllipseStack, FloatArray, arc_lengths, joined_legs, polyline_length
from services.planner.lattice import WIDER, clear_of, lead_in, through, turning_arc
from services.planner.refine import Refined, RefineSettings, SolverFailure, curvature_broken, leg_counts, refine
from services.planner.route import KeepTo, tangent_route
from services.smoother.core import Smoothed, Verification

_STRAIGHT_COS = math.cos(1e-6)  # legs and heading within 1e-6 rad of parallel need no turn
# A turning lead-in (`_turns`) is planned this much wider than the turning radius: an arc at the radius
# itself would break the refinement's curvature budget, which its step floors make stricter.
_TURN_WIDER = 1.15
_APPROACHES = 8  # directions the last goal is approached from, when its approach breaks the curvature bound
_MIN_TURN_RAD = math.pi / 8  # turns smaller than this (either way round) get no turning lead-in
# A lead-in searched over the car's turns (`lattice.lead_in`, its arcs `lattice.WIDER` planning radii):
# where it joins the route, in turning radii along it.
_LEAD_AHEAD = 3.0
_SAME_POINT_M = 1e-6  # goals this close are one point (the smoother's tolerance on the start)
# A drivable path handed in (`route_seed`) is refined whole, its steps shrinking by at most 1 % an
# iteration: its arcs are only 5 % wider than the planning radius, and under the default 5 % step floor
# the first subproblem's curvature budget, κ (0.95 h)², is stricter than they are (measured: each
# iteration shortened the steps of r01's loop, docs/maps.md stop 44, and it ended with its curvature unmet).
_SEED_REFINE = dict(window_radii=None, step_shrink=0.99)


@dataclass(frozen=True)
class PathPlan:
    status: Literal["ok", "no_path"]
    points: FloatArray  # the optimised points (empty when there is no path)
    goal_indices: tuple[int, ...] = ()
    reason: str = ""
    iterations: int = 0
    # No route refined clear: by how far along it the refined path that ran furthest clear entered an ellipse.
    entered_m: float | None = None


class Refinements:
    """The refinements made in one plan, by everything they were given: `refine` is deterministic, so one
    asked for again is answered from here. A plan on a map asks again where a round is planned again
    without its corridor (`services.maps.corridor`) and its route search finds the same routes, each of
    which would otherwise cost what its first refinement did (docs/maps.md, stop 47).
    Ellipses are keyed by identity (as `EllipseStack.of` keys them), held here with the rest; the routes'
    points by value. The refined points are read-only: whoever reads them shares them."""

    def __init__(self) -> None:
        self._done: dict[tuple, Refined | SolverFailure] = {}

    def refine(self, *, legs: list[FloatArray], ellipses: list[Ellipse], bounds_min: FloatArray,
               bounds_max: FloatArray, max_curvature: float, heading_rad: float | None,
               settings: RefineSettings) -> Refined:
        """`refine` on these, or what it gave (or raised) when last asked the same."""
        key = (tuple(ellipses), tuple((leg.shape, np.ascontiguousarray(leg, dtype=float).tobytes()) for leg in legs),
               tuple(np.asarray(bounds_min, dtype=float).tolist()), tuple(np.asarray(bounds_max, dtype=float).tolist()),
               float(max_curvature), heading_rad, settings)
        if key not in self._done:
            try:
                done = refine(legs=legs, ellipses=ellipses, bounds_min=bounds_min, bounds_max=bounds_max,
                              max_curvature=max_curvature, heading_rad=heading_rad, settings=settings)
                done.points.setflags(write=False)
            except SolverFailure as failure:
                done = failure
            self._done[key] = done
        if isinstance(done := self._done[key], SolverFailure):
            raise done
        return done


def goals_ahead(start: FloatArray, goals: FloatArray, *, tolerance_m: float) -> FloatArray:
    """The goals a path from `start` still has to reach, in order, without zero-length legs.

    The goals from the first within `tolerance_m` of the start are reached there at once, as the run's
    goal tracker counts them (every goal in order the car is within tolerance of), and a goal at the
    point of the goal before it is reached with it: no optimiser can space points along a leg of length
    zero. A path through the goals left passes within tolerance of every goal, the dropped ones included.
    """
    z = np.asarray(goals, dtype=float).reshape(-1, 2)
    first = 0
    while first < len(z) and math.dist(z[first], start) <= tolerance_m:
        first += 1
    z = z[first:]
    if len(z) < 2:
        return z
    return z[np.concatenate([[True], np.linalg.norm(np.diff(z, axis=0), axis=1) > _SAME_POINT_M])]


def stay_at_start(start: FloatArray, ellipses: list[Ellipse]) -> tuple[PathPlan, Smoothed]:
    """The plan and curve of a robot whose every goal is within tolerance of its start: the start itself."""
    point = np.asarray(start, dtype=float).reshape(1, 2)
    level = float(EllipseStack.of(ellipses).levels(point).min()) if ellipses else math.inf
    verification = Verification(level > 1.0, level, 0.0,
                                "" if level > 1.0 else "start lies inside an obstacle's grown ellipse")
    return PathPlan("ok", point), Smoothed(points=point, verification=verification)


def intersected(points: FloatArray, ellipses: list[Ellipse], *, level: float = 1.0) -> FloatArray:
    """Indices of the ellipses a polyline enters: the paper's eq. (2), exact on every segment."""
    if not ellipses or len(points) < 2:
        return np.zeros(0, dtype=int)
    _, cols, levels = EllipseStack.of(ellipses).segment_pairs(points[:-1], points[1:])
    return np.unique(cols[levels < level])


def _straight(
    *,
    start: FloatArray,
    heading_rad: float | None,
    goals: FloatArray,
    stack: EllipseStack,
    bounds_min: FloatArray,
    bounds_max: FloatArray,
    settings: RefineSettings,
    keep_to: KeepTo | None = None,
) -> PathPlan | None:
    """The straight line start → goals when it needs no turn, clears every ellipse and keeps to where the
    route may go (`keep_to`, if given), else None.

    Sampled as `resample_legs` samples the legs: each leg gets its share of the points evenly spaced
    in arc length, p + d s (d the unit direction, s = k L / count), and ends at its goal exactly.
    Formed here from the directions and lengths already at hand, without its interpolation, and
    written into one array. The few waypoints are plain floats until the sampling: the same
    arithmetic as numpy's on them, without the cost of a numpy call per step.
    """
    waypoints = [start.tolist(), *goals.tolist()]
    (x_min, y_min), (x_max, y_max) = np.asarray(bounds_min, dtype=float).tolist(), np.asarray(bounds_max, dtype=float).tolist()
    if not all(x_min <= x <= x_max and y_min <= y <= y_max for x, y in waypoints):
        return None
    legs = []  # (unit direction x, y, length) of each leg
    for (x0, y0), (x1, y1) in zip(waypoints, waypoints[1:]):
        dx, dy = x1 - x0, y1 - y0
        length = math.sqrt(dx * dx + dy * dy)  # as np.linalg.norm forms it
        if length <= 0.0:
            return None
        legs.append((dx / length, dy / length, length))
    turns = [(ux, uy) for ux, uy, _ in legs]
    if heading_rad is not None:
        turns.insert(0, (math.cos(heading_rad), math.sin(heading_rad)))
    if any(ux * vx + uy * vy < _STRAIGHT_COS for (ux, uy), (vx, vy) in zip(turns, turns[1:])):
        return None
    # A leg or two against every ellipse: the exact test on all pairs is cheaper than a broad phase.
    if not stack.polyline_level(waypoints) >= settings.level:
        return None
    if keep_to is not None and not np.all(keep_to(np.array(waypoints[:-1]), np.array(waypoints[1:]))):
        return None
    lengths = [length for _, _, length in legs]
    n = max(math.ceil(sum(lengths) / settings.spacing_m) + 1, len(goals) + 2)
    counts = leg_counts(lengths, n=n)
    goal_indices = tuple(accumulate(counts))
    points = np.empty((n, 2))
    points[0] = waypoints[0]
    for (px, py), goal, (ux, uy, length), count, end in zip(waypoints, waypoints[1:], legs, counts, goal_indices):
        s = np.arange(1, count) * (length / count)  # the leg's inner points' distances from p
        inner = points[end - count + 1 : end]
        inner[:, 0] = s * ux + px  # a column at a time, with plain floats: no tuple turned into an array
        inner[:, 1] = s * uy + py
        points[end] = goal
    return PathPlan("ok", points, goal_indices)


def _route(
    *,
    start: FloatArray,
    lead: FloatArray | None,
    goals: FloatArray,
    ellipses: list[Ellipse],
    bounds_min: FloatArray,
    bounds_max: FloatArray,
    level: float,
    extra_m: float,
    estimate_m: Sequence[float] | None,
    keep_to: KeepTo | None,
) -> list[FloatArray] | None:
    """Legs of the shortest route, after a lead-in (a polyline from the start; None: none), round
    ellipses enlarged by `extra_m`. The caller has checked the lead-in against the ellipses themselves;
    here it is checked against the enlarged ones."""
    grown = ellipses
    if extra_m > 0:
        grown = [e.grown(extra_m) for e in ellipses]
        if lead is not None and len(intersected(lead, grown, level=level)):
            return None
    origin = start if lead is None else lead[-1]
    reference = np.vstack([origin, goals])
    if len(intersected(reference, grown, level=level)) == 0 and (
            keep_to is None or np.all(keep_to(reference[:-1], reference[1:]))):
        legs = [reference[k : k + 2] for k in range(len(goals))]
    else:
        legs = tangent_route(
            start=origin, goals=goals, ellipses=grown, bounds_min=bounds_min, bounds_max=bounds_max, level=level,
            estimate_m=estimate_m, keep_to=keep_to,
        )
    if legs is not None and lead is not None:
        legs[0] = np.vstack([lead[:-1], legs[0]])
    return legs


def _turns(start: FloatArray, heading_rad: float, leg: FloatArray, *, radius: float, step_m: float) -> list[FloatArray]:
    """Lead-ins that turn the car onto the direction the route leaves the start in (towards its point a
    turning radius on): the short way round, then the long way (a loop, which a corridor too narrow to
    make the short turn in may leave room for). The route search is blind to the heading, and the
    refinement, local, keeps the side of the turn it is handed."""
    along = arc_lengths(leg)
    ahead = leg[min(int(np.searchsorted(along, radius)), len(leg) - 1)] - start
    left = (math.atan2(ahead[1], ahead[0]) - heading_rad) % (2.0 * math.pi)
    out = []
    for turn in sorted((left, left - 2.0 * math.pi), key=abs):
        if _MIN_TURN_RAD <= abs(turn) <= 2.0 * math.pi - _MIN_TURN_RAD:
            out.append(turning_arc(start, heading_rad, radius=radius, turn_rad=turn, step_m=step_m))
    return out


def _entered_m(points: FloatArray, stack: EllipseStack) -> float:
    """How far along the polyline its first segment that enters an ellipse ends (eq. 2, exact)."""
    rows, _, levels = stack.segment_pairs(points[:-1], points[1:])
    return polyline_length(points[: int(np.min(rows[levels < 1.0])) + 2])


def _clear(lead: FloatArray, ellipses: list[Ellipse], bounds_min: FloatArray, bounds_max: FloatArray, *,
           level: float) -> bool:
    """Whether a lead-in stays within the bounds and outside every ellipse (at `level`)."""
    return bool(np.all(lead >= bounds_min) and np.all(lead <= bounds_max)
                and not len(intersected(lead, ellipses, level=level)))


def _broken_near_start(points: FloatArray, kappa: float, within_m: float) -> bool:
    """Whether the polyline breaks the curvature bound `kappa` within `within_m` of its start."""
    first = _first_broken(points, kappa)
    return first is not None and polyline_length(points[: first + 1]) <= within_m


def _broken_near_end(points: FloatArray, kappa: float, within_m: float) -> bool:
    """Whether the polyline breaks the curvature bound `kappa` somewhere, and only within `within_m` of its end."""
    first = _first_broken(points, kappa)
    return first is not None and polyline_length(points[first:]) <= within_m


def _broken_at_a_goal(plan: PathPlan, kappa: float, within_m: float) -> bool:
    """Whether the plan first breaks the curvature bound `kappa` within `within_m` (along it) of a goal
    before its last."""
    first = _first_broken(plan.points, kappa)
    if first is None or len(plan.goal_indices) < 2:
        return False
    along = arc_lengths(plan.points)
    return bool(np.any(np.abs(along[list(plan.goal_indices[:-1])] - along[first]) <= within_m))


def _first_broken(points: FloatArray, kappa: float) -> int | None:
    """The first point at which the polyline breaks the curvature bound `kappa`, None where it keeps it."""
    broken = np.flatnonzero(curvature_broken(points, kappa))
    return None if not len(broken) else 1 + int(broken[0])


def _approaches(goal: FloatArray, ellipses: list[Ellipse], bounds_min: FloatArray, bounds_max: FloatArray, *,
                length_m: float, level: float) -> list[FloatArray]:
    """Points `length_m` from the goal in `_APPROACHES` directions whose straight segment to it stays
    within the bounds and outside every ellipse: where a route may come in to the goal from."""
    angles = 2.0 * np.pi * np.arange(_APPROACHES) / _APPROACHES
    points = goal - length_m * np.column_stack([np.cos(angles), np.sin(angles)])
    return [point for point in points
            if _clear(np.vstack([point, goal]), ellipses, bounds_min, bounds_max, level=level)]


# Whether a plan (and its smoothed curve, once there is one) meets an obstacle it was not made among.
MeetsOthers = Callable[[PathPlan, Smoothed | None], bool]


def meets_none(plan: PathPlan, smoothed: Smoothed | None) -> bool:
    """`MeetsOthers` where the plan is made among every obstacle there is."""
    return False


def plan_path(
    *,
    start: FloatArray,
    heading_rad: float | None,
    goals: FloatArray,
    ellipses: list[Ellipse],
    bounds_min: FloatArray,
    bounds_max: FloatArray,
    max_curvature: float,
    settings: RefineSettings = RefineSettings(),
    route_estimate_m: Sequence[float] | None = None,
    route_keep_to: KeepTo | None = None,
    late: Callable[[], bool] = lambda: False,
    meets_others: MeetsOthers = meets_none,
    route_seed: list[FloatArray] | None = None,
    refinements: Refinements | None = None,
) -> PathPlan:
    """Shortest drivable path start → goals (in order) outside every (grown) ellipse, or `no_path`.

    `route_estimate_m`: each leg's length as a coarser search found it, where the route search starts
    its bounds; `route_keep_to`: where the route may go, a corridor (`route.shortest_route`);
    `route_seed`: legs the car can drive from the start through the first goals, found elsewhere where the
    routes below failed (`services.maps.seed`): they are refined as the route (on from the last of those
    goals as the route search finds it), and nothing else is tried. `refinements`: the refinements made
    earlier in the same plan (a fresh one if None), whose answers a refinement asked again takes.

    The route search ignores curvature, so its shortest route can demand a turn the car cannot make
    (a sharp swing off the start heading, a zigzag through a tight passage). When the refinement
    cannot meet the curvature bound on it, the route is searched again with a lead-in along the start
    heading and round ellipses enlarged by part of the turning radius — which leaves out passages too
    tight to turn in — and refined once more against the true ellipses; last, after a turning lead-in
    onto the direction the first route leaves in, either way round (`_turns`). Where every one of those
    fails within two turning radii of the start (too sharp there, or entering an ellipse), a lead-in is
    searched over the car's own turns (`lattice.lead_in`: straight on past a pillar, then round it) and
    that route refined. Where every route refined clear breaks the bound only near the last goal (tucked
    beside a wall the route rounds tightly), the goal is approached in a straight line from a turning
    radius away, from each direction that leaves clear, the shortest such route first: the refinement
    is local, and may need to come in from elsewhere than the route did (swinging wide of the corner
    and back). Where the first route's refinement breaks it first within two turning radii of a goal
    before the last (the route turns back there, and the curve must loop through the goal), a path over
    the car's own turns through the goals (`lattice.through`, on the ellipses) is refined as a seed is,
    before any other route: a lead-in at the start changes nothing at the goal, and a route round
    enlarged ellipses seldom comes in to it less sharply, each refined at the first one's cost (where
    the first does not break it there, the best of them all is tested so at the end); where the loop
    breaks it at a goal too, the lead-ins at the start (along the heading, turning onto the route) are not
    tried at all, the enlarged routes still are. Once `late()` (the
    replan was called off), no further route is tried after one that refined clear. A plan that
    `meets_others` (an obstacle it was not planned among) is returned at once as an "ok" plan, for the
    caller to plan again among more obstacles, never to publish: any route refined clear, and the
    shortest route within a corridor (`route_keep_to`) unrefined. (Without a corridor the shortest route
    may roam the whole map, through one wall mass after another that no plan was made among: it is
    refined first, and its refinement may fail among the walls it was given.)
    """
    start = np.asarray(start, dtype=float)
    goals = np.asarray(goals, dtype=float).reshape(-1, 2)
    refinements = Refinements() if refinements is None else refinements
    stack = EllipseStack.of(ellipses)
    straight = _straight(
        start=start,
        heading_rad=heading_rad,
        goals=goals,
        stack=stack,
        bounds_min=bounds_min,
        bounds_max=bounds_max,
        settings=settings,
        keep_to=route_keep_to,
    )
    # A line clear of every ellipse at a level above 1 has its ends outside them: no need to check.
    if straight is not None and settings.level > 1.0:
        return straight
    if len(stack) and np.min(stack.levels(np.vstack([start, goals]))) < 1.0:
        inside = "start" if np.min(stack.levels(start)) < 1.0 else "a goal"
        return PathPlan("no_path", np.zeros((0, 2)), reason=f"{inside} lies inside an obstacle's grown ellipse")
    if straight is not None:
        return straight
    radius = 1.0 / (settings.curvature_factor * max_curvature)
    # The lead-in: one turning radius along the start heading (none without a heading). Where it
    # leaves the map or crosses an ellipse, it crosses the enlarged ones too: no route after it.
    tries: list[tuple[FloatArray | None, float]] = [(None, 0.0)]
    if heading_rad is None:
        tries.append((None, 0.5 * radius))
    else:
        lead = np.vstack([start, start + radius * np.array([np.cos(heading_rad), np.sin(heading_rad)])])
        if _clear(lead, ellipses, bounds_min, bounds_max, level=settings.level):
            tries += [(lead, 0.0), (lead, 0.5 * radius)]
    tries.append((None, radius))

    def search(to: FloatArray, *, lead: FloatArray | None = None, extra_m: float = 0.0) -> list[FloatArray] | None:
        """The route to the goals `to`, the last of `goals` (their legs' estimates the last ones)."""
        return _route(start=start, lead=lead, goals=to, ellipses=ellipses, bounds_min=bounds_min,
                      bounds_max=bounds_max, level=settings.level, extra_m=extra_m,
                      estimate_m=None if route_estimate_m is None else route_estimate_m[len(goals) - len(to):],
                      keep_to=route_keep_to)

    best: PathPlan | None = None
    best_slack = np.inf
    entered_m = None

    def refined(legs: list[FloatArray], *, how: RefineSettings = settings) -> tuple[PathPlan | None, bool]:
        """The route refined (with `how`), kept as the best if it meets the bound better: (a plan to return at
        once, one that meets others, or None; whether to try no further route: one met the bound, or it is late)."""
        nonlocal best, best_slack, entered_m
        try:
            result = refinements.refine(legs=legs, ellipses=ellipses, bounds_min=bounds_min, bounds_max=bounds_max,
                                        max_curvature=max_curvature, heading_rad=heading_rad, settings=how)
        except SolverFailure as failure:
            if best is None:
                best = PathPlan("no_path", np.zeros((0, 2)), reason=str(failure))
            return None, False
        if len(intersected(result.points, ellipses)):
            entered_m = max(entered_m or 0.0, _entered_m(result.points, stack))
            return None, False
        candidate = PathPlan("ok", result.points, result.goal_indices, iterations=result.iterations)
        if meets_others(candidate, None):
            return candidate, True
        if result.curvature_slack < best_slack:
            best_slack, best = result.curvature_slack, candidate
        return None, best_slack <= 1e-6 or late()

    def verdict() -> PathPlan:
        """The best plan refined, or why there is none."""
        if best is None:
            return PathPlan("no_path", np.zeros((0, 2)), reason="no refined route stays clear of the ellipses",
                            entered_m=entered_m)
        return best

    def seeded(seed: list[FloatArray]) -> PathPlan | None:
        """The seed's legs refined whole, the route going on from the last goal they reach (its last leg's
        last pose on to that goal and any after it, as the route search joins it): kept as the best if it
        meets the bound better (`refined`); the plan to hand back at once, if it meets others."""
        *before, last = seed
        legs = search(goals[len(before):], lead=last[:-1])
        return None if legs is None else refined(before + legs, how=replace(settings, **_SEED_REFINE))[0]

    looped = False

    def loop_through() -> PathPlan | None:
        """Where the best plan first breaks the bound within two turning radii of a goal before the last (the
        route turns back there, and the curve must loop through the goal, which no refinement of a route
        that goes there and back bends into): a path over the car's own turns through the goals, each
        arrived at facing the way on where that is found, refined as a seed is (`seeded`). Tried once."""
        nonlocal looped
        if (looped or best is None or best.status != "ok" or heading_rad is None or late() or best_slack <= 1e-6
                or not _broken_at_a_goal(best, 1.0 / radius, 2.0 * radius)):
            return None
        looped = True
        seed = through(start=start, heading_rad=heading_rad, goals=goals, clear=clear_of(stack, settings.level),
                       bounds_min=bounds_min, bounds_max=bounds_max, radius=WIDER * radius,
                       spacing_m=settings.spacing_m)
        return None if seed is None else seeded(seed)

    if route_seed is not None:
        return seeded(route_seed) or verdict()
    first_leg = None  # the first route's, where the car has a heading
    at_a_goal = False  # the first route and the loop break the bound at a goal before the last
    for attempt, (lead, extra_m) in enumerate(tries):
        if at_a_goal and lead is not None and extra_m == 0.0:
            continue
        legs = search(goals, lead=lead, extra_m=extra_m)
        if legs is None:
            if attempt == 0:
                return PathPlan("no_path", np.zeros((0, 2)), reason="every route to the goals is blocked")
            continue
        if attempt == 0 and route_keep_to is not None:
            route = PathPlan("ok", joined_legs(legs), tuple(accumulate(len(leg) - 1 for leg in legs)))
            if meets_others(route, None):
                return route
        if attempt == 0 and heading_rad is not None:
            first_leg = legs[0]
            tries += [(turn, 0.0) for turn in _turns(start, heading_rad, first_leg, radius=_TURN_WIDER * radius,
                                                     step_m=settings.spacing_m)
                      if _clear(turn, ellipses, bounds_min, bounds_max, level=settings.level)]
        handed, enough = refined(legs)
        if handed is None and attempt == 0:  # a turn back at a goal: before the other routes
            handed = loop_through()
            enough = enough or best_slack <= 1e-6
            at_a_goal = looped and best is not None and _broken_at_a_goal(best, 1.0 / radius, 2.0 * radius)
        if handed is not None:
            return handed
        if enough:
            break
    else:
        # Every lead-in of one turn failed where the car leaves the start: a search over its own turns.
        failed_at_start = ((best is None and entered_m is not None and entered_m <= 2.0 * radius)
                           or (best is not None and best.status == "ok"
                               and _broken_near_start(best.points, 1.0 / radius, 2.0 * radius)))
        if first_leg is not None and failed_at_start and not late():
            lead = lead_in(start=start, heading_rad=heading_rad, route=first_leg, stack=stack,
                           bounds_min=bounds_min, bounds_max=bounds_max, radius=WIDER * radius,
                           level=settings.level, spacing_m=settings.spacing_m, ahead_m=_LEAD_AHEAD * radius)
            if lead is not None and _clear(lead, ellipses, bounds_min, bounds_max, level=settings.level):
                legs = search(goals, lead=lead)
                if legs is not None:
                    handed, _ = refined(legs)
                    if handed is not None:
                        return handed
        if (best is not None and best.status == "ok" and not late()
                and _broken_near_end(best.points, 1.0 / radius, 4.0 * radius)):
            routes = []
            for point in _approaches(goals[-1], ellipses, bounds_min, bounds_max, length_m=radius,
                                     level=settings.level):
                to_point = search(np.vstack([goals[:-1], point]))
                if to_point is not None:
                    routes.append(to_point[:-1] + [np.vstack([to_point[-1], goals[-1:]])])
            for legs in sorted(routes, key=lambda legs: sum(map(polyline_length, legs))):
                handed, enough = refined(legs)
                if handed is not None:
                    return handed
                if enough:
                    break
        if (handed := loop_through()) is not None:
            return handed
    return verdict()


@dataclass(frozen=True)
class Attempted:
    """What `plan_within` found: the plan and its smoothed curve (as `plan_until_verified` returns them)."""

    plan: PathPlan
    smoothed: Smoothed | None


def margin_ladder(settings: RefineSettings, repairs: tuple[tuple[float, float], ...]) -> list[RefineSettings]:
    """The settings `plan_until_verified` tries in turn: `settings`, then each repair's margins."""
    return [settings, *(replace(settings, level=level, curvature_factor=factor) for level, factor in repairs)]


def plan_until_verified(
    *,
    smooth_fn: Callable[[FloatArray], Smoothed],
    settings: RefineSettings,
    repairs: tuple[tuple[float, float], ...],
    timer: Callable[[str], AbstractContextManager] = nullcontext,
    **problem,
) -> tuple[PathPlan, Smoothed | None]:
    """`plan_path`, re-optimised with the `repairs`' margins (level, curvature factor) in turn until the
    smoothed curve verifies; the plan and its smoothed curve.

    Without a verified curve: the last plan whose curve failed, with that curve; else (every attempt
    found no route) the first attempt's no_path, with None. An attempt's no_path does not end the
    search: a repair with a narrower margin may open a passage the wider ones closed.

    A wider margin is for a curve that clips an ellipse. Once a curve has broken the curvature bound,
    the margins that are no narrower and bend no more sharply are skipped: their feasible sets lie
    within the one that failed. The refinement is local, so that is a heuristic, not a proof: on
    field-60 each such attempt cost 12 solves and failed too, but in three of fifteen unseen closed
    loops one of them once verified (the car went another way there; all three still reached their goal).
    `timer(stage)` wraps the "optimize" and "smooth" steps, for callers that report stage timings.
    """
    attempted = plan_within(smooth_fn=smooth_fn, ladder=margin_ladder(settings, repairs), timer=timer, **problem)
    return attempted.plan, attempted.smoothed


def plan_within(
    *,
    smooth_fn: Callable[[FloatArray], Smoothed],
    ladder: list[RefineSettings],
    timer: Callable[[str], AbstractContextManager] = nullcontext,
    late: Callable[[], bool] = lambda: False,
    meets_others: MeetsOthers = meets_none,
    **problem,
) -> Attempted:
    """`plan_until_verified` on the `ladder` of settings, cut short once `late()` (a replan called off).

    `late` is checked between attempts (a solve is not interrupted): once it is true, the ladder stops
    before its next attempt. Within an attempt, `plan_path` stops trying routes once one refined clear.
    Whatever is returned unverified is never published.

    `meets_others(plan, smoothed)`: whether a plan made among the given ellipses (or its curve, once
    smoothed) meets an obstacle it was not made among, which the caller will add and plan again with
    (`services.maps.corridor`). Such a plan is returned as soon as it is found, unverified: every route
    and margin still to try would be tried on too few obstacles.
    """
    fallback: Attempted | None = None
    too_sharp: list[RefineSettings] = []  # attempts whose curve broke the curvature bound
    for attempt in ladder:
        if any(attempt.level >= failed.level and attempt.curvature_factor <= failed.curvature_factor
               for failed in too_sharp):
            continue
        if fallback is not None and late():
            return fallback
        with timer("optimize"):
            plan = plan_path(**problem, settings=attempt, late=late, meets_others=meets_others)
        if plan.status != "ok":
            fallback = fallback or Attempted(plan, None)
            continue
        if meets_others(plan, None):
            return Attempted(plan, None)
        with timer("smooth"):
            smoothed = smooth_fn(plan.points)
        if smoothed.verification.ok or meets_others(plan, smoothed):
            return Attempted(plan, smoothed)
        if smoothed.verification.max_curvature > problem["max_curvature"]:
            too_sharp.append(attempt)
        fallback = Attempted(plan, smoothed)
    assert fallback is not None  # the first attempt is never skipped
    return fallback


def why_no_path(plan: PathPlan, smoothed: Smoothed | None, *, max_curvature: float,
                goals: FloatArray | None = None) -> str:
    """Why `plan_until_verified` found no verified path: the plan's reason, or its curve's verdict. A curve
    too sharp within a turning radius of the start, or refined routes that all enter an ellipse there,
    mean that no route found could be joined from the start's heading in the room there (the turning
    lead-ins included), and the reason says so. A curve too sharp within two turning radii of a goal
    before the last (in the plan's frame, and `goals` every goal the plan was asked for, the ones reached
    at the start included) means that no path found passes through that goal on to the next (a turn
    back there needs a loop, `lattice.through`), and the reason names the goal."""
    radius = 1.0 / max_curvature
    if smoothed is None:
        if plan.entered_m is not None and plan.entered_m <= radius:
            return (f"{plan.reason} (each enters one within {plan.entered_m:.2f} m of the start): {_at_start(radius)}")
        return plan.reason
    verdict = smoothed.verification
    # The verdict tests clearance first: a clear curve that failed above the bound failed on its curvature.
    if verdict.min_level > 1.0 and verdict.max_curvature > max_curvature:
        if verdict.sharpest_m <= radius:
            return f"{verdict.reason}: {_at_start(radius)}"
        if goals is not None and (number := _goal_near(plan, smoothed, goals, within_m=2.0 * radius)) is not None:
            return (f"{verdict.reason}: within two turning radii ({2.0 * radius:.2f} m) of goal {number} of "
                    f"{len(goals)}, no path found passes through it on to the next goal in the room there, and a "
                    "plan never reverses")
    return verdict.reason


def _goal_near(plan: PathPlan, smoothed: Smoothed, goals: FloatArray, *, within_m: float) -> int | None:
    """The number (from 1, among `goals`) of the goal before the plan's last that its curve's sharpest point
    lies within `within_m` of, if any. The plan's goals are some of `goals`, in order, exactly."""
    curve = smoothed.points
    along = arc_lengths(curve)
    sharpest = np.array([np.interp(smoothed.verification.sharpest_m, along, curve[:, k]) for k in range(2)])
    numbers, j = [], 0
    for goal in plan.points[list(plan.goal_indices)]:
        while j < len(goals) and math.dist(goals[j], goal) > _SAME_POINT_M:
            j += 1
        numbers.append(j + 1)
    passed = plan.points[list(plan.goal_indices[:-1])]
    if not len(passed) or numbers[-1] > len(goals):
        return None
    distances = np.linalg.norm(passed - sharpest, axis=1)
    nearest = int(np.argmin(distances))
    return numbers[nearest] if distances[nearest] <= within_m else None


def _at_start(radius: float) -> str:
    """What a failure within a turning radius of the start means."""
    return (f"within a turning radius ({radius:.2f} m) of the start, no route found turns off the start's heading "
            "in the room there, and a plan never reverses")
