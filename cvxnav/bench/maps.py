"""`cvxnav bench` on occupancy-grid maps: cvxnav against a NavFn-like grid planner and OMPL's BIT*, each
timed from reading the scenario and its map file to its path.

The maps: the public depot queries (`shared/map-scenarios`, with their REFERENCE optimum), MovingAI's
arena (its `.map` written as a map_server PGM, 1 m cells, the paper's car), four corridor queries on the
ACES building (`shared/external/carmen`: a real SLAM map, 58 × 58 m at 0.05 m, routes along its
corridors), and a 30 × 50 m warehouse at 0.03 m made from the depot (resampled from 0.05 m to 0.03 m by
nearest neighbour, three copies stacked with a doorway cut through the walls between each pair and an
unknown band on top; a query from the bottom copy to the top one). Every file but the shared ones is
written by the bench into its work directory, so the runs are reproducible from `shared/` alone.

The planners, each a fresh call that reads the files:

* cvxnav: `cvxnav plan`'s pipeline (`plan_scenario`: the corridor, the tiles' cover, route search,
  refinement, verified smoothing), its stage times from the plan's `timings_ms`.
* grid (NavFn-like): distance-transform inflation by the same margin and an 8-connected Dijkstra over
  the whole grid (`cvxnav.bench.grid_planner`), scipy.
* BIT* (OMPL), for a point robot (R²) and for a Dubins car at the car's turning radius (SE(2), the goal
  any of 16 headings at the goal): valid = a free cell of the grid planner's inflated grid (the same
  margin), motions checked every grid cell or 0.05 m, whichever is shorter; each stops once within 1 % of
  the REFERENCE optimum, or of cvxnav's own length where there is none, or at its budget. With more goals
  than one, leg by leg (the Dubins car leaving each goal at the heading it arrived at), each leg with the
  whole budget.

Every path is judged on the true geometry (the exact distance to the blocked squares,
`Scenario.clearance`, on the path resampled at 0.02 m). Each scenario is timed in a process of its own
(`_isolated`). Growth: the depot tiled side by side 1×, 2× and 4×, depot-1's query in the first copy,
cvxnav and the grid planner timed in turns, each tiling in a process of its own. Memory: the peak
resident set (the kernel's `VmHWM`) of a `cvxnav plan` process on the 30 × 50 m map, and of a process
running the grid planner on it.
"""

from __future__ import annotations

import ctypes
import json
import math
import multiprocessing
import os
import queue
import statistics
import subprocess
import sys
import time
import traceback
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TypeVar

import numpy as np
from PIL import Image

from cvxnav.bench.report import (
    MapBenchResult,
    MapGrowthPoint,
    MapPlannerResult,
    MapScenarioResult,
    MapTargets,
)
from cvxnav.bench.turns import in_turns, ratio_interval
from services.geometry import FloatArray, joined_legs, polyline_length, resample_polyline
from schemas.occupancy import OccupancyGrid
from schemas.scenario import OccupancyGridObstacle, Scenario, load_scenario

CVXNAV = "cvxnav"
GRID = "grid (NavFn-like)"
BIT_POINT = "BIT* (OMPL, point)"
BIT_DUBINS = "BIT* (OMPL, Dubins)"
COLLISION_TOLERANCE_M = 0.02
_T = TypeVar("_T")
_DEPOT_CAR = {"width": 0.3, "length": 0.6, "wheelbase": 0.6, "safety_distance": 0.3, "max_speed": 1.0,
              "max_steering_angle": 0.6, "max_steering_rate": 0.5}
_SENSOR = {"fov_deg": 180.0, "range": 5.0, "rays": 181, "rate_hz": 10.0}
# ACES corridor ends (free, 0.7 m or more from any blocked cell) and the heading along the corridor there.
_ACES = {"west": (-20.641, -18.104), "east": (18.109, -18.804), "south": (-4.591, -41.054), "north": (-0.491, 2.446)}
_ACES_QUERIES = (("west", "east", -0.0341), ("east", "north", 3.077), ("south", "north", 1.1575),
                 ("west", "south", -1.5056))


@dataclass(frozen=True)
class MapCase:
    """One scenario/2 file of the suite, what it is, and its true-geometry optimum where one is known."""

    path: Path
    note: str
    reference_m: float | None = None


# --------------------------------------------------------------------------- the suite


def _scenario_doc(name: str, *, map_path: str, start: tuple[float, float, float], goal: tuple[float, float],
                  description: str, robot: dict | None = None, sensor: dict | None = None) -> dict:
    return {"format": "cvxnav.scenario/2", "name": name, "description": description,
            "robot": robot or _DEPOT_CAR, "sensor": sensor or _SENSOR, "goal_tolerance": 0.3,
            "obstacles": [{"type": "occupancy_grid", "map": map_path}], "expect": "reach",
            "start": {"x": start[0], "y": start[1], "theta": start[2]}, "goals": [list(goal)]}


