"""Output files `cvxnav.plan/2` (and `/1`, still read) and `cvxnav.run/2` (and `/1`, still read) (CONTRACTS §4)
as frozen pydantic models.

Writers and readers share these models, so a file that `read` accepts is exactly what `write` produces:
finite numbers, no unknown fields, the format string pinned.

`cvxnav.run/2` is `cvxnav.run/1` with two changes. `min_clearance` may be `null`: the world had no
obstacle to measure a clearance from (`/1` could not say so, and a run in an empty world wrote no valid
file). And one more status, `interrupted`: the run was stopped (SIGINT or SIGTERM of `cvxnav run` or of
the sim, or the death of its supervisor) before it reached an outcome; `cvxnav run` then exits with 130.
Its `latency_ms` counts every scan sent, an unanswered one as the time until the next answer to it or a
later scan (or until the run ended).
"""

from __future__ import annotations

from pathlib import Path
from typing import Literal, TypeVar

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator

from schemas.scenario import FieldError, Real, Vec2, parse_json_model, read_text

PLAN_FORMAT = "cvxnav.plan/2"  # /2: `timings_ms` gains `load` and `corridor`, the file `reason`
RUN_FORMAT = "cvxnav.run/2"  # /2: `min_clearance` null when there is no obstacle; the status `interrupted`
RUN_FORMATS = ("cvxnav.run/1", RUN_FORMAT)  # read; the newest is written

MAX_OUTPUT_BYTES = 256 << 20  # a plan or run file larger than this is not one cvxnav wrote
Pair = tuple[Real, Real]

_File = TypeVar("_File", bound="_OutputFile")


class OutputFileError(ValueError):
    """A plan or run file that cannot be read; `str()` is one line naming the file, the field and the reason."""


class _Frozen(BaseModel):
    model_config = ConfigDict(frozen=True, extra="forbid", allow_inf_nan=False)


class _OutputFile(_Frozen):
    def write(self, path: str | Path) -> None:
        """Write as JSON (indent 1, like the scenario files)."""
        Path(path).write_text(self.model_dump_json(indent=1) + "\n", encoding="utf-8")

    @classmethod
    def read(cls: type[_File], path: str | Path) -> _File:
        """Read and validate; any problem raises OutputFileError with one line."""
        text, source = read_text(path, error=OutputFileError, max_bytes=MAX_OUTPUT_BYTES)
        return parse_json_model(cls, text, source=source, error=OutputFileError)


class EllipseModel(_Frozen):
    """One ellipse in the paper's form {z : ‖A z + b‖₂ ≤ 1}; A must be symmetric positive definite."""

    A: tuple[Pair, Pair]
    b: Pair  # −A·centre: not a coordinate, far larger than one for a thin ellipse far from the origin

    @model_validator(mode="after")
    def _positive_definite(self) -> EllipseModel:
        (a11, a12), (a21, a22) = self.A
        if abs(a12 - a21) > 1e-9 * max(1.0, abs(a11), abs(a22)):
            raise FieldError(("A",), f"must be symmetric, got A[0][1]={a12} and A[1][0]={a21}")
        if not (a11 > 0.0 and a11 * a22 - a12 * a21 > 0.0):
            raise FieldError(("A",), "must be positive definite")
        return self


class PlanTimings(_Frozen):
    """Wall time per pipeline stage in milliseconds: load → corridor → cluster → fit → group → optimise →
    smooth, and their total (`load`, reading the scenario and its map, included: the time a user waits).

    `corridor` is the coarse search on an occupancy grid; `load` and `corridor` are new in
    `cvxnav.plan/2` (a `/1` file has neither, and reads as 0).
    """

    load: float = Field(default=0.0, ge=0)
    corridor: float = Field(default=0.0, ge=0)
    cluster: float = Field(ge=0)
    fit: float = Field(ge=0)
    group: float = Field(ge=0)
    optimize: float = Field(ge=0)
    smooth: float = Field(ge=0)
    total: float = Field(ge=0)


class PlanFile(_OutputFile):
    """`cvxnav plan` output: the smoothed centre line, the raw path, and the inflated ellipses it avoids."""

    format: Literal["cvxnav.plan/1", "cvxnav.plan/2"] = PLAN_FORMAT
    scenario: str
    status: Literal["ok", "no_path"]
    path: list[Vec2]
    raw_path: list[Vec2]
    ellipsoids: list[EllipseModel]
    timings_ms: PlanTimings
    reason: str = ""  # why there is no path (new in /2)

    @model_validator(mode="after")
    def _versioned(self) -> PlanFile:
        if self.format == PLAN_FORMAT:
            missing = [k for k in ("load", "corridor") if k not in self.timings_ms.model_fields_set]
            if missing:
                raise FieldError(("timings_ms", missing[0]), f"missing (required in {PLAN_FORMAT})")
        elif self.reason or {"load", "corridor"} & self.timings_ms.model_fields_set:
            raise FieldError(("format",), f"{self.format} has no reason, load or corridor: the file is {PLAN_FORMAT}")
        return self


class LatencyStats(_Frozen):
    """Sensor scan → smoothed path received by the sim, in milliseconds."""

    p50: float = Field(ge=0)
    p99: float = Field(ge=0)
    max: float = Field(ge=0)


class RunFile(_OutputFile):
    """`cvxnav run` output: one trajectory row [t_s, x, y, theta] per simulation step, and the outcome."""

    format: Literal["cvxnav.run/1", "cvxnav.run/2"] = RUN_FORMAT
    scenario: str
    status: Literal["reached", "no_path", "timeout", "collision", "interrupted"]
    goals_reached: int = Field(ge=0)
    trajectory: list[tuple[float, float, float, float]]
    replans: int = Field(ge=0)
    latency_ms: LatencyStats
    min_clearance: float | None  # the footprint's least distance to an obstacle; None: there is none

    @model_validator(mode="after")
    def _new_in_run_2(self) -> RunFile:
        if self.format == "cvxnav.run/1":
            if self.min_clearance is None:
                raise FieldError(("min_clearance",), f"null is new in {RUN_FORMAT}")
            if self.status == "interrupted":
                raise FieldError(("status",), f"interrupted is new in {RUN_FORMAT}")
        return self

    def backed_out(self) -> tuple[int, float]:
        """How many times, and how far in all (m), the car moved against its heading: backing out of
        dead ends along its tracks (`sim.core`)."""
        traj = np.asarray(self.trajectory, dtype=float).reshape(-1, 4)
        along = np.einsum("ij,ij->i", np.diff(traj[:, 1:3], axis=0),
                          np.column_stack([np.cos(traj[:-1, 3]), np.sin(traj[:-1, 3])]))
        back = along < -1e-9
        starts = back & ~np.concatenate([[False], back[:-1]])
        return int(np.count_nonzero(starts)), float(np.sum(-along[back]))
