"""Paths found by a search over the car's own turns: a lead-in where the planner's single-turn lead-ins
fail, and legs through the goals where its routes do (`through`: on the map, `services.maps.seed`; on the
ellipses, where a route turns back at a goal, `services.planner.core`).

The route search is blind to the heading. Where the route leaves the start in another direction than
the car faces, `services.planner.core` hands the refinement lead-ins of one turn each (straight on, a
turn onto the route's direction the short way or the long way round), and the refinement, local, keeps
the way round it is handed. In a room where no single turn fits the car may still get out: straight on
past a pillar, then round it. `search` finds such a way: best-first over the car's forward motions
(Dubins' car on a lattice of motion primitives, as in hybrid A*: Dolgov, Thrun, Montemerlo & Diebel,
2010), arcs turning π/8 hard left or hard right at a radius a little wider than the car's, or as long
straight on, each checked by the caller's test on its chords, ordered by the length driven plus the
distance left to the target, within `reach_m` of the start. It ends at the target, from a pose near it
facing along a given direction or facing it with a clear straight run in; or, arriving any way round,
from a pose that turns at the same radius until it faces the target and runs straight in. It is a
heuristic, not complete: a path where it finds one, None where it does not (within `max_nodes` poses).
`through` chains it goal by goal, each leg from where the one before arrived.
"""

from __future__ import annotations

import heapq
import math
from collections.abc import Callable

import numpy as np

from services.geometry import EllipseStack, FloatArray, arc_lengths

_TURN_RAD = math.pi / 8  # each motion turns by this much (or not at all)
_HEADINGS = 16  # 2π / _TURN_RAD: the headings a search reaches, from the start's
_TURN_IN = 4.0  # arriving any way round: a pose this many radii from the target or nearer tries to turn in
MAX_NODES = 3000  # poses a search (a lead-in, a leg through the goals) takes at most, by default
# A searched path's arcs are this many planning radii: a little wider, for the refinement's curvature budget
# (which its step floors make stricter), than the radius itself, and narrower than the single-turn lead-ins'
# (`services.planner.core`), so that a hall those do not fit in may fit it.
WIDER = 1.05

_ONWARD_DIRECTIONS = 16  # directions round a goal the way on to the next is chosen among (`through`)
# The weight on the distance left (`search`'s greed) of a search arriving any way round (`through`): along
# a long corridor the lattice's paths run a few per cent longer than a grid's distance round the walls, and
# unweighted the search takes every pose within that slack before it reaches the goal. A search arriving
# facing a given way is not weighted: its way in may go round the goal, which a search drawn to the goal
# runs out of poses before it takes.
_GREED = 1.1

Clear = Callable[[FloatArray, FloatArray], np.ndarray]  # (starts, ends) → whether each chord is clear
ToGo = Callable[[FloatArray], FloatArray]  # points → the distance left from each to the target


def lead_in(*, start: FloatArray, heading_rad: float, route: FloatArray, stack: EllipseStack, bounds_min: FloatArray,
            bounds_max: FloatArray, radius: float, level: float, spacing_m: float, ahead_m: float,
            max_nodes: int = MAX_NODES) -> FloatArray | None:
    """Points from the start, at most `spacing_m` apart, along forward arcs of `radius` and straight
    stretches, ending at the point of `route` (a polyline from the start) `ahead_m` along it, facing along
    the route there; None if none is found within that point's distance plus two radii of the start, or
    the route is shorter than `ahead_m`. Every chord keeps at least `level` from each ellipse of `stack`
    and stays within the bounds."""
    along = arc_lengths(route)
    if ahead_m >= along[-1]:
        return None
    at = int(np.searchsorted(along, ahead_m, side="right")) - 1  # the segment holding the point
    d = route[at + 1] - route[at]
    target = route[at] + (ahead_m - along[at]) / (along[at + 1] - along[at]) * d
    return search(start=start, heading_rad=heading_rad, target=target, facing=math.atan2(d[1], d[0]),
                  clear=clear_of(stack, level), bounds_min=bounds_min, bounds_max=bounds_max, radius=radius,
                  spacing_m=spacing_m, reach_m=float(np.linalg.norm(target - start)) + 2.0 * radius,
                  max_nodes=max_nodes)


def clear_of(stack: EllipseStack, level: float) -> Clear:
    """The chord test that keeps at least `level` from each ellipse of `stack` (exact on each segment,
    `EllipseStack.segments_clear`)."""

    def clear(starts: FloatArray, ends: FloatArray) -> np.ndarray:
        return stack.segments_clear(starts, ends, level=level)

    return clear


