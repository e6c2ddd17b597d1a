"""The path guard's own checks, which no message moves: the map's bounds and the car's own scan hits,
at the hard floor (`Scenario.keep_out_m`), on the continuous path; and the real sim's car refusing a
forged empty ellipse set with a forged path through a wall it has seen."""

from __future__ import annotations

import json

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from schemas.messages import Ellipsoids, Header, SmoothPath
from schemas.scenario import Scenario, bundled_scenario
from sim.core import SimConfig, SimCore
from services.drive.guard import DISTANCE_TOL_M, START_SLACK, PathGuard

PAPER = bundled_scenario()
KEEP = PAPER.keep_out_m


def guard(**kwargs) -> PathGuard:
    return PathGuard(inflation_m=PAPER.inflation_m, keep_out_m=KEEP, bounds_min=(-5.0, -10.0),
                     bounds_max=(25.0, 10.0), **kwargs)


def wall_field() -> Scenario:
    """The paper's car heading east on an open map, a wall across its way at x = 4, open to the north."""
    doc = json.loads(PAPER.model_dump_json())
    doc.update(name="wall", start={"x": 0.0, "y": 0.0, "theta": 0.0}, goals=[[12.0, 0.0]],
               bounds={"min": [-5.0, -10.0], "max": [25.0, 10.0]},
               obstacles=[{"type": "polygon", "vertices": [[4.0, -10.0], [4.3, -10.0], [4.3, 5.0], [4.0, 5.0]]}])
    return Scenario.model_validate(doc)


def test_a_path_off_the_map_or_hugging_its_edge_is_refused_and_one_inside_is_not():
    g = guard()
    assert g.check([(0.0, 0.0), (10.0, 0.0)], start=(0.0, 0.0)) is None
    assert "outside its bounds" in g.check([(0.0, 0.0), (30.0, 0.0)], start=(0.0, 0.0))
    edge = 10.0 - KEEP + 0.02  # inside the map, but the footprint could touch its edge
    assert "inside (< 0.585)" in g.check([(0.0, 0.0), (5.0, edge)], start=(0.0, 0.0))
    assert g.check([(0.0, 0.0), (5.0, 10.0 - KEEP + DISTANCE_TOL_M / 2)], start=(0.0, 0.0)) is None
    # A car already nearer the edge than the floor may drive along it or away, not nearer still.
    near = (0.0, 9.7)
    assert g.check([near, (5.0, 9.7), (8.0, 5.0)], start=near) is None
    assert g.check([near, (5.0, 9.9)], start=near) is not None


def test_the_cars_own_hits_hold_a_path_at_the_floor_between_the_vertices_too():
    g = guard()
    g.sense([(5.0, 0.0)])
    hit = g.check([(0.0, 0.0), (10.0, 0.0)], start=(0.0, 0.0))  # two vertices, the hit between them
    assert hit is not None and "hit of the car's own scans at (5.00, 0.00)" in hit and "near (5.00, 0.00)" in hit
    assert g.check([(0.0, 0.0), (10.0, KEEP - 0.02)], start=(0.0, 0.0)) is not None  # passes 0.56 m from it
    assert g.check([(0.0, KEEP + 0.001), (10.0, KEEP + 0.001)], start=(0.0, KEEP + 0.001)) is None
    # From a start already closer than the floor: away is fine, deeper (beyond START_SLACK) is not.
    start = (5.0, 0.4)
    assert g.check([start, (5.0, 3.0)], start=start) is None
    assert g.check([start, (8.0, 0.4)], start=start) is None  # along it at the start's own distance
    assert g.check([start, (5.0, 0.4 / (1 + START_SLACK) - 2 * DISTANCE_TOL_M), (8.0, 3.0)], start=start) is not None


