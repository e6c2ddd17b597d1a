"""The car and how it is driven, for the sim and the ROS 2 bridge alike (pure, no I/O): the kinematic
bicycle (`vehicle`), the path tracker (`controller`) and the check of every path before it is followed
(`guard`)."""

from services.drive.controller import Command, GoalTracker, PurePursuit
from services.drive.vehicle import VehicleLimits, VehicleState, footprint, step

__all__ = [
    "Command",
    "GoalTracker",
    "PurePursuit",
    "VehicleLimits",
    "VehicleState",
    "footprint",
    "step",
]
