"""The bridge's ROS 2 interface (CONTRACTS.md §6), declared once: topic, type, direction, QoS.

Topic names are relative, so ``--namespace NS`` puts every one under ``/NS`` as rclcpp would. The QoS
profiles are the usual ones for each topic on a Nav2 robot (sensor data for /scan, latched for /map,
rclcpp's default otherwise); over Zenoh any publisher reaches any subscription whatever their QoS
(rmw_zenoh ``docs/design.md``, "Quality of Service"), so they serve ``ros2 topic info -v`` and decide
only where a late joiner needs history (transient local).

Each input has a payload cap the shell holds it to before the bridge decodes it: the shell's default
(1 MiB, ample for a LaserScan of tens of thousands of rays), and for /map a grid of `MAX_MAP_CELLS`.
"""

from __future__ import annotations

from dataclasses import dataclass
from types import MappingProxyType
from typing import Literal, Mapping

from services.limits import DEFAULT_MAX_PAYLOAD_BYTES
from services.ros2.typesupport import type_hash
from services.ros2.wire import LATCHED_QOS, SENSOR_DATA_QOS, QosProfile

BRIDGE_NODE = "cvxnav_bridge"
MAX_MAP_CELLS = 4096 * 4096  # a /map larger than this is refused (16 MiB of int8)
_MAP_HEADER_BYTES = 4096  # an OccupancyGrid's header, frame and metadata, far more than they take


@dataclass(frozen=True)
class RosTopic:
    """One topic of the bridge: a relative ROS name, its interface type and which way it goes."""

    name: str
    msgtype: str
    direction: Literal["in", "out"]
    qos: QosProfile = QosProfile()
    max_payload_bytes: int = DEFAULT_MAX_PAYLOAD_BYTES  # an input sample larger than this is refused undecoded

    @property
    def type_hash(self) -> str:
        """RIHS01 of the type in Jazzy's definitions, computed by rosbags (never written down)."""
        return type_hash(self.msgtype)


BRIDGE_TOPICS: Mapping[str, RosTopic] = MappingProxyType(
    {
        topic.name: topic
        for topic in (
            RosTopic(name="scan", msgtype="sensor_msgs/msg/LaserScan", direction="in", qos=SENSOR_DATA_QOS),
            RosTopic(name="odom", msgtype="nav_msgs/msg/Odometry", direction="in"),
            RosTopic(name="goal_pose", msgtype="geometry_msgs/msg/PoseStamped", direction="in"),
            RosTopic(name="map", msgtype="nav_msgs/msg/OccupancyGrid", direction="in", qos=LATCHED_QOS,
                     max_payload_bytes=MAX_MAP_CELLS + _MAP_HEADER_BYTES),
            RosTopic(name="plan", msgtype="nav_msgs/msg/Path", direction="out"),
            RosTopic(name="cmd_vel", msgtype="geometry_msgs/msg/Twist", direction="out"),
        )
    }
)
