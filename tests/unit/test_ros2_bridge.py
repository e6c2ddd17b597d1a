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
from ros2_messages import header, laser_scan, map_server_grid, occupancy_grid, odometry, pose, ros
from schemas.messages import EllipsoidMsg, Ellipsoids, Header, Map, SmoothPath, decode, encode
from schemas.occupancy import FREE, OCCUPIED, UNKNOWN, load_map
from schemas.scenario import load_scenario
from schemas.wiring import PIPELINE, subscribers_of
from services.convert import grid_from_msg
from services.limits import DEFAULT_MAX_PAYLOAD_BYTES
from services.drive.vehicle import VehicleState, step
from services.ros2 import typesupport
from services.ros2.bridge import BridgeConfig, Ros2Bridge, body_twist
from services.ros2.stage import BridgeStage
from services.ros2.interface import BRIDGE_TOPICS

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
        # The robot's route passes the scenario's goal: from then on the scans go on alone, with no state to
        # plan from.
        *states, (_, made) = output.pipeline
        assert [name for name, _ in states] == ([] if bridge.goals.done else ["state"])
        assert made.header.frame_id == "map" and made.header.seq == scans
        assert all(state.header.seq == scans for _, state in states)
        assert made.header.stamp_s == pytest.approx(scan.header.stamp.sec + 1e-9 * scan.header.stamp.nanosec)
        assert (made.pose.x_m, made.pose.y_m, made.pose.theta_rad) == pytest.approx((p.x, p.y, yaw), abs=1e-12)
        np.testing.assert_allclose(np.asarray(made.points).reshape(-1, 2), np.asarray(expected).reshape(-1, 2),
                                   rtol=0, atol=1e-9)
        scans += 1
    assert scans == 440 and bridge.goals.done
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
        assert output.refused == topic
        assert output.error is not None and reason in output.error and "\n" not in output.error
        assert output.error.startswith(f"{topic}: ")
        assert bridge.path is None and output.pipeline == []
        (twist,) = decoded(output, "cmd_vel")
        assert (twist.linear.x, twist.angular.z) == (0.0, 0.0)
    # Still running: the next good messages go through.
    assert feed(bridge, odom).error is None
    scan_output = feed(bridge, scan)
    assert scan_output.error is None and scan_output.pipeline[1][0] == "scan"


def test_a_scan_is_placed_at_the_pose_of_its_stamp_and_waits_for_the_odometry_if_it_comes_first(bridge) -> None:
    """Over the network a scan may overtake the odometry stamped with it (the ACES bag's pairs do): it
    waits up to max_pose_age_s for the odometry after its stamp, as tf's message filter waits for a
    transform, and is placed at the pose interpolated between the odometry on either side."""
    scan = laser_scan([1.0], t_s=5.0, angle_min=0.0, angle_increment=0.0)
    assert put(bridge, "scan", scan, t_s=100.0).error is None  # no odometry yet: it waits
    (twist,) = decoded(tick := bridge.tick(received_s=100.6), "cmd_vel")
    assert tick.error == "scan: no odometry yet to place the scan" and tick.refused == "scan"
    assert (twist.linear.x, twist.angular.z) == (0.0, 0.0)

    put(bridge, "odom", odometry(x=0.0, y=0.0, yaw=0.0, t_s=4.0), t_s=101.0)
    assert put(bridge, "scan", scan, t_s=101.1).pipeline == []  # 1 s from the newest odometry: it waits
    placed = put(bridge, "odom", odometry(x=2.0, y=1.0, yaw=0.5, t_s=5.0), t_s=101.15)
    (_, robot), (_, state), (_, made) = placed.pipeline
    assert placed.error is None and (made.pose.x_m, made.pose.y_m, made.pose.theta_rad) == (2.0, 1.0, 0.5)
    assert made.points == [pytest.approx((2.0 + math.cos(0.5), 1.0 + math.sin(0.5)))]
    assert robot.header.stamp_s == state.header.stamp_s == 5.0

    # Between two odometry messages: the pose interpolated to its stamp (a robot turning on the spot).
    put(bridge, "scan", laser_scan([1.0], t_s=5.25, angle_min=0.0, angle_increment=0.0), t_s=101.2)
    (_, between), = [item for item in put(bridge, "odom", odometry(x=3.0, y=1.0, yaw=-0.5, t_s=5.5),
                                           t_s=101.25).pipeline if item[0] == "scan"]
    assert (between.pose.x_m, between.pose.y_m, between.pose.theta_rad) == pytest.approx((2.5, 1.0, 0.0))

    # Odometry on both sides, neither within 0.5 s: refused, with the robot braking.
    put(bridge, "scan", laser_scan([1.0], t_s=6.2, angle_min=0.0, angle_increment=0.0), t_s=101.3)
    refused = put(bridge, "odom", odometry(x=2.0, y=1.0, yaw=0.5, t_s=7.0), t_s=101.4)
    assert refused.error == ("scan: stamped 6.200 s but the nearest odometry is from 5.500 s (0.700 s apart > "
                             "max_pose_age_s 0.5)") and refused.refused == "scan"
    assert [name for name, _ in refused.pipeline] == ["state"]  # the odometry itself was good
    assert [cmd.linear.x for cmd in decoded(refused, "cmd_vel")] == [0.0, 0.0]


