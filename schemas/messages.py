"""The messages the cvxnav stages exchange over Zenoh (CONTRACTS.md §5).

Every top-level message is a frozen pydantic model that rejects unknown fields and non-finite
numbers, and carries a namespaced, versioned schema name (``SCHEMA``/``VERSION``) that travels in
the Zenoh encoding as ``application/json;cvxnav.<Model>/<version>``. Changing a model's fields is a
versioned change: bump ``VERSION``.

Ellipsoids are in the paper's form {z : ||A z + b||_2 <= 1} with A symmetric positive definite.
"""

from __future__ import annotations

import base64
import binascii
import zlib
from typing import Annotated, ClassVar, Literal, TypeVar

from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from schemas.occupancy import FREE, MAX_CELLS, OCCUPIED, UNKNOWN

# A world-frame point [x, y] in metres; JSON carries it as a two-element array.
Point = tuple[float, float]
NonNegativeInt = Annotated[int, Field(ge=0)]
Status = Literal["ok", "no_path"]

_SYMMETRY_RTOL = 1e-9
MAP_CELL_STATES = bytes((FREE, OCCUPIED, UNKNOWN))  # a Map's cell bytes


class _Frozen(BaseModel):
    """Shared config: immutable, no unknown fields, finite floats only (also inside lists)."""

    model_config = ConfigDict(frozen=True, extra="forbid", allow_inf_nan=False)


class Message(_Frozen):
    """A top-level message: one per Zenoh key, named and versioned."""

    SCHEMA: ClassVar[str]
    VERSION: ClassVar[int]

    @classmethod
    def schema_id(cls) -> str:
        """``cvxnav.<Model>/<version>``: the schema suffix of the Zenoh encoding."""
        return f"{cls.SCHEMA}/{cls.VERSION}"

    @classmethod
    def encoding(cls) -> str:
        """The Zenoh encoding string, e.g. ``application/json;cvxnav.Scan/1``."""
        return f"application/json;{cls.schema_id()}"

    def to_json_bytes(self) -> bytes:
        return self.model_dump_json().encode()


class Header(_Frozen):
    """Stamp of a message: sim time in seconds, frame, and the publisher's sequence number."""

    stamp_s: float = Field(ge=0.0)
    frame_id: str = "map"
    seq: NonNegativeInt


class Pose2D(_Frozen):
    x_m: float
    y_m: float
    theta_rad: float


class Scan(Message):
    """Range-sensor hits in the world frame, taken from ``pose`` (the point cap is stage config)."""

    SCHEMA: ClassVar[str] = "cvxnav.Scan"
    VERSION: ClassVar[int] = 1

    header: Header
    pose: Pose2D
    points: list[Point]


class ClusterMsg(_Frozen):
    cluster_id: int
    points: list[Point] = Field(min_length=1)
    solid: bool = False


class Clusters(Message):
    SCHEMA: ClassVar[str] = "cvxnav.Clusters"
    VERSION: ClassVar[int] = 1

    header: Header
    scan_seq: NonNegativeInt
    clusters: list[ClusterMsg]


class EllipsoidMsg(_Frozen):
    """{z : ||A z + b||_2 <= 1}; A must be symmetric positive definite (a bounded, solid ellipse)."""

    A: tuple[Point, Point]
    b: Point
    group: int
    cluster_id: int

    @field_validator("A")
    @classmethod
    def _symmetric_positive_definite(cls, a: tuple[Point, Point]) -> tuple[Point, Point]:
        (a11, a12), (a21, a22) = a
        scale = max(abs(a11), abs(a12), abs(a21), abs(a22))
        if abs(a12 - a21) > _SYMMETRY_RTOL * scale:
            raise ValueError(f"A must be symmetric, got A12={a12!r} != A21={a21!r}")
        # Sylvester's criterion for a symmetric 2x2 matrix.
        if not (a11 > 0.0 and a11 * a22 - a12 * a21 > 0.0):
            raise ValueError("A must be positive definite")
        return a


class Ellipsoids(Message):
    SCHEMA: ClassVar[str] = "cvxnav.Ellipsoids"
    VERSION: ClassVar[int] = 1

    header: Header
    scan_seq: NonNegativeInt
    inflation_m: float = Field(ge=0.0)
    ellipsoids: list[EllipsoidMsg]


