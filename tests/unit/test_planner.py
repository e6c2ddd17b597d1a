"""Planner core: eq. (2) on segments, the global route, and the convex refinement against known optima."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy import sparse

from services.geometry import Ellipse, EllipseStack, distance, polyline_length
from services.planner.core import goals_ahead, intersected, plan_path, stay_at_start
from services.planner.refine import RefineSettings, curvature_broken, resample_legs
from services.planner.route import tangent_route
from services.planner.route.arcs import Arcs, cuts
from services.planner.route.cells import DeepCells
from services.planner.route.frames import Frames
from services.planner.route.roots import trig_roots
from services.planner.route.tangents import pair_tangents

BOX = dict(bounds_min=np.array([-20.0, -20.0]), bounds_max=np.array([20.0, 20.0]))
coord = st.floats(-5, 5, allow_nan=False)


def _random_ellipses(rng: np.random.Generator, count: int, *, extent: float, semi: tuple[float, float]) -> list[Ellipse]:
    """`count` ellipses centred in [0, extent]², semi-axes drawn from `semi`, at random angles."""
    return [Ellipse.from_axes(center=rng.uniform(0, extent, 2), semi_axes=np.sort(rng.uniform(*semi, 2))[::-1],
                              angle_rad=rng.uniform(0, np.pi)) for _ in range(count)]


@settings(max_examples=60, deadline=None)
@given(
    p=st.tuples(coord, coord),
    q=st.tuples(coord, coord),
    center=st.tuples(coord, coord),
    axes=st.tuples(st.floats(0.2, 3), st.floats(0.2, 3)),
    angle=st.floats(0, np.pi),
)
def test_segment_test_agrees_with_dense_sampling(p, q, center, axes, angle):
    ellipse = Ellipse.from_axes(center=center, semi_axes=axes, angle_rad=angle)
    exact = EllipseStack.of([ellipse]).segment_levels([p], [q])[0, 0]
    t = np.linspace(0.0, 1.0, 20001)[:, None]
    sampled = ellipse.level(np.asarray(p) + t * (np.asarray(q) - np.asarray(p))).min()
    assert exact <= sampled + 1e-12
    assert sampled - exact < 1e-3  # the sampling can only miss by its resolution


@pytest.mark.parametrize("run, count, semi", [
    (2, 60, (0.1, 1.5)), (16, 60, (0.1, 1.5)), (37, 60, (0.1, 1.5)),
    (16, 300, (0.05, 5.0)),  # a map's cover: long walls among specks, asked in classes of reach
])
def test_the_broad_phase_in_runs_finds_the_same_pairs_in_the_same_order(run, count, semi):
    rng = np.random.default_rng(run)
    ellipses = _random_ellipses(rng, count, extent=20.0, semi=semi)
    stack = EllipseStack.of(ellipses)
    curve = 10.0 + np.cumsum(rng.normal(0.0, 0.05, (1000, 2)), axis=0)
    radii = rng.uniform(0.0, 0.3, len(curve))
    rows, cols = stack.near_pairs(curve, radii)
    assert len(rows) > 0
    for got, expected in zip(stack.near_pairs(curve, radii, run=run), (rows, cols)):
        assert np.array_equal(got, expected)


@pytest.mark.parametrize("count, extent, semi, reach_m", [
    (300, 30.0, (0.1, 2.0), 6.0),  # a tangent graph's segments, metres long, along walls of many ellipses
    (3000, 300.0, (0.05, 0.5), 1.0),  # a scan-built model's: many small ellipses, short segments, far apart
])
def test_the_swept_broad_phase_keeps_every_pair_at_level_at_most_one_with_the_trees_levels(count, extent, semi, reach_m):
    """Every pair (segment, ellipse) at level ≤ 1 by the dense exact test is kept, by segment then ellipse,
    with the level the KD-tree's broad phase gives it; the pairs left out are outside the bounding disc.
    A segment of length zero and a very short one are among them."""
    rng = np.random.default_rng(count)
    stack = EllipseStack.of(_random_ellipses(rng, count, extent=extent, semi=semi))
    p = rng.uniform(0, extent, (1500, 2))
    q = p + rng.normal(0.0, reach_m, (1500, 2))
    q[0], q[1] = p[0], p[1] + 0.01
    rows, cols, levels = stack.segment_pairs_swept(p, q)
    assert np.all(np.diff(rows * len(stack) + cols) > 0)
    dense = stack.segment_levels(p, q)
    touching = set(zip(*np.nonzero(dense <= 1.0)))
    kept = dict(zip(zip(rows.tolist(), cols.tolist()), levels.tolist()))
    assert len(touching) > 40 and touching <= set(kept)
    tree_rows, tree_cols, tree_levels = stack.segment_pairs(p, q)
    tree = dict(zip(zip(tree_rows.tolist(), tree_cols.tolist()), tree_levels.tolist()))
    assert len(kept) < len(tree) and all(tree[pair] == level for pair, level in kept.items())
    left = [pair for pair in tree if pair not in kept]
    i, j = np.array(left).T
    d = q[i] - p[i]
    t = np.clip(np.einsum("ij,ij->i", stack.centers[j] - p[i], d) / np.maximum(np.einsum("ij,ij->i", d, d), 1e-300), 0, 1)
    assert np.all(np.linalg.norm(p[i] + t[:, None] * d - stack.centers[j], axis=1) > stack.reach[j])


@pytest.mark.parametrize("seed", [4, 5, 6])
def test_the_tangent_graph_on_the_swept_broad_phase_finds_the_kd_trees_route(seed, monkeypatch):
    """A field of about 150 ellipses, two goals: the route searched with the swept broad phase is, to the bit,
    the one searched with the KD-tree's (which keeps a superset of its pairs)."""
    rng = np.random.default_rng(seed)
    start, goals = np.array([0.5, 0.5]), np.array([[19.5, 19.0], [1.0, 19.5]])
    ellipses = [e for e in _random_ellipses(rng, 150, extent=20.0, semi=(0.1, 1.2))
                if np.all(e.level(np.vstack([start, goals])) > 1.05)]  # the terminals outside every one

    def route():
        return tangent_route(start=start, goals=goals, ellipses=ellipses, bounds_min=np.array([-1.0, -1.0]),
                             bounds_max=np.array([21.0, 21.0]))

    swept = route()
    monkeypatch.setattr(EllipseStack, "segment_pairs_swept", lambda self, p, q: self.segment_pairs(p, q))
    tree = route()
    assert swept is not None and tree is not None
    assert all(np.array_equal(a, b) for a, b in zip(swept, tree, strict=True))


def test_intersected_names_the_crossed_ellipses():
    ellipses = [Ellipse.circle(center=[5, 0], radius=1), Ellipse.circle(center=[5, 3], radius=1)]
    assert intersected(np.array([[0.0, 0.0], [10.0, 0.0]]), ellipses).tolist() == [0]
    assert intersected(np.array([[0.0, 1.6], [10.0, 1.6]]), ellipses).tolist() == []


