"""Ellipses between their wire and file forms (`EllipsoidMsg`, `EllipseModel`) and the geometry the cores
compute with, and every message and file between the world frame and a core's local frame
(`LocalFrame`): the models know no geometry, so the conversions live here, above both."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, TypeVar

import numpy as np
from pydantic import BaseModel

from schemas.files import EllipseModel, PlanFile, RunFile
from schemas.messages import (
    Clusters,
    EllipsoidMsg,
    Ellipsoids,
    Goals,
    Header,
    Map,
    Pose2D,
    RawPath,
    RobotState,
    Scan,
    SmoothPath,
    StageStatus,
    World,
)
from schemas.occupancy import OccupancyGrid
from schemas.scenario import Scenario
from services.geometry import Ellipse, FloatArray

FRAME_QUANTUM_M = 1000.0  # the local origin is the bounds' lower corner rounded to a multiple of this
_Model = TypeVar("_Model", bound=BaseModel)


def ellipse_to_msg(ellipse: Ellipse, *, group: int, cluster_id: int) -> EllipsoidMsg:
    (a11, a12), (a21, a22) = ellipse.A.tolist()
    # Ellipse symmetrises A; write the mean of the off-diagonals so the message is exactly symmetric.
    off = 0.5 * (a12 + a21)
    return EllipsoidMsg(
        A=((a11, off), (off, a22)), b=tuple(ellipse.b.tolist()), group=group, cluster_id=cluster_id
    )


def ellipses_from_msgs(messages: list[EllipsoidMsg]) -> list[Ellipse]:
    return [Ellipse(A=msg.A, b=msg.b) for msg in messages]


def ellipse_to_model(ellipse: Ellipse) -> EllipseModel:
    """The ellipse as `plan.json` writes it (CONTRACTS §4): A and b as computed."""
    A = ellipse.A.tolist()
    return EllipseModel(A=(tuple(A[0]), tuple(A[1])), b=tuple(ellipse.b.tolist()))


def ellipse_from_model(model: EllipseModel) -> Ellipse:
    return Ellipse(A=model.A, b=model.b)


def grid_to_msg(grid: OccupancyGrid, *, header: Header) -> Map:
    """An occupancy grid as the pipeline's `Map` message (its cells' states, row 0 at the origin's side)."""
    rows, cols = grid.shape
    return Map(header=header, width=cols, height=rows, resolution_m=grid.resolution_m,
               origin=Pose2D(x_m=grid.origin_x_m, y_m=grid.origin_y_m, theta_rad=grid.origin_yaw_rad),
               cells=Map.pack_cells(grid.state.tobytes()))


def grid_from_msg(message: Map) -> OccupancyGrid:
    """The occupancy grid a `Map` message carries."""
    state = np.frombuffer(message.cell_bytes(), dtype=np.uint8).reshape(message.height, message.width)
    o = message.origin
    return OccupancyGrid(state=state, resolution_m=message.resolution_m, origin_x_m=o.x_m, origin_y_m=o.y_m,
                         origin_yaw_rad=o.theta_rad, source="<Map>")


def answer_header(*, scan_header: Header, seq: int) -> Header:
    """Header of a stage output: the scan's stamp (sim time) so every status and output of one scan
    carries the same stamp, and the publishing stage's own sequence number."""
    return Header(stamp_s=scan_header.stamp_s, frame_id=scan_header.frame_id, seq=seq)


# ---------------------------------------------------------------------------------------------------
# The local frame
# ---------------------------------------------------------------------------------------------------


def _points(points: Any, d: FloatArray) -> list[tuple[float, float]]:
    z = np.asarray(points, dtype=float).reshape(-1, 2) + d
    return [(x, y) for x, y in z.tolist()]


def _pose(pose: Pose2D, d: FloatArray) -> Pose2D:
    return pose.model_copy(update={"x_m": pose.x_m + float(d[0]), "y_m": pose.y_m + float(d[1])})


def _ellipsoids(ellipsoids: list[Any], d: FloatArray) -> list[Any]:
    """Ellipses (`EllipsoidMsg`s or `EllipseModel`s) {z : ‖A z + b‖ ≤ 1} moved by d: {z : ‖A z + (b − A d)‖ ≤ 1}."""
    return [e.model_copy(update={"b": tuple((np.asarray(e.b) - np.asarray(e.A) @ d).tolist())}) for e in ellipsoids]


