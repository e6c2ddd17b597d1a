"""The scenario files `cvxnav.scenario/1` and `/2` (CONTRACTS §1, §1b) as frozen pydantic models, with
true geometry.

Everything a stage needs to know about the world is validated here once: a scenario that loads is finite,
non-degenerate, and has its start and goals in free space inside the bounds. Obstacle geometry is the
*true* solid (no inflation); planners grow it by `Scenario.inflation_m` themselves. A `/2` file may name
an occupancy grid (a Nav2 `map_server` map), read when the scenario is validated, relative to the file.
"""

from __future__ import annotations

import dataclasses
import importlib.resources
import json
import math
import os
import re
import stat
import sys
from functools import cached_property
from pathlib import Path
from typing import Annotated, Any, Literal, Union

import numpy as np
import shapely
from numpy.typing import ArrayLike, NDArray
from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    PrivateAttr,
    Strict,
    ValidationError,
    ValidationInfo,
    field_serializer,
    field_validator,
    model_validator,
)
from shapely.geometry.base import BaseGeometry

from schemas.occupancy import FREE, STATE_NAMES, MapError, OccupancyGrid, load_map

FloatArray = NDArray[np.float64]

SCENARIO_FORMAT = "cvxnav.scenario/1"
MAP_SCENARIO_FORMAT = "cvxnav.scenario/2"  # /1 and occupancy grids
BUNDLED_SCENARIO = "paper-two-goals.json"

# Bounds of the scenario contract (docs/contracts.md says why each is what it is). They keep a file's cost
# bounded: its size, the work per scan and per plan, and the memory of every process that loads it.
MAX_SCENARIO_BYTES = 8 << 20  # the scenario file (a map's image has its own bound, `MAX_CELLS`)
MAX_OBSTACLES = 10_000
MAX_VERTICES = 10_000  # per polygon, per point set
MAX_TOTAL_VERTICES = 100_000  # over every obstacle
MAX_GOALS = 1_000
MAX_RAYS = 4_096  # a scan of this many hits stays far below the stages' 1 MiB payload cap
MAX_COORDINATE_M = 1e10  # |x|, |y|: float64 still resolves 2 µm there; the cores work in a local frame
MAX_EXTENT_M = 10_000.0  # the bounds' side: one site, not a continent
MAX_SIZE_M = 100.0  # the robot's dimensions, safety distance and goal tolerance
MIN_SIZE_M = 0.01
MAX_NAME_CHARS = 200

Real = Annotated[float, Strict()]
"""A number: an int or a float, never a string or a bool (pydantic's strict float accepts ints)."""

Coordinate = Annotated[float, Strict(), Field(ge=-MAX_COORDINATE_M, le=MAX_COORDINATE_M)]

Vec2 = tuple[Coordinate, Coordinate]
"""A point [x, y] in metres; finiteness comes from the model config (`allow_inf_nan=False`)."""


def _size(*, low: float = MIN_SIZE_M, high: float = MAX_SIZE_M) -> Any:
    return Field(ge=low, le=high, strict=True)


class ScenarioError(ValueError):
    """A scenario that cannot be used; `str()` is one line naming the file, the field and the reason."""


class FieldError(ValueError):
    """A validator's complaint about a field below the one pydantic is validating.

    pydantic keeps the raised exception in the error's `ctx`, so `format_validation_error` can append
    `loc` to pydantic's own location and name the exact field (e.g. `goals[1]`) in the message.
    """

    def __init__(self, loc: tuple[str | int, ...], message: str) -> None:
        super().__init__(message)
        self.loc = loc


class _Frozen(BaseModel):
    model_config = ConfigDict(frozen=True, extra="forbid", allow_inf_nan=False)


# ---------------------------------------------------------------------------------------------------
# Error formatting, shared with schemas.files
# ---------------------------------------------------------------------------------------------------

_OBSTACLE_TAGS = frozenset({"polygon", "circle", "points", "occupancy_grid"})


def format_loc(loc: tuple[str | int, ...]) -> str:
    """`('obstacles', 1, 'vertices', 0)` -> `obstacles[1].vertices[0]`."""
    out = ""
    for part in loc:
        if isinstance(part, int):
            out += f"[{part}]"
        else:
            out += f".{part}" if out else str(part)
    return out