# --------------------------------------------------------------------------- paths and commands


def straight_path(*, x: float, y: float, yaw: float, length_m: float = 6.0) -> list[tuple[float, float]]:
    s = np.arange(0.0, length_m + 1e-9, 0.05)
    return [(x + d * math.cos(yaw), y + d * math.sin(yaw)) for d in s]


def heading_to_its_end(bridge: Ros2Bridge, points) -> Ros2Bridge:
    """The bridge with its goal at the end of ``points``: a path is followed only if it ends at the goal."""
    return Ros2Bridge(config=dataclasses.replace(bridge.config, goals=(tuple(points[-1]),)))


def answer(bridge: Ros2Bridge, points, *, scan_seq: int, plan_id: int = 1) -> SmoothPath:
    return SmoothPath(header=Header(stamp_s=0.0, seq=scan_seq), scan_seq=scan_seq, status="ok", goal_index=0,
                      points=points, max_curvature=0.0, min_level=2.0, plan_id=plan_id)


def known(bridge: Ros2Bridge, *, scan_seq: int, t_s: float, ellipses=()):
    """The ellipsoid stage's answer to a scan, as the bridge receives it."""
    message = Ellipsoids(header=Header(stamp_s=t_s, seq=scan_seq), scan_seq=scan_seq, inflation_m=0.35,
                         ellipsoids=list(ellipses))
    return bridge.take_ellipsoids(message, received_s=t_s)


def scan_at(bridge: Ros2Bridge, *, x: float, y: float, yaw: float, t_s: float, ellipses=(), ahead_rad: float = 1.5):
    """Odometry and a scan at ``t_s`` of a wall 3 m away, `ahead_rad` to the left of the heading (the
    default: beside the path), and the ellipsoid stage's answer to the scan."""
    put(bridge, "odom", odometry(x=x, y=y, yaw=yaw, t_s=t_s), t_s=t_s)
    output = put(bridge, "scan", laser_scan([3.0, 3.0, 3.0], t_s=t_s, angle_min=ahead_rad - 0.1, angle_increment=0.1),
                 t_s=t_s)
    known(bridge, scan_seq=output.pipeline[-1][1].header.seq, t_s=t_s, ellipses=ellipses)
    return output


