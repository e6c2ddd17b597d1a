"""The tangent graph within the legs' informed ellipses, and Dijkstra on it: the exact shortest route.

Only points x with ‖x − from‖ + ‖x − to‖ ≤ bound can lie on a leg no longer than `bound`, so the graph
is built within that informed ellipse, starting a little above the straight distance and widening it
(to the length of a route found beyond the bound, else by a factor) until the leg found is within it —
then it is the exact shortest. Tangents, cuts and segment tests are kept as it widens.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
from scipy.sparse import csr_array
from scipy.sparse.csgraph import dijkstra

from services.geometry import Ellipse, EllipseStack, FloatArray, distance
from services.planner.route.arcs import Arcs, arc_length, arc_polyline, cuts
from services.planner.route.cells import DeepCells
from services.planner.route.frames import Frames
from services.planner.route.tangents import Segments, pair_tangents, terminal_tangents

_CHUNK = 20_000  # segments checked at once: bounds the memory of the broad phase
_BLOCK_TOL = 1e-9  # a segment touching a third ellipse (level 1 up to rounding) is clear
# Segments to test at once for the grid to pay: below it the exact test alone is faster (a sparse map
# tests tens of segments, a dense one thousands: docs/benchmarks.md, measurement history).
_DEEP_MIN_SEGMENTS = 256
_BOUND_FACTORS = (1.03, 1.1, 1.2, 1.35, 1.6, 2.2, np.inf)  # informed-ellipse bounds tried, × the straight distance
# (or × a longer estimate of the leg: `shortest_route`)


# Where a route may go, as a test of segments: starts (n, 2), ends (n, 2) → whether each stays there.
KeepTo = Callable[[FloatArray, FloatArray], np.ndarray]


@dataclass(frozen=True)
class Route:
    """The shortest route, one polyline per leg, and each leg's exact length.

    Arcs are polylines circumscribing the scaled ellipse (every chord tangent to it), so the whole
    polyline stays at level ≥ `level`; its length exceeds the exact one by at most 1/cos(π/32) − 1.
    """

    legs: list[FloatArray]
    lengths_m: list[float]


class _TangentGraph:
    """The tangent graph, built within the legs' informed ellipses and grown as their bounds widen.

    Tangents, cuts, free arcs and segment tests do not depend on the bound, so each is computed once:
    a wider bound only adds the pairs, ellipses and segments it newly lets in. A pair is given tangents
    only when both ellipses have a free arc: a tangent point anywhere else is dropped (in a wall of
    overlapping ellipses, about half of them lie wholly inside the others).
    """

    def __init__(self, *, frames: Frames, stack: EllipseStack, terminals: FloatArray, bounds_min, bounds_max,
                 keep_to: KeepTo | None = None) -> None:
        self.frames, self.stack, self.terminals = frames, stack, terminals
        self.bounds_min, self.bounds_max = bounds_min, bounds_max
        self.keep_to = keep_to
        m, t = len(frames.A), len(terminals)
        self.covered = np.zeros(m, dtype=bool)  # ellipses whose cuts are known
        self.cuts = (np.zeros(0, dtype=int), np.zeros(0), np.zeros(0, dtype=int), np.zeros(0, dtype=int), np.zeros((0, 5)))
        self.arcs = Arcs(frames, self.cuts, self.covered, bounds_min, bounds_max)
        self.pair_done = np.zeros((m, m), dtype=bool)  # pairs (i < j) with tangents
        kk, ee = np.meshgrid(np.arange(t), np.arange(m), indexing="ij")
        tk, tl = np.triu_indices(t, k=1)
        self.segments = Segments.concat([
            terminal_tangents(frames, terminals, kk.ravel(), ee.ravel()),
            Segments(terminals[tk], terminals[tl], -1 - tk, -1 - tl, np.zeros(len(tk)), np.zeros(len(tk))),
        ])
        self.status = np.zeros(len(self.segments.p), dtype=np.int8)  # 0 untested, 1 clear, 2 blocked
        self.deep: DeepCells | None = None  # built for the first batch of segments big enough to pay for it

    def _informed(self, bound: FloatArray, x: FloatArray, extra, y: FloatArray) -> FloatArray:
        """Whether a path through x (then `extra` further, then y) can fit some leg's bound."""
        a, z = self.terminals[:-1], self.terminals[1:]
        ok = np.zeros(len(x), dtype=bool)
        for leg in range(len(a)):
            if bound[leg] <= 0.0:
                continue
            if not np.isfinite(bound[leg]):
                return np.ones(len(x), dtype=bool)
            forward = distance(x, a[leg]) + extra + distance(y, z[leg])
            backward = distance(y, a[leg]) + extra + distance(x, z[leg])
            ok |= np.minimum(forward, backward) <= bound[leg] * (1.0 + 1e-12)
        return ok

    def _grow(self, bound: FloatArray) -> None:
        """Cuts of the ellipses and tangents of the pairs that the bound newly lets in."""
        frames = self.frames
        c, r = frames.centers, frames.reach
        # Ellipses that reach into some leg's informed ellipse (distance to a centre minus the reach).
        relevant = np.flatnonzero(self._informed(bound, c, -2.0 * r, c))
        new = relevant[~self.covered[relevant]]
        if len(new):
            parts = cuts(frames, self.stack, self.bounds_min, self.bounds_max, new)
            self.cuts = tuple(np.concatenate([old, part]) for old, part in zip(self.cuts, parts))
            self.covered[new] = True
            self.arcs = Arcs(frames, self.cuts, self.covered, self.bounds_min, self.bounds_max)
        relevant = relevant[self.arcs.has_free[relevant]]
        # Pairs none of whose tangents fits a leg: a path through p ∈ i and q ∈ j is at least
        # ‖from − cᵢ‖ − rᵢ + gap(discs) + ‖cⱼ − to‖ − rⱼ long (either way round).
        ii, jj = np.triu_indices(len(relevant), k=1)
        ii, jj = relevant[ii], relevant[jj]
        fresh = ~self.pair_done[ii, jj]
        ii, jj = ii[fresh], jj[fresh]
        gap = np.maximum(distance(c[ii], c[jj]) - r[ii] - r[jj], 0.0)
        keep = self._informed(bound, c[ii], gap - r[ii] - r[jj], c[jj])
        ii, jj = ii[keep], jj[keep]
        if len(ii):
            added = pair_tangents(frames, self.arcs, ii, jj)
            self.segments = Segments.concat([self.segments, added])
            self.status = np.concatenate([self.status, np.zeros(len(added.p), dtype=np.int8)])
            self.pair_done[ii, jj] = True

    def build(self, bound: FloatArray):
        """The graph within the bounds: (csr graph, node points, node owners, unwrapped angles, arc spans)."""
        self._grow(bound)
        arcs = self.arcs
        all_seg = self.segments
        length_all = distance(all_seg.q, all_seg.p)
        pick = np.flatnonzero((self.status != 2) & self._informed(bound, all_seg.p, length_all, all_seg.q))
        seg, length = all_seg.take(pick), length_all[pick]

        # Tangent points must lie on a free arc (outside every other ellipse, inside the bounds).
        arc_p = np.full(len(seg.p), -1)
        arc_q = np.full(len(seg.p), -1)
        unw_p, unw_q = seg.theta_p.copy(), seg.theta_q.copy()
        on_p, on_q = seg.owner_p >= 0, seg.owner_q >= 0
        arc_p[on_p], unw_p[on_p] = arcs.locate(seg.owner_p[on_p], seg.theta_p[on_p])
        arc_q[on_q], unw_q[on_q] = arcs.locate(seg.owner_q[on_q], seg.theta_q[on_q])
        valid = np.ones(len(seg.p), dtype=bool)
        valid[on_p] &= arcs.free[arc_p[on_p]]
        valid[on_q] &= arcs.free[arc_q[on_q]]
        self.status[pick[~valid]] = 2

        # Exact segment test against every ellipse but the two it touches, once per segment.
        untested = np.flatnonzero(valid & (self.status[pick] == 0))
        if self.deep is None and len(untested) >= _DEEP_MIN_SEGMENTS and len(self.stack):
            self.deep = DeepCells(self.stack)
        for lo in range(0, len(untested), _CHUNK):
            k = untested[lo : lo + _CHUNK]
            if self.deep is not None:  # most are proved blocked cheaply; the rest get the exact test
                sure = self.deep.blocked(seg.p[k], seg.q[k])
                self.status[pick[k[sure]]] = 2
                k = k[~sure]
            rows, cols, levels = self.stack.segment_pairs_swept(seg.p[k], seg.q[k])
            hit = (levels < 1.0 - _BLOCK_TOL) & (cols != seg.owner_p[k][rows]) & (cols != seg.owner_q[k][rows])
            blocked = np.zeros(len(k), dtype=bool)
            blocked[rows[hit]] = True
            if self.keep_to is not None:  # a clear segment that leaves where the route may go is no edge
                clear = np.flatnonzero(~blocked)
                blocked[clear[~self.keep_to(seg.p[k[clear]], seg.q[k[clear]])]] = True
            self.status[pick[k]] = np.where(blocked, 2, 1)
        keep = self.status[pick] == 1
        seg, length = seg.take(keep), length[keep]
        arc_p, arc_q, unw_p, unw_q = arc_p[keep], arc_q[keep], unw_p[keep], unw_q[keep]
        return self._assemble(seg, length, arcs, arc_p, arc_q, unw_p, unw_q)

    def _assemble(self, seg, length, arcs, arc_p, arc_q, unw_p, unw_q):
        frames, t, terminals = self.frames, len(self.terminals), self.terminals
        # Nodes: terminals 0 … t − 1, then both ends of every segment that touch an ellipse.
        s = len(seg.p)
        node_p = np.where(seg.owner_p < 0, -1 - seg.owner_p, t + np.arange(s))
        node_q = np.where(seg.owner_q < 0, -1 - seg.owner_q, t + s + np.arange(s))
        points = np.vstack([terminals, seg.p, seg.q])
        owner = np.concatenate([np.full(t, -1), seg.owner_p, seg.owner_q])
        unwrapped = np.concatenate([np.zeros(t), unw_p, unw_q])
        arc = np.concatenate([np.full(t, -1), arc_p, arc_q])
        # Arcs: consecutive tangent points of one free arc, in angle order.
        on = np.flatnonzero(owner >= 0)
        on = on[np.lexsort((unwrapped[on], arc[on]))]
        consecutive = arc[on[:-1]] == arc[on[1:]]
        u, v = on[:-1][consecutive], on[1:][consecutive]
        arc_span = unwrapped[v] - unwrapped[u]
        arc_len = arc_length(frames, owner[u], unwrapped[u], arc_span)
        # An ellipse with no cut is one free loop: also join its last tangent point to its first.
        whole = arcs.count[owner[on]] == 0
        ends = on[whole]
        if len(ends):
            o = owner[ends]
            last = np.r_[o[1:] != o[:-1], True]
            firstm = np.r_[True, o[1:] != o[:-1]]
            lu, fv = ends[last], ends[firstm]
            two = lu != fv
            lu, fv = lu[two], fv[two]
            wrap_span = unwrapped[fv] + 2.0 * np.pi - unwrapped[lu]
            wrap_len = arc_length(frames, owner[lu], unwrapped[lu], wrap_span)
            u, v = np.concatenate([u, lu]), np.concatenate([v, fv])
            arc_len, arc_span = np.concatenate([arc_len, wrap_len]), np.concatenate([arc_span, wrap_span])
        i = np.concatenate([node_p, u])
        j = np.concatenate([node_q, v])
        w = np.concatenate([length, arc_len]) + 1e-12  # explicit zeros would be no edge
        span = np.concatenate([np.zeros(len(length)), arc_span])  # the angle from i to j along an arc
        # Keep the shorter of parallel edges (two arcs joining the only two points of a loop).
        lo_, hi_ = np.minimum(i, j), np.maximum(i, j)
        order = np.lexsort((w, hi_, lo_))
        first = np.ones(len(order), dtype=bool)
        first[1:] = (lo_[order][1:] != lo_[order][:-1]) | (hi_[order][1:] != hi_[order][:-1])
        order = order[first]
        n = len(points)
        # The order sorts by lo, then hi: the edges are already in CSR order, row lo, column hi.
        rows, cols = lo_[order], hi_[order]
        graph = csr_array((w[order], cols, np.searchsorted(rows, np.arange(n + 1))), shape=(n, n))
        # Each kept edge's key lo · n + hi, ascending, and its angle from lo.
        spans = _Spans(keys=rows * n + cols, from_lo=np.where(i == lo_, span, -span)[order], nodes=n)
        return graph, points, owner, unwrapped, spans


