"""A lead-in found by a search over the car's own turns, where the planner's single-turn lead-ins fail.

The route search is blind to the heading. Where the route leaves the start in another direction than
the car faces, `services.planner.core` hands the refinement lead-ins of one turn each (straight on, a
turn onto the route's direction the short way or the long way round), and the refinement, local, keeps
the way round it is handed. In a room where no single turn fits the car may still get out: straight on
past a pillar, then round it. This search finds such a way: best-first over the car's forward motions
(Dubins' car on a lattice of motion primitives, as in hybrid A*: Dolgov, Thrun, Montemerlo & Diebel,
2010), arcs turning π/8 hard left or hard right at a radius a little wider than the car's, or as long
straight on, each checked exactly against the ellipses (segment tests on its chords), ordered by the
length driven plus the distance left to the route's point `ahead_m` on, within that point's distance
plus two radii of the start. It ends at that point, from a pose near it facing along the route, or
facing it with a clear straight run in; the route search takes over from there. It is a heuristic, not
complete: a lead-in where it finds one, None where it does not (within `max_nodes` poses, or on a route
shorter than `ahead_m`).
"""

from __future__ import annotations

import heapq
import math

import numpy as np

from services.geometry import EllipseStack, FloatArray

_TURN_RAD = math.pi / 8  # each motion turns by this much (or not at all)
_HEADINGS = 16  # 2π / _TURN_RAD: the headings a search reaches, from the start's


def lead_in(*, start: FloatArray, heading_rad: float, route: FloatArray, stack: EllipseStack, bounds_min: FloatArray,
            bounds_max: FloatArray, radius: float, level: float, spacing_m: float, ahead_m: float,
            max_nodes: int = 3000) -> FloatArray | None:
    """Points from the start, at most `spacing_m` apart, along forward arcs of `radius` and straight
    stretches, ending at the point of `route` (a polyline from the start) `ahead_m` along it (see the
    module docstring); None if none is found. Every chord keeps at least `level` from each ellipse of
    `stack` and stays within the bounds."""
    along = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(route, axis=0), axis=1))])
    if ahead_m >= along[-1]:
        return None
    at = int(np.searchsorted(along, ahead_m, side="right")) - 1  # the segment holding the point
    d = route[at + 1] - route[at]
    target = route[at] + (ahead_m - along[at]) / (along[at + 1] - along[at]) * d
    facing = math.atan2(d[1], d[0])
    step = radius * _TURN_RAD
    count = max(2, math.ceil(step / spacing_m))
    s = step * np.arange(1, count + 1) / count
    # Each motion's points in the frame of the pose it starts from: left, straight, right.
    arc = np.column_stack([radius * np.sin(s / radius), radius * (1.0 - np.cos(s / radius))])
    motions = np.stack([arc, np.column_stack([s, np.zeros_like(s)]), arc * [1.0, -1.0]])
    turns = (1, 0, -1)
    reach = float(np.linalg.norm(target - start)) + 2.0 * radius
    lo, hi = np.asarray(bounds_min, dtype=float), np.asarray(bounds_max, dtype=float)

    xs, ys, ks, parents = [float(start[0])], [float(start[1])], [0], [-1]
    paths: list[FloatArray] = [np.asarray(start, dtype=float).reshape(1, 2)]
    seen = {(round(xs[0] / step), round(ys[0] / step), 0)}
    heap = [(float(np.linalg.norm(target - start)), 0.0, 0)]
    while heap and len(xs) < max_nodes:
        _, g, node = heapq.heappop(heap)
        x, y, k = xs[node], ys[node], ks[node]
        theta = heading_rad + k * _TURN_RAD
        if _joins(x, y, theta, target, facing, step=step, stack=stack, level=level):
            return np.vstack([_traced(node, parents, paths), target])
        c, sn = math.cos(theta), math.sin(theta)
        points = motions @ np.array([[c, sn], [-sn, c]]) + (x, y)  # (3, count, 2)
        starts = np.concatenate([np.full((3, 1, 2), (x, y)), points[:, :-1]], axis=1).reshape(-1, 2)
        levels = stack.segment_levels(starts, points.reshape(-1, 2)).min(axis=1, initial=np.inf)
        clear = (levels >= level).reshape(3, count).all(axis=1)
        inside = ((points >= lo) & (points <= hi)).all(axis=(1, 2))
        for m in np.flatnonzero(clear & inside):
            (px, py), pk = points[m, -1], (k + turns[m]) % _HEADINGS
            key = (round(px / step), round(py / step), pk)
            if key in seen or math.hypot(px - start[0], py - start[1]) > reach:
                continue
            seen.add(key)
            xs.append(float(px))
            ys.append(float(py))
            ks.append(pk)
            parents.append(node)
            paths.append(points[m])
            heapq.heappush(heap, (g + step + math.hypot(px - target[0], py - target[1]), g + step, len(xs) - 1))
    return None


def _joins(x: float, y: float, theta: float, target: FloatArray, facing: float, *, step: float,
           stack: EllipseStack, level: float) -> bool:
    """Whether the pose (x, y, θ) joins the route at `target`: there already (within a motion, facing along
    the route within π/8), or facing it (within π/8, and the line to it within π/4 of the route's
    direction there) with a clear straight line to it."""
    gap = math.hypot(target[0] - x, target[1] - y)
    if gap <= step:
        return abs(math.remainder(theta - facing, 2.0 * math.pi)) <= _TURN_RAD
    towards = math.atan2(target[1] - y, target[0] - x)
    return (abs(math.remainder(theta - towards, 2.0 * math.pi)) <= _TURN_RAD
            and abs(math.remainder(towards - facing, 2.0 * math.pi)) <= 2.0 * _TURN_RAD
            and float(stack.segment_levels([[x, y]], [target]).min(initial=np.inf)) >= level)


def _traced(node: int, parents: list[int], paths: list[FloatArray]) -> FloatArray:
    """The points from the start to `node`, motion by motion."""
    chain = []
    while node >= 0:
        chain.append(paths[node])
        node = parents[node]
    return np.vstack(chain[::-1])