class RawPath(Message):
    """The planner's piecewise-linear path, with the ellipsoids it avoided so the smoother can verify."""

    SCHEMA: ClassVar[str] = "cvxnav.RawPath"
    VERSION: ClassVar[int] = 3  # 2: plan_id and reason; 3: replanning

    header: Header
    scan_seq: NonNegativeInt
    status: Status
    goal_index: NonNegativeInt
    points: list[Point]
    ellipsoids: list[EllipsoidMsg]
    # Bumped by the planner on every replan (a re-published, trimmed plan keeps its id), so a
    # consumer can count replans without comparing paths.
    plan_id: NonNegativeInt = 0
    reason: str = ""  # why there is no path (status no_path); empty otherwise
    # no_path for now, with no verdict yet: a replan goes on in the background (to the sim, as if the
    # answer were still to come: no brake, no back-out, as from a no_path verdict)
    replanning: bool = False


class SmoothPath(Message):
    """The smoothed centre line; ``min_level`` = min over the curve of ||A z + b|| (> 1 is clear)."""

    SCHEMA: ClassVar[str] = "cvxnav.SmoothPath"
    VERSION: ClassVar[int] = 3  # 2: plan_id and reason; 3: replanning

    header: Header
    scan_seq: NonNegativeInt
    status: Status
    goal_index: NonNegativeInt
    points: list[Point]
    max_curvature: float = Field(ge=0.0)
    min_level: float
    plan_id: NonNegativeInt = 0  # the RawPath's plan_id this curve smooths
    reason: str = ""  # why there is no path (status no_path); empty otherwise
    replanning: bool = False  # the RawPath's: no_path with no verdict yet, a replan under way


class RobotState(Message):
    SCHEMA: ClassVar[str] = "cvxnav.RobotState"
    VERSION: ClassVar[int] = 1

    header: Header
    pose: Pose2D
    speed_mps: float
    steering_rad: float
    goal_index: NonNegativeInt
    goals_reached: NonNegativeInt
    done: bool


class Goals(Message):
    """The goals to drive to, in order, replacing the scenario's (from a robot's ``/goal_pose``, via the
    ROS 2 bridge). A ``RobotState``'s ``goal_index`` and ``goals_reached`` count in the newest list."""

    SCHEMA: ClassVar[str] = "cvxnav.Goals"
    VERSION: ClassVar[int] = 1

    header: Header
    goals: list[Point] = Field(min_length=1)


class StageStatus(Message):
    """Published by every stage after each input: ``error`` names what was rejected and why.

    ``input_stamp_s`` is the stamp of the input this status judges, ``None`` when there is none (a
    timer tick) or it could not be decoded: a consumer that waits for the verdict on one scan (the
    sim) matches on it, so garbage published on a key is never taken for a verdict on a real scan.
    """

    SCHEMA: ClassVar[str] = "cvxnav.StageStatus"
    VERSION: ClassVar[int] = 2  # 2: input_stamp_s

    header: Header
    stage: str
    state: Literal["ok", "error"]
    reason: str = ""
    input_key: str | None = None
    input_stamp_s: float | None = None
    processing_ms: float = Field(ge=0.0)


class CircleMsg(_Frozen):
    center: Point
    radius_m: float = Field(gt=0.0)


class World(Message):
    """The true map, from the sim: for the monitor and plots only (the planning stages must sense it).

    Published once when the sim starts and served on request to late joiners; polygons are the
    obstacles' outlines (a point obstacle's convex hull), circles stay exact.
    """

    SCHEMA: ClassVar[str] = "cvxnav.World"
    VERSION: ClassVar[int] = 1

    header: Header
    scenario: str
    bounds_min: Point
    bounds_max: Point
    robot_width_m: float = Field(gt=0.0)
    robot_length_m: float = Field(gt=0.0)
    start: Pose2D
    goals: list[Point]
    goal_tolerance_m: float = Field(gt=0.0)
    polygons: list[list[Point]]
    circles: list[CircleMsg]