@dataclass(frozen=True)
class _Spans:
    """The angle each edge of the graph turns through along its arc (0 for a tangent segment), by edge."""

    keys: FloatArray  # lo · nodes + hi of each edge (lo < hi), ascending
    from_lo: FloatArray  # the signed angle from node lo to node hi
    nodes: int

    def between(self, a: FloatArray, b: FloatArray) -> FloatArray:
        """The signed angle from node a to node b of each edge a–b."""
        lo, hi = np.minimum(a, b), np.maximum(a, b)
        return np.where(a == lo, 1.0, -1.0) * self.from_lo[np.searchsorted(self.keys, lo * self.nodes + hi)]


def _polyline(frames: Frames, points, owner, unwrapped, spans: _Spans, chain: list[int]) -> FloatArray:
    """The route's points along the node chain: tangent segments straight, arcs circumscribed."""
    out = [points[chain[:1]]]
    tails, heads = np.array(chain[:-1]), np.array(chain[1:])
    for a, b, span in zip(chain[:-1], chain[1:], spans.between(tails, heads).tolist()):
        if owner[a] >= 0 and owner[a] == owner[b]:
            out.append(arc_polyline(frames, int(owner[a]), float(unwrapped[a]), span)[1:])
        else:
            out.append(points[[b]])
    return np.vstack(out)