def _clean_loc(loc: tuple[str | int, ...]) -> tuple[str | int, ...]:
    """Drop the tag level pydantic inserts after a discriminated-union member: `obstacles[1].polygon`."""
    out: list[str | int] = []
    for i, part in enumerate(loc):
        if i >= 2 and part in _OBSTACLE_TAGS and isinstance(loc[i - 1], int) and loc[i - 2] == "obstacles":
            continue
        out.append(part)
    return tuple(out)


def format_validation_error(err: ValidationError) -> str:
    """The first error of a ValidationError as one line `field.path: reason` (+ how many more)."""
    errors = err.errors()
    first = errors[0]
    loc = _clean_loc(tuple(first["loc"]))
    cause = first.get("ctx", {}).get("error")
    if first["type"] == "extra_forbidden":
        where = format_loc(loc[:-1]) or "top level"
        line = f"unknown field '{loc[-1]}' at {where}"
    else:
        if isinstance(cause, FieldError):
            loc = loc + cause.loc
            reason = str(cause)
        elif isinstance(cause, ValueError):
            reason = str(cause)
        else:
            reason = first["msg"]
        path = format_loc(loc)
        line = f"{path}: {reason}" if path else reason
    if len(errors) > 1:
        line += f" (and {len(errors) - 1} more)"
    return " ".join(line.split())


def parse_json_model(
    model: type[BaseModel], text: str | bytes, *, source: str, error: type[ValueError], context: dict | None = None,
    max_items: int | None = None,
) -> Any:
    """Validate JSON text against `model`, turning every failure into one `error` line prefixed by `source`.

    The text goes through `json.loads` first so that invalid JSON is reported with line and column, and so
    that `NaN` / `Infinity` literals reach the model and are rejected there by name. Nesting deeper than
    the parser's recursion limit, and an integer longer than Python converts (4300 digits), are refused
    as such; an array longer than `max_items` (the most any field of the model holds) is refused before
    the model validates its items.
    """
    try:
        data = json.loads(text)
    except json.JSONDecodeError as exc:
        raise error(f"{source}: invalid JSON: {exc.msg} at line {exc.lineno} column {exc.colno}") from None
    except UnicodeDecodeError as exc:
        raise error(f"{source}: not UTF-8 text: {exc.reason}") from None
    except RecursionError:
        raise error(f"{source}: invalid JSON: arrays or objects nested too deeply") from None
    except ValueError:  # int() refused the digits (sys.get_int_max_str_digits)
        raise error(f"{source}: invalid JSON: {_long_integer(text)}") from None
    if max_items is not None:
        where = _array_longer_than(data, max_items)
        if where is not None:
            raise error(f"{source}: {format_loc(where[0]) or 'top level'}: an array of {where[1]} items, more than "
                        f"any field holds ({max_items})")
    try:
        return model.model_validate(data, context=context)
    except ValidationError as exc:
        raise error(f"{source}: {format_validation_error(exc)}") from None


def _array_longer_than(data: Any, limit: int) -> tuple[tuple[str | int, ...], int] | None:
    """Where the first array of more than `limit` items is in parsed JSON, and its length; None if none is.
    (Iterative: a JSON document is as deep as the parser allowed.)"""
    stack: list[tuple[tuple[str | int, ...], Any]] = [((), data)]
    while stack:
        loc, node = stack.pop()
        if isinstance(node, list):
            if len(node) > limit:
                return loc, len(node)
            stack += [(loc + (k,), item) for k, item in enumerate(node) if isinstance(item, (list, dict))]
        elif isinstance(node, dict):
            stack += [(loc + (k,), item) for k, item in node.items() if isinstance(item, (list, dict))]
    return None


def _long_integer(text: str | bytes) -> str:
    """Where the integer is that has more digits than Python converts."""
    text = text.decode("utf-8") if isinstance(text, bytes) else text
    found = re.search(rf"\d{{{sys.get_int_max_str_digits() + 1},}}", text)
    if found is None:
        return f"an integer of more than {sys.get_int_max_str_digits()} digits"
    line = text.count("\n", 0, found.start()) + 1
    column = found.start() - text.rfind("\n", 0, found.start())
    return f"an integer of {len(found.group())} digits at line {line} column {column}"