def test_a_verified_path_is_published_on_plan_and_followed_within_the_speed_bound(bridge, scenario) -> None:
    x, y, yaw = 0.897, -0.181, -0.454
    points = straight_path(x=x, y=y, yaw=yaw)
    bridge = heading_to_its_end(bridge, points)
    scan_at(bridge, x=x, y=y, yaw=yaw, t_s=100.25)
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
    bridge = heading_to_its_end(bridge, straight_path(x=x, y=y, yaw=yaw))
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
    bridge.stage_lost("planner", now_s=20.0)
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
    assert known(bridge, scan_seq=2, t_s=20.45, ellipses=[ellipse]).error is None
    assert bridge.path is None and "newer obstacles" in bridge.braking_reason and command(20.5) == 0.0
    # A path through the known ellipse is not followed; one starting against the heading neither.
    scan_at(bridge, x=x, y=y, yaw=yaw, t_s=20.6, ellipses=[ellipse])
    refused = bridge.take_path(answer(bridge, straight_path(x=x, y=y, yaw=yaw), scan_seq=3), received_s=20.7)
    assert "enters a known obstacle's ellipse (cluster 7" in refused.error and decoded(refused, "plan") == []
    round_the_back = [(x, y), (x - 0.05, y), (x, y + 1.5), (x + 4.0, y + 1.5), bridge.goals.goals[-1]]
    backwards = bridge.take_path(answer(bridge, round_the_back, scan_seq=3), received_s=20.7)
    assert "against the robot's heading" in backwards.error
    # A path to somewhere else than the goal (planned for goals since replaced) is not followed.
    scan_at(bridge, x=x, y=y, yaw=yaw, t_s=20.8)
    elsewhere = bridge.take_path(answer(bridge, straight_path(x=x, y=y + 2.0, yaw=yaw), scan_seq=4), received_s=20.9)
    assert elsewhere.error is None and decoded(elsewhere, "plan") == [] and bridge.path is None
    # The robot's own hits hold the path, whatever the ellipses say: a wall it sensed ahead, an empty
    # ellipse set answering that scan, a path to the goal through the wall; and a path off the map.
    scan_at(bridge, x=x, y=y, yaw=yaw, t_s=20.85, ahead_rad=0.0)
    blind = bridge.take_path(answer(bridge, straight_path(x=x, y=y, yaw=yaw), scan_seq=5), received_s=20.9)
    assert "from a hit of the car's own scans" in blind.error and decoded(blind, "plan") == []
    off_the_map = [(x, y), (x + 1.0, y), (x + 1.0, y - 80.0), bridge.goals.goals[-1]]
    away = bridge.take_path(answer(bridge, off_the_map, scan_seq=5), received_s=20.9)
    assert "leaves the map" in away.error and bridge.path is None
    # An answer to a scan the bridge never sent is refused.
    assert "did not send" in bridge.take_path(answer(bridge, [(0.0, 0.0), (1.0, 0.0)], scan_seq=99),
                                              received_s=21.0).error


def test_a_no_path_while_the_planner_replans_keeps_the_path_and_a_verdict_brakes(bridge) -> None:
    x, y, yaw = 0.9, -0.2, 0.0
    points = straight_path(x=x, y=y, yaw=yaw)
    bridge = heading_to_its_end(bridge, points)

    def command(t_s: float) -> float:
        (twist,) = decoded(put(bridge, "odom", odometry(x=x, y=y, yaw=yaw, t_s=t_s, speed=0.5), t_s=t_s), "cmd_vel")
        return twist.linear.x

    scan_at(bridge, x=x, y=y, yaw=yaw, t_s=10.0)
    bridge.take_path(answer(bridge, points, scan_seq=0), received_s=10.1)
    assert command(10.1) > 0.0
    scan_at(bridge, x=x, y=y, yaw=yaw, t_s=10.2)
    pending = SmoothPath(header=Header(stamp_s=10.2, seq=1), scan_seq=1, status="no_path", goal_index=0, points=[],
                         max_curvature=0.0, min_level=0.0, plan_id=1, reason="replanning past its budget",
                         replanning=True)
    assert bridge.take_path(pending, received_s=10.25).error is None
    assert bridge.path is not None and command(10.3) > 0.0
    scan_at(bridge, x=x, y=y, yaw=yaw, t_s=10.4)
    verdict = pending.model_copy(update=dict(header=Header(stamp_s=10.4, seq=2), scan_seq=2, replanning=False,
                                             reason="the goal is enclosed"))
    bridge.take_path(verdict, received_s=10.45)
    assert bridge.path is None and "the goal is enclosed" in bridge.braking_reason and command(10.5) == 0.0