def _around_disc_length(distance: float, radius: float) -> float:
    """Tangent–arc–tangent shortest path between (−d, 0) and (d, 0) round a disc of radius R at 0."""
    tangent = np.sqrt(distance**2 - radius**2)
    arc = radius * (np.pi - 2.0 * np.arccos(radius / distance))
    return 2.0 * tangent + arc


def test_shortest_path_round_one_disc_matches_the_analytic_length():
    disc = Ellipse.circle(center=[0.0, 0.0], radius=2.0)
    plan = plan_path(
        start=np.array([-6.0, 0.0]),
        heading_rad=None,
        goals=np.array([[6.0, 0.0]]),
        ellipses=[disc],
        max_curvature=100.0,
        **BOX,
    )
    assert plan.status == "ok"
    level = RefineSettings().level  # the refined points keep this level: a disc of radius 2·level
    optimum = _around_disc_length(6.0, 2.0 * level)
    assert polyline_length(plan.points) == pytest.approx(optimum, rel=0.01)
    assert disc.level(plan.points).min() >= level - 1e-6


def test_trig_roots_are_every_real_angle_of_each_polynomial():
    # cos 2θ: π/4 + kπ/2; 1/2 + cos θ: 2π/3 and 4π/3; 2 + cos θ: none; cos 2θ − 0.999: two pairs of
    # roots ±a/2 about 0 and π, each pair inside one grid step (the companion matrix finds them).
    coef = np.array([[0.0, 0.0, 0.0, 1.0, 0.0], [0.5, 1.0, 0.0, 0.0, 0.0], [2.0, 1.0, 0.0, 0.0, 0.0],
                     [-0.999, 0.0, 0.0, 1.0, 0.0]])
    theta, real = trig_roots(coef)
    half = 0.5 * np.arccos(0.999)
    expected = [np.pi / 4 + np.pi / 2 * np.arange(4), [2 * np.pi / 3, 4 * np.pi / 3], [],
                np.mod([half, -half, np.pi + half, np.pi - half], 2 * np.pi)]
    for row, angles in enumerate(expected):
        np.testing.assert_allclose(np.sort(theta[row][real[row]]), np.sort(angles), atol=1e-9)


def test_deep_cells_call_blocked_only_segments_the_exact_test_finds_blocked():
    rng = np.random.default_rng(3)
    ellipses = _random_ellipses(rng, 60, extent=20.0, semi=(0.3, 1.5))
    stack = EllipseStack.of(ellipses)
    p, q = rng.uniform(-1, 21, (2000, 2)), rng.uniform(-1, 21, (2000, 2))
    sure = DeepCells(stack).blocked(p, q)
    exact = stack.min_segment_levels(p, q) < 1.0 - 1e-9
    assert not np.any(sure & ~exact)
    assert np.sum(sure) > 0.8 * np.sum(exact)  # and it finds most of them


def test_deep_cells_first_pass_changes_no_answer():
    # Every 8th sample first, then all of them for the rest: the answer of reading every sample at once.
    rng = np.random.default_rng(5)
    stack = EllipseStack.of(_random_ellipses(rng, 60, extent=20.0, semi=(0.3, 1.5)))
    deep = DeepCells(stack)
    p, q = rng.uniform(-1, 21, (3000, 2)), rng.uniform(-1, 21, (3000, 2))
    q[:500] = p[:500] + rng.uniform(-0.2, 0.2, (500, 2))  # shorter than a stride, down to a point
    count = np.ceil(distance(q, p) / deep.cell).astype(int) + 2
    np.testing.assert_array_equal(deep.blocked(p, q), deep._hits(p, q, count, 1))


@pytest.mark.parametrize("seed, ratio", [(1, 1.5), (2, 4.0), (3, 12.0)])
def test_tangent_windows_skipped_for_lack_of_free_arcs_hold_no_tangent_the_graph_keeps(seed, ratio):
    # Every pair of a random field (round to very eccentric ellipses, which stress the outer tangents'
    # side): the tangents found with windows skipped are exactly those found solving every window.
    rng = np.random.default_rng(seed)
    ellipses = []
    for _ in range(70):
        major = rng.uniform(0.3, 1.6)
        ellipses.append(Ellipse.from_axes(center=rng.uniform(0, 20, 2), semi_axes=[major, major / rng.uniform(1.0, ratio)],
                                          angle_rad=rng.uniform(0, np.pi)))
    stack = EllipseStack.of(ellipses)
    frames = Frames.of(stack, np.full(len(stack), 1.01))
    low, high = np.array([-1.0, -1.0]), np.array([21.0, 21.0])
    every = np.arange(len(stack))
    arcs = Arcs(frames, cuts(frames, EllipseStack(A=frames.A, b=frames.b), low, high, every),
                 np.ones(len(stack), dtype=bool), low, high)

    class EveryWindow(Arcs):
        def meets_free(self, owner, lo, hi):
            return np.ones(len(owner), dtype=bool)

    solve_all = object.__new__(EveryWindow)
    solve_all.__dict__.update(arcs.__dict__)
    i, j = np.triu_indices(len(stack), k=1)
    skipped, full = pair_tangents(frames, arcs, i, j), pair_tangents(frames, solve_all, i, j)
    assert len(full.p) > 100
    for got, expected in zip((skipped.p, skipped.q, skipped.owner_p, skipped.owner_q), (full.p, full.q, full.owner_p, full.owner_q)):
        assert np.array_equal(got, expected)


def test_route_passes_a_u_trap_instead_of_entering_it():
    # A U of three bars opening towards the start, right on the straight line.
    bars = [
        Ellipse.from_axes(center=[5.0, 0.0], semi_axes=[2.0, 0.3], angle_rad=np.pi / 2),
        Ellipse.from_axes(center=[3.5, 2.0], semi_axes=[1.7, 0.3]),
        Ellipse.from_axes(center=[3.5, -2.0], semi_axes=[1.7, 0.3]),
    ]
    legs = tangent_route(start=np.array([0.0, 0.0]), goals=np.array([[10.0, 0.0]]), ellipses=bars, **BOX)
    assert legs is not None
    route = legs[0]
    assert np.all(EllipseStack.of(bars).segment_levels(route[:-1], route[1:]) >= 1.0)
    assert np.abs(route[:, 1]).max() > 2.0  # it goes round the U, not into it


def test_a_route_search_among_no_ellipses_kept_off_the_straight_line_finds_none():
    """With no ellipse the only candidate is the straight segment; a corridor that rejects it leaves no
    route (the graph has terminals and no tangent point)."""
    def nowhere(p, q):
        return np.zeros(len(p), dtype=bool)

    assert tangent_route(start=np.zeros(2), goals=np.array([[5.0, 0.0]]), ellipses=[], keep_to=nowhere, **BOX) is None