# Per message model, the message moved by d: every coordinate it carries (an unregistered model with
# coordinates would reach a core unmoved, so a frame that is not the identity refuses unregistered ones).
_MOVERS: dict[type, Callable[[Any, FloatArray], Any]] = {
    Scan: lambda m, d: m.model_copy(update={"pose": _pose(m.pose, d), "points": _points(m.points, d)}),
    Clusters: lambda m, d: m.model_copy(update={"clusters": [
        c.model_copy(update={"points": _points(c.points, d)}) for c in m.clusters]}),
    Ellipsoids: lambda m, d: m.model_copy(update={"ellipsoids": _ellipsoids(m.ellipsoids, d)}),
    RawPath: lambda m, d: m.model_copy(update={"points": _points(m.points, d),
                                               "ellipsoids": _ellipsoids(m.ellipsoids, d)}),
    SmoothPath: lambda m, d: m.model_copy(update={"points": _points(m.points, d)}),
    RobotState: lambda m, d: m.model_copy(update={"pose": _pose(m.pose, d)}),
    Goals: lambda m, d: m.model_copy(update={"goals": _points(m.goals, d)}),
    StageStatus: lambda m, d: m,
    Map: lambda m, d: m.model_copy(update={"origin": _pose(m.origin, d)}),
    World: lambda m, d: m.model_copy(update={
        "bounds_min": _points([m.bounds_min], d)[0], "bounds_max": _points([m.bounds_max], d)[0],
        "start": _pose(m.start, d), "goals": _points(m.goals, d),
        "polygons": [_points(polygon, d) for polygon in m.polygons],
        "circles": [c.model_copy(update={"center": _points([c.center], d)[0]}) for c in m.circles]}),
    PlanFile: lambda m, d: m.model_copy(update={
        "path": _points(m.path, d), "raw_path": _points(m.raw_path, d), "ellipsoids": _ellipsoids(m.ellipsoids, d)}),
    RunFile: lambda m, d: m.model_copy(update={
        "trajectory": [(t, x + float(d[0]), y + float(d[1]), theta) for t, x, y, theta in m.trajectory]}),
}


@dataclass(frozen=True)
class LocalFrame:
    """The frame a core computes in: the world frame moved so that the scenario lies near its origin.

    world = local + `origin`. Coordinates far from the origin (a map in UTM metres, 10⁶–10⁷ m) keep
    only ulp(x) ≈ 2e-16 |x| of resolution, and a core squares and differences them (b = −A c of an
    ellipse at 10⁷ m is 10⁷/r; fits, solves and route searches lose their digits or fail: no_path at
    10⁶–10⁸ m, `LinAlgError` at 10⁹). So every core works in the local frame, and the edges convert:
    the shell moves each message it decodes for a core by −origin and each one the core publishes by
    +origin (`services.shell.stage`), the core is built from `scenario_to_local`, and `cvxnav plan`
    plans the local scenario and moves the plan back (`cvxnav.plan`). So a scenario moved by 10⁶ m
    plans as at home: exactly, when the move loses no digit of its coordinates (docs/contracts.md).

    The origin is the scenario's bounds' lower corner rounded to a multiple of `FRAME_QUANTUM_M`: an
    integer, so x − origin is exact for every x within a factor two of it (Sterbenz), and 0 for every
    scenario within 500 m of the world's origin, which therefore runs exactly as before.
    """

    origin: tuple[float, float] = (0.0, 0.0)

    @classmethod
    def of(cls, scenario: Scenario) -> LocalFrame:
        corner = np.round(np.asarray(scenario.bounds.min, dtype=float) / FRAME_QUANTUM_M) * FRAME_QUANTUM_M
        return cls(origin=(float(corner[0]) + 0.0, float(corner[1]) + 0.0))  # + 0.0: no −0.0

    @property
    def identity(self) -> bool:
        return self.origin == (0.0, 0.0)

    def scenario_to_local(self, scenario: Scenario) -> Scenario:
        return scenario if self.identity else scenario.translated(-np.asarray(self.origin))

    def to_local(self, message: _Model) -> _Model:
        """A message (or file) in the world frame, moved into this one."""
        return message if self.identity else self._move(message, -np.asarray(self.origin))

    def to_world(self, message: _Model) -> _Model:
        """A message (or file) in this frame, moved into the world frame."""
        return message if self.identity else self._move(message, np.asarray(self.origin))

    @staticmethod
    def _move(message: _Model, d: FloatArray) -> _Model:
        mover = _MOVERS.get(type(message))
        if mover is None:
            raise TypeError(f"no local-frame conversion for {type(message).__name__}: register it in _MOVERS")
        return mover(message, d)