def through(*, start: FloatArray, heading_rad: float, goals: FloatArray, clear: Clear, bounds_min: FloatArray,
            bounds_max: FloatArray, radius: float, spacing_m: float, max_nodes: int = MAX_NODES,
            to_go: Callable[[FloatArray], ToGo] | None = None) -> list[FloatArray] | None:
    """Legs from the start, leaving along its heading, through `goals` in order (`search`'s points), each
    leaving its goal the way the one before arrived. A goal with another after it is arrived at facing
    within a right angle of the way on (`_onward`) where the search finds such an arrival, else any way
    round, as the last goal is. Each leg is searched within `max_nodes` poses; the legs found before the
    first that is not, None if that is the first. `to_go(goal)`: the distance left from points to the
    goal (None: the straight distance)."""
    goals = np.asarray(goals, dtype=float).reshape(-1, 2)
    ways = [None if to_go is None else to_go(goal) for goal in goals]
    legs: list[FloatArray] = []
    at, heading = np.asarray(start, dtype=float), heading_rad
    for k, goal in enumerate(goals):
        # An arrival any way round may face a wall with no room to turn on to the next goal.
        facings = [None] if k + 1 == len(goals) else [_onward(goal, goals[k + 1], ways[k + 1], radius), None]
        for facing in facings:
            leg = search(start=at, heading_rad=heading, target=goal, facing=facing, clear=clear,
                         bounds_min=bounds_min, bounds_max=bounds_max, radius=radius, spacing_m=spacing_m,
                         reach_m=math.inf, max_nodes=max_nodes, to_go=ways[k],
                         greed=_GREED if facing is None else 1.0, facing_within=0.5 * math.pi)
            if leg is not None:
                break
        if leg is None:
            break
        legs.append(leg)
        at, heading = leg[-1], math.atan2(*(leg[-1] - leg[-2])[::-1])
    return legs or None


def _onward(goal: FloatArray, after: FloatArray, to_go: ToGo | None, radius: float) -> float:
    """The direction from `goal` on to the goal `after` it: of the points a turning radius round it, towards
    the one with the least distance left (`to_go`, or the straight distance)."""
    angles = 2.0 * math.pi * np.arange(_ONWARD_DIRECTIONS) / _ONWARD_DIRECTIONS
    points = goal + radius * np.column_stack([np.cos(angles), np.sin(angles)])
    left = np.hypot(*(after - points).T) if to_go is None else to_go(points)
    return float(angles[int(np.argmin(left))])


def search(*, start: FloatArray, heading_rad: float, target: FloatArray, facing: float | None, clear: Clear,
           bounds_min: FloatArray, bounds_max: FloatArray, radius: float, spacing_m: float, reach_m: float,
           max_nodes: int, to_go: ToGo | None = None, greed: float = 1.0,
           facing_within: float = 2.0 * _TURN_RAD) -> FloatArray | None:
    """Points from the start, at most `spacing_m` apart, along forward arcs of `radius` and straight
    stretches, ending at `target`. With a `facing`, from a pose within a motion of it facing that way
    (within π/8), or from one facing it (within π/8, the line to it within `facing_within` of `facing`)
    with a clear straight line to it. Without (any way round): from a pose that turns at `radius` until it
    faces the target and runs straight in (`_turned_towards`), so the path keeps the car's curvature to its end.
    Every chord passes `clear` and stays within the bounds, every point within `reach_m` of the start;
    None if none is found within `max_nodes` poses (see the module docstring). Poses are taken in order
    of the length driven plus `greed` times `to_go` (the straight distance to the target if None; a pose
    whose `to_go` is ∞ is dropped): above 1, weighted A* (Pohl, 1970), which takes fewer poses before it
    reaches the target, by a path at most `greed` times the shortest the lattice holds if `to_go` never
    overestimates."""
    step = radius * _TURN_RAD
    count = max(2, math.ceil(step / spacing_m))
    s = step * np.arange(1, count + 1) / count
    # Each motion's points in the frame of the pose it starts from: left, straight, right.
    arc = np.column_stack([radius * np.sin(s / radius), radius * (1.0 - np.cos(s / radius))])
    motions = np.stack([arc, np.column_stack([s, np.zeros_like(s)]), arc * [1.0, -1.0]])
    turns = (1, 0, -1)
    lo, hi = np.asarray(bounds_min, dtype=float), np.asarray(bounds_max, dtype=float)
    target = np.asarray(target, dtype=float)

    def straight_to_go(points: FloatArray) -> FloatArray:
        return np.hypot(*(target - points).T)

    to_go = to_go or straight_to_go

    xs, ys, ks, parents = [float(start[0])], [float(start[1])], [0], [-1]
    paths: list[FloatArray] = [np.asarray(start, dtype=float).reshape(1, 2)]
    seen = {(round(xs[0] / step), round(ys[0] / step), 0)}
    heap = [(float(to_go(np.reshape(start, (1, 2)))[0]), 0.0, 0)]
    while heap and len(xs) < max_nodes:
        _, g, node = heapq.heappop(heap)
        x, y, k = xs[node], ys[node], ks[node]
        theta = heading_rad + k * _TURN_RAD
        if facing is not None:
            joins = _joins(x, y, theta, target, facing, within=facing_within, step=step, clear=clear)
            tail = target.reshape(1, 2) if joins else None
        elif math.hypot(target[0] - x, target[1] - y) <= _TURN_IN * radius:
            tail = _turned_towards(x, y, theta, target, radius=radius, spacing_m=spacing_m, clear=clear)
        else:
            tail = None
        if (tail is not None and ((tail >= lo) & (tail <= hi)).all()
                and np.hypot(*(tail - start).T).max() <= reach_m):
            return np.vstack([_traced(node, parents, paths), tail])
        c, sn = math.cos(theta), math.sin(theta)
        points = motions @ np.array([[c, sn], [-sn, c]]) + (x, y)  # (3, count, 2)
        starts = np.concatenate([np.full((3, 1, 2), (x, y)), points[:, :-1]], axis=1).reshape(-1, 2)
        passed = clear(starts, points.reshape(-1, 2)).reshape(3, count).all(axis=1)
        inside = ((points >= lo) & (points <= hi)).all(axis=(1, 2))
        moves = np.flatnonzero(passed & inside)
        left = greed * to_go(points[moves, -1])
        for m, h in zip(moves.tolist(), left.tolist()):
            (px, py), pk = points[m, -1], (k + turns[m]) % _HEADINGS
            key = (round(px / step), round(py / step), pk)
            if key in seen or h == math.inf or math.hypot(px - start[0], py - start[1]) > reach_m:
                continue
            seen.add(key)
            xs.append(float(px))
            ys.append(float(py))
            ks.append(pk)
            parents.append(node)
            paths.append(points[m])
            heapq.heappush(heap, (g + step + h, g + step, len(xs) - 1))
    return None