def test_enclosed_goal_is_no_path():
    ring = [Ellipse.circle(center=[5 + 2 * np.cos(a), 2 * np.sin(a)], radius=0.8) for a in np.linspace(0, 2 * np.pi, 10)]
    plan = plan_path(
        start=np.array([0.0, -6.0]),
        heading_rad=None,
        goals=np.array([[5.0, 0.0]]),
        ellipses=ring,
        max_curvature=2.0,
        **BOX,
    )
    assert plan.status == "no_path"
    assert "blocked" in plan.reason


@pytest.mark.parametrize("inside, start, goals", [
    ("start", [5.0, 0.2], [[10.0, 0.2]]),
    ("a goal", [0.0, 0.2], [[5.0, 0.2], [10.0, 0.2]]),
])
def test_a_start_or_goal_inside_an_ellipse_is_no_path_with_the_reason(inside, start, goals):
    plan = plan_path(
        start=np.array(start),
        heading_rad=0.0,
        goals=np.array(goals),
        ellipses=[Ellipse.circle(center=[5.0, 0.0], radius=1.0)],
        max_curvature=2.0,
        **BOX,
    )
    assert plan.status == "no_path"
    assert plan.reason == f"{inside} lies inside an obstacle's grown ellipse"


def test_a_clear_straight_reference_is_returned_as_resample_legs_samples_it():
    start, goals = np.array([0.0, 1.0]), np.array([[3.0, 5.0], [4.5, 7.0], [7.5, 11.0]])  # collinear, heading along
    settings = RefineSettings()
    plan = plan_path(
        start=start,
        heading_rad=np.arctan2(4.0, 3.0),
        goals=goals,
        ellipses=[Ellipse.circle(center=[5.0, 0.0], radius=1.0)],
        max_curvature=2.0,
        settings=settings,
        **BOX,
    )
    reference = np.vstack([start, goals])
    n = int(np.ceil(polyline_length(reference) / settings.spacing_m)) + 1
    points, goal_indices = resample_legs([reference[k : k + 2] for k in range(len(goals))], n=n)
    assert plan.status == "ok" and plan.iterations == 0  # no refinement
    assert np.array_equal(plan.points, points) and plan.goal_indices == goal_indices


def test_refined_path_honours_heading_curvature_and_goals_in_order():
    obstacles = [Ellipse.circle(center=[4.0, 0.3], radius=1.2), Ellipse.circle(center=[9.0, 3.0], radius=1.0)]
    goals = np.array([[8.0, 0.0], [12.0, 5.0]])
    kappa = 0.5
    plan = plan_path(
        start=np.array([0.0, 0.0]),
        heading_rad=0.0,
        goals=goals,
        ellipses=obstacles,
        max_curvature=kappa,
        **BOX,
    )
    assert plan.status == "ok"
    z = plan.points
    assert np.allclose(z[0], [0.0, 0.0])
    first = z[1] - z[0]
    assert abs(np.arctan2(first[1], first[0])) < 1e-6
    for goal, index in zip(goals, plan.goal_indices):
        assert np.allclose(z[index], goal, atol=1e-6)
    assert list(plan.goal_indices) == sorted(plan.goal_indices)
    steps = np.linalg.norm(np.diff(z, axis=0), axis=1)
    assert steps.max() <= 0.1 + 1e-6  # the paper's step bound
    # The curvature the refinement converges to, measured with the actual spacing, is within its
    # convergence factor of the bound.
    second = np.linalg.norm(z[2:] - 2 * z[1:-1] + z[:-2], axis=1)
    spacing = np.minimum(steps[:-1], steps[1:])
    assert np.all(second <= RefineSettings().curvature_met_factor * kappa * spacing**2 * (1 + 1e-3) + 1e-9)
    assert len(intersected(z, obstacles)) == 0


def test_direct_clarabel_route_agrees_with_the_cvxpy_model():
    from services.planner.refine import refine

    obstacles = [Ellipse.circle(center=[4.0, 0.3], radius=1.2), Ellipse.from_axes(center=[9.0, 2.0], semi_axes=[1.5, 0.5], angle_rad=0.4)]
    legs = tangent_route(start=np.array([0.0, 0.0]), goals=np.array([[8.0, 0.0], [12.0, 5.0]]), ellipses=obstacles, **BOX)
    results = {
        backend: refine(legs=legs, ellipses=obstacles, max_curvature=0.8, heading_rad=0.3,
                        settings=RefineSettings(backend=backend), **BOX)
        for backend in ("cvxpy", "clarabel")
    }
    assert results["cvxpy"].iterations == results["clarabel"].iterations
    assert np.abs(results["cvxpy"].points - results["clarabel"].points).max() < 1e-4


@pytest.mark.parametrize("n, slacks", [(2, 0), (3, 4), (96, 130)])
def test_the_path_hessian_s_quadratic_form_is_the_sum_of_squared_steps(n, slacks):
    from services.planner.refine import _path_hessian

    upper = _path_hessian(n, 2 * n + slacks)
    P = (upper + upper.T - sparse.diags(upper.diagonal())).toarray()
    x = np.random.default_rng(n).normal(size=2 * n + slacks)
    z = x[: 2 * n].reshape(n, 2)
    assert 0.5 * x @ P @ x == pytest.approx(np.sum(np.diff(z, axis=0) ** 2), rel=1e-12)
    assert upper.has_sorted_indices and np.allclose(upper.toarray(), np.triu(upper.toarray()))


def test_forgotten_subproblems_are_compiled_afresh_and_refine_to_the_same_path():
    """What `cvxnav bench` clears before each timed plan: the compiled subproblems (and their solvers'
    set-ups) go, and the next refinement, building its own, finds the same path."""
    from services.planner.refine import _problem, forget_problems, refine

    obstacles = [Ellipse.circle(center=[4.0, 0.3], radius=1.2)]
    legs = tangent_route(start=np.array([0.0, 0.0]), goals=np.array([[8.0, 0.0]]), ellipses=obstacles, **BOX)
    first = refine(legs=legs, ellipses=obstacles, max_curvature=0.8, heading_rad=0.0, **BOX)
    assert _problem.cache_info().currsize >= 1
    forget_problems()
    assert _problem.cache_info().currsize == 0
    again = refine(legs=legs, ellipses=obstacles, max_curvature=0.8, heading_rad=0.0, **BOX)
    assert _problem.cache_info().misses >= 1 and _problem.cache_info().currsize >= 1
    assert np.abs(again.points - first.points).max() < 1e-8  # the solver's tolerance (a fresh set-up)