def test_hits_out_of_view_still_count_and_the_memory_forgets_only_the_least_recently_seen():
    g = guard(max_hits=3)
    g.sense([(5.0, 0.0), (5.0, 5.0)])
    g.sense(np.zeros((0, 2)))  # turned away: an empty scan forgets nothing
    assert g.check([(0.0, 0.0), (10.0, 0.0)], start=(0.0, 0.0)) is not None
    g.sense([(5.0, 5.0), (20.0, 0.0), (20.0, 5.0)])  # (5, 5) seen again; the memory holds 3: (5, 0) goes
    assert g.check([(0.0, 0.0), (10.0, 0.0)], start=(0.0, 0.0)) is None
    assert g.check([(0.0, 5.0), (10.0, 5.0)], start=(0.0, 5.0)) is not None


@settings(max_examples=40, deadline=None)
@given(batches=st.lists(st.lists(st.tuples(st.floats(-4.0, 24.0), st.floats(-9.0, 9.0)), max_size=300),
                        min_size=1, max_size=12),
       path=st.lists(st.tuples(st.floats(-4.0, 24.0), st.floats(-9.0, 9.0)), min_size=2, max_size=6))
def test_the_hit_trees_answer_as_a_brute_force_check_over_the_remembered_hits(batches, path):
    """However the hits came (merged into the big tree, still in the newest one, some forgotten), the
    check is the brute-force distance of every segment to every remembered hit."""
    g = guard(max_hits=700)
    for batch in batches:
        g.sense(np.array(batch, dtype=float).reshape(-1, 2))
    hits = g.hits.memory.points()
    z = np.array(path)
    a, e = z[:-1], np.diff(z, axis=0)
    u = np.clip(np.einsum("hsk,sk->hs", hits[:, None, :] - a[None], e) / np.maximum((e * e).sum(1), 1e-18), 0, 1)
    distance = np.linalg.norm(hits[:, None, :] - (a[None] + u[..., None] * e[None]), axis=2)
    floor = np.minimum(KEEP, np.linalg.norm(hits - z[0], axis=1) / (1 + START_SLACK)) - DISTANCE_TOL_M
    expected = bool(len(hits)) and bool((distance.min(axis=1) < floor).any())
    assert (g._near_hit(z, z[0]) is not None) == expected


def answer(core: SimCore, points, *, plan_id: int) -> SmoothPath:
    return SmoothPath(header=Header(stamp_s=core.t_s, seq=0), scan_seq=core.scan_seq, status="ok", goal_index=0,
                      points=[tuple(p) for p in points], max_curvature=0.0, min_level=2.0, plan_id=plan_id)


def test_a_forged_empty_ellipse_set_and_a_path_through_a_wall_the_car_saw_do_not_move_it():
    """The attack of issue 27: ellipses answering a real scan, but none, and a path straight through the
    wall the car's sensor sees 4 m ahead. The car stays at rest; a path around the wall is driven."""
    core = SimCore(scenario=wall_field(), config=SimConfig(stale_after_s=100.0))
    _, scan = core.sense()
    assert scan.points  # the wall is in view
    core.know(Ellipsoids(header=Header(stamp_s=0.0, seq=0), scan_seq=scan.header.seq, inflation_m=PAPER.inflation_m,
                         ellipsoids=[]))
    xs = np.linspace(0.0, 12.0, 241)
    reason = core.accept(answer(core, np.column_stack([xs, np.zeros_like(xs)]), plan_id=1))
    assert reason is not None and "hit of the car's own scans" in reason and core.path is None
    for _ in range(30):  # short of giving up (no_path_patience_s)
        assert core.advance() is None and core.state.speed_mps == 0.0
    core.sense()
    around = [(0.0, 0.0), (1.5, 0.0), (3.0, 7.0), (5.5, 7.0), (12.0, 0.0)]
    assert core.accept(answer(core, around, plan_id=2)) is None and core.path is not None


@pytest.mark.parametrize("end", [(12.0, 40.0), (12.0, 9.9)])
def test_a_forged_path_off_the_map_is_refused_by_the_real_sims_car(end):
    core = SimCore(scenario=wall_field(), config=SimConfig(stale_after_s=100.0))
    core.sense()
    reason = core.accept(answer(core, [(0.0, 0.0), (3.0, 0.0), end], plan_id=1))
    assert reason is not None and "leaves the map" in reason and core.path is None