def test_a_path_waits_until_the_guard_knows_the_obstacles_of_every_scan_the_robot_has_had_a_while(bridge) -> None:
    """The guard must be current: it knows the ellipses of the path's own scan, and of the newest scan
    received guard_window_s before. Without that wait this path, checked against scan 0's obstacles only,
    would have been followed into the obstacle scan 1 showed 0.6 s earlier."""
    x, y, yaw = 0.9, -0.2, 0.0
    points = straight_path(x=x, y=y, yaw=yaw)
    bridge = heading_to_its_end(bridge, points)
    put(bridge, "odom", odometry(x=x, y=y, yaw=yaw, t_s=0.0), t_s=0.0)
    # A wall beside the path (its own hits would refuse a path into them whatever the ellipses say).
    put(bridge, "scan", laser_scan([3.0], t_s=0.0, angle_min=1.5, angle_increment=0.0), t_s=0.0)
    held = bridge.take_path(answer(bridge, points, scan_seq=0), received_s=0.2)
    assert decoded(held, "plan") == [] and held.error is None  # its scan's ellipses are still on their way
    (plan,) = decoded(known(bridge, scan_seq=0, t_s=0.3), "plan")
    assert len(plan.poses) == len(points)

    put(bridge, "odom", odometry(x=x, y=y, yaw=yaw, t_s=1.0), t_s=1.0)
    put(bridge, "scan", laser_scan([3.0], t_s=1.0, angle_min=1.5, angle_increment=0.0), t_s=1.0)
    held = bridge.take_path(answer(bridge, points, scan_seq=0, plan_id=2), received_s=1.6)
    assert decoded(held, "plan") == [] and bridge.held is not None
    ellipse = EllipsoidMsg(A=((2.0, 0.0), (0.0, 2.0)), b=(-2.0 * (x + 3.0), -2.0 * y), group=0, cluster_id=3)
    refused = known(bridge, scan_seq=1, t_s=1.7, ellipses=[ellipse])
    assert decoded(refused, "plan") == [] and "plan 2 for scan 0 not followed" in refused.error
    assert "(cluster 3, of scan 1)" in refused.error and bridge.held is None and bridge.path is None


def test_the_timer_repeats_the_command_between_sparse_odometry_and_brakes_when_it_falls_silent(bridge) -> None:
    """A base times its command out (often after 0.5 s): with odometry slower than that the timer repeats
    the last command every command_period_s; with none for odom_timeout_s it commands zero, every tick."""
    x, y, yaw = 0.9, -0.2, 0.0
    bridge = heading_to_its_end(bridge, straight_path(x=x, y=y, yaw=yaw))
    scan_at(bridge, x=x, y=y, yaw=yaw, t_s=50.0)
    bridge.take_path(answer(bridge, straight_path(x=x, y=y, yaw=yaw), scan_seq=0), received_s=50.1)
    (moving,) = decoded(put(bridge, "odom", odometry(x=x, y=y, yaw=yaw, t_s=50.2, speed=0.3), t_s=50.2), "cmd_vel")
    assert moving.linear.x > 0.0
    assert bridge.tick(received_s=50.6).ros == []  # 0.4 s since the command: nothing yet
    (again,) = decoded(bridge.tick(received_s=50.7), "cmd_vel")
    assert (again.linear.x, again.angular.z) == (moving.linear.x, moving.angular.z)
    assert bridge.tick(received_s=51.1).ros == [] and decoded(bridge.tick(received_s=51.2), "cmd_vel")
    (stop,) = decoded(bridge.tick(received_s=51.3), "cmd_vel")  # 1.1 s without odometry
    assert (stop.linear.x, stop.angular.z) == (0.0, 0.0) and bridge.braking_reason == "no odometry"
    (still,) = decoded(bridge.tick(received_s=51.4), "cmd_vel")
    assert still.linear.x == 0.0 and bridge.path is None


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
    (state_name, state), = put(bridge, "odom", odometry(x=2.0, y=-3.0, yaw=0.0, t_s=1.1)).pipeline
    assert state.goal_index == 0 and state.goals_reached == 0 and not state.done
    # Reached: the robot stands, and the planner gets no state until there is a goal again.
    reached = put(bridge, "odom", odometry(x=4.8, y=-3.0, yaw=0.0, t_s=1.2))
    (twist,) = decoded(reached, "cmd_vel")
    assert bridge.goals.done and reached.pipeline == [] and (twist.linear.x, twist.angular.z) == (0.0, 0.0)


