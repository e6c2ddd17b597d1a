"""The benchmark's output, defined once as frozen pydantic models and exported as JSON Schema.

`BenchReport` is what `cvxnav bench --json` writes; `BenchReport.model_json_schema()` is its contract
for anyone reading it without this package. Floats are finite; a quantity that does not exist (the
length of a failed plan, BIT*'s time to 1 % when it never got there) is null, never NaN.
"""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field

FORMAT = "cvxnav.bench/6"  # /2: `ScalingPoint.local_exponent`; /3: every call's time (`times_ms`), the ratios'
# intervals; /4: the fit on several point sets (`FitResult.point_sets`); /5: occupancy-grid maps (`maps`); /6: the
# maps' cvxnav and grid planner timed again with the allocator keeping freed memory (`planners_kept_memory`)


class _Frozen(BaseModel):
    model_config = ConfigDict(frozen=True, extra="forbid", allow_inf_nan=False)


class PlannerResult(_Frozen):
    """One planner on one scenario, summarised over its repeats."""

    planner: str
    success: bool  # produced a path on every repeat and none of them collides with the true geometry
    collision: bool  # some returned path comes closer than width/2 + safety − tolerance to a true obstacle
    reason: str = ""  # why it failed, or what its numbers mean
    repeats: int = Field(ge=0)
    length_m: float | None = None  # median length of the returned paths
    length_ratio: float | None = None  # length_m ÷ the grown-ellipse optimum
    min_clearance_m: float | None = None  # worst true-geometry clearance over the returned paths
    time_median_ms: float | None = None  # the planner's planning time (what it means: `time_meaning`)
    time_p90_ms: float | None = None
    times_ms: list[float] = []  # every timed call's time, in call order (the median and p90 are of these)
    time_meaning: str = ""
    cold_ms: float | None = None  # cvxnav only: the first call on the scenario in this process
    first_solution_ms: float | None = None  # sampling planners: median time to the first solution
    target_reached: int | None = None  # sampling planners: repeats that reached 1.01 × optimum in budget
    peak_memory_kib: float | None = None  # tracemalloc peak of one extra, untimed call


class ScenarioResult(_Frozen):
    name: str
    obstacles: int = Field(ge=0)
    grown_ellipses: int = Field(ge=0)
    optimum_m: float | None  # shortest path outside the grown ellipses (tangent graph, see `optimum_note`)
    optimum_note: str
    reference_m: float | None  # REFERENCE.json: the shortest path among the true obstacles grown
    planners: list[PlannerResult]


class FitResult(_Frozen):
    """Minimum-volume ellipse of `points` random points: one fitting route."""

    method: str
    points: int = Field(gt=0)
    point_sets: int = Field(default=1, gt=0)  # seeded sets of `points` points timed, in turn (those every method solved)
    time_median_ms: float | None
    times_ms: list[float] = []  # every timed call's time (the median is of these)
    area_rel_diff: float | None  # max over the sets of |area − reference| / reference (reference: mvee, cvxpy)
    error: str = ""  # why it failed (for a method timed on some sets only: why it failed on the others)


class ScalingPoint(_Frozen):
    obstacles: int = Field(gt=0)
    grown_ellipses: int = Field(ge=0)
    time_median_ms: float | None
    success: bool
    # slope of log(time) on log(obstacles) from the previous successful point: where the growth is steep
    local_exponent: float | None = None


class ScalingResult(_Frozen):
    """cvxnav planning time against obstacle count on seeded random fields; exponent from log-log fit."""

    points: list[ScalingPoint]
    growth_exponent: float | None  # slope of log(time) against log(obstacles), least squares
    time_meaning: str


