"""`cvxnav plan`: the whole pipeline in one process on a known map.

cluster → fit → grow → optimise → smooth, each stage the same pure code the distributed services run.
On a known map each obstacle is one cluster whose solid is known (a convex cover of it), so the fit
can measure its ellipses against the true shape. An occupancy grid is not fitted whole: the corridor
planner (`services.maps.corridor`) fits the tiles of its cover that the query comes near. Before it, a
start facing walls nearer than the car can turn is proved to have no forward path (`services.maps.start`);
where its plans fail, it refines a path the car can drive searched on the map (`services.maps.seed`).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager, nullcontext
from dataclasses import dataclass, field, replace

import numpy as np

from schemas.files import PlanFile, PlanTimings
from schemas.occupancy import OccupancyGrid
from schemas.scenario import OccupancyGridObstacle, Scenario
from services.convert import LocalFrame, ellipse_to_model
from services.ellipsoids.cover import cover_polygon
from services.ellipsoids.grid_cover import GridCover, GridCoverSettings
from services.geometry import Ellipse
from services.planner.core import (
    MeetsOthers, PathPlan, Refinements, goals_ahead, meets_none, plan_until_verified, stay_at_start, why_no_path,
)
from services.maps.corridor import CoarseGrid, CorridorSettings, plan_in_corridor
from services.maps.seed import drivable_paths
from services.maps.start import hemmed_in
from services.planner.lattice import WIDER
from services.planner.refine import RefineSettings
from services.planner.route import KeepTo
from services.smoother.core import Smoothed, smooth


@dataclass(frozen=True)
class PlanSettings:
    cover_tolerance_m: float = 0.1  # how far a fitted ellipse may stick out of its obstacle
    max_pieces: int = 64  # ellipses per obstacle at most
    refine: RefineSettings = field(default_factory=RefineSettings)
    # When the smoothed curve fails verification, re-optimise with wider margins, in this order.
    repairs: tuple[tuple[float, float], ...] = ((1.05, 0.8),)  # (level, curvature_factor)
    # Occupancy grids' cover: looser than the cover's default (0.1 m), which the live stage keeps, since the
    # corridor planner fits it tighter where that closes a passage (`services.maps.corridor`).
    grid_cover: GridCoverSettings = field(default_factory=lambda: GridCoverSettings(tolerance_m=0.15))
    corridor: CorridorSettings = field(default_factory=CorridorSettings)  # ... and where it is fitted
    # On an occupancy grid the route is long and mostly straight: it is refined in windows round its turns
    # and its start, this many turning radii wide (`RefineSettings.window_radii`).
    map_window_radii: float | None = 2.0


@dataclass
class _Clock:
    """Milliseconds by stage. A stage timed within another (the cover fitted while a plan is checked) is
    charged to the inner one alone, so the stages add up to the time spent in them."""

    ms: dict[str, float] = field(default_factory=dict)
    _open: list[str] = field(default_factory=list)  # the stages being timed, innermost last
    _since: float = 0.0  # when the innermost was last charged

    def _charge(self) -> None:
        now = time.perf_counter()
        if self._open:
            self.ms[self._open[-1]] = self.ms.get(self._open[-1], 0.0) + 1e3 * (now - self._since)
        self._since = now

    @contextmanager
    def stage(self, name: str) -> Iterator[None]:
        self._charge()
        self._open.append(name)
        try:
            yield
        finally:
            self._charge()
            self._open.pop()


def fit_known_obstacles(
    scenario: Scenario, *, settings: PlanSettings, clock: _Clock
) -> tuple[list[Ellipse], np.ndarray]:
    """Raw (un-grown) ellipses covering every obstacle of a known map tightly, and each one's obstacle
    (occupancy grids aside: see `plan_scenario`)."""
    with clock.stage("cluster"):
        clusters = [obstacle.cover_vertices() for obstacle in scenario.obstacles if obstacle.type != "occupancy_grid"]
    with clock.stage("fit"):
        covers = [
            cover_polygon(vertices, tolerance_m=settings.cover_tolerance_m, max_pieces=settings.max_pieces)
            for vertices in clusters
        ]
    ellipses = [ellipse for cover in covers for ellipse in cover]
    return ellipses, np.repeat(np.arange(len(covers)), [len(cover) for cover in covers])


def plan_on_model(
    scenario: Scenario, grown: list[Ellipse], *, settings: PlanSettings = PlanSettings(), clock: _Clock | None = None,
    route_estimate_m: tuple[float, ...] | None = None, route_keep_to: KeepTo | None = None,
    meets_others: MeetsOthers = meets_none, route_seed: list[np.ndarray] | None = None,
    refinements: Refinements | None = None,
) -> tuple[PathPlan, Smoothed | None]:
    """Optimise and smooth on a fitted model (the grown ellipses): the plan and its smoothed curve, as
    `plan_until_verified` returns them. The planning half of `plan_scenario`, which `cvxnav bench` times
    on the model every planner is handed. Goals reached at the start, or with the goal before them
    (`goals_ahead`), get no leg; with none left, the plan is the start (`stay_at_start`).
    `route_estimate_m`, `route_keep_to`: each leg's length as a coarser search found it, and where the
    route may go, and drivable legs through the first goals to refine instead (`services.planner.core.plan_path`);
    `meets_others`: whether a plan meets an obstacle it was not made among (`services.planner.core.plan_within`);
    `refinements`: those made by earlier plans of the same query, to answer a repeated one (`Refinements`)."""
    goals = goals_ahead(scenario.start.xy, scenario.goals_array, tolerance_m=scenario.goal_tolerance)
    if not len(goals):
        return stay_at_start(scenario.start.xy, grown)
    problem = dict(
        start=scenario.start.xy,
        heading_rad=scenario.start.theta,
        goals=goals,
        ellipses=grown,
        bounds_min=np.array(scenario.bounds.min),
        bounds_max=np.array(scenario.bounds.max),
        max_curvature=scenario.max_curvature,
        route_estimate_m=route_estimate_m,
        route_keep_to=route_keep_to,
        meets_others=meets_others,
        route_seed=route_seed,
        refinements=refinements,
    )
    return plan_until_verified(
        **problem,
        settings=settings.refine,
        repairs=settings.repairs,
        timer=nullcontext if clock is None else clock.stage,
        smooth_fn=lambda points: smooth(
            points,
            ellipses=grown,
            max_curvature=problem["max_curvature"],
            heading_rad=problem["heading_rad"],
            goals=scenario.goals_array,  # every goal, the dropped ones included
            goal_tolerance_m=scenario.goal_tolerance,
            bounds_min=problem["bounds_min"],
            bounds_max=problem["bounds_max"],
        ),
    )


def plan_scenario(scenario: Scenario, *, settings: PlanSettings = PlanSettings(), load_ms: float = 0.0,
                  on_round: Callable[[int, int], None] | None = None) -> PlanFile:
    """Plan once on the scenario's known map; the result is verified or reported as `no_path`.

    `load_ms`: how long reading the scenario and its map took, counted in the total (`cvxnav plan` times
    it), so that the total is the whole time from the files to the path. The planning runs in the
    scenario's local frame (`services.convert.LocalFrame`), the plan is moved back into the world's.
    `on_round(round, ellipses)`: told as each plan on an occupancy grid starts (`plan_in_corridor`).
    """
    frame = LocalFrame.of(scenario)
    return frame.to_world(_plan_local(frame.scenario_to_local(scenario), settings=settings, load_ms=load_ms,
                                      on_round=on_round))


def _drivable(scenario: Scenario, grid: OccupancyGrid, goals: np.ndarray, coarse: CoarseGrid, *,
              settings: PlanSettings) -> Iterator[list[np.ndarray]]:
    """Legs the car can drive, searched on the map, for the corridor's plans to go on from where they
    fail (`services.maps.seed`): the planning radius a little widened (`lattice.WIDER`), ordered by the
    coarse grid's distance left."""
    return drivable_paths(grid, start=scenario.start.xy, heading_rad=scenario.start.theta, goals=goals,
                          radius_m=WIDER / (settings.refine.curvature_factor * scenario.max_curvature),
                          margin_m=scenario.inflation_m, spacing_m=settings.refine.spacing_m,
                          bounds_min=np.array(scenario.bounds.min), bounds_max=np.array(scenario.bounds.max),
                          to_go=coarse.distances_to)