def read_text(path: str | Path, *, error: type[ValueError], max_bytes: int) -> tuple[str, str]:
    """(text, source name) of a regular file of at most `max_bytes`, or one `error` line saying why it cannot
    be read.

    It is opened without blocking and checked to be a regular file before anything is read: a FIFO would
    otherwise block until a writer came, and a device such as /dev/zero never ends.
    """
    p = Path(path)
    try:
        fd = os.open(p, os.O_RDONLY | os.O_NONBLOCK)
    except FileNotFoundError:
        raise error(f"{p}: no such file") from None
    except OSError as exc:
        raise error(f"{p}: cannot read: {exc.strerror or exc}") from None
    with os.fdopen(fd, "rb") as file:
        mode = os.fstat(fd).st_mode
        if stat.S_ISDIR(mode):
            raise error(f"{p}: is a directory, not a file")
        if not stat.S_ISREG(mode):
            raise error(f"{p}: not a regular file (a FIFO, socket or device)")
        try:
            data = file.read(max_bytes + 1)
        except OSError as exc:
            raise error(f"{p}: cannot read: {exc.strerror or exc}") from None
    if len(data) > max_bytes:
        raise error(f"{p.name}: larger than the {max_bytes} bytes such a file may have")
    try:
        return data.decode("utf-8"), p.name
    except UnicodeDecodeError as exc:
        raise error(f"{p.name}: not UTF-8 text: {exc.reason}") from None


# ---------------------------------------------------------------------------------------------------
# Map, robot, sensor
# ---------------------------------------------------------------------------------------------------


class Bounds(_Frozen):
    """The map's axis-aligned extent; the robot stays inside."""

    min: Vec2
    max: Vec2

    @model_validator(mode="after")
    def _ordered(self) -> Bounds:
        if not (self.min[0] < self.max[0] and self.min[1] < self.max[1]):
            raise FieldError(("max",), f"must exceed bounds.min {list(self.min)} on both axes, got {list(self.max)}")
        return self

    def shown(self) -> str:
        """The bounds as an error message shows them, "[x, y]..[x, y]": to a nanometre, for bounds taken from a
        map's extent are sums of its origin and cells (24 cells of 0.05 m are 1.2000000000000002 m)."""
        return "..".join(str([round(v, 9) for v in corner]) for corner in (self.min, self.max))

    def contains(self, points: ArrayLike) -> NDArray[np.bool_]:
        """True for each point inside or on the bounds."""
        z = np.atleast_2d(np.asarray(points, dtype=float))
        lo, hi = np.asarray(self.min), np.asarray(self.max)
        return np.all((z >= lo) & (z <= hi), axis=1)


class Robot(_Frozen):
    """Footprint and kinematic bicycle limits (the paper: 0.3 × 0.6 m, L = 0.6, d_r = 0.5, |δ| ≤ 0.2).

    Each within a range that holds every ground robot with room to spare (docs/contracts.md); a number
    outside it is a typo or an attack, and left in it would overflow (tan, squares of 1e200) downstream.
    """

    width: float = _size()
    length: float = _size()
    wheelbase: float = _size()
    safety_distance: float = Field(gt=0, le=MAX_SIZE_M, strict=True)
    max_speed: float = Field(ge=0.01, le=100.0, strict=True)  # m/s
    max_steering_angle: float = Field(ge=0.01, le=1.5, strict=True)  # rad; tan(1.5) = 14
    max_steering_rate: float = Field(gt=0, le=100.0, strict=True)  # rad/s


class Sensor(_Frozen):
    """2-D range sensor centred on the heading."""

    fov_deg: float = Field(gt=0, le=360, strict=True)
    range: float = Field(ge=MIN_SIZE_M, le=1_000.0, strict=True)
    rays: int = Field(ge=2, le=MAX_RAYS, strict=True)
    rate_hz: float = Field(ge=0.1, le=1_000.0, strict=True)


class Pose(_Frozen):
    x: Coordinate
    y: Coordinate
    theta: float = Field(ge=-1e3, le=1e3, strict=True)  # rad; any turn, and 1e-13 rad resolution

    @property
    def xy(self) -> FloatArray:
        return np.array([self.x, self.y])