@pytest.mark.parametrize("heading_rad, binds", [(0.0, False), (1.0, True)])
def test_the_rows_the_first_clarabel_solve_leaves_out_hold_where_they_bind(heading_rad, binds):
    """Clarabel first solves without the step cones and box rows past the first turning radius. Heading
    for the goal past one disc, they do not bind and the relaxation's answer stands. Heading 1 rad off
    it, the car swings out, the path lengthens until steps reach the paper's bound 2.6 m from the start,
    and the whole subproblem is solved. Either way the answer is the cvxpy model's, which has every row,
    after as many iterations."""
    from services.planner.refine import refine

    obstacles = [Ellipse.circle(center=[4.0, 0.3], radius=1.2)]
    legs = tangent_route(start=np.array([0.0, 0.0]), goals=np.array([[8.0, 0.0]]), ellipses=obstacles, **BOX)
    results = {
        backend: refine(legs=legs, ellipses=obstacles, max_curvature=0.8, heading_rad=heading_rad,
                        settings=RefineSettings(backend=backend), **BOX)
        for backend in ("cvxpy", "clarabel")
    }
    z = results["clarabel"].points
    steps = np.linalg.norm(np.diff(z, axis=0), axis=1)
    step_m = RefineSettings().step_m
    assert steps.max() <= step_m + 1e-6
    assert (steps.max() >= step_m - 1e-6) == binds
    if binds:
        assert np.linalg.norm(z[np.argmax(steps)]) > 1.0 / 0.8  # beyond the first turning radius
    assert results["cvxpy"].iterations == results["clarabel"].iterations
    assert np.abs(results["cvxpy"].points - z).max() < 1e-4


@pytest.mark.parametrize("seed", range(6))
def test_on_random_fields_the_clarabel_route_agrees_with_the_cvxpy_model(seed):
    """Seeded 8-obstacle fields, the start heading 0.4 to 1.15 rad off the way to the goal, so that some
    refinements take two or four solves and some of those solves meet the step bound: Clarabel, solving
    first without the rows that seldom bind, answers as the cvxpy model with every row does."""
    from cvxnav.bench.fitting import random_field
    from cvxnav.bench.problem import BenchProblem
    from services.planner.refine import refine

    problem = BenchProblem.of(random_field(obstacles=8, seed=300 + seed, side_m=12.0))
    box = dict(bounds_min=problem.bounds_min, bounds_max=problem.bounds_max)
    legs = tangent_route(start=problem.start, goals=problem.goals, ellipses=problem.grown, level=RefineSettings().level, **box)
    heading = np.pi / 4 + (-1) ** seed * (0.4 + 0.15 * seed)
    results = {
        backend: refine(legs=legs, ellipses=problem.grown, max_curvature=problem.scenario.max_curvature,
                        heading_rad=heading, settings=RefineSettings(backend=backend), **box)
        for backend in ("cvxpy", "clarabel")
    }
    assert results["cvxpy"].iterations == results["clarabel"].iterations
    assert np.abs(results["cvxpy"].points - results["clarabel"].points).max() < 1e-4


def test_after_a_curve_breaks_the_curvature_bound_no_stricter_margin_is_tried():
    """A goal 1 m to the left of a car that turns no tighter than 2 m: no curve verifies. The repair with
    a wider margin and a sharper bend is skipped; the one with a narrower margin is still tried."""
    from services.planner.core import plan_until_verified
    from services.smoother.core import smooth

    goals = np.array([[0.0, 1.0]])
    attempts = []

    def smooth_fn(points):
        attempts.append(points)
        return smooth(points, ellipses=[], max_curvature=0.5, heading_rad=0.0, goals=goals, goal_tolerance_m=0.1, **BOX)

    plan, smoothed = plan_until_verified(
        start=np.array([0.0, 0.0]), heading_rad=0.0, goals=goals, ellipses=[], max_curvature=0.5, **BOX,
        settings=RefineSettings(), repairs=((1.05, 0.8), (1.0, 0.97)), smooth_fn=smooth_fn,
    )
    assert plan.status == "ok" and not smoothed.verification.ok
    assert smoothed.verification.max_curvature > 0.5
    assert len(attempts) == 2  # the base margin and (1.0, 0.97); (1.05, 0.8) is stricter than the base


def test_a_route_that_meets_an_obstacle_it_was_not_planned_among_is_handed_back_unrefined():
    """Within a corridor, a shortest route that meets an obstacle the plan was not made among (a wall
    beyond the ellipses given, as `services.maps.corridor` finds) comes back as the route itself, not
    smoothed: the caller plans again among more, and spends no refinement, repair or smoothing on too
    few. A route that meets none is refined and smoothed."""
    from services.planner.core import margin_ladder, plan_within
    from services.smoother.core import smooth

    start, goals = np.array([0.0, 0.0]), np.array([[10.0, 0.0]])
    disc = Ellipse.circle(center=[5.0, -0.2], radius=1.0)  # the route passes over it, at y ≈ 0.8
    wall = Ellipse.circle(center=[5.0, 1.0], radius=0.3)  # not among the ellipses planned among
    smoothed = []

    def smooth_fn(points):
        smoothed.append(points)
        return smooth(points, ellipses=[disc], max_curvature=0.5, heading_rad=0.0, goals=goals, goal_tolerance_m=0.1,
                      **BOX)

    def everywhere(p, q):
        return np.ones(len(p), dtype=bool)

    problem = dict(start=start, heading_rad=0.0, goals=goals, ellipses=[disc], max_curvature=0.5,
                   route_keep_to=everywhere, smooth_fn=smooth_fn, ladder=margin_ladder(RefineSettings(), ((1.05, 0.8),)),
                   **BOX)
    route = tangent_route(start=start, goals=goals, ellipses=[disc], level=RefineSettings().level, keep_to=everywhere,
                          **BOX)[0]
    assert len(intersected(route, [wall]))
    met = plan_within(**problem, meets_others=lambda plan, curve: bool(len(intersected(plan.points, [wall]))))
    assert met.plan.status == "ok" and met.smoothed is None and not smoothed
    assert np.array_equal(met.plan.points, route)
    clear = plan_within(**problem)
    assert clear.smoothed is not None and clear.smoothed.verification.ok
    assert len(clear.plan.points) > len(route)  # refined


def test_a_solve_that_clears_the_curvature_slack_without_moving_the_path_ends_the_refinement():
    """On the benchmark's 200-obstacle field, refined from the route itself (not from the robot's pose,
    which would first drive the car onto the route: `_driven_onto`), the first solve cannot meet the
    curvature bound without slack; the second clears it and moves the path by less than the tolerance.
    That is converged: a refinement run on to a tolerance of 1e-6 ends no more than 0.1 % shorter."""
    from cvxnav.bench.fitting import random_field
    from cvxnav.bench.problem import BenchProblem
    from services.planner.refine import refine

    problem = BenchProblem.of(random_field(obstacles=200, seed=207))
    box = dict(bounds_min=problem.bounds_min, bounds_max=problem.bounds_max)
    legs = tangent_route(start=problem.start, goals=problem.goals, ellipses=problem.grown, level=RefineSettings().level, **box)
    kwargs = dict(legs=legs, ellipses=problem.grown, max_curvature=problem.scenario.max_curvature,
                  heading_rad=problem.scenario.start.theta, at_robot=False, **box)
    assert refine(**kwargs, settings=RefineSettings(max_iterations=1)).curvature_slack > 1e-3
    refined = refine(**kwargs)
    assert refined.iterations == 2 and refined.curvature_slack <= 1e-9
    tight = refine(**kwargs, settings=RefineSettings(rel_tolerance=1e-6))
    assert tight.iterations > 2
    assert polyline_length(refined.points) <= 1.001 * polyline_length(tight.points)