class TargetRatios(_Frozen):
    """The issue's targets, each a measured ratio (≤ 1 meets the time targets; ≤ 1.01 the length one)."""

    length_ratio_worst: float | None  # max over scenarios of cvxnav length ÷ grown-ellipse optimum
    time_ratio_vs_bitstar: dict[str, float | None]  # per scenario: cvxnav warm median ÷ BIT* median to 1 %
    time_ratio_vs_bitstar_is_lower_bound: dict[str, bool]  # BIT* missed 1 % in budget: ratio uses the budget
    # per scenario: the ratio's 95 % bootstrap interval (both planners' calls resampled, seeded)
    time_ratio_vs_bitstar_interval: dict[str, tuple[float, float]] = {}
    fit_ratio_vs_drake: dict[str, float | None]  # per point count: mvee_fast ÷ Drake time
    fit_ratio_vs_drake_interval: dict[str, tuple[float, float]] = {}  # the same 95 % bootstrap interval
    growth_exponent: float | None


class Machine(_Frozen):
    platform: str
    processor: str
    cpus: int
    python: str
    packages: dict[str, str]


class MapPlannerResult(_Frozen):
    """One planner on one map scenario, over its repeats; times from reading the files to the path."""

    planner: str
    success: bool  # a path on every repeat, none colliding with the true geometry, every goal reached
    collision: bool
    reason: str = ""
    repeats: int = Field(ge=0)
    length_m: float | None = None  # median
    length_ratio: float | None = None  # ÷ the REFERENCE optimum, where there is one
    min_clearance_m: float | None = None  # worst true clearance over the paths
    time_median_ms: float | None = None
    time_p90_ms: float | None = None
    times_ms: list[float] = []
    stages_ms: dict[str, float] = {}  # median time per stage (cvxnav's timings_ms; the grid planner's own)
    target_reached: int | None = None  # BIT*: repeats within 1 % of `MapScenarioResult.target_m` in budget


class MapScenarioResult(_Frozen):
    name: str
    note: str
    cells: int = Field(gt=0)
    resolution_m: float = Field(gt=0)
    area_m2: float = Field(gt=0)
    reference_m: float | None  # REFERENCE.json's true-geometry optimum (the depot queries)
    target_m: float | None  # BIT*'s: the reference, else cvxnav's length
    planners: list[MapPlannerResult]
    # cvxnav and the grid planner again, in a process whose C library keeps freed memory for reuse (empty where
    # the C library has no `mallopt`)
    planners_kept_memory: list[MapPlannerResult] = []


class MapGrowthPoint(_Frozen):
    """The depot tiled `tiles` times side by side, depot-1's query: median times in turns."""

    tiles: int = Field(gt=0)
    cells: int = Field(gt=0)
    cvxnav_ms: float
    grid_ms: float
    ok: bool


class MapTargets(_Frozen):
    length_ratio_vs_reference: dict[str, float]  # cvxnav length ÷ REFERENCE (target ≤ 1.02)
    time_ratio_vs_grid: dict[str, float]  # cvxnav median ÷ grid planner median (target ≤ 1, goal ≤ 0.3)
    time_ratio_vs_grid_interval: dict[str, tuple[float, float]] = {}  # its 95 % bootstrap interval
    time_ratio_vs_grid_kept_memory: dict[str, float] = {}  # the same with freed memory kept (`planners_kept_memory`)
    time_ratio_vs_grid_kept_memory_interval: dict[str, tuple[float, float]] = {}
    growth_exponent_in_cells: dict[str, float] = {}  # slope of log time on log cells over the tiled depots
    peak_rss_mib: float | None = None  # cvxnav plan on the 30 × 50 m map (target ≤ 1024)


class MapBenchResult(_Frozen):
    scenarios: list[MapScenarioResult]
    growth: list[MapGrowthPoint]
    peak_rss_mib: dict[str, float]  # per planner, on the 30 × 50 m map
    targets: MapTargets
    notes: list[str]


class BenchReport(_Frozen):
    format: Literal["cvxnav.bench/6"] = FORMAT
    command: str
    machine: Machine
    quick: bool
    repeats: int = Field(ge=1)
    sampling_budget_s: float = Field(gt=0)
    collision_tolerance_m: float = Field(ge=0)
    notes: list[str]
    scenarios: list[ScenarioResult]
    fit: list[FitResult]
    scaling: ScalingResult | None
    targets: TargetRatios
    maps: MapBenchResult | None = None  # `cvxnav bench --maps`, or scenario/2 files given
    wall_s: float = Field(ge=0)