# ---------------------------------------------------------------------------------------------------
# Obstacles: true solids
# ---------------------------------------------------------------------------------------------------


def _as_points(points: ArrayLike) -> FloatArray:
    return np.atleast_2d(np.asarray(points, dtype=float)).reshape(-1, 2)


def _moved(points: ArrayLike, offset: FloatArray) -> list[Vec2]:
    return [(x, y) for x, y in (_as_points(points) + offset).tolist()]


def _hull_vertices(geom: BaseGeometry) -> FloatArray:
    """Vertices of a convex hull geometry: CCW ring for a polygon, endpoints for a segment, one point."""
    if isinstance(geom, shapely.Polygon):
        ring = np.asarray(geom.exterior.coords)[:-1]
        extent = float(np.ptp(ring, axis=0).max())
        if geom.area > 1e-12 * extent**2:
            return ring if shapely.is_ccw(geom.exterior) else ring[::-1].copy()
        # A hull of points that coincide to rounding is a segment: keep its two extreme points.
        far = np.linalg.norm(ring[:, None, :] - ring[None, :, :], axis=2)
        i, j = np.unravel_index(np.argmax(far), far.shape)
        return ring[[i, j]]
    return np.asarray(geom.coords, dtype=float).reshape(-1, 2)


def _shapely_distance(geom: BaseGeometry, points: ArrayLike) -> FloatArray:
    return np.asarray(shapely.distance(geom, shapely.points(_as_points(points))), dtype=float)


class PolygonObstacle(_Frozen):
    """A simple polygon (convex or not), vertices in either orientation."""

    type: Literal["polygon"] = "polygon"
    vertices: list[Vec2] = Field(max_length=MAX_VERTICES)

    @field_validator("vertices")
    @classmethod
    def _simple(cls, vertices: list[Vec2]) -> list[Vec2]:
        if len(vertices) < 3:
            raise ValueError(f"polygon needs at least 3 vertices, got {len(vertices)}")
        v = np.asarray(vertices, dtype=float)
        span = float(np.linalg.norm(v.max(axis=0) - v.min(axis=0)))
        hull = shapely.MultiPoint(v).convex_hull
        if hull.area <= 1e-9 * span**2:
            raise ValueError("polygon has zero area (its vertices are collinear or coincide)")
        poly = shapely.Polygon(v)
        if not poly.is_valid:
            raise ValueError(f"polygon is self-intersecting ({shapely.is_valid_reason(poly)})")
        if poly.area <= 1e-9 * span**2:
            raise ValueError("polygon has zero area")
        return vertices

    @cached_property
    def _solid(self) -> BaseGeometry:
        geom = shapely.Polygon(self.vertices)
        shapely.prepare(geom)
        return geom

    def solid(self) -> BaseGeometry:
        return self._solid

    def distance(self, points: ArrayLike) -> FloatArray:
        """Euclidean distance from each point to the polygon (0 inside or on it)."""
        return _shapely_distance(self._solid, points)

    def cover_vertices(self, *, circle_sides: int = 16) -> FloatArray:
        """The convex hull, CCW: the smallest convex polygon containing the solid."""
        return _hull_vertices(self._solid.convex_hull)

    def translated(self, offset: FloatArray) -> PolygonObstacle:
        return PolygonObstacle.model_construct(vertices=_moved(self.vertices, offset))


class CircleObstacle(_Frozen):
    """A disc; distances are analytic, so no polygonal approximation error enters the checks."""

    type: Literal["circle"] = "circle"
    center: Vec2
    radius: float = Field(ge=1e-3, le=MAX_EXTENT_M, strict=True)

    def solid(self, *, quad_segs: int = 64) -> BaseGeometry:
        """A polygon inscribed in the disc (shapely has no true circle); for drawing and set operations."""
        return shapely.Point(self.center).buffer(self.radius, quad_segs=quad_segs)

    def distance(self, points: ArrayLike) -> FloatArray:
        """max(0, ‖p − c‖ − r) for each point."""
        d = np.linalg.norm(_as_points(points) - np.asarray(self.center), axis=1)
        return np.maximum(0.0, d - self.radius)

    def cover_vertices(self, *, circle_sides: int = 16) -> FloatArray:
        """The circumscribed regular `circle_sides`-gon, CCW.

        Its edges are tangent to the circle at their midpoints, so its vertices lie at radius
        r / cos(π / sides): the apothem of a regular n-gon with circumradius R is R cos(π / n).
        """
        if circle_sides < 3:
            raise ValueError(f"circle_sides must be at least 3, got {circle_sides}")
        t = 2.0 * np.pi * np.arange(circle_sides) / circle_sides
        big = self.radius / np.cos(np.pi / circle_sides)
        return np.asarray(self.center) + big * np.column_stack([np.cos(t), np.sin(t)])

    def translated(self, offset: FloatArray) -> CircleObstacle:
        return CircleObstacle.model_construct(center=_moved([self.center], offset)[0], radius=self.radius)