def _plan_local(scenario: Scenario, *, settings: PlanSettings, load_ms: float,
                on_round: Callable[[int, int], None] | None) -> PlanFile:
    clock = _Clock()
    t0 = time.perf_counter()
    raw, _ = fit_known_obstacles(scenario, settings=settings, clock=clock)
    with clock.stage("group"):  # plan.json's `group` timing (CONTRACTS §4): the growth
        # No labels are needed: obstacles closer than the robot's passage width have overlapping grown
        # ellipses, which the route search treats as one wall.
        grown = [e.grown(scenario.inflation_m) for e in raw]

    grids = [o for o in scenario.obstacles if isinstance(o, OccupancyGridObstacle)]
    goals = goals_ahead(scenario.start.xy, scenario.goals_array, tolerance_m=scenario.goal_tolerance)
    if grids and len(goals):
        settings = replace(settings, refine=replace(settings.refine, window_radii=settings.map_window_radii))
        with clock.stage("corridor"):
            stuck = hemmed_in(grids[0].grid, start=scenario.start.xy, heading_rad=scenario.start.theta, goal=goals[0],
                              radius_m=1.0 / scenario.max_curvature, margin_m=scenario.inflation_m)
        if stuck:
            plan, smoothed = PathPlan("no_path", np.zeros((0, 2)), reason=stuck), None
        else:
            cover = GridCover(grids[0].grid, margin_m=scenario.inflation_m, settings=settings.grid_cover)
            refinements = Refinements()  # a round planned again without its corridor may refine the same routes
            found = plan_in_corridor(
                cover=cover,
                waypoints=np.vstack([scenario.start.xy, goals]),
                fixed=grown,
                plan_fn=lambda ellipses, lengths, keep_to, meets_others, seed: plan_on_model(
                    scenario, ellipses, settings=settings, clock=clock, route_estimate_m=lengths,
                    route_keep_to=keep_to, meets_others=meets_others, route_seed=seed, refinements=refinements),
                seed_fn=lambda coarse: _drivable(scenario, grids[0].grid, goals, coarse, settings=settings),
                settings=settings.corridor,
                timer=clock.stage,
                on_round=on_round,
            )
            plan, smoothed, grown = found.plan, found.smoothed, found.grown
    else:
        plan, smoothed = plan_on_model(scenario, grown, settings=settings, clock=clock)
    ok = plan.status == "ok" and smoothed is not None and smoothed.verification.ok
    for name in ("corridor", "cluster", "fit", "group", "optimize", "smooth"):
        clock.ms.setdefault(name, 0.0)
    clock.ms["load"] = load_ms
    clock.ms["total"] = load_ms + 1e3 * (time.perf_counter() - t0)
    return PlanFile(
        scenario=scenario.name,
        status="ok" if ok else "no_path",
        path=smoothed.points.tolist() if ok else [],
        raw_path=plan.points.tolist(),
        ellipsoids=[ellipse_to_model(e) for e in grown],
        timings_ms=PlanTimings(**clock.ms),
        reason="" if ok else why_no_path(plan, smoothed, max_curvature=scenario.max_curvature,
                                         goals=scenario.goals_array),
    )
