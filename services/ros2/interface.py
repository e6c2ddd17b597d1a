"""The bridge's ROS 2 interface (CONTRACTS.md §6), declared once: topic, type, direction, QoS.

Topic names are relative, so ``--namespace NS`` puts every one under ``/NS`` as rclcpp would. The QoS
profiles are the usual ones for each topic on a Nav2 robot (sensor data for /scan, latched for /map,
rclcpp's default otherwise); over Zenoh any publisher reaches any subscription whatever their QoS
(rmw_zenoh ``docs/design.md``, "Quality of Service"), so they serve ``ros2 topic info -v`` and decide
only where a late joiner needs history (transient local).
"""

from __future__ import annotations

from dataclasses import dataclass
from types import MappingProxyType
from typing import Literal, Mapping

from services.ros2.typesupport import type_hash
from services.ros2.wire import LATCHED_QOS, SENSOR_DATA_QOS, QosProfile

BRIDGE_NODE = "cvxnav_bridge"


@dataclass(frozen=True)
class RosTopic:
    """One topic of the bridge: a relative ROS name, its interface type and which way it goes."""

    name: str
    msgtype: str
    direction: Literal["in", "out"]
    qos: QosProfile = QosProfile()

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
            RosTopic(name="map", msgtype="nav_msgs/msg/OccupancyGrid", direction="in", qos=LATCHED_QOS),
            RosTopic(name="plan", msgtype="nav_msgs/msg/Path", direction="out"),
            RosTopic(name="cmd_vel", msgtype="geometry_msgs/msg/Twist", direction="out"),
        )
    }
)