def shortest_route(
    *,
    start: FloatArray,
    goals: FloatArray,
    ellipses: list[Ellipse],
    bounds_min: FloatArray,
    bounds_max: FloatArray,
    level: float = 1.01,
    estimate_m: Sequence[float] | None = None,
    keep_to: KeepTo | None = None,
) -> Route | None:
    """The exact shortest route start → goal₁ → … outside every ellipse scaled to `level`; None if none.

    An ellipse that would contain a terminal at `level` is scaled only as far as leaves the terminal
    outside (never below the ellipse itself), so a robot just inside a margin can still leave.
    `estimate_m`: each leg's length as a coarser search found it (the corridor planner's); the informed
    bounds are then factors of it where it is longer than the straight distance (a winding leg would
    otherwise build and search the graph once per factor before its bound reaches the route). It is
    only where the search starts: a bound is widened until the leg found is within it, either way.
    `keep_to`: where the route may go (a corridor): a tangent segment it rejects is no edge of the
    graph, so the route is the shortest among those that keep to it (arcs, which follow the ellipses,
    are not tested).
    """
    start = np.asarray(start, dtype=float)
    goals = np.atleast_2d(np.asarray(goals, dtype=float))
    bounds_min, bounds_max = np.asarray(bounds_min, dtype=float), np.asarray(bounds_max, dtype=float)
    terminals = np.vstack([start, goals])
    stack = EllipseStack.of(ellipses)
    if len(stack):
        nearest = np.min(stack.levels(terminals), axis=0)
        scale = np.maximum(np.minimum(level, nearest * (1.0 - 1e-9)), 1.0)
    else:
        scale = np.zeros(0)
    frames = Frames.of(stack, scale)
    scaled = EllipseStack(A=frames.A, b=frames.b)
    # Each leg's bounds are factors of its straight distance, or of its estimate where that is longer.
    base = np.linalg.norm(np.diff(terminals, axis=0), axis=1)
    if estimate_m is not None:
        base = np.maximum(base, np.asarray(estimate_m, dtype=float))
    legs: list[FloatArray | None] = [None] * len(goals)
    lengths = [np.inf] * len(goals)
    # Each leg's bound: the next factor, or the length of a route found beyond the last bound (any
    # route is an upper bound, and a tighter one than the next factor).
    step = np.zeros(len(goals), dtype=int)
    bound = _BOUND_FACTORS[0] * base + 1e-9
    tangents = _TangentGraph(frames=frames, stack=scaled, terminals=terminals, bounds_min=bounds_min,
                             bounds_max=bounds_max, keep_to=keep_to)
    while True:
        todo = [k for k in range(len(goals)) if legs[k] is None]
        if not todo:
            return Route(legs=legs, lengths_m=lengths)
        active = np.where(np.isin(np.arange(len(goals)), todo), bound, 0.0)
        graph, points, owner, unwrapped, spans = tangents.build(active)
        dist, pred = dijkstra(graph, directed=False, indices=todo, return_predecessors=True)
        for row, leg in enumerate(todo):
            target = leg + 1
            found = dist[row, target]
            if np.isfinite(found) and found <= bound[leg]:
                chain = [target]
                while chain[-1] != leg:
                    chain.append(int(pred[row, chain[-1]]))
                legs[leg] = _polyline(frames, points, owner, unwrapped, spans, chain[::-1])
                lengths[leg] = float(found)
            elif not np.isfinite(bound[leg]):
                return None  # the whole graph has no route
            elif np.isfinite(found):
                bound[leg] = found * (1.0 + 1e-9)
            else:
                step[leg] += 1
                bound[leg] = _BOUND_FACTORS[step[leg]] * base[leg] + 1e-9


def tangent_route(
    *,
    start: FloatArray,
    goals: FloatArray,
    ellipses: list[Ellipse],
    bounds_min: FloatArray,
    bounds_max: FloatArray,
    level: float = 1.01,
    estimate_m: Sequence[float] | None = None,
    keep_to: KeepTo | None = None,
) -> list[FloatArray] | None:
    """Shortest polylines start → goal₁ → … (one per leg) outside every ellipse; None if there is none.

    The polyline stays at level ≥ `level` (arcs circumscribed, tangents exact), inside the bounds.
    `estimate_m`, `keep_to`: see `shortest_route`.
    """
    route = shortest_route(
        start=start, goals=goals, ellipses=ellipses, bounds_min=bounds_min, bounds_max=bounds_max, level=level,
        estimate_m=estimate_m, keep_to=keep_to,
    )
    return None if route is None else route.legs
