"""ROS 2 messages built for tests, as a robot's nodes would publish them: rosbags' Jazzy types, CDR."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import yaml
from PIL import Image

from services.ros2 import typesupport


def ros(msgtype: str, **fields):
    return typesupport.message_class(msgtype)(**fields)


def stamp(t_s: float):
    sec = math.floor(t_s)
    return ros("builtin_interfaces/msg/Time", sec=sec, nanosec=round((t_s - sec) * 1e9))


def header(t_s: float, frame: str):
    return ros("std_msgs/msg/Header", stamp=stamp(t_s), frame_id=frame)


def pose(x: float, y: float, yaw: float):
    return ros("geometry_msgs/msg/Pose", position=ros("geometry_msgs/msg/Point", x=x, y=y, z=0.0),
               orientation=ros("geometry_msgs/msg/Quaternion", x=0.0, y=0.0, z=math.sin(yaw / 2), w=math.cos(yaw / 2)))


def odometry(*, x: float, y: float, yaw: float, t_s: float, frame: str = "odom", speed: float = 0.0) -> bytes:
    vector = lambda **v: ros("geometry_msgs/msg/Vector3", **{"x": 0.0, "y": 0.0, "z": 0.0, **v})  # noqa: E731
    message = ros("nav_msgs/msg/Odometry", header=header(t_s, frame), child_frame_id="base_link",
                  pose=ros("geometry_msgs/msg/PoseWithCovariance", pose=pose(x, y, yaw), covariance=np.zeros(36)),
                  twist=ros("geometry_msgs/msg/TwistWithCovariance",
                            twist=ros("geometry_msgs/msg/Twist", linear=vector(x=speed), angular=vector()),
                            covariance=np.zeros(36)))
    return typesupport.encode(message, "nav_msgs/msg/Odometry")


def laser_scan(ranges, *, t_s: float, angle_min: float, angle_increment: float, range_max: float = 30.0) -> bytes:
    ranges = np.asarray(ranges, dtype=np.float32)
    message = ros("sensor_msgs/msg/LaserScan", header=header(t_s, "laser"), angle_min=angle_min,
                  angle_max=angle_min + angle_increment * (len(ranges) - 1), angle_increment=angle_increment,
                  time_increment=0.0, scan_time=0.0, range_min=0.05, range_max=range_max, ranges=ranges,
                  intensities=np.zeros(0, dtype=np.float32))
    return typesupport.encode(message, "sensor_msgs/msg/LaserScan")


def goal_pose(*, x: float, y: float, t_s: float, frame: str = "odom") -> bytes:
    message = ros("geometry_msgs/msg/PoseStamped", header=header(t_s, frame), pose=pose(x, y, 0.0))
    return typesupport.encode(message, "geometry_msgs/msg/PoseStamped")


def occupancy_grid(data, *, width: int, height: int, resolution_m: float, origin: tuple[float, float],
                   frame: str = "odom") -> bytes:
    message = ros("nav_msgs/msg/OccupancyGrid", header=header(0.0, frame),
                  info=ros("nav_msgs/msg/MapMetaData", map_load_time=stamp(0.0), resolution=resolution_m, width=width,
                           height=height, origin=pose(*origin, 0.0)),
                  data=np.asarray(data, dtype=np.int8))
    return typesupport.encode(message, "nav_msgs/msg/OccupancyGrid")


def map_server_grid(yaml_path: Path, *, frame: str = "odom", t_s: float = 0.0) -> bytes:
    """The nav_msgs/OccupancyGrid a map server publishes for a trinary map_server map, read here from its
    YAML and image with Pillow (not with `load_map`): the image's top row last, p = (255 − shade) / 255,
    100 above occupied_thresh, map_saver's unknown shade 205 and anything between the thresholds −1, 0 below
    free_thresh."""
    doc = yaml.safe_load(yaml_path.read_text())
    assert doc["mode"] == "trinary" and doc["negate"] == 0
    shade = np.asarray(Image.open(yaml_path.parent / doc["image"]).convert("L"), dtype=float)[::-1]
    p = (255.0 - shade) / 255.0
    data = np.where(p > doc["occupied_thresh"], 100, np.where((p < doc["free_thresh"]) & (shade != 205), 0, -1))
    height, width = shade.shape
    x, y, yaw = doc["origin"]
    message = ros("nav_msgs/msg/OccupancyGrid", header=header(t_s, frame),
                  info=ros("nav_msgs/msg/MapMetaData", map_load_time=stamp(t_s), resolution=doc["resolution"],
                           width=width, height=height, origin=pose(x, y, yaw)),
                  data=data.astype(np.int8).reshape(-1))
    return typesupport.encode(message, "nav_msgs/msg/OccupancyGrid")
