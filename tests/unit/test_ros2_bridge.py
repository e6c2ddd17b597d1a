"""The ROS 2 bridge core on the real ACES laser log and on messages built to break it.

The ACES messages are read with mcap-ros2-support (``ros2_bag``), not with rosbags, which the bridge
decodes with: the expected hits are computed here from that second decoder's fields, ray by ray.
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from ros2_bag import Recorded, aces_bag_dir, independent_decoder, read_mcap
from schemas.messages import EllipsoidMsg, Ellipsoids, Header, SmoothPath
from schemas.scenario import load_scenario
from services.ros2 import typesupport
from services.ros2.bridge import BridgeConfig, Ros2Bridge, body_twist
from services.ros2.interface import BRIDGE_TOPICS
from sim.vehicle import VehicleState, step

SCENARIO = Path(__file__).resolve().parents[1] / "data" / "aces-bridge.json"


@pytest.fixture(scope="module")
def aces(shared_dir) -> list[Recorded]:
    return read_mcap(aces_bag_dir(shared_dir) / "aces-bag.mcap")


@pytest.fixture(scope="module")
def scenario():
    return load_scenario(SCENARIO)


@pytest.fixture
def bridge(scenario) -> Ros2Bridge:
    return Ros2Bridge(config=BridgeConfig.from_scenario(scenario))


def feed(bridge: Ros2Bridge, recorded: Recorded):
    topic = recorded.topic.strip("/")
    return bridge.receive(topic=topic, key_expr=bridge.keys[topic], payload=recorded.data,
                          received_s=recorded.log_time_ns * 1e-9)


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


def put(bridge: Ros2Bridge, topic: str, payload: bytes, *, t_s: float = 0.0):
    return bridge.receive(topic=topic, key_expr=bridge.keys[topic], payload=payload, received_s=t_s)


def decoded(output, topic: str) -> list:
    """Every ROS message ``output`` publishes on ``topic``, encoded and decoded again by mcap-ros2-support."""
    decode = independent_decoder(BRIDGE_TOPICS[topic].msgtype)
    return [decode(typesupport.encode(message, BRIDGE_TOPICS[topic].msgtype))
            for name, message in output.ros if name == topic]


# --------------------------------------------------------------------------- scans → hits


def test_every_real_hit_lies_where_the_laser_says_and_no_return_rays_are_dropped(bridge, aces, scenario) -> None:
    max_range = float(scenario.sensor.range)
    odom = None
    scans = dropped = dropped_at_50 = 0
    for recorded in aces:
        output = feed(bridge, recorded)
        assert output.error is None
        if recorded.topic == "/odom":
            odom = recorded.message
            continue
        scan = recorded.message
        p, q = odom.pose.pose.position, odom.pose.pose.orientation
        yaw = Rotation.from_quat([q.x, q.y, q.z, q.w]).as_euler("zyx")[0]
        expected = []
        for i, r in enumerate(scan.ranges):
            if math.isfinite(r) and scan.range_min <= r <= min(scan.range_max, max_range):
                a = yaw + scan.angle_min + i * scan.angle_increment
                expected.append((p.x + r * math.cos(a), p.y + r * math.sin(a)))
            else:
                dropped += 1
                dropped_at_50 += r == 50.0
        (_, state), (_, made) = output.pipeline
        assert made.header.frame_id == "map" and made.header.seq == scans == state.header.seq
        assert made.header.stamp_s == pytest.approx(scan.header.stamp.sec + 1e-9 * scan.header.stamp.nanosec)
        assert (made.pose.x_m, made.pose.y_m, made.pose.theta_rad) == pytest.approx((p.x, p.y, yaw), abs=1e-12)
        np.testing.assert_allclose(np.asarray(made.points).reshape(-1, 2), np.asarray(expected).reshape(-1, 2),
                                   rtol=0, atol=1e-9)
        scans += 1
    assert scans == 440
    # The log writes "no return" as 50.0 m (not inf): beyond the sensor's 20 m, every one is dropped.
    assert dropped_at_50 == 620 and dropped > dropped_at_50


def test_inf_nan_and_out_of_range_rays_are_no_returns(bridge, aces) -> None:
    odom, scan = next(r for r in aces if r.topic == "/odom"), next(r for r in aces if r.topic == "/scan")
    feed(bridge, odom)
    message = typesupport.decode(scan.data, "sensor_msgs/msg/LaserScan")
    ranges = np.full(180, 3.0, dtype=np.float32)
    ranges[:5] = [np.inf, np.nan, 0.01, 85.0, 25.0]  # no return, NaN, below range_min, above range_max, > 20 m
    message.ranges = ranges
    output = put(bridge, "scan", typesupport.encode(message, "sensor_msgs/msg/LaserScan"), t_s=1.0)
    points = np.asarray(output.pipeline[1][1].points)
    assert output.error is None and len(points) == 175
    p = odom.message.pose.pose.position
    np.testing.assert_allclose(np.hypot(points[:, 0] - p.x, points[:, 1] - p.y), 3.0, atol=1e-6)


@pytest.mark.parametrize("count, angle_min, increment", [
    (180, -math.pi, -2 * math.pi / 180),  # a full turn, clockwise
    (7, -0.3, 0.1),  # a narrow fan
    (1, 1.0, 0.0),  # one ray
])
def test_any_angle_range_and_count_is_placed_ray_by_ray(bridge, count, angle_min, increment) -> None:
    put(bridge, "odom", odometry(x=1.0, y=-2.0, yaw=0.7, t_s=5.0))
    ranges = 1.0 + 0.1 * np.arange(count)
    output = put(bridge, "scan", laser_scan(ranges, t_s=5.0, angle_min=angle_min, angle_increment=increment))
    # The message carries float32: the bridge places each ray at those values, computed in float64.
    angles = 0.7 + float(np.float32(angle_min)) + float(np.float32(increment)) * np.arange(count)
    r = ranges.astype(np.float32).astype(float)
    expected = np.column_stack([1.0 + r * np.cos(angles), -2.0 + r * np.sin(angles)])
    np.testing.assert_allclose(np.asarray(output.pipeline[1][1].points), expected, atol=1e-9)


# --------------------------------------------------------------------------- rejected inputs


def test_each_bad_input_is_refused_with_a_reason_the_robot_brakes_and_the_bridge_carries_on(bridge, aces) -> None:
    odom = next(r for r in aces if r.topic == "/odom")
    scan = next(r for r in aces if r.topic == "/scan")
    assert feed(bridge, odom).error is None
    other_hash = BRIDGE_TOPICS["odom"].type_hash
    bad = [
        ("scan", bridge.keys["scan"], scan.data[:200], "malformed CDR"),
        ("scan", bridge.keys["scan"].rsplit("/", 1)[0] + "/" + other_hash,
         scan.data, f"type hash {other_hash} is not sensor_msgs/msg/LaserScan's"),
        ("scan", bridge.keys["scan"], laser_scan(np.full(100_000, 2.0), t_s=1.0, angle_min=-1.5,
                                                 angle_increment=3e-5), "100000 exceeds the limit of 180"),
        ("odom", bridge.keys["odom"], odometry(x=math.nan, y=0.0, yaw=0.0, t_s=1.0), "not finite: x=nan"),
        ("odom", bridge.keys["odom"], odometry(x=1.0, y=0.0, yaw=0.0, t_s=1.0, frame="map"),
         "changed from 'odom' to 'map' mid-run"),
        ("goal_pose", bridge.keys["goal_pose"],
         typesupport.encode(ros("geometry_msgs/msg/PoseStamped", header=header(1.0, "map"), pose=pose(5.0, 0.0, 0.0)),
                            "geometry_msgs/msg/PoseStamped"), "not the odometry's 'odom'"),
        ("odom", bridge.keys["odom"], odometry(x=500.0, y=0.0, yaw=0.0, t_s=1.0), "outside the map bounds"),
    ]
    for topic, key, payload, reason in bad:
        bridge.path = np.array([[0.0, 0.0], [1.0, 0.0]])  # a path being followed: each rejection drops it
        output = bridge.receive(topic=topic, key_expr=key, payload=payload, received_s=1.0)
        assert output.error is not None and reason in output.error and "\n" not in output.error
        assert output.error.startswith(f"{topic}: ")
        assert bridge.path is None and output.pipeline == []
        (twist,) = decoded(output, "cmd_vel")
        assert (twist.linear.x, twist.angular.z) == (0.0, 0.0)
    # Still running: the next good messages go through.
    assert feed(bridge, odom).error is None
    scan_output = feed(bridge, scan)
    assert scan_output.error is None and scan_output.pipeline[1][0] == "scan"


def test_a_scan_far_from_the_newest_odometry_in_time_is_refused(bridge) -> None:
    assert put(bridge, "scan", laser_scan([1.0], t_s=0.0, angle_min=0.0, angle_increment=0.0)).error == \
        "scan: no odometry yet to place the scan"
    put(bridge, "odom", odometry(x=0.0, y=0.0, yaw=0.0, t_s=10.0))
    error = put(bridge, "scan", laser_scan([1.0], t_s=11.0, angle_min=0.0, angle_increment=0.0)).error
    assert "1.000 s apart > max_pose_age_s 0.5" in error


# --------------------------------------------------------------------------- paths and commands


def straight_path(*, x: float, y: float, yaw: float, length_m: float = 6.0) -> list[tuple[float, float]]:
    s = np.arange(0.0, length_m + 1e-9, 0.05)
    return [(x + d * math.cos(yaw), y + d * math.sin(yaw)) for d in s]


def answer(bridge: Ros2Bridge, points, *, scan_seq: int, plan_id: int = 1) -> SmoothPath:
    return SmoothPath(header=Header(stamp_s=0.0, seq=scan_seq), scan_seq=scan_seq, status="ok", goal_index=0,
                      points=points, max_curvature=0.0, min_level=2.0, plan_id=plan_id)


def scan_at(bridge: Ros2Bridge, *, x: float, y: float, yaw: float, t_s: float, ahead_rad: float = 1.5):
    """A scan of a wall 3 m away, `ahead_rad` to the left of the heading (the default: beside the path)."""
    put(bridge, "odom", odometry(x=x, y=y, yaw=yaw, t_s=t_s), t_s=t_s)
    return put(bridge, "scan", laser_scan([3.0, 3.0, 3.0], t_s=t_s, angle_min=ahead_rad - 0.1, angle_increment=0.1),
               t_s=t_s)


def test_a_verified_path_is_published_on_plan_and_followed_within_the_speed_bound(bridge, scenario) -> None:
    x, y, yaw = 0.897, -0.181, -0.454
    scan_at(bridge, x=x, y=y, yaw=yaw, t_s=100.25)
    points = straight_path(x=x, y=y, yaw=yaw)
    output = bridge.take_path(answer(bridge, points, scan_seq=0), received_s=100.4)
    assert output.error is None and bridge.latencies_ms == [pytest.approx(150.0)]
    (plan,) = decoded(output, "plan")
    assert plan.header.frame_id == "odom" and (plan.header.stamp.sec, plan.header.stamp.nanosec) == (100, 250_000_000)
    assert len(plan.poses) == len(points)
    assert all(p.header.frame_id == "odom" and p.header.stamp.sec == 100 for p in plan.poses)
    assert (plan.poses[0].pose.position.x, plan.poses[0].pose.position.y) == pytest.approx(points[0])
    assert (plan.poses[-1].pose.position.x, plan.poses[-1].pose.position.y) == pytest.approx(points[-1])
    q = plan.poses[0].pose.orientation
    assert 2 * math.atan2(q.z, q.w) == pytest.approx(yaw)
    speeds = []
    for k in range(1, 11):  # odometry at 10 Hz: one command each
        out = put(bridge, "odom", odometry(x=x, y=y, yaw=yaw, t_s=100.25 + 0.1 * k, speed=0.5), t_s=100.25 + 0.1 * k)
        (state_name, state), = out.pipeline
        (twist,) = decoded(out, "cmd_vel")
        assert state_name == "state" and state.goal_index == 0 and not state.done
        speeds.append(twist.linear.x)
        assert 0.0 < twist.linear.x <= scenario.robot.max_speed and abs(twist.angular.z) < 1e-9
    assert speeds[-1] > 0.3


def test_the_robot_brakes_without_a_fresh_verified_path(bridge) -> None:
    x, y, yaw = 0.9, -0.2, 0.0
    scan_at(bridge, x=x, y=y, yaw=yaw, t_s=10.0)

    def command(t_s: float) -> float:
        (twist,) = decoded(put(bridge, "odom", odometry(x=x, y=y, yaw=yaw, t_s=t_s, speed=0.5), t_s=t_s), "cmd_vel")
        return twist.linear.x

    assert command(10.1) == 0.0  # no path yet
    bridge.take_path(answer(bridge, straight_path(x=x, y=y, yaw=yaw), scan_seq=0), received_s=10.2)
    assert command(10.2) > 0.0
    # Stale: the plan answers a scan older than stale_after_s (robot time).
    assert command(10.0 + bridge.config.stale_after_s + 0.1) == 0.0
    # A stage lost: zero, and answers to scans sent before it came back do not count.
    scan_at(bridge, x=x, y=y, yaw=yaw, t_s=20.0)
    bridge.stage_lost("planner")
    bridge.take_path(answer(bridge, straight_path(x=x, y=y, yaw=yaw), scan_seq=1), received_s=20.1)
    assert command(20.1) == 0.0
    bridge.stage_back("planner")
    bridge.take_path(answer(bridge, straight_path(x=x, y=y, yaw=yaw), scan_seq=1), received_s=20.1)
    assert command(20.2) == 0.0
    scan_at(bridge, x=x, y=y, yaw=yaw, t_s=20.3)
    bridge.take_path(answer(bridge, straight_path(x=x, y=y, yaw=yaw), scan_seq=2), received_s=20.4)
    assert command(20.4) > 0.0
    # Newer ellipses across the path: the guard drops it.
    ellipse = EllipsoidMsg(A=((2.0, 0.0), (0.0, 2.0)), b=(-2.0 * (x + 2.0), -2.0 * y), group=0, cluster_id=7)
    assert bridge.take_ellipsoids(Ellipsoids(header=Header(stamp_s=20.3, seq=0), scan_seq=2, inflation_m=0.65,
                                             ellipsoids=[ellipse])).error is None
    assert bridge.path is None and "newer obstacles" in bridge.braking_reason and command(20.5) == 0.0
    # A path through the known ellipse is not followed; one starting against the heading neither.
    scan_at(bridge, x=x, y=y, yaw=yaw, t_s=20.6)
    refused = bridge.take_path(answer(bridge, straight_path(x=x, y=y, yaw=yaw), scan_seq=3), received_s=20.7)
    assert "enters a known obstacle's ellipse (cluster 7" in refused.error and decoded(refused, "plan") == []
    backwards = bridge.take_path(answer(bridge, straight_path(x=x, y=y, yaw=math.pi), scan_seq=3), received_s=20.7)
    assert "against the robot's heading" in backwards.error
    # The robot's own hits hold the path, whatever the ellipses say: a wall it sensed ahead, an empty
    # ellipse set, a path through the wall; and a path off the map.
    scan_at(bridge, x=x, y=y, yaw=yaw, t_s=20.8, ahead_rad=0.0)
    assert bridge.take_ellipsoids(Ellipsoids(header=Header(stamp_s=20.8, seq=1), scan_seq=4, inflation_m=0.65,
                                             ellipsoids=[])).error is None
    blind = bridge.take_path(answer(bridge, straight_path(x=x, y=y, yaw=yaw), scan_seq=4), received_s=20.9)
    assert "from a hit of the car's own scans" in blind.error and decoded(blind, "plan") == []
    away = bridge.take_path(answer(bridge, straight_path(x=x, y=y, yaw=yaw - 1.5, length_m=80.0), scan_seq=4),
                            received_s=20.9)
    assert "leaves the map" in away.error
    # An answer to a scan the bridge never sent is refused.
    assert "did not send" in bridge.take_path(answer(bridge, [(0.0, 0.0), (1.0, 0.0)], scan_seq=99),
                                              received_s=21.0).error


def test_the_odometry_falling_silent_brakes_on_the_timer(bridge) -> None:
    put(bridge, "odom", odometry(x=0.0, y=0.0, yaw=0.0, t_s=1.0), t_s=50.0)
    assert bridge.tick(received_s=50.5).ros == []
    (twist,) = decoded(bridge.tick(received_s=51.5), "cmd_vel")
    assert (twist.linear.x, twist.angular.z) == (0.0, 0.0) and bridge.braking_reason == "no odometry"


def test_body_twist_turns_the_footprint_centre_on_the_bicycles_circle(bridge, scenario) -> None:
    """ω / v is the curvature of the circle the sim's bicycle drives its footprint centre on at that steering."""
    v, L = 0.8, scenario.robot.wheelbase
    for delta in (0.05, 0.15, -0.2):
        speed, omega = body_twist(speed_mps=v, steering_rad=delta, wheelbase_m=L)
        car = VehicleState(x_m=0.0, y_m=0.0, theta_rad=0.0, speed_mps=v, steering_rad=delta)
        centres = []
        for _ in range(60):
            car = step(car, limits=bridge.config.limits, target_speed_mps=v, target_steering_rad=delta, dt_s=0.05)
            centres.append((car.x_m, car.y_m))
        a, b, c = np.asarray(centres[0]), np.asarray(centres[30]), np.asarray(centres[59])
        cross = (b - a)[0] * (c - a)[1] - (b - a)[1] * (c - a)[0]
        curvature = 2.0 * cross / (np.linalg.norm(b - a) * np.linalg.norm(c - b) * np.linalg.norm(c - a))
        assert speed == v and omega / speed == pytest.approx(curvature, rel=1e-6)