class Map(Message):
    """An occupancy grid to plan on (a robot's /map, from the ROS 2 bridge), in the pipeline's frame.

    ``cells`` holds ``height`` rows of ``width`` cells, row 0 at the origin's side and cell (0, 0) first,
    as nav_msgs/OccupancyGrid orders them; each cell one byte, its state as `schemas.occupancy` has it
    (0 free, 1 occupied, 2 unknown), the bytes zlib-compressed and base64-encoded: a building's map is tens of
    kilobytes (ACES, 1.4 M cells: 68 kB), within the pipeline's payload cap. ``origin`` is the pose of
    cell (0, 0)'s outer corner. The cells are checked on decoding: base64, a zlib stream that inflates
    to exactly width × height bytes (never more is inflated), every byte a state.
    """

    SCHEMA: ClassVar[str] = "cvxnav.Map"
    VERSION: ClassVar[int] = 1

    header: Header
    width: int = Field(ge=1)
    height: int = Field(ge=1)
    resolution_m: float = Field(gt=0.0)
    origin: Pose2D
    cells: str

    @model_validator(mode="after")
    def _cells_decode(self) -> Map:
        self.cell_bytes()
        return self

    def cell_bytes(self) -> bytes:
        """The cells, row-major: one state byte each; ValueError (one line) when they are not that."""
        count = self.width * self.height
        if count > MAX_CELLS:
            raise ValueError(f"{self.width} x {self.height} cells is more than the {MAX_CELLS} a map may have")
        try:
            packed = base64.b64decode(self.cells, validate=True)
            inflate = zlib.decompressobj()
            data = inflate.decompress(packed, count + 1)  # one more than needed tells a longer stream
        except (binascii.Error, zlib.error) as error:
            raise ValueError(f"cells: not base64 of a zlib stream ({error})") from None
        if len(data) != count:
            got = f"more than {count}" if len(data) > count else str(len(data))
            raise ValueError(f"cells: {got} bytes for a {self.width} x {self.height} grid (needs {count})")
        if not inflate.eof or inflate.unused_data:
            raise ValueError("cells: not one whole zlib stream (truncated, or data after its end)")
        if data.translate(None, MAP_CELL_STATES):
            raise ValueError("cells: a byte that is not 0 (free), 1 (occupied) or 2 (unknown)")
        return data

    @classmethod
    def pack_cells(cls, data: bytes) -> str:
        """State bytes (row-major) as ``cells`` carries them."""
        return base64.b64encode(zlib.compress(data, 6)).decode("ascii")


MESSAGE_MODELS: tuple[type[Message], ...] = (
    Scan,
    Clusters,
    Ellipsoids,
    RawPath,
    SmoothPath,
    RobotState,
    Goals,
    StageStatus,
    World,
    Map,
)


M = TypeVar("M", bound=Message)


class DecodeError(ValueError):
    """A payload that is not a valid message of the expected schema; the text is one line."""


# The encodings a payload may carry: JSON, or Zenoh's default (a sender that named none).
_ACCEPTED_MIME = ("application/json", "zenoh/bytes")


def _split_encoding(encoding: str) -> tuple[str, str | None]:
    mime, sep, schema = encoding.partition(";")
    return mime, (schema if sep else None)


def _one_line(error: ValidationError) -> str:
    errors = error.errors(include_url=False)
    first = errors[0]
    if first["type"] == "json_invalid":
        return f"invalid JSON: {first['ctx']['error']}"
    field = ".".join(str(part) for part in first["loc"]) or "<root>"
    more = f" (+{len(errors) - 1} more)" if len(errors) > 1 else ""
    return f"{field}: {first['msg']}{more}"


def decode(model_cls: type[M], payload: bytes, *, encoding: str | None = None) -> M:
    """Validate ``payload`` as ``model_cls``; raise ``DecodeError`` with a one-line reason.

    When the sender's Zenoh ``encoding`` names a cvxnav schema, it must be this model's schema and
    version; a payload without a schema suffix is judged by its content alone. An encoding other
    than JSON (or Zenoh's default, which a sender that names none gets) is rejected.
    """
    mime, schema = _split_encoding(encoding) if encoding else (None, None)
    if mime is not None and mime not in _ACCEPTED_MIME:
        raise DecodeError(f"wrong encoding: expected application/json;{model_cls.schema_id()}, got {encoding[:80]}")
    if schema is not None and schema.startswith("cvxnav.") and schema != model_cls.schema_id():
        raise DecodeError(f"wrong schema: expected {model_cls.schema_id()}, got {schema[:80]}")
    try:
        return model_cls.model_validate_json(payload)
    except ValidationError as error:
        raise DecodeError(f"{model_cls.schema_id()}: {_one_line(error)}") from None


def encode(message: Message) -> bytes:
    return message.to_json_bytes()