class PointsObstacle(_Frozen):
    """Sensed corner points; the solid is their convex hull (the paper's obstacle corners)."""

    type: Literal["points"] = "points"
    points: list[Vec2] = Field(min_length=1, max_length=MAX_VERTICES)

    @cached_property
    def _solid(self) -> BaseGeometry:
        # GEOS's orientation tests fail on coordinates such as 1e-144 beside 1e-237 (their products
        # underflow) and return a hull that is not convex; to a nanometre they are 0.
        geom = shapely.MultiPoint(np.round(_as_points(self.points), 9)).convex_hull
        shapely.prepare(geom)
        return geom

    def solid(self) -> BaseGeometry:
        """The convex hull of the points to a nanometre: a polygon, or a segment / single point when the
        points are degenerate."""
        return self._solid

    def distance(self, points: ArrayLike) -> FloatArray:
        """Euclidean distance from each point to the convex hull (0 inside or on it)."""
        return _shapely_distance(self._solid, points)

    def cover_vertices(self, *, circle_sides: int = 16) -> FloatArray:
        """The hull's vertices, CCW; one or two points are returned as given."""
        if len(self.points) <= 2:
            return np.asarray(self.points, dtype=float).reshape(-1, 2)
        return _hull_vertices(self._solid)

    def translated(self, offset: FloatArray) -> PointsObstacle:
        return PointsObstacle.model_construct(points=_moved(self.points, offset))


class OccupancyGridObstacle(_Frozen):
    """A Nav2 `map_server` map (`map`: its YAML, relative to the scenario file): blocked cells are solid
    squares. The grid is read when the scenario is validated (`schemas.occupancy.load_map`), or handed in
    built from an array (`from_grid`: a ROS `/map`)."""

    type: Literal["occupancy_grid"] = "occupancy_grid"
    map: str = Field(min_length=1)
    _grid: OccupancyGrid | None = PrivateAttr(default=None)
    _path: Path | None = PrivateAttr(default=None)

    @model_validator(mode="after")
    def _read(self, info: ValidationInfo) -> OccupancyGridObstacle:
        path = Path((info.context or {}).get("base_dir", ".")) / self.map
        try:
            self._grid = load_map(path)
        except MapError as exc:
            raise FieldError(("map",), str(exc)) from None
        self._path = path.resolve()
        return self

    @field_serializer("map")
    def _where(self, value: str) -> str:
        """The map file read, as an absolute path: a scenario written out (a recording's attachment) reads
        back from anywhere."""
        return str(self._path) if self._path is not None else value

    @classmethod
    def from_grid(cls, grid: OccupancyGrid) -> OccupancyGridObstacle:
        """The obstacle of a grid already in memory; `map` names its source."""
        obstacle = cls.model_construct(map=grid.source)
        obstacle._grid = grid
        return obstacle

    @property
    def grid(self) -> OccupancyGrid:
        assert self._grid is not None  # set by validation or `from_grid`
        return self._grid

    def distance(self, points: ArrayLike) -> FloatArray:
        """Exact distance from each point to the nearest blocked cell (0 in one, or beyond the map)."""
        return self.grid.clearance(_as_points(points))

    def translated(self, offset: FloatArray) -> OccupancyGridObstacle:
        """The same map with its origin moved by `offset` (its file, for `map`, unchanged)."""
        grid = self.grid
        moved = OccupancyGridObstacle.from_grid(dataclasses.replace(
            grid, origin_x_m=grid.origin_x_m + float(offset[0]), origin_y_m=grid.origin_y_m + float(offset[1])))
        moved._path = self._path
        return moved