@pytest.mark.parametrize("name", ["external/carmen/aces-map.yaml", "maps/depot.yaml"])
def test_a_map_servers_map_becomes_the_pipelines_map_as_load_map_reads_its_files(bridge, shared_dir, name) -> None:
    path = shared_dir / name
    output = put(bridge, "map", map_server_grid(path))
    assert output.error is None and output.pipeline == []  # the map waits for the odometry to show its frame
    first = put(bridge, "odom", odometry(x=0.0, y=0.0, yaw=0.0, t_s=1.0))
    (topic, message), state = first.pipeline[0], first.pipeline[1]
    assert topic == "map" and state[0] == "state"  # the map goes out before the first state
    payload = encode(message)
    assert len(payload) < DEFAULT_MAX_PAYLOAD_BYTES
    grid, expected = grid_from_msg(decode(Map, payload, encoding=Map.encoding())), load_map(path)
    np.testing.assert_array_equal(grid.state, expected.state)
    assert grid.resolution_m == pytest.approx(expected.resolution_m, rel=1e-7)  # MapMetaData's is a float32
    assert (grid.origin_x_m, grid.origin_y_m, grid.origin_yaw_rad) == (
        expected.origin_x_m, expected.origin_y_m, expected.origin_yaw_rad)
    assert all(name != "map" for name, _ in put(bridge, "odom", odometry(x=0.0, y=0.0, yaw=0.0, t_s=1.1)).pipeline)


def test_a_map_is_in_the_odometrys_frame_or_refused(bridge, shared_dir) -> None:
    depot = shared_dir / "maps" / "depot.yaml"
    put(bridge, "odom", odometry(x=0.0, y=0.0, yaw=0.0, t_s=1.0))
    refused = put(bridge, "map", map_server_grid(depot, frame="map"))
    assert "map: frame 'map' is not the odometry's 'odom'" in refused.error and bridge.map is None
    assert decoded(refused, "cmd_vel")[0].linear.x == 0.0
    (topic, _), = put(bridge, "map", map_server_grid(depot)).pipeline  # the frame is known: out at once
    assert topic == "map"
    data = np.array([0, 100, -1, 0, 0, 100], dtype=np.int8)
    broken = occupancy_grid(data[:5], width=3, height=2, resolution_m=0.05, origin=(0.0, 0.0))
    assert "5 cells of data for a 3 x 2 grid" in put(bridge, "map", broken).error


def test_a_map_whose_cells_do_not_compress_within_the_pipelines_payload_cap_is_refused(bridge) -> None:
    noise = np.random.default_rng(7).choice(np.array([0, 100, -1], dtype=np.int8), size=2048 * 2048)
    put(bridge, "odom", odometry(x=0.0, y=0.0, yaw=0.0, t_s=1.0))
    refused = put(bridge, "map", occupancy_grid(noise, width=2048, height=2048, resolution_m=0.05, origin=(0.0, 0.0)))
    assert f"more than the pipeline's {DEFAULT_MAX_PAYLOAD_BYTES} a message may have" in refused.error
    assert refused.pipeline == [] and bridge.map is None


def test_a_stage_that_reads_the_map_gets_it_again_when_it_comes_back(scenario, shared_dir) -> None:
    stage = BridgeStage.from_scenario(scenario)
    for name in PIPELINE:
        assert stage.stage_alive(stage=name, alive=True, now_s=0.0) == []  # no map yet
    stage.receive(port="map", key_expr=stage.bridge.keys["map"], payload=map_server_grid(shared_dir / "maps" /
                                                                                        "depot.yaml"), now_s=0.0)
    sent = [m for topic, m in stage.receive(port="odom", key_expr=stage.bridge.keys["odom"], now_s=0.1,
                                            payload=odometry(x=0.0, y=0.0, yaw=0.0, t_s=1.0)) if topic == "map"]
    for name in PIPELINE:
        stage.stage_alive(stage=name, alive=False, now_s=0.2)
        again = stage.stage_alive(stage=name, alive=True, now_s=0.3)
        assert again == ([("map", sent[0])] if name in subscribers_of("map") else [])


def test_an_odometry_in_another_frame_than_the_maps_is_refused(bridge) -> None:
    grid = occupancy_grid([0, 100, -1, 0, 0, 100], width=3, height=2, resolution_m=0.05, origin=(-27.266, -48.329))
    assert put(bridge, "map", grid).error is None
    assert "is not the map's 'odom'" in put(bridge, "odom", odometry(x=0.0, y=0.0, yaw=0.0, t_s=1.0,
                                                                      frame="world")).error
    (topic, message), _ = put(bridge, "odom", odometry(x=0.0, y=0.0, yaw=0.0, t_s=1.1)).pipeline
    np.testing.assert_array_equal(grid_from_msg(message).state, [[FREE, OCCUPIED, UNKNOWN], [FREE, FREE, OCCUPIED]])