def test_a_short_last_leg_still_gets_its_points():
    """Three collinear goals whose last leg is 1 cm: rounding the longer legs' shares up used to leave
    it no point, and a clear straight reference raised instead of being planned."""
    goals = np.array([[10.0, 0.0], [10.01, 0.0]])
    plan = plan_path(start=np.array([0.0, 0.0]), heading_rad=0.0, goals=goals,
                     ellipses=[Ellipse.circle(center=[5.0, 3.0], radius=1.0)], max_curvature=1.0, **BOX)
    assert plan.status == "ok" and plan.iterations == 0
    first, last = plan.goal_indices
    assert first < last == len(plan.points) - 1
    np.testing.assert_array_equal(plan.points[[first, last]], goals)


def test_bounds_may_be_plain_sequences():
    common = dict(start=np.array([0.0, 0.0]), heading_rad=0.0, goals=np.array([[5.0, 0.0]]),
                  ellipses=[Ellipse.circle(center=[2.0, 3.0], radius=1.0)], max_curvature=1.0)
    as_lists = plan_path(**common, bounds_min=[-20, -20], bounds_max=(20.0, 20.0))
    assert as_lists.status == "ok" and np.array_equal(as_lists.points, plan_path(**common, **BOX).points)


@pytest.mark.parametrize("heading_rad", [0.05, 1.3])
def test_a_route_refined_in_windows_keeps_its_straight_stretches_and_meets_every_bound(heading_rad):
    """A 30 m route with one sharp turn round a disc: refined in windows round the turn and the start
    (widened until the swing off a heading 1.3 rad from the route fits), the straight stretches between
    are the route's own points, and the path keeps the heading, the goals, the step and curvature bounds
    and its clearance, within 0.2 % of the length the whole refinement gives."""
    from services.planner.refine import refine

    obstacles = [Ellipse.circle(center=[15.0, 0.9], radius=1.0), Ellipse.circle(center=[15.0, -3.0], radius=1.0)]
    kappa = 1.0
    start, goals = np.array([0.0, 0.0]), np.array([[30.0, 0.0]])
    box = dict(bounds_min=np.array([-5.0, -10.0]), bounds_max=np.array([35.0, 10.0]))
    legs = tangent_route(start=start, goals=goals, ellipses=obstacles, level=RefineSettings().level, **box)
    common = dict(legs=legs, ellipses=obstacles, max_curvature=kappa, heading_rad=heading_rad, **box)
    whole = refine(**common)
    windowed = refine(**common, settings=RefineSettings(window_radii=2.0))
    z = windowed.points
    assert windowed.curvature_slack <= 1e-6 and len(intersected(z, obstacles)) == 0
    assert np.allclose(z[0], start) and windowed.goal_indices == (len(z) - 1,) and np.allclose(z[-1], goals[-1])
    first = z[1] - z[0]
    assert abs(np.arctan2(first[1], first[0]) - heading_rad) < 1e-6
    steps = np.linalg.norm(np.diff(z, axis=0), axis=1)
    assert steps.max() <= 0.1 + 1e-6
    # Curvature, as the smoother will see it: between points of one window (equal spacing) the discrete
    # measure; everywhere, the angle turned per metre over any three points.
    second = np.linalg.norm(z[2:] - 2 * z[1:-1] + z[:-2], axis=1)
    turn = np.abs(np.angle(np.exp(1j * np.diff(np.arctan2(np.diff(z[:, 1]), np.diff(z[:, 0]))))))
    met = RefineSettings().curvature_met_factor * kappa
    assert np.all(turn <= met * np.minimum(steps[:-1], steps[1:]) * 1.01 + 1e-9)
    assert np.all(second <= 2.0 * kappa * np.minimum(steps[:-1], steps[1:]) ** 2 + 1e-6)
    # The stretch from 9 m to 12.5 m lies between the start's window and the turn's: the route's own points.
    route, _ = resample_legs(legs, n=int(np.ceil(polyline_length(np.vstack(legs)) / RefineSettings().spacing_m)) + 1)
    middle = route[(route[:, 0] > 9.0) & (route[:, 0] < 12.5)]
    assert len(middle) > 30 and all(np.any(np.all(z == point, axis=1)) for point in middle)
    assert abs(polyline_length(z) - polyline_length(whole.points)) <= 2e-3 * polyline_length(whole.points)


@pytest.mark.parametrize("heading_rad", [-np.pi / 2, np.pi / 2, -1.0])
def test_a_car_facing_off_its_route_is_driven_onto_it_before_the_refinement(heading_rad):
    """A car 0.8 m off a corridor's centre line, facing across the corridor (or 1 rad off the route): the
    refinement starts from a drive onto the route that leaves along the heading and turns within the
    turning radius, and one solve meets every bound, where refining from the route takes three to five
    (each turns a step by at most acos(0.95) ≈ 18°). Its length is within 0.3 % of that refinement run to
    a tolerance of 1e-6."""
    from services.planner.refine import _driven_path, refine

    walls = [Ellipse.from_axes(center=[15.0, 2.5], semi_axes=[25.0, 0.6]),
             Ellipse.from_axes(center=[15.0, -2.5], semi_axes=[25.0, 0.6])]
    box = dict(bounds_min=np.array([-5.0, -4.0]), bounds_max=np.array([35.0, 4.0]))
    start, goal = np.array([0.0, 0.8]), np.array([20.0, 0.0])
    legs = tangent_route(start=start, goals=goal[None], ellipses=walls, level=RefineSettings().level, **box)
    radius, step = 1.0 / (RefineSettings().curvature_factor * 1.0), RefineSettings().spacing_m
    drive, _ = _driven_path(legs[0], heading_rad, radius_m=radius, step_m=step)
    first = drive[1] - drive[0]
    assert np.allclose(drive[0], start) and np.allclose(drive[-1], goal)
    assert abs(np.arctan2(first[1], first[0]) - heading_rad) < 1e-9 + 0.5 * step / radius
    direction = np.arctan2(np.diff(drive[:-1, 1]), np.diff(drive[:-1, 0]))
    assert np.all(np.abs(np.angle(np.exp(1j * np.diff(direction)))) <= step / radius * (1.0 + 1e-9))

    common = dict(legs=legs, ellipses=walls, max_curvature=1.0, heading_rad=heading_rad, **box)
    from_route = refine(**common, at_robot=False)
    driven = refine(**common, settings=RefineSettings(window_radii=2.0))
    tight = refine(**common, settings=RefineSettings(rel_tolerance=1e-6, max_iterations=40))
    assert from_route.iterations >= 3 and driven.iterations == 1
    z = driven.points
    assert driven.curvature_slack <= 1e-9 and len(intersected(z, walls)) == 0 and np.allclose(z[-1], goal)
    assert abs(np.arctan2(z[1, 1] - z[0, 1], z[1, 0] - z[0, 0]) - heading_rad) < 1e-6
    assert polyline_length(z) <= 1.003 * polyline_length(tight.points)


