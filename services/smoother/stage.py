"""The smoother stage core: RawPath → SmoothPath, verified on the continuous curve.

A curve that fails verification is never published: the core raises `StageInputError` with the
verification's reason, the stage reports it on its status key, and the previous good path stays in
force at the sim. A `no_path` RawPath passes through as a `no_path` SmoothPath with its reason.

The smoothing function is a parameter (`SmoothFn`), so an alternative smoother (e.g.
`services.smoother.coarse`) reuses this shell and the same verification.

A RawPath is bounded before any work (``services.limits``): at most ``MAX_PATH_POINTS`` points, all
within the map's reach, and an ellipse set bounded in size and reach. New ``Goals`` (a robot's
/goal_pose, from the ROS 2 bridge) replace the scenario's, as in the planner.
"""

from __future__ import annotations

import sys
from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np
from pydantic import BaseModel

from schemas.messages import Goals, RawPath, SmoothPath
from schemas.scenario import Scenario
from services.contract import Outputs, StageInputError
from services.convert import answer_header, ellipses_from_msgs
from services.geometry import FloatArray, polyline_length, resample_polyline
from services.limits import MAX_PATH_POINTS, Reach, check_count
from services.smoother.core import Smoothed, smooth

SmoothFn = Callable[..., Smoothed]  # same keywords as services.smoother.core.smooth
_MIN_CONTROL_POINTS = 4  # a cubic B-spline needs four


@dataclass(frozen=True)
class SmootherConfig:
    goals: FloatArray
    goal_tolerance_m: float
    bounds_min: FloatArray
    bounds_max: FloatArray
    max_curvature: float  # the footprint centre's (Scenario.centre_max_curvature): the sim drives the centre
    reach: Reach
    output_spacing_m: float = 0.05  # CONTRACTS §4: the path is sampled at most 0.05 m apart

    @classmethod
    def from_scenario(cls, scenario: Scenario) -> SmootherConfig:
        return cls(
            goals=scenario.goals_array,
            goal_tolerance_m=float(scenario.goal_tolerance),
            bounds_min=np.array(scenario.bounds.min, dtype=float),
            bounds_max=np.array(scenario.bounds.max, dtype=float),
            max_curvature=scenario.centre_max_curvature,
            reach=Reach.of(scenario),
        )


class SmootherStage:
    def __init__(self, *, config: SmootherConfig, smooth_fn: SmoothFn = smooth) -> None:
        self.config = config
        self.smooth_fn = smooth_fn
        self._seq = 0

    @classmethod
    def from_scenario(cls, scenario: Scenario) -> SmootherStage:
        return cls(config=SmootherConfig.from_scenario(scenario))

    def process(self, *, topic: str, message: BaseModel, now_s: float) -> Outputs:
        if isinstance(message, Goals):
            goals = np.asarray(message.goals, dtype=float).reshape(-1, 2)
            self.config.reach.check_goals(goals, what="goals")
            self.config = replace(self.config, goals=goals)
            return []
        if not isinstance(message, RawPath):
            raise StageInputError(f"smoother does not handle {topic!r}")
        config = self.config
        check_count(len(message.points), limit=MAX_PATH_POINTS, what="raw path points")
        config.reach.check_points(np.asarray(message.points, dtype=float).reshape(-1, 2), what="raw path")
        config.reach.check_ellipses(message.ellipsoids, what="raw path")
        header = answer_header(scan_header=message.header, seq=self._seq)
        common = dict(header=header, scan_seq=message.scan_seq, goal_index=message.goal_index,
                      plan_id=message.plan_id)
        if message.status == "no_path":
            self._seq += 1
            return [("smooth_path", SmoothPath(status="no_path", points=[], max_curvature=0.0, min_level=0.0,
                                               reason=message.reason, replanning=message.replanning, **common))]
        if message.goal_index >= len(config.goals):
            raise StageInputError(f"goal_index {message.goal_index} but the scenario has {len(config.goals)} goals")
        control = np.asarray(message.points, dtype=float).reshape(-1, 2)
        if len(control) < 2:
            raise StageInputError(f"raw path has {len(control)} points, needs at least 2")
        if len(control) < _MIN_CONTROL_POINTS:
            length = polyline_length(control)
            if length <= 0.0:
                raise StageInputError("raw path has zero length")
            control = resample_polyline(control, max_spacing_m=length / _MIN_CONTROL_POINTS)
        smoothed = self.smooth_fn(
            control,
            ellipses=ellipses_from_msgs(message.ellipsoids),
            max_curvature=config.max_curvature,
            # The planner imposes the robot's heading on a new plan; a re-published plan is trimmed
            # to start one vertex behind the robot, where no heading is defined, so none is checked.
            heading_rad=None,
            goals=config.goals[message.goal_index:],
            goal_tolerance_m=config.goal_tolerance_m,
            bounds_min=config.bounds_min,
            bounds_max=config.bounds_max,
            output_spacing_m=config.output_spacing_m,
        )
        verification = smoothed.verification
        if not verification.ok:
            raise StageInputError(f"smoothed path rejected (plan {message.plan_id}): {verification.reason}")
        self._seq += 1
        return [("smooth_path", SmoothPath(
            status="ok",
            points=[(float(x), float(y)) for x, y in smoothed.points],
            max_curvature=verification.max_curvature,
            # No ellipses: verify reports inf; the wire carries finite numbers only.
            min_level=min(verification.min_level, sys.float_info.max),
            **common,
        ))]