Obstacle = Annotated[
    Union[PolygonObstacle, CircleObstacle, PointsObstacle, OccupancyGridObstacle], Field(discriminator="type")
]


# ---------------------------------------------------------------------------------------------------
# Scenario
# ---------------------------------------------------------------------------------------------------


class Scenario(_Frozen):
    """One planning problem: map, robot, sensor, start, goals in order, and the expected outcome."""

    format: Literal["cvxnav.scenario/1", "cvxnav.scenario/2"]
    name: str = Field(min_length=1, max_length=MAX_NAME_CHARS, pattern=r"^[^\x00-\x1f\x7f]+$", strict=True)
    description: str = Field(default="", max_length=10_000, strict=True)
    bounds: Bounds = None  # type: ignore[assignment]  # /2 with a map: the maps' extent when left out
    robot: Robot
    sensor: Sensor
    start: Pose
    goals: list[Vec2] = Field(min_length=1, max_length=MAX_GOALS)
    goal_tolerance: float = _size(low=1e-3)
    obstacles: list[Obstacle] = Field(default_factory=list, max_length=MAX_OBSTACLES)
    expect: Literal["reach", "no_path"]

    @model_validator(mode="after")
    def _maps_and_bounds(self) -> Scenario:
        grids = [o.grid for o in self.obstacles if o.type == "occupancy_grid"]
        at = [j for j, o in enumerate(self.obstacles) if o.type == "occupancy_grid"]
        if grids and self.format != MAP_SCENARIO_FORMAT:
            raise FieldError(("obstacles", at[0], "type"), f"occupancy_grid needs format {MAP_SCENARIO_FORMAT}, "
                                                          f"got {self.format}")
        if len(grids) > 1:
            raise FieldError(("obstacles", at[1], "type"), f"one occupancy_grid per scenario (obstacles[{at[0]}] is one)")
        for j, grid in zip(at, grids):
            lo, hi = grid.bounds()
            if max(np.abs(lo).max(), np.abs(hi).max()) > MAX_COORDINATE_M:
                raise FieldError(("obstacles", j, "map"), f"the map reaches {lo.tolist()}..{hi.tolist()}, beyond "
                                                          f"±{MAX_COORDINATE_M:g} m")
        if self.bounds is None:
            if not grids:
                raise FieldError(("bounds",), "missing (it may be left out only when the scenario names a map)")
            lo = np.min([g.bounds()[0] for g in grids], axis=0)
            hi = np.max([g.bounds()[1] for g in grids], axis=0)
            object.__setattr__(self, "bounds", Bounds(min=tuple(lo.tolist()), max=tuple(hi.tolist())))
        side = max(self.bounds.max[0] - self.bounds.min[0], self.bounds.max[1] - self.bounds.min[1])
        if side > MAX_EXTENT_M:
            raise FieldError(("bounds",), f"span {side:.6g} m, more than the {MAX_EXTENT_M:g} m a side may have")
        vertices = sum(len(o.vertices) if o.type == "polygon" else len(o.points) if o.type == "points" else 0
                       for o in self.obstacles)
        if vertices > MAX_TOTAL_VERTICES:
            raise FieldError(("obstacles",), f"{vertices} vertices and points in all, more than {MAX_TOTAL_VERTICES}")
        return self

    @model_validator(mode="after")
    def _start_and_goals_free(self) -> Scenario:
        named: list[tuple[tuple[str | int, ...], Vec2]] = [(("start",), (self.start.x, self.start.y))]
        named += [(("goals", i), g) for i, g in enumerate(self.goals)]
        pts = np.array([p for _, p in named], dtype=float)
        inside = self.bounds.contains(pts)
        for (loc, p), ok in zip(named, inside):
            if not ok:
                raise FieldError(loc, f"{list(p)} is outside bounds {self.bounds.shown()}")
        for j, obstacle in enumerate(self.obstacles):
            if obstacle.type == "occupancy_grid":
                inside = obstacle.grid.cells_of(pts)[2]
                for (loc, p), state, within in zip(named, obstacle.grid.state_at(pts), inside):
                    if not within:
                        raise FieldError(loc, f"{list(p)} is beyond obstacles[{j}]'s map ({obstacle.map})")
                    if state != FREE:
                        raise FieldError(loc, f"{list(p)} is in an {STATE_NAMES[state]} cell of obstacles[{j}]'s map "
                                              f"({obstacle.map})")
                # On a cell's edge or corner: a blocked cell a hair away in some direction touches it.
                nudged = pts[:, None, :] + 1e-9 * np.array([[1, 1], [1, -1], [-1, 1], [-1, -1]])
                touching = np.any(obstacle.grid.state_at(nudged.reshape(-1, 2)).reshape(-1, 4) != FREE, axis=1)
                for (loc, p), bad in zip(named, touching):
                    if bad:
                        raise FieldError(loc, f"{list(p)} is on the edge of a blocked cell of obstacles[{j}]'s map "
                                              f"({obstacle.map})")
                continue
            hit = obstacle.distance(pts) <= 0.0
            for (loc, p), bad in zip(named, hit):
                if bad:
                    raise FieldError(loc, f"{list(p)} is inside or on obstacles[{j}] ({obstacle.type})")
        return self

    @model_validator(mode="after")
    def _start_footprint_free(self) -> Scenario:
        """The robot's rectangle at the start lies inside the bounds and touches no obstacle: a run would
        otherwise end in a collision on its first step (the sim judges the footprint, not the centre)."""
        shape = self.footprint(self.start)
        size = f"the robot's {self.robot.length:g} × {self.robot.width:g} m footprint"
        x0, y0, x1, y1 = shape.bounds
        (bx0, by0), (bx1, by1) = self.bounds.min, self.bounds.max
        if not (x0 >= bx0 and y0 >= by0 and x1 <= bx1 and y1 <= by1):
            raise FieldError(("start",), f"{size} leaves bounds {self.bounds.shown()}")
        for j, obstacle in enumerate(self.obstacles):
            if obstacle.type == "occupancy_grid":
                touches = _footprint_on_grid(obstacle.grid, shape)
            elif obstacle.type == "circle":
                touches = shape.distance(shapely.Point(obstacle.center)) <= obstacle.radius
            else:
                touches = shapely.intersects(shape, obstacle.solid())
            if touches:
                raise FieldError(("start",), f"{size} overlaps or touches obstacles[{j}] ({obstacle.type})")
        return self

    def footprint(self, pose: Pose) -> shapely.Polygon:
        """The robot's rectangle at `pose`: `length` along the heading, `width` across, centred on (x, y)."""
        c, s = math.cos(pose.theta), math.sin(pose.theta)
        hl, hw = 0.5 * self.robot.length, 0.5 * self.robot.width
        return shapely.Polygon([(pose.x + c * a - s * b, pose.y + s * a + c * b)
                                for a, b in ((hl, hw), (-hl, hw), (-hl, -hw), (hl, -hw))])

    @property
    def inflation_m(self) -> float:
        """Clearance the centre line keeps from true obstacles: the paper's d_w + d_r."""
        return self.robot.width / 2.0 + self.robot.safety_distance

    @property
    def keep_out_m(self) -> float:
        """Distance from a true obstacle that the footprint centre never goes below: half the footprint's
        diagonal plus half the safety distance, so the footprint, in any heading, stays at least half the
        safety distance clear (the run's hard floor; plans keep the full `inflation_m` wherever they can);
        but never more than `inflation_m`. A car long for its safety distance (Nav2's depot robot, 0.3 ×
        0.6 m with 0.3 m: 0.485 m against 0.45) would otherwise have its own fully clear plans refused by
        the guard; its full margin still keeps its footprint clear in any heading (by d_r − the
        diagonal's excess over the half-width, 0.115 m there).
        """
        return min(math.hypot(self.robot.length, self.robot.width) / 2.0 + self.robot.safety_distance / 2.0,
                   self.inflation_m)

    @property
    def max_curvature(self) -> float:
        """Kinematic bicycle bound κ = tan(δ_max) / L (minimum turn radius L / tan δ_max)."""
        return math.tan(self.robot.max_steering_angle) / self.robot.wheelbase

    @property
    def centre_max_curvature(self) -> float:
        """The tightest curvature the footprint centre can drive: 1 / sqrt(R² + (L/2)²), R = L / tan δ_max.

        The centre sits L/2 ahead of the rear axle, so at full lock it turns on a wider circle than the
        axle's minimum radius R; a centre line planned to `max_curvature` cannot be tracked exactly.
        """
        rear_radius = self.robot.wheelbase / math.tan(self.robot.max_steering_angle)
        return 1.0 / math.hypot(rear_radius, self.robot.wheelbase / 2.0)

    @property
    def goals_array(self) -> FloatArray:
        """Goals as an (m, 2) array, in visiting order."""
        return np.asarray(self.goals, dtype=float).reshape(-1, 2)

    def translated(self, offset: ArrayLike) -> Scenario:
        """The scenario moved by `offset` (x, y) m: bounds, start, goals and every obstacle, headings kept.

        Not validated again: a translation keeps everything validation checks, and the scenario was
        valid. Moving a far scenario to the origin (`services.convert.LocalFrame`) is exact, since x − o
        is for x within a factor two of o (Sterbenz); moving it back rounds each coordinate once.
        """
        d = np.asarray(offset, dtype=float).reshape(2)
        (lo,), (hi,) = _moved([self.bounds.min], d), _moved([self.bounds.max], d)
        (start,) = _moved([(self.start.x, self.start.y)], d)
        return self.model_copy(update=dict(
            bounds=Bounds.model_construct(min=lo, max=hi),
            start=Pose.model_construct(x=start[0], y=start[1], theta=self.start.theta),
            goals=_moved(self.goals, d),
            obstacles=[obstacle.translated(d) for obstacle in self.obstacles],
        ))

    def clearance(self, points: ArrayLike) -> FloatArray:
        """Distance from each point to the nearest true obstacle solid (inf when there are none)."""
        z = _as_points(points)
        out = np.full(len(z), np.inf)
        for obstacle in self.obstacles:
            np.minimum(out, obstacle.distance(z), out=out)
        return out

    def in_collision(self, points: ArrayLike, *, margin_m: float = 0.0) -> NDArray[np.bool_]:
        """True where a point is within `margin_m` of a true solid (inside or on it for the default 0)."""
        return self.clearance(points) <= margin_m