@settings(max_examples=60, deadline=None)
@given(st.floats(-np.pi, np.pi), st.lists(st.tuples(st.floats(0.3, 3.0), st.floats(-1.2, 1.2)), min_size=1, max_size=6),
       st.floats(0.5, 3.0))
def test_a_drive_onto_any_route_leaves_along_the_heading_within_the_turning_radius_and_ends_on_it(
        heading_rad, turns, radius_m):
    """Any route (a polyline of legs 0.3–3 m, each turned up to 1.2 rad from the last), any heading, any
    turning radius: a drive that comes back onto the route leaves along the heading, steps a step of
    arc at a time turning by at most step / radius, and then is the route's own points to its end."""
    from services.planner.refine import _driven_path

    direction = np.cumsum([angle for _, angle in turns])
    legs = np.array([length for length, _ in turns])[:, None] * np.column_stack([np.cos(direction), np.sin(direction)])
    route = np.vstack([[0.0, 0.0], np.cumsum(legs, axis=0)])
    step = 0.09
    found = _driven_path(route, heading_rad, radius_m=radius_m, step_m=step)
    if found is None:
        return
    drive, _ = found
    first = drive[1] - drive[0]
    assert np.allclose(drive[0], route[0])
    assert abs(np.angle(np.exp(1j * (np.arctan2(first[1], first[0]) - heading_rad)))) <= 0.5 * step / radius_m + 1e-9
    # It ends with the route's own last points (at least its end), after the car's.
    shared = next(m for m in range(min(len(drive), len(route)), 0, -1) if np.array_equal(drive[-m:], route[-m:]))
    car = drive[: len(drive) - shared]
    assert len(car) >= 1 and np.array_equal(drive[-1], route[-1])
    # The car's points lie a step of arc apart, each turning by at most step / radius from the last.
    chords = np.linalg.norm(np.diff(car, axis=0), axis=1)
    assert np.all(chords <= step * (1.0 + 1e-9)) and np.all(chords >= 2.0 * radius_m * np.sin(0.5 * step / radius_m) - 1e-9)
    heading = np.arctan2(np.diff(car[:, 1]), np.diff(car[:, 0]))
    assert np.all(np.abs(np.angle(np.exp(1j * np.diff(heading)))) <= step / radius_m * (1.0 + 1e-9))


def test_a_window_whose_path_the_pins_still_hold_is_widened():
    """A hairpin round the tip of a long wall: a window two turning radii round the turn still moves the
    path 8 cm off the route where it is pinned, so it is widened, until the path comes back onto the route
    before its pins; the path is then the whole refinement's, to within 0.2 % of its length."""
    from services.planner.refine import refine

    obstacles = [Ellipse.from_axes(center=[15.0, -1.0], semi_axes=[0.5, 4.0]),
                 Ellipse.circle(center=[15.0, 5.6], radius=1.0)]
    box = dict(bounds_min=np.array([-5.0, -10.0]), bounds_max=np.array([35.0, 10.0]))
    legs = tangent_route(start=np.array([0.0, 0.0]), goals=np.array([[17.5, 0.0]]), ellipses=obstacles,
                         level=RefineSettings().level, **box)
    common = dict(legs=legs, ellipses=obstacles, max_curvature=1.0, heading_rad=0.05, **box)
    whole = refine(**common)
    windowed = refine(**common, settings=RefineSettings(window_radii=2.0))
    assert windowed.curvature_slack <= 1e-6 and len(intersected(windowed.points, obstacles)) == 0
    # Two radii before the turn the path has left the route: the window reaches further back.
    route, _ = resample_legs(legs, n=int(np.ceil(polyline_length(np.vstack(legs)) / RefineSettings().spacing_m)) + 1)
    before = route[(route[:, 0] > 11.0) & (route[:, 0] < 12.5)]
    assert not any(np.any(np.all(windowed.points == point, axis=1)) for point in before)
    assert abs(polyline_length(windowed.points) - polyline_length(whole.points)) <= 2e-3 * polyline_length(whole.points)


def test_goals_reached_at_the_start_or_with_the_goal_before_get_no_leg():
    start = np.array([0.0, 0.0])
    goals = np.array([[0.1, 0.0], [5.0, 5.0], [5.0, 5.0], [5.0, 5.0 + 1e-9], [8.0, 1.0], [8.0, 1.0]])
    ahead = goals_ahead(start, goals, tolerance_m=0.3)
    np.testing.assert_array_equal(ahead, [[5.0, 5.0], [8.0, 1.0]])
    assert len(goals_ahead(start, np.array([[0.0, 0.0], [0.2, 0.1]]), tolerance_m=0.3)) == 0
    # A goal near, but not at, the one before it keeps its (short) leg: only the car's position counts it.
    np.testing.assert_array_equal(goals_ahead(start, np.array([[5.0, 5.0], [5.1, 5.0]]), tolerance_m=0.3),
                                  [[5.0, 5.0], [5.1, 5.0]])


def test_a_robot_whose_goals_are_all_at_its_start_stays_there():
    plan, smoothed = stay_at_start(np.array([1.0, 2.0]), [Ellipse.from_axes(center=(4.0, 2.0), semi_axes=(1.0, 1.0))])
    assert plan.status == "ok" and plan.points.tolist() == [[1.0, 2.0]] == smoothed.points.tolist()
    assert smoothed.verification.ok and smoothed.verification.min_level == pytest.approx(3.0)
    _, inside = stay_at_start(np.array([4.5, 2.0]), [Ellipse.from_axes(center=(4.0, 2.0), semi_axes=(1.0, 1.0))])
    assert not inside.verification.ok and "inside" in inside.verification.reason


def test_a_start_window_that_widening_does_not_help_is_not_widened_to_the_whole_route():
    """A car facing back down a 60 m corridor 1.8 m wide, with a turning radius of 1.03 m: no window
    round the start meets the curvature bound (turning round takes 2.06 m). The start's window, widened
    once to no better slack, is left as it is: the result reports the unmet bound, and the route beyond
    the window keeps its own points, where the whole route used to be refined (seconds on a building's
    map) to the same slack."""
    from services.planner.refine import refine

    walls = [Ellipse.from_axes(center=[30.0, 1.5], semi_axes=[40.0, 0.6]),
             Ellipse.from_axes(center=[30.0, -1.5], semi_axes=[40.0, 0.6])]
    box = dict(bounds_min=np.array([-12.0, -3.0]), bounds_max=np.array([72.0, 3.0]))
    start, goals = np.array([0.0, 0.0]), np.array([[60.0, 0.0]])
    legs = tangent_route(start=start, goals=goals, ellipses=walls, level=RefineSettings().level, **box)
    windowed = refine(legs=legs, ellipses=walls, max_curvature=1.0, heading_rad=np.pi,
                      settings=RefineSettings(window_radii=2.0), **box)
    assert windowed.curvature_slack > 1e-6
    route, _ = resample_legs(legs, n=int(np.ceil(polyline_length(np.vstack(legs)) / RefineSettings().spacing_m)) + 1)
    beyond = route[route[:, 0] > 30.0]
    assert len(beyond) > 300 and all(np.any(np.all(windowed.points == point, axis=1)) for point in beyond)


