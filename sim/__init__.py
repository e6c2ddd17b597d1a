"""Pure simulator core: kinematic bicycle, range sensor, path tracker and the true world (no I/O)."""

from sim.controller import Command, GoalTracker, PurePursuit
from sim.sensor import Circle, RangeSensor, RayTargets
from sim.vehicle import VehicleLimits, VehicleState, footprint, step
from sim.world import World

__all__ = [
    "Circle",
    "Command",
    "GoalTracker",
    "PurePursuit",
    "RangeSensor",
    "RayTargets",
    "VehicleLimits",
    "VehicleState",
    "World",
    "footprint",
    "step",
]
