"""What a stage accepts from the wire beyond its schema: bounded counts, coordinates within reach.

The schema (``schemas.messages``) already guarantees well-formed, finite numbers. These checks bound
the work one message can cause (points per scan, per cluster set, per path; ellipses per set) and
reject values no honest pipeline produces (a point kilometres outside the map, a robot outside its
bounds, an ellipse a micron wide), each with a one-line ``StageInputError`` so the stage reports it
and keeps its last good output. Every limit derives from the scenario.

They cannot tell a plausible lie from the truth (a well-formed scan of an obstacle that is not
there): keeping such messages off the keys is access control's job (docs/security.md).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from schemas.messages import EllipsoidMsg, Pose2D
from schemas.scenario import Scenario
from services.contract import StageInputError
from services.geometry import FloatArray

DEFAULT_MAX_PAYLOAD_BYTES = 1 << 20  # an input message larger than this is rejected undecoded
MAX_SENSED_POINTS = 50_000  # points the sensing stage remembers; so at most this many per Clusters
MAX_ELLIPSES = 1024  # per Ellipsoids / RawPath message: far above a real map's, far below a stall
MAX_PATH_POINTS = 10_000  # per RawPath / SmoothPath: 1 km at the planner's 0.1 m step
MAX_GOALS = 256  # per Goals message: a tour the planner searches in one plan
MIN_SEMI_AXIS_M = 1e-6


def check_count(count: int, *, limit: int, what: str) -> None:
    if count > limit:
        raise StageInputError(f"{what}: {count} exceeds the limit of {limit}")


@dataclass(frozen=True)
class Reach:
    """The scenario's bounds (where the robot may be) and the extent a sensor at the bounds can see."""

    bounds_min: FloatArray
    bounds_max: FloatArray
    margin_m: float  # the sensor's range: hits may lie that far outside the bounds

    @classmethod
    def of(cls, scenario: Scenario) -> Reach:
        return cls(bounds_min=np.array(scenario.bounds.min, dtype=float),
                   bounds_max=np.array(scenario.bounds.max, dtype=float), margin_m=float(scenario.sensor.range))

    @property
    def diagonal_m(self) -> float:
        return float(np.linalg.norm(self.bounds_max - self.bounds_min)) + 2.0 * self.margin_m

    def check_points(self, points: FloatArray, *, what: str) -> None:
        """Every point within the bounds grown by the sensor range."""
        if len(points) == 0:
            return
        outside = np.any((points < self.bounds_min - self.margin_m) | (points > self.bounds_max + self.margin_m),
                         axis=1)
        if outside.any():
            k = int(np.argmax(outside))
            x, y = points[k]
            raise StageInputError(f"{what}: point {k} ({x:.6g}, {y:.6g}) lies more than {self.margin_m:g} m "
                                  f"outside the map bounds")

    def check_pose(self, pose: Pose2D, *, what: str) -> None:
        """The robot's pose inside the map bounds (the sim ends a run that leaves them)."""
        xy = np.array([pose.x_m, pose.y_m])
        if np.any(xy < self.bounds_min) or np.any(xy > self.bounds_max):
            raise StageInputError(f"{what}: pose ({pose.x_m:.6g}, {pose.y_m:.6g}) is outside the map bounds")

    def check_goals(self, goals: FloatArray, *, what: str) -> None:
        """At most ``MAX_GOALS``, each inside the map bounds (where the robot can be)."""
        check_count(len(goals), limit=MAX_GOALS, what=f"{what}: goals")
        for k, (x, y) in enumerate(np.asarray(goals, dtype=float).reshape(-1, 2).tolist()):
            self.check_pose(Pose2D(x_m=x, y_m=y, theta_rad=0.0), what=f"{what}: goal {k}")

    def check_ellipses(self, ellipses: Sequence[EllipsoidMsg], *, what: str) -> None:
        """At most ``MAX_ELLIPSES``; centres within reach; semi-axes between a micron and the map's size."""
        check_count(len(ellipses), limit=MAX_ELLIPSES, what=f"{what}: ellipses")
        if not ellipses:
            return
        A = np.array([e.A for e in ellipses], dtype=float)
        b = np.array([e.b for e in ellipses], dtype=float)
        eig = np.linalg.eigvalsh(A)  # ascending; the semi-axes are their reciprocals
        bad = (eig[:, 1] > 1.0 / MIN_SEMI_AXIS_M) | (eig[:, 0] < 1.0 / self.diagonal_m)
        if bad.any():
            k = int(np.argmax(bad))
            raise StageInputError(f"{what}: ellipse {k} has semi-axes {1.0 / eig[k, 1]:.3g} m and "
                                  f"{1.0 / eig[k, 0]:.3g} m; they must lie in [{MIN_SEMI_AXIS_M:g}, "
                                  f"{self.diagonal_m:.3g}] m")
        self.check_points(-np.linalg.solve(A, b[:, :, None])[:, :, 0], what=f"{what}: ellipse centres")