def test_a_car_2_cm_from_an_obstacle_and_facing_it_is_told_why_no_route_refines_clear():
    """The car stands 2 cm outside a grown obstacle, facing its centre, the goal behind it: every refined
    route's first step is along the heading, into the obstacle. The reason says where, and that the car
    cannot turn off its heading there (as for a curve too sharp at the start)."""
    from services.planner.core import why_no_path

    disc = Ellipse.circle(center=[0.0, 0.0], radius=1.0)
    plan = plan_path(start=np.array([1.02, 0.0]), heading_rad=np.pi, goals=np.array([[10.0, 0.0]]),
                     ellipses=[disc], max_curvature=1.0, **BOX)
    assert plan.status == "no_path" and plan.entered_m is not None and plan.entered_m <= 0.2
    reason = why_no_path(plan, None, max_curvature=1.0)
    assert reason.startswith("no refined route stays clear of the ellipses (each enters one within")
    assert "within a turning radius (1.00 m) of the start" in reason and "never reverses" in reason


def test_a_goal_the_next_lies_back_from_is_passed_round_a_loop():
    """Two goals on the car's way, the second 2 m back from the first, a disc beside them: the route goes
    to the first and turns straight back, which no refinement of it bends into a loop. A path over the
    car's turns through both goals is refined instead, and its curve verifies through both in order."""
    from services.planner.core import plan_until_verified
    from services.smoother.core import smooth

    goals = np.array([[6.0, 0.0], [4.0, 0.0]])
    disc = [Ellipse.circle(center=[5.0, -2.5], radius=1.0)]

    def smooth_fn(points):
        return smooth(points, ellipses=disc, max_curvature=1.0, heading_rad=0.0, goals=goals, goal_tolerance_m=0.1,
                      **BOX)

    plan, smoothed = plan_until_verified(start=np.array([0.0, 0.0]), heading_rad=0.0, goals=goals, ellipses=disc,
                                         max_curvature=1.0, **BOX, settings=RefineSettings(), repairs=(),
                                         smooth_fn=smooth_fn)
    assert plan.status == "ok" and smoothed.verification.ok, smoothed.verification.reason
    assert np.allclose(plan.points[list(plan.goal_indices)], goals)


@pytest.fixture
def refined(monkeypatch) -> list:
    """The routes the planner core refines, as it refines them."""
    import services.planner.core as core

    made = []
    refine = core.refine

    def counted(**kwargs):
        made.append(kwargs["legs"])
        return refine(**kwargs)

    monkeypatch.setattr(core, "refine", counted)
    return made


def test_a_turn_back_at_a_goal_is_looped_round_before_any_other_route_is_refined(refined):
    """As above: the first route's refinement breaks the bound at the first goal, where it turns back. No
    lead-in at the start changes that turn, and refining a route round enlarged ellipses costs as much as
    the first: the loop through the goals is refined next, and with its bound met nothing else is."""
    goals = np.array([[6.0, 0.0], [4.0, 0.0]])
    disc = [Ellipse.circle(center=[5.0, -2.5], radius=1.0)]
    plan = plan_path(start=np.array([0.0, 0.0]), heading_rad=0.0, goals=goals, ellipses=disc, max_curvature=1.0,
                     **BOX)
    assert plan.status == "ok" and np.allclose(plan.points[list(plan.goal_indices)], goals)
    assert len(refined) == 2  # the route there and back, then the loop


def test_a_window_widened_to_no_better_slack_than_the_one_it_grew_from_is_not_widened_again():
    """A window's slack 0.088, widened to 0.062, then to 0.060: the last is stuck, though it is well down on
    the first narrow window's (a route that turns back at a goal, whose windows would otherwise widen to
    the whole route at about the same slack)."""
    from services.planner.refine import Refined, _stuck

    def solved(slack: float) -> Refined:
        return Refined(points=np.zeros((2, 2)), goal_indices=(1,), iterations=10, curvature_slack=slack)

    windows = {(0, 95): solved(0.0), (118, 309): solved(0.088), (0, 351): solved(0.062)}
    assert not _stuck(windows, 0, 351)  # down by nearly a third on the window it grew from
    assert _stuck({**windows, (0, 479): solved(0.060)}, 0, 479)
    assert not _stuck({**windows, (0, 479): solved(0.050)}, 0, 479)


@pytest.mark.parametrize("heading_rad", [-np.pi / 2, np.pi / 2])
def test_the_first_solve_keeps_the_trust_region_over_a_drive_onto_the_route(monkeypatch, heading_rad):
    """The car of the test above, facing across the corridor: the drive swings it onto the route over
    about two metres, and where it joins, the refinement moves the points most. Clarabel's first solve
    keeps the trust region and step bounds over the drive and a turning radius past it, so each
    iteration is solved once (with them kept over the first turning radius only, the answer broke the
    trust region past it and was solved again, whole)."""
    import services.planner.refine as refine_module

    solves = []
    solve = refine_module._ClarabelPathProblem.solve

    def counted(self, data):
        solves.append(self.bounded)
        return solve(self, data)

    monkeypatch.setattr(refine_module._ClarabelPathProblem, "solve", counted)
    walls = [Ellipse.from_axes(center=[15.0, 2.5], semi_axes=[25.0, 0.6]),
             Ellipse.from_axes(center=[15.0, -2.5], semi_axes=[25.0, 0.6])]
    box = dict(bounds_min=np.array([-5.0, -4.0]), bounds_max=np.array([35.0, 4.0]))
    start, goal = np.array([0.0, 0.8]), np.array([20.0, 0.0])
    legs = tangent_route(start=start, goals=goal[None], ellipses=walls, level=RefineSettings().level, **box)
    first, drive_m = refine_module._driven_onto(legs[0], heading_rad, stack=EllipseStack.of(walls),
                                                max_curvature=RefineSettings().curvature_factor, settings=RefineSettings())
    assert 1.0 < drive_m < polyline_length(first) - 10.0  # a drive, then the route's own points
    result = refine_module.refine(legs=legs, ellipses=walls, max_curvature=1.0, heading_rad=heading_rad, **box)
    assert result.curvature_slack <= 1e-9 and len(intersected(result.points, walls)) == 0
    assert len(solves) == result.iterations


