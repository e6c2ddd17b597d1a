"""A scenario for Nav2's depot robot (0.3 × 0.6 m, safety 0.3 m: a margin of 0.45 m, the guard's floor as
much) with no obstacles of its own: the tests that hand a stage its inputs by hand build on it."""

from __future__ import annotations

import json

from schemas.scenario import Scenario, parse_scenario


def depot_car_scenario(*, bounds: tuple[tuple[float, float], tuple[float, float]], start: tuple[float, float, float],
                       goals: list[tuple[float, float]]) -> Scenario:
    doc = {"format": "cvxnav.scenario/1", "name": "depot-car",
           "bounds": {"min": list(bounds[0]), "max": list(bounds[1])},
           "robot": {"width": 0.3, "length": 0.6, "wheelbase": 0.6, "safety_distance": 0.3, "max_speed": 1.0,
                     "max_steering_angle": 0.6, "max_steering_rate": 0.5},
           "sensor": {"fov_deg": 180, "range": 5.0, "rays": 181, "rate_hz": 10}, "goal_tolerance": 0.3,
           "start": {"x": start[0], "y": start[1], "theta": start[2]}, "goals": [list(g) for g in goals],
           "obstacles": [], "expect": "reach"}
    return parse_scenario(json.dumps(doc), source="depot-car")