def _joins(x: float, y: float, theta: float, target: FloatArray, facing: float, *, within: float, step: float,
           clear: Clear) -> bool:
    """Whether the pose (x, y, θ) joins the target: there already (within a motion, facing `facing`
    within π/8), or facing it (within π/8, and the line to it within `within` of `facing`) with a clear
    straight line to it."""
    gap = math.hypot(target[0] - x, target[1] - y)
    if gap <= step:
        return abs(math.remainder(theta - facing, 2.0 * math.pi)) <= _TURN_RAD
    towards = math.atan2(target[1] - y, target[0] - x)
    return (abs(math.remainder(theta - towards, 2.0 * math.pi)) <= _TURN_RAD
            and abs(math.remainder(towards - facing, 2.0 * math.pi)) <= within
            and bool(clear(np.array([[x, y]]), target.reshape(1, 2))[0]))


def _turned_towards(x: float, y: float, theta: float, target: FloatArray, *, radius: float, spacing_m: float,
                    clear: Clear) -> FloatArray | None:
    """From the pose (x, y, θ) to the target: an arc of `radius`, left or right, until the car faces the
    target, then straight in (Dubins' CS path to a point), as points at most `spacing_m` apart after the
    pose; the shorter of the two whose chords pass `clear`, None if neither does (or the target lies
    within both turning circles). The tangent point of the circle centred c, for a target v = t − c at
    distance D ≥ r, lies at angle atan2(v) ∓ acos(r / D) round c (left, right)."""
    best: tuple[float, FloatArray] | None = None
    for side in (1.0, -1.0):
        c = np.array([x - side * radius * math.sin(theta), y + side * radius * math.cos(theta)])
        v = target - c
        gap = math.hypot(v[0], v[1])
        if gap < radius:
            continue
        leave = math.atan2(v[1], v[0]) - side * math.acos(radius / gap)  # where the straight run leaves
        begin = theta - side * 0.5 * math.pi  # the pose's angle round c
        sweep = ((leave - begin) * side) % (2.0 * math.pi)
        arc = turning_arc(np.array([x, y]), theta, radius=radius, turn_rad=side * sweep, step_m=spacing_m)[1:]
        run = math.sqrt(max(gap * gap - radius * radius, 0.0))
        inner = max(1, math.ceil(run / spacing_m))
        straight = arc[-1] + (target - arc[-1]) * (np.arange(1, inner + 1) / inner)[:, None]
        tail = np.vstack([arc, straight])
        length = sweep * radius + run
        if (best is None or length < best[0]) and clear(np.vstack([[x, y], tail[:-1]]), tail).all():
            best = (length, tail)
    return None if best is None else best[1]


def turning_arc(start: FloatArray, heading_rad: float, *, radius: float, turn_rad: float,
                step_m: float) -> FloatArray:
    """The circle of `radius` a car at (start, heading) follows turning by `turn_rad` (left > 0, right < 0,
    −0.0 on the right), as points at most `step_m` apart from the start on."""
    side = math.copysign(1.0, turn_rad)
    centre = start + side * radius * np.array([-math.sin(heading_rad), math.cos(heading_rad)])
    count = max(2, math.ceil(abs(turn_rad) * radius / step_m) + 1)
    angle = heading_rad - side * 0.5 * math.pi + np.linspace(0.0, turn_rad, count)
    return centre + radius * np.column_stack([np.cos(angle), np.sin(angle)])


def _traced(node: int, parents: list[int], paths: list[FloatArray]) -> FloatArray:
    """The points from the start to `node`, motion by motion."""
    chain = []
    while node >= 0:
        chain.append(paths[node])
        node = parents[node]
    return np.vstack(chain[::-1])