def test_a_plan_made_again_on_the_same_ellipses_refines_no_route_twice(refined):
    """A round planned again without its corridor (`services.maps.corridor`), whose route search finds the
    same routes, is answered from the refinements of the first: the same plan, no refinement made again.
    The same routes among other ellipses (a new one in place of one) are refined afresh."""
    from services.planner.core import Refinements

    goals = np.array([[6.0, 0.0], [4.0, 0.0]])
    disc = [Ellipse.circle(center=[5.0, -2.5], radius=1.0)]
    problem = dict(start=np.array([0.0, 0.0]), heading_rad=0.0, goals=goals, max_curvature=1.0, **BOX)
    refinements = Refinements()
    first = plan_path(**problem, ellipses=disc, route_keep_to=lambda p, q: np.ones(len(p), dtype=bool),
                      refinements=refinements)
    assert first.status == "ok" and len(refined) == 2  # the route there and back, then the loop
    again = plan_path(**problem, ellipses=disc, refinements=refinements)
    assert len(refined) == 2 and np.array_equal(again.points, first.points)
    other = plan_path(**problem, ellipses=[Ellipse.circle(center=[5.0, -2.5], radius=1.0)], refinements=refinements)
    # Refined afresh: the same plan to the solver's tolerance, not to the bit (the process's first setup of a
    # compiled problem and its later reuse differ by 6e-10 m, so the test order decided it).
    assert len(refined) == 4 and np.allclose(other.points, first.points, rtol=0.0, atol=1e-8)


def test_a_goal_the_car_cannot_turn_back_at_is_named_in_the_reason():
    """A corridor 1.6 m wide, the car's turning radius 1 m: it reaches goal 6 m ahead but cannot turn back
    to the next, 3 m behind, without reversing. No path, and the reason names the goal it fails at,
    numbered among every goal asked for (the first, at the start, reached there)."""
    from services.planner.core import goals_ahead, plan_until_verified, why_no_path
    from services.smoother.core import smooth

    walls = [Ellipse.from_axes(center=[15.0, 1.4], semi_axes=[25.0, 0.6]),
             Ellipse.from_axes(center=[15.0, -1.4], semi_axes=[25.0, 0.6])]
    box = dict(bounds_min=np.array([-5.0, -4.0]), bounds_max=np.array([35.0, 4.0]))
    start, asked = np.array([0.0, 0.0]), np.array([[0.0, 0.0], [6.0, 0.0], [3.0, 0.0]])
    goals = goals_ahead(start, asked, tolerance_m=0.1)

    def smooth_fn(points):
        return smooth(points, ellipses=walls, max_curvature=1.0, heading_rad=0.0, goals=goals, goal_tolerance_m=0.1,
                      **box)

    plan, smoothed = plan_until_verified(start=start, heading_rad=0.0, goals=goals, ellipses=walls, max_curvature=1.0,
                                         **box, settings=RefineSettings(), repairs=(), smooth_fn=smooth_fn)
    assert not smoothed.verification.ok
    why = why_no_path(plan, smoothed, max_curvature=1.0, goals=asked)
    assert why.startswith(smoothed.verification.reason) and "of goal 2 of 3, no path found passes through it" in why
    assert "goal" not in why_no_path(plan, smoothed, max_curvature=1.0)  # without the goals asked for: unnamed


def test_a_route_that_breaks_the_bound_at_a_goal_is_not_led_in_again_from_the_start(monkeypatch):
    """The corridor of the test above, goals 6 m ahead, 3 m back and 12 m ahead: the route and the loop
    through the goals both break the curvature bound at the first goal. A lead-in along the start heading
    (or a turn onto the route) changes the route at the start, not at that goal: no route is searched with
    one (each cost the refinement of a whole route on the depot's waypoint queries, docs/maps.md stop 47).
    The routes round enlarged ellipses, which may come in to the goal less sharply, are still tried."""
    import services.planner.core as core

    searched = []
    route = core._route

    def spied(**kwargs):
        searched.append((kwargs["lead"], kwargs["extra_m"]))
        return route(**kwargs)

    monkeypatch.setattr(core, "_route", spied)
    walls = [Ellipse.from_axes(center=[15.0, 1.4], semi_axes=[25.0, 0.6]),
             Ellipse.from_axes(center=[15.0, -1.4], semi_axes=[25.0, 0.6])]
    start = np.array([0.0, 0.0])
    plan = plan_path(start=start, heading_rad=0.0, goals=np.array([[6.0, 0.0], [3.0, 0.0], [12.0, 0.0]]),
                     ellipses=walls, max_curvature=1.0, bounds_min=np.array([-5.0, -4.0]),
                     bounds_max=np.array([35.0, 4.0]))
    assert plan.status == "ok" and curvature_broken(plan.points, 1.0).any()  # no plan meets the bound
    # One route searched with a lead and no enlargement: the loop's, on from its last pose (not the start's
    # lead-in, searched before this change, nor a turn onto the route); and the enlarged ones.
    assert sum(1 for lead, extra in searched if lead is not None and extra == 0.0) == 1
    assert any(extra > 0.0 for _, extra in searched)


def test_a_window_broken_only_where_the_route_turns_back_at_a_goal_is_not_widened():
    """`refine_in_windows` widens a window whose curve breaks the bound, except where every break lies
    within two turning radii of a goal before the last that the path turns back at: a there-and-back route
    needs a loop through the goal, which the caller searches for (`lattice.through`), and a wider window
    only costs more solves. A goal at a right-angle corner is widened round as any other break."""
    from services.planner.refine import Refined, _broken_at_goals

    out = np.column_stack([np.linspace(0.0, 3.0, 31), np.zeros(31)])  # 3 m east to a goal, then back
    hairpin = np.vstack([out, out[-2::-1] + [0.0, 0.05]])  # 5 cm over
    north = np.column_stack([np.zeros(20), 0.05 + 0.1 * np.arange(1, 21)])  # then a right angle, 3 m on
    cuts = [100, 160, 161]  # the route's points the window's legs end at: a goal, then the window's last two

    def window(path: np.ndarray) -> Refined:
        return Refined(points=path, goal_indices=(30, len(path) - 2, len(path) - 1), iterations=3,
                       curvature_slack=0.1)

    assert _broken_at_goals(window(hairpin), cuts, (100, 400), kappa=1.0, radius_m=1.0)
    assert not _broken_at_goals(window(np.vstack([hairpin, north])), cuts, (100, 400), kappa=1.0, radius_m=1.0)
    assert not _broken_at_goals(window(hairpin), cuts, (100,), kappa=1.0, radius_m=1.0)  # the last goal
    assert not _broken_at_goals(window(hairpin), cuts, (50, 400), kappa=1.0, radius_m=1.0)  # no goal in it
    corner = np.vstack([out, out[-1] + np.column_stack([np.zeros(30), 0.1 * np.arange(1, 31)])])  # a right angle
    assert not _broken_at_goals(window(corner), cuts, (100, 400), kappa=1.0, radius_m=1.0)  # not turned back