def _footprint_on_grid(grid: OccupancyGrid, shape: shapely.Polygon) -> bool:
    """Whether a polygon touches a blocked cell of the grid, or reaches beyond the map (blocked too): the
    cells under its box, each a square in the grid frame, against the polygon in that frame."""
    corners = grid.to_grid(np.asarray(shape.exterior.coords)[:-1]) / grid.resolution_m
    (i0, j0), (i1, j1) = np.floor(corners.min(axis=0)).astype(int), np.floor(corners.max(axis=0)).astype(int)
    rows, cols = grid.shape
    if i0 < 0 or j0 < 0 or i1 >= cols or j1 >= rows:
        return True
    j, i = np.nonzero(grid.blocked[j0 : j1 + 1, i0 : i1 + 1])
    if not len(i):
        return False
    cells = shapely.box(i + i0, j + j0, i + i0 + 1, j + j0 + 1)
    return bool(np.any(shapely.intersects(shapely.Polygon(corners), cells)))


def parse_scenario(text: str | bytes, *, source: str = "<string>", base_dir: str | Path = ".") -> Scenario:
    """Validate scenario JSON text; any problem raises ScenarioError with one line naming the field. A map
    it names is read relative to `base_dir`."""
    return parse_json_model(Scenario, text, source=source, error=ScenarioError, context={"base_dir": Path(base_dir)},
                            max_items=max(MAX_OBSTACLES, MAX_VERTICES, MAX_GOALS))


def load_scenario(path: str | Path) -> Scenario:
    """Read and validate a scenario file (and any map it names, relative to it); any problem raises
    ScenarioError with one line."""
    text, source = read_text(path, error=ScenarioError, max_bytes=MAX_SCENARIO_BYTES)
    return parse_scenario(text, source=source, base_dir=Path(path).parent)


def bundled_scenario() -> Scenario:
    """The paper's two-goal scenario shipped inside the package, the default for `cvxnav run`."""
    resource = importlib.resources.files("cvxnav") / "data" / BUNDLED_SCENARIO
    return parse_scenario(resource.read_text(encoding="utf-8"), source=BUNDLED_SCENARIO)
