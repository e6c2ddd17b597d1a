"""Pure simulator core: the range sensor and the true world the simulated car drives in (no I/O).

The car itself, its path tracker and its path guard are `services.drive`'s: the ROS 2 bridge drives a
real robot with the same ones.
"""

from sim.sensor import Circle, RangeSensor, RayTargets
from sim.world import World

__all__ = [
    "Circle",
    "RangeSensor",
    "RayTargets",
    "World",
]