def _write_map(folder: Path, stem: str, pixels: np.ndarray, *, resolution_m: float,
               origin: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> str:
    """A map_server map (PGM + YAML) of 8-bit pixels (top row first); the YAML's name."""
    Image.fromarray(pixels.astype(np.uint8), mode="L").save(folder / f"{stem}.pgm")
    (folder / f"{stem}.yaml").write_text(
        f"image: {stem}.pgm\nmode: trinary\nresolution: {resolution_m}\norigin: [{origin[0]}, {origin[1]}, {origin[2]}]\n"
        "negate: 0\noccupied_thresh: 0.65\nfree_thresh: 0.25\n")
    return f"{stem}.yaml"


def _depot_pixels(shared: Path) -> np.ndarray:
    return np.asarray(Image.open(shared / "maps" / "depot.pgm"))


def warehouse_pixels(shared: Path) -> np.ndarray:
    """The 30 × 50 m map at 0.03 m (1007 × 1667 cells): the depot resampled from 0.05 m by nearest
    neighbour, three copies stacked, a 2.4 m doorway cut through the walls between the first and second
    copy (x 3.0–5.4 m) and between the second and third (x 24.8–27.2 m), unknown above."""
    depot = _depot_pixels(shared)
    rows, cols = depot.shape
    size = (round(cols * 5 / 3), round(rows * 5 / 3))
    copy = np.asarray(Image.fromarray(depot).resize(size, Image.Resampling.NEAREST))
    stacked = np.vstack([copy] * 3)  # top row first: the third copy on top
    out = np.full((1667, size[0]), 205, dtype=np.uint8)
    out[-len(stacked):] = stacked
    for k, (x0, x1) in enumerate(((3.0, 5.4), (24.8, 27.2))):
        c0, c1 = int(x0 / 0.03), int(x1 / 0.03)
        # Between the middles of copy k (from the bottom) and copy k + 1 the band's only blocked cells are
        # their walls (and the unknown between them): all of it, wall to wall, becomes free.
        bottom = len(out) - 1 - k * size[1] - size[1] // 2  # a row in the middle of copy k
        top = bottom - size[1]  # ... and of copy k + 1
        walls = top + np.flatnonzero(np.any(out[top:bottom, c0:c1] != 254, axis=1))
        out[walls.min() : walls.max() + 1, c0:c1] = 254
    return out


def write_map_suite(folder: Path, *, shared: Path, quick: bool = False) -> list[MapCase]:
    """The map scenarios of the benchmark, writing the generated maps and scenario files to `folder`."""
    folder.mkdir(parents=True, exist_ok=True)
    public = shared / "map-scenarios"
    references = json.loads((public / "REFERENCE.json").read_text())["optimal_length"] if (public / "REFERENCE.json").is_file() else {}
    cases = [MapCase(public / f"{name}.json", "Nav2's depot map, 604 × 307 cells at 0.05 m", references.get(name))
             for name in ("depot-1", "depot-2") if (public / f"{name}.json").is_file()]
    arena = shared / "external" / "movingai"
    if (arena / "arena.map").is_file() and not quick:
        rows = (arena / "arena.map").read_text().split("map\n", 1)[1].split()
        pixels = np.where(np.array([[c in ".G" for c in row] for row in rows]), 254, 0)
        yaml_name = _write_map(folder, "arena", pixels, resolution_m=1.0)
        paper = json.loads((Path(__file__).resolve().parents[1] / "data" / "paper-two-goals.json").read_text())
        queries = [line.split("\t") for line in (arena / "arena.map.scen").read_text().splitlines()[1:] if line]
        for index in (0, 1, 2, 3, 5, 6):
            q = queries[index]
            (sx, sy), (gx, gy) = [(int(q[k]) + 0.5, len(rows) - int(q[k + 1]) - 0.5) for k in (4, 6)]
            name = f"arena-{index}"
            doc = _scenario_doc(name, map_path=yaml_name, start=(sx, sy, math.atan2(gy - sy, gx - sx)), goal=(gx, gy),
                                description=f"MovingAI arena, .scen query {index}", robot=paper["robot"],
                                sensor=paper["sensor"])
            (folder / f"{name}.json").write_text(json.dumps(doc, indent=1))
            cases.append(MapCase(folder / f"{name}.json", "MovingAI arena, 49 × 49 cells at 1 m, the paper's car"))
    aces = shared / "external" / "carmen" / "aces-map.yaml"
    if aces.is_file():
        for a, b, heading in _ACES_QUERIES[: 2 if quick else None]:
            name = f"aces-{a}-{b}"
            doc = _scenario_doc(name, map_path=str(aces.resolve()), start=(*_ACES[a], heading), goal=_ACES[b],
                                description=f"ACES building (CARMEN), {a} to {b} along its corridors")
            (folder / f"{name}.json").write_text(json.dumps(doc, indent=1))
            cases.append(MapCase(folder / f"{name}.json", "ACES building, 1175 × 1173 cells at 0.05 m, 72 % unknown"))
    if (shared / "maps" / "depot.pgm").is_file():
        yaml_name = _write_map(folder, "warehouse-30x50", warehouse_pixels(shared), resolution_m=0.03)
        doc = _scenario_doc("warehouse-30x50", map_path=yaml_name, start=(9.675, 5.875, 2.022),  # towards the door
                            goal=(28.975, 8.475 + 2 * 15.36),
                            description="the depot at 0.03 m, three copies stacked with doorways: bottom to top")
        (folder / "warehouse-30x50.json").write_text(json.dumps(doc, indent=1))
        cases.append(MapCase(folder / "warehouse-30x50.json",
                             "30 × 50 m at 0.03 m (1007 × 1667 cells): the depot resampled, three copies stacked"))
    return cases


def write_growth_maps(folder: Path, *, shared: Path, tiles: tuple[int, ...]) -> list[tuple[int, Path]]:
    """The depot tiled side by side `k` times for each k, with depot-1's query in the first copy."""
    folder.mkdir(parents=True, exist_ok=True)
    depot = _depot_pixels(shared)
    query = json.loads((shared / "map-scenarios" / "depot-1.json").read_text())
    out = []
    for k in tiles:
        yaml_name = _write_map(folder, f"depot-x{k}", np.hstack([depot] * k), resolution_m=0.05)
        doc = _scenario_doc(f"depot-x{k}", map_path=yaml_name, start=(query["start"]["x"], query["start"]["y"],
                                                                       query["start"]["theta"]),
                            goal=tuple(query["goals"][0]), description=f"the depot tiled {k}×, depot-1's query")
        (folder / f"depot-x{k}.json").write_text(json.dumps(doc, indent=1))
        out.append((k, folder / f"depot-x{k}.json"))
    return out


# --------------------------------------------------------------------------- the planners


@dataclass(frozen=True)
class MapAttempt:
    path: FloatArray | None
    time_s: float
    stages_ms: dict[str, float]
    reason: str = ""
    target_s: float | None = None  # BIT*: time to within 1 % of its target


def call_cvxnav(path: Path) -> MapAttempt:
    """`cvxnav plan`'s work in this process: read the scenario and its map, plan, verify; nothing kept from
    an earlier call (the ellipse stacks, the refinement's compiled subproblems)."""
    from cvxnav.bench.planners import forget_kept
    from cvxnav.plan import plan_scenario

    forget_kept()
    t0 = time.perf_counter()
    scenario = load_scenario(path)
    plan = plan_scenario(scenario, load_ms=1e3 * (time.perf_counter() - t0))
    elapsed = time.perf_counter() - t0
    stages = {k: v for k, v in plan.timings_ms.model_dump().items() if k != "total"}
    if plan.status != "ok":
        return MapAttempt(None, elapsed, stages, f"cvxnav: no_path ({plan.reason})")
    return MapAttempt(np.asarray(plan.path), elapsed, stages)


def call_grid(path: Path) -> MapAttempt:
    """The NavFn-like grid planner: read the scenario and its map, inflate, Dijkstra."""
    from cvxnav.bench.grid_planner import plan_on_grid

    t0 = time.perf_counter()
    scenario = load_scenario(path)
    load_s = time.perf_counter() - t0
    plan = plan_on_grid(_grid(scenario), start=scenario.start.xy, goals=scenario.goals_array,
                        margin_m=scenario.inflation_m)
    stages = {"load": 1e3 * load_s, **plan.stages_ms}
    return MapAttempt(plan.path, time.perf_counter() - t0, stages, plan.reason)


def _grid(scenario: Scenario) -> OccupancyGrid:
    return next(o.grid for o in scenario.obstacles if isinstance(o, OccupancyGridObstacle))


def call_bitstar(path: Path, *, dubins: bool, budget_s: float, target_m: float | None) -> MapAttempt:
    """OMPL's BIT* on the grid planner's inflated grid (see the module docstring)."""
    from ompl import base as ob
    from ompl import geometric as og
    from ompl import util as ou

    from cvxnav.bench.grid_planner import inflated_free

    ou.setLogLevel(ou.LOG_NONE)
    t0 = time.perf_counter()
    scenario = load_scenario(path)
    grid = _grid(scenario)
    rows, cols = grid.shape
    res = grid.resolution_m
    free = inflated_free(grid, margin_m=scenario.inflation_m)
    inverse = grid.rotation.T
    ox, oy = grid.origin_x_m, grid.origin_y_m

    def valid_xy(x: float, y: float) -> bool:
        gx = (inverse[0, 0] * (x - ox) + inverse[0, 1] * (y - oy)) / res
        gy = (inverse[1, 0] * (x - ox) + inverse[1, 1] * (y - oy)) / res
        i, j = int(math.floor(gx)), int(math.floor(gy))
        return 0 <= i < cols and 0 <= j < rows and bool(free[j, i])

    lo, hi = np.asarray(scenario.bounds.min, dtype=float), np.asarray(scenario.bounds.max, dtype=float)
    box = ob.RealVectorBounds(2)
    for axis in range(2):
        box.setLow(axis, float(lo[axis]))
        box.setHigh(axis, float(hi[axis]))
    if dubins:
        space = ob.DubinsStateSpace(1.0 / scenario.max_curvature)
        space.setBounds(box)
        valid = lambda s: valid_xy(s.getX(), s.getY())  # noqa: E731
    else:
        space = ob.RealVectorStateSpace(2)
        space.setBounds(box)
        valid = lambda s: valid_xy(s[0], s[1])  # noqa: E731
    si = ob.SpaceInformation(space)
    si.setStateValidityChecker(valid)
    si.setStateValidityCheckingResolution(min(res, 0.05) / space.getMaximumExtent())
    si.setup()
    # Leg by leg, each from where the one before ended (a Dubins leg leaving at the heading it arrived at),
    # each with the whole budget; the 1 % target is the whole path's, so it stops a single leg only.
    at = (scenario.start.x, scenario.start.y, scenario.start.theta)
    legs: list[FloatArray] = []
    length = 0.0
    goals_xy = scenario.goals_array
    for number, goal_xy in enumerate(goals_xy, start=1):
        pdef = ob.ProblemDefinition(si)
        start = si.allocState()
        if dubins:
            start.setX(at[0])
            start.setY(at[1])
            start.setYaw(at[2])
            goals = ob.GoalStates(si)
            for k in range(16):
                g = si.allocState()
                g.setX(float(goal_xy[0]))
                g.setY(float(goal_xy[1]))
                g.setYaw(-math.pi + 2.0 * math.pi * k / 16)
                goals.addState(g)
            goals.setThreshold(scenario.goal_tolerance)
            pdef.addStartState(start)
            pdef.setGoal(goals)
        else:
            start[0], start[1] = at[0], at[1]
            goal = si.allocState()
            goal[0], goal[1] = float(goal_xy[0]), float(goal_xy[1])
            pdef.setStartAndGoalStates(start, goal)
        objective = ob.PathLengthOptimizationObjective(si)
        if target_m is not None and len(goals_xy) == 1:
            objective.setCostThreshold(ob.Cost(1.01 * target_m))
        pdef.setOptimizationObjective(objective)
        planner = og.BITstar(si)
        planner.setProblemDefinition(pdef)
        planner.setup()
        begun = time.perf_counter()
        planner.solve(ob.PlannerTerminationCondition(lambda begun=begun: time.perf_counter() - begun >= budget_s))
        if not pdef.hasExactSolution():
            where = "" if len(goals_xy) == 1 else f" to goal {number}"
            return MapAttempt(None, time.perf_counter() - t0, {}, f"BITstar: no path{where} in {budget_s:g} s")
        solution = pdef.getSolutionPath()
        length += solution.length()
        if dubins:
            solution.interpolate(max(2, int(solution.length() / 0.05)))
        states = solution.getStates()
        if dubins:
            legs.append(np.array([(state.getX(), state.getY()) for state in states]))
            at = (states[-1].getX(), states[-1].getY(), states[-1].getYaw())
        else:
            legs.append(np.array([(state[0], state[1]) for state in states]))
            at = (states[-1][0], states[-1][1], 0.0)
    elapsed = time.perf_counter() - t0
    reached = target_m is not None and length <= 1.01 * target_m
    reason = "" if reached else f"BITstar: not within 1 % of {target_m:.3f} m in {budget_s:g} s" if target_m else ""
    return MapAttempt(joined_legs(legs), elapsed, {}, reason, target_s=elapsed if reached else None)


# --------------------------------------------------------------------------- judging and running


@dataclass(frozen=True)
class Judged:
    length_m: float
    min_clearance_m: float
    collides: bool
    reaches: bool


def judge(scenario: Scenario, path: FloatArray) -> Judged:
    """True-geometry clearance of the path resampled at 0.02 m, and whether it starts at the start and
    passes within the goal tolerance of each goal in order."""
    dense = resample_polyline(path, max_spacing_m=0.02)
    clearance = float(np.min(scenario.clearance(dense)))
    cursor, reaches = 0, bool(np.linalg.norm(path[0] - scenario.start.xy) <= 1e-6)
    for goal in scenario.goals_array:
        hits = np.flatnonzero(np.linalg.norm(dense[cursor:] - goal, axis=1) <= scenario.goal_tolerance + 1e-9)
        if not len(hits):
            reaches = False
            break
        cursor += int(hits[0])
    return Judged(polyline_length(path), clearance, clearance < scenario.inflation_m - COLLISION_TOLERANCE_M, reaches)


def _summary(name: str, scenario: Scenario, attempts: list[MapAttempt], *, reference_m: float | None,
             sampling: bool) -> MapPlannerResult:
    judged = [judge(scenario, a.path) if a.path is not None else None for a in attempts]
    failed = [a.reason or "no path" for a, j in zip(attempts, judged) if j is None]
    collides = any(j is not None and j.collides for j in judged)
    misses = any(j is not None and not j.reaches for j in judged)
    reasons = [f"{len(failed)}/{len(attempts)} failed: {failed[0]}"] if failed else []
    if collides:
        worst = min(j.min_clearance_m for j in judged if j is not None)
        reasons.append(f"collides: true clearance {worst:.3f} m < {scenario.inflation_m - COLLISION_TOLERANCE_M:.3f} m")
    if misses:
        reasons.append("misses a goal")
    reasons += sorted({a.reason for a in attempts if a.path is not None and a.reason})
    lengths = [j.length_m for j in judged if j is not None]
    times = [1e3 * a.time_s for a in attempts]
    stage_names = sorted({k for a in attempts for k in a.stages_ms})
    stages = {k: statistics.median(a.stages_ms.get(k, 0.0) for a in attempts) for k in stage_names}
    length = statistics.median(lengths) if lengths else None
    return MapPlannerResult(
        planner=name, success=not failed and not collides and not misses, collision=collides,
        reason="; ".join(reasons), repeats=len(attempts), length_m=length,
        length_ratio=length / reference_m if length is not None and reference_m else None,
        min_clearance_m=min((j.min_clearance_m for j in judged if j is not None), default=None),
        time_median_ms=statistics.median(times), time_p90_ms=float(np.percentile(times, 90)), times_ms=times,
        stages_ms=stages,
        target_reached=sum(a.target_s is not None for a in attempts) if sampling else None)


@dataclass(frozen=True)
class MapBenchOptions:
    repeats: int = 3  # timed calls per planner at least (BIT*: exactly, it is slow)
    min_timed_s: float = 1.0  # cvxnav and the grid planner: called again until this much of their time is timed
    max_repeats: int = 30
    sampling_budget_s: float = 5.0
    growth_tiles: tuple[int, ...] = (1, 2, 4)
    growth_repeats: int = 5
    memory: bool = True
    seed: int = 0


def run_map_bench(cases: list[MapCase], *, options: MapBenchOptions, work_dir: Path, shared: Path | None,
                  with_ompl: bool, on_step: Callable[[str], None] = lambda text: None) -> MapBenchResult:
    """Every planner on every case in turns, the growth run and the memory figure; each case and each
    growth point in a process of its own (`_isolated`)."""
    results = []
    for case in cases:
        result = _isolated(bench_case, case, options, with_ompl=with_ompl, on_step=on_step)
        kept = _isolated(bench_case, case, options, with_ompl=False, keep_memory=True, on_step=on_step)
        results.append(result if kept is None else result.model_copy(update={"planners_kept_memory": kept.planners}))
    growth = []
    if shared is not None and options.growth_tiles and (shared / "maps" / "depot.pgm").is_file():
        on_step("growth: the depot tiled")
        growth = [_isolated(growth_point, k, path, options.growth_repeats, options.seed, on_step=on_step)
                  for k, path in write_growth_maps(work_dir / "growth", shared=shared, tiles=options.growth_tiles)]
    memory: dict[str, float] = {}
    big = next((c for c in cases if c.path.stem == "warehouse-30x50"), None)
    if options.memory and big is not None:
        on_step("memory: peak resident set on the 30 × 50 m map")
        memory = {CVXNAV: peak_rss_mib("cvxnav", "plan", str(big.path), "--out", str(work_dir / "warehouse-plan.json"),
                                       work_dir=work_dir),
                  GRID: peak_rss_mib("cvxnav.bench.grid_planner", str(big.path), work_dir=work_dir)}
    return MapBenchResult(scenarios=results, growth=growth, peak_rss_mib=memory, targets=_targets(results, growth, memory),
                          notes=_notes(options))


def bench_case(case: MapCase, options: MapBenchOptions, *, with_ompl: bool, keep_memory: bool = False,
               on_step: Callable[[str], None]) -> MapScenarioResult | None:
    """Every planner on one case, in turns, after one untimed call each. `keep_memory`: first set the C
    library to keep freed memory for reuse (`_keep_freed_memory`); None where it cannot."""
    if keep_memory and not _keep_freed_memory():
        return None
    scenario = load_scenario(case.path)
    grid = _grid(scenario)
    label = f"{scenario.name} (freed memory kept)" if keep_memory else scenario.name
    on_step(f"{label}: cold calls")
    cold = call_cvxnav(case.path)  # warms the process (imports, compiled problems) as for every peer
    call_grid(case.path)
    target = case.reference_m or (polyline_length(cold.path) if cold.path is not None else None)
    calls: dict[str, Callable[[int], MapAttempt]] = {CVXNAV: lambda k: call_cvxnav(case.path),
                                                     GRID: lambda k: call_grid(case.path)}
    if with_ompl:
        for name, dubins in ((BIT_POINT, False), (BIT_DUBINS, True)):
            calls[name] = lambda k, dubins=dubins: call_bitstar(case.path, dubins=dubins,
                                                                budget_s=options.sampling_budget_s, target_m=target)

    def wants_more(name: str, done: list[MapAttempt]) -> bool:
        if name in (BIT_POINT, BIT_DUBINS):
            return len(done) < options.repeats
        timed = sum(a.time_s for a in done)
        return len(done) < options.repeats or (len(done) < options.max_repeats and timed < options.min_timed_s)

    attempts = in_turns(calls, wants_more, seed=options.seed,
                        on_round=lambda k: on_step(f"{label}: in turns, round {k + 1}"))
    rows = [_summary(name, scenario, done, reference_m=case.reference_m, sampling=name.startswith("BIT"))
            for name, done in attempts.items()]
    return MapScenarioResult(
        name=scenario.name, note=case.note, cells=int(np.prod(grid.shape)), resolution_m=grid.resolution_m,
        area_m2=float(np.prod(grid.size_m)), reference_m=case.reference_m, target_m=target, planners=rows)


def growth_point(tiles: int, path: Path, repeats: int, seed: int, *, on_step: Callable[[str], None]) -> MapGrowthPoint:
    """cvxnav's and the grid planner's times on one tiled depot, in turns (medians)."""
    on_step(f"growth: the depot tiled {tiles}×")
    call_cvxnav(path)
    call_grid(path)
    calls = {CVXNAV: lambda i: call_cvxnav(path), GRID: lambda i: call_grid(path)}
    done = in_turns(calls, lambda name, got: len(got) < repeats, seed=seed)
    grid = _grid(load_scenario(path))
    return MapGrowthPoint(tiles=tiles, cells=int(np.prod(grid.shape)),
                          cvxnav_ms=statistics.median(1e3 * a.time_s for a in done[CVXNAV]),
                          grid_ms=statistics.median(1e3 * a.time_s for a in done[GRID]),
                          ok=all(a.path is not None for a in done[CVXNAV]))


_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3  # glibc's mallopt parameters (malloc.h)


def _keep_freed_memory() -> bool:
    """Set this process's C library to keep freed memory for reuse, as a planner that keeps its buffers
    between plans does (Nav2's NavFn allocates its arrays once per map size): blocks up to 32 MiB (its
    largest) from the heap instead of fresh pages from the system, and the heap never trimmed back
    (glibc's `mallopt`, which the variables MALLOC_MMAP_THRESHOLD_ and MALLOC_TRIM_THRESHOLD_ also set);
    whether it could (no `mallopt`: not glibc)."""
    try:
        mallopt = ctypes.CDLL(None).mallopt
    except (OSError, AttributeError):
        return False
    return bool(mallopt(_M_MMAP_THRESHOLD, 32 << 20)) and bool(mallopt(_M_TRIM_THRESHOLD, 1 << 30))


def _isolated(work: Callable[..., _T], *args: object, on_step: Callable[[str], None], **kwargs: object) -> _T:
    """`work(*args, **kwargs, on_step=...)` in a fresh process (spawned: it inherits nothing but the arguments), its
    progress relayed to `on_step`, its result (or its traceback, raised here) handed back.

    What ran before in a process moves a planner's time: numpy's large arrays come from the C library's
    allocator, which, once a larger map's arrays were freed, keeps blocks of a smaller map's size for
    reuse instead of handing them back to the system and faulting them in afresh on the next call, so the
    figures would depend on the order of the scenarios (docs/maps.md has the measurement). In a process
    of its own each case starts from the state a planner serving that map alone would be in."""
    context = multiprocessing.get_context("spawn")
    messages = context.Queue()
    process = context.Process(target=_reporting, args=(work, args, kwargs, messages), daemon=True)
    process.start()
    try:
        while True:
            try:
                kind, value = messages.get(timeout=0.5)
            except queue.Empty:
                if process.is_alive():
                    continue
                try:  # it may have ended just after its last message
                    kind, value = messages.get(timeout=1.0)
                except queue.Empty:
                    raise RuntimeError(f"{work.__name__}{args!r}: its process ended (exit code {process.exitcode}) "
                                       "without a result") from None
            if kind == "step":
                on_step(value)
            elif kind == "done":
                return value
            else:
                raise RuntimeError(f"{work.__name__}{args!r} failed in its process:\n{value}")
    finally:
        process.join(timeout=5.0)
        if process.is_alive():
            process.kill()
            process.join()


def _reporting(work: Callable[..., object], args: tuple, kwargs: dict, messages) -> None:
    """`_isolated`'s child: run the work, sending its progress and then its result or traceback."""
    try:
        messages.put(("done", work(*args, **kwargs, on_step=lambda text: messages.put(("step", text)))))
    except BaseException:  # the parent raises it, with this traceback
        messages.put(("error", traceback.format_exc()))


_PEAK_RSS = ("import atexit, os, runpy, sys\n"
             "def report():\n"
             "    peak = [l for l in open('/proc/self/status') if l.startswith('VmHWM:')][0].split()[1]\n"
             "    open(os.environ['CVXNAV_PEAK_RSS_FILE'], 'w').write(peak)\n"
             "atexit.register(report)\n"
             "sys.argv = sys.argv[1:]\n"
             "runpy.run_module(sys.argv[0], run_name='__main__', alter_sys=True)\n")


def peak_rss_mib(module: str, *args: str, work_dir: Path) -> float:
    """The peak resident set of a Python process running `python -m module args`: the kernel's high-water
    mark of the process's own memory (`VmHWM`, read as it exits; `ru_maxrss` would count the parent's
    pages the child shares before it execs)."""
    report = work_dir / f"peak-rss-{module}.txt"
    subprocess.run([sys.executable, "-c", _PEAK_RSS, module, *args], stdout=subprocess.DEVNULL,
                   stderr=subprocess.DEVNULL, env={**os.environ, "CVXNAV_PEAK_RSS_FILE": str(report)}, check=False)
    return int(report.read_text()) / 1024.0


def _targets(results: list[MapScenarioResult], growth: list[MapGrowthPoint], memory: dict[str, float]) -> MapTargets:

    ratios, intervals, kept, kept_intervals, lengths = {}, {}, {}, {}, {}
    for scenario in results:
        for planners, into, spread in ((scenario.planners, ratios, intervals),
                                       (scenario.planners_kept_memory, kept, kept_intervals)):
            rows = {p.planner: p for p in planners}
            ours, grid = rows.get(CVXNAV), rows.get(GRID)
            if ours is not None and grid is not None and ours.time_median_ms and grid.time_median_ms:
                into[scenario.name] = ours.time_median_ms / grid.time_median_ms
                if (interval := ratio_interval(ours.times_ms, grid.times_ms)) is not None:
                    spread[scenario.name] = interval
        ours = next((p for p in scenario.planners if p.planner == CVXNAV), None)
        if ours is not None and ours.length_ratio is not None:
            lengths[scenario.name] = ours.length_ratio
    exponent = {}
    if len(growth) >= 2:
        x = np.log([g.cells for g in growth])
        for name, values in ((CVXNAV, [g.cvxnav_ms for g in growth]), (GRID, [g.grid_ms for g in growth])):
            exponent[name] = float(np.polyfit(x, np.log(values), 1)[0])
    return MapTargets(length_ratio_vs_reference=lengths, time_ratio_vs_grid=ratios, time_ratio_vs_grid_interval=intervals,
                      time_ratio_vs_grid_kept_memory=kept, time_ratio_vs_grid_kept_memory_interval=kept_intervals,
                      growth_exponent_in_cells=exponent, peak_rss_mib=memory.get(CVXNAV))


def _notes(options: MapBenchOptions) -> list[str]:
    return [
        "Times are from reading the scenario and its map file to the path, each call a fresh read; cvxnav, the grid "
        "planner and BIT* are called in turns (an order shuffled per round), after one untimed call each, each scenario "
        "(and each tiled depot) in a process of its own: what ran before in a process (another map's large arrays, "
        "which the C library's allocator then keeps for reuse) moved the grid planner's time on the depot by a third. "
        "cvxnav and the grid planner are then timed again in a process whose C library keeps freed memory for reuse "
        "(glibc's mallopt: as a planner that keeps its buffers between plans): the grid planner's time falls by up "
        "to a third there, cvxnav's hardly moves.",
        "grid (NavFn-like): a cell is free when its centre is at least the margin plus half a cell from the nearest "
        "blocked cell's centre (scipy's exact EDT), then an 8-connected Dijkstra over the whole grid (scipy.sparse.csgraph).",
        f"BIT*: valid = a free cell of that inflated grid, motions checked every grid cell or 0.05 m (the shorter); it "
        f"stops within 1 % of the "
        f"REFERENCE optimum (or of cvxnav's length where there is none) or at {options.sampling_budget_s:g} s. Point: "
        "R²; Dubins: SE(2) at the car's turning radius (rear axle), the goal any of 16 headings within the goal tolerance.",
        f"Collision = true clearance (exact distance to the blocked squares, path resampled at 0.02 m) below the margin − "
        f"{COLLISION_TOLERANCE_M} m. Only cvxnav's path is smooth and honours the start heading and curvature bound; "
        "the grid planner's runs through cell centres, BIT* Dubins' honours the turning radius but not the start's "
        "steering.",
        "Peak memory: the kernel's high-water mark of a separate process's resident set (VmHWM): `cvxnav plan FILE`, "
        "and `python -m cvxnav.bench.grid_planner FILE` (both include the interpreter and imports).",
    ]


# --------------------------------------------------------------------------- rendering


def _num(value: float | None, fmt: str) -> str:
    return "—" if value is None else format(value, fmt)


_STAGES = {CVXNAV: ("load", "corridor", "fit", "optimize", "smooth"), GRID: ("load", "inflate", "graph", "search")}


def map_tables(result: MapBenchResult) -> list[tuple[str, tuple[str, ...], list[tuple[str, ...]]]]:
    """(title, header, rows) of the map tables: planners per scenario, growth, memory."""
    header = ("scenario", "planner", "ok", "length m", "÷ ref", "median ms", "p90 ms", "÷ grid", "stages ms (median)",
              "note")
    rows = []
    for scenario in result.scenarios:
        grid = next((p for p in scenario.planners if p.planner == GRID), None)
        label = f"{scenario.name} ({scenario.cells / 1e6:.2f} M cells, {scenario.resolution_m:g} m"
        label += f", ref {scenario.reference_m:.3f})" if scenario.reference_m else ")"
        for k, p in enumerate(scenario.planners):
            stages = " / ".join(f"{name} {p.stages_ms[name]:.0f}" for name in _STAGES.get(p.planner, ())
                                if name in p.stages_ms)
            ratio = (p.time_median_ms / grid.time_median_ms if grid is not None and grid.time_median_ms
                     and p.time_median_ms and p.planner != GRID else None)
            reached = f"{p.target_reached}/{p.repeats} within 1 % of the target" if p.target_reached is not None else ""
            rows.append((label if k == 0 else "", p.planner, "yes" if p.success else ("COLLIDES" if p.collision else "no"),
                         _num(p.length_m, ".2f"), _num(p.length_ratio, ".4f"), _num(p.time_median_ms, ".0f"),
                         _num(p.time_p90_ms, ".0f"), _num(ratio, ".2f"), stages,
                         "; ".join(note for note in (p.reason, reached) if note)[:160]))
    tables = [("maps: planners from reading the map file to the path", header, rows)]
    kept = []
    for scenario in result.scenarios:
        if (ratio := result.targets.time_ratio_vs_grid_kept_memory.get(scenario.name)) is not None:
            times = {p.planner: p.time_median_ms for p in scenario.planners_kept_memory}
            spread = result.targets.time_ratio_vs_grid_kept_memory_interval.get(scenario.name)
            kept.append((scenario.name, f"{times[CVXNAV]:.0f}", f"{times[GRID]:.0f}", f"{ratio:.2f}{_interval(spread)}"))
    if kept:
        tables.append(("maps: cvxnav and the grid planner with the C library keeping freed memory",
                       ("scenario", "cvxnav median ms", "grid median ms", "cvxnav ÷ grid (95 % interval)"), kept))
    if result.growth:
        tables.append(("maps: growth with map area (the depot tiled, depot-1's query)",
                       ("tiles", "cells", "cvxnav median ms", "grid median ms", "cvxnav ÷ grid", "ok"),
                       [(str(g.tiles), f"{g.cells:,}", f"{g.cvxnav_ms:.0f}", f"{g.grid_ms:.0f}",
                         f"{g.cvxnav_ms / g.grid_ms:.2f}", "yes" if g.ok else "no") for g in result.growth]))
    if result.peak_rss_mib:
        tables.append(("maps: peak resident memory on the 30 × 50 m map at 0.03 m", ("process", "peak RSS MiB"),
                       [(name, f"{mib:.0f}") for name, mib in result.peak_rss_mib.items()]))
    return tables


def _interval(spread: tuple[float, float] | None, label: str = "") -> str:
    """A ratio's 95 % interval as shown after the ratio, " (label lo–hi)"; "" without one."""
    return f" ({label}{spread[0]:.2f}–{spread[1]:.2f})" if spread else ""


def map_target_lines(result: MapBenchResult) -> list[str]:
    t = result.targets
    lines = [f"length ÷ REFERENCE, {name} (target ≤ 1.02): {ratio:.4f}" for name, ratio in t.length_ratio_vs_reference.items()]
    for name, ratio in t.time_ratio_vs_grid.items():
        spread = _interval(t.time_ratio_vs_grid_interval.get(name), "95 % interval ")
        lines.append(f"time ÷ grid planner, {name} (target ≤ 1, goal ≤ 0.3): {ratio:.2f}{spread}")
    for name, ratio in t.time_ratio_vs_grid_kept_memory.items():
        spread = _interval(t.time_ratio_vs_grid_kept_memory_interval.get(name), "95 % interval ")
        lines.append(f"time ÷ grid planner with freed memory kept, {name}: {ratio:.2f}{spread}")
    for name, exponent in t.growth_exponent_in_cells.items():
        lines.append(f"growth exponent of {name}'s time in map cells (tiled depot): {exponent:.2f}")
    if t.peak_rss_mib is not None:
        lines.append(f"peak RSS of cvxnav plan on the 30 × 50 m map (target ≤ 1024 MiB): {t.peak_rss_mib:.0f} MiB")
    return lines + result.notes