# --------------------------------------------------------------------------- goals and maps


def test_a_goal_pose_replaces_the_scenarios_goals(bridge) -> None:
    put(bridge, "odom", odometry(x=0.0, y=0.0, yaw=0.0, t_s=1.0))
    goal = ros("geometry_msgs/msg/PoseStamped", header=header(1.0, "odom"), pose=pose(5.0, -3.0, 0.0))
    output = put(bridge, "goal_pose", typesupport.encode(goal, "geometry_msgs/msg/PoseStamped"))
    assert output.error is None and output.goals == ((5.0, -3.0),)
    (state_name, state), = put(bridge, "odom", odometry(x=4.8, y=-3.0, yaw=0.0, t_s=1.1)).pipeline
    assert state.goals_reached == 1 and state.done


def test_an_occupancy_grid_is_kept_as_an_array_with_its_resolution_and_origin(bridge) -> None:
    data = np.array([0, 100, -1, 0, 0, 100], dtype=np.int8)
    grid = ros("nav_msgs/msg/OccupancyGrid", header=header(0.0, "odom"),
               info=ros("nav_msgs/msg/MapMetaData", map_load_time=stamp(0.0), resolution=0.05, width=3, height=2,
                        origin=pose(-27.266, -48.329, 0.0)),
               data=data)
    output = put(bridge, "map", typesupport.encode(grid, "nav_msgs/msg/OccupancyGrid"))
    known = output.known_map
    assert output.error is None and known is bridge.known_map
    np.testing.assert_array_equal(known.occupancy, [[0, 100, -1], [0, 0, 100]])
    assert known.resolution_m == pytest.approx(0.05) and (known.origin.x_m, known.origin.y_m) == (-27.266, -48.329)
    broken = dataclasses.replace(grid, data=data[:5])
    assert "5 cells of data for a 3 x 2 grid" in put(bridge, "map", typesupport.encode(
        broken, "nav_msgs/msg/OccupancyGrid")).error
    # An odometry in another frame than the map's is refused.
    assert "is not the map's 'odom'" in put(bridge, "odom", odometry(x=0.0, y=0.0, yaw=0.0, t_s=1.0,
                                                                      frame="world")).error
