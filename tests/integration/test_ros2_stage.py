"""The ROS 2 bridge as a stage in the one shell, over real Zenoh sessions on loopback.

``run_stage("ros2", BridgeStage)`` runs in a thread on one peer; the other peer plays both sides of it:
the robot (a ROS node publishing CDR on rmw_zenoh's keys, and a plain subscriber of /plan and /cmd_vel)
and the pipeline (the stages' liveliness tokens, smooth_path and ellipsoids in JSON). What the bridge
publishes on ROS keys is decoded with mcap-ros2-support, not with rosbags, which the bridge encodes with.
"""

from __future__ import annotations

import itertools
import math
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass

import numpy as np
import pytest
import zenoh

from cvxnav.supervisor import free_ports
from ros2_bag import independent_decoder
from ros2_messages import goal_pose, laser_scan, occupancy_grid, odometry
from schemas.messages import Ellipsoids, Goals, Header, RobotState, Scan, SmoothPath, StageStatus, decode
from schemas.scenario import bundled_scenario
from schemas.wiring import PIPELINE, ROS2, alive_key, default_prefix, key, status_key
from services.ros2.interface import BRIDGE_TOPICS, MAX_MAP_CELLS
from services.ros2.stage import BridgeStage
from services.ros2.wire import EntityKind, gid_of, parse_token, topic_key
from services.shell.ros2 import Attachment, RosNode
from services.shell.stage import run_stage
from services.shell.zenoh_config import build_zenoh_config

WAIT_S = 10.0
DOMAIN = 7
SCENARIO = bundled_scenario()  # start (0, 0) facing (10, 10), then (15, 15); obstacles come from the scans
PREFIX = default_prefix()


@dataclass
class Robot:
    """The test's session: a robot's ROS node and the pipeline's side of the bridge."""

    session: zenoh.Session
    node: RosNode
    publishers: dict
    received: dict[str, list]  # by bridge output (plan, cmd_vel) and pipeline key (scan, state, goals, status)
    arrivals: dict[str, list[int]]  # for each received item, its place in the order everything arrived in
    stop: threading.Event
    thread: threading.Thread
    stage_tokens: dict

    def put(self, topic: str, payload: bytes) -> None:
        self.publishers[topic].put(payload)

    def wait(self, name: str, match: Callable[[object], bool] = lambda _: True, *, after: int = 0) -> object:
        deadline = time.monotonic() + WAIT_S
        while time.monotonic() < deadline:
            for item in self.received[name][after:]:
                if match(item):
                    return item
            time.sleep(0.01)
        pytest.fail(f"nothing on {name} matched within {WAIT_S} s: {self.received[name][-3:]}")

    def count(self, name: str) -> int:
        return len(self.received[name])

    def odom(self, *, t_s: float, x: float = 0.0, y: float = 0.0, yaw: float = math.pi / 4, frame: str = "odom",
             speed: float = 0.0):
        """Send one odometry message; the command that answers it: the bridge publishes it right after the
        state, so it is the first to arrive after the state (a watchdog command may arrive before it)."""
        states = self.count("state")
        self.put("odom", odometry(x=x, y=y, yaw=yaw, t_s=t_s, frame=frame, speed=speed))
        state = self.wait("state", lambda s: abs(s.header.stamp_s - t_s) < 1e-6, after=states)
        after = self.arrivals["state"][self.received["state"].index(state)]
        deadline = time.monotonic() + WAIT_S
        while time.monotonic() < deadline:
            answers = [c for c, order in zip(self.received["cmd_vel"], self.arrivals["cmd_vel"]) if order > after]
            if answers:
                return answers[0]
            time.sleep(0.01)
        pytest.fail(f"no command answered the odometry at {t_s} s")

    def error(self, needle: str, *, after: int) -> StageStatus:
        return self.wait("status", lambda s: s.state == "error" and needle in s.reason, after=after)


def cmd(sample) -> tuple[float, float]:
    twist = sample[0]
    return twist.linear.x, twist.angular.z


@pytest.fixture
def robot() -> Iterator[Robot]:
    endpoint = f"tcp/127.0.0.1:{free_ports(1)[0]}"
    stop, ready = threading.Event(), threading.Event()
    core = BridgeStage.from_scenario(SCENARIO, domain_id=DOMAIN, namespace="robot9")
    thread = threading.Thread(target=run_stage, kwargs=dict(
        stage=ROS2.name, core=core, session_config=build_zenoh_config(listen=[endpoint]), prefix=PREFIX,
        stop_event=stop, ready_event=ready))
    received: dict[str, list] = {name: [] for name in ("plan", "cmd_vel", "scan", "state", "goals", "status")}
    arrivals: dict[str, list[int]] = {name: [] for name in received}
    order = itertools.count()

    def keep(name: str, item) -> None:
        arrivals[name].append(next(order))  # before the item: a reader that sees the item sees its place
        received[name].append(item)

    decoders = {name: independent_decoder(BRIDGE_TOPICS[name].msgtype) for name in ("plan", "cmd_vel")}
    models = {"scan": Scan, "state": RobotState, "goals": Goals}
    with zenoh.open(build_zenoh_config(connect=[endpoint])) as session:
        def on_ros(name: str):
            return lambda sample: keep(name, (decoders[name](sample.payload.to_bytes()),
                                              Attachment.from_bytes(sample.attachment.to_bytes()), str(sample.key_expr)))

        subscribers = [session.declare_subscriber(f"{DOMAIN}/robot9/{name}/**", on_ros(name))
                       for name in ("plan", "cmd_vel")]
        def on_json(name: str, model):
            return lambda sample: keep(name, decode(model, sample.payload.to_bytes()))

        subscribers += [session.declare_subscriber(key(PREFIX, topic), on_json(topic, model))
                        for topic, model in models.items()]
        subscribers.append(session.declare_subscriber(status_key(PREFIX, ROS2.name), on_json("status", StageStatus)))
        tokens = {stage: session.liveliness().declare_token(alive_key(PREFIX, stage)) for stage in PIPELINE}
        node = RosNode(session, name="robot_base", namespace="robot9", domain_id=DOMAIN)
        publishers = {name: node.publisher(topic=topic.name, msgtype=topic.msgtype, type_hash=topic.type_hash,
                                           qos=topic.qos)
                      for name, topic in BRIDGE_TOPICS.items() if topic.direction == "in"}
        thread.start()
        assert ready.wait(WAIT_S)
        robot = Robot(session=session, node=node, publishers=publishers, received=received, arrivals=arrivals,
                      stop=stop, thread=thread, stage_tokens=tokens)
        wait_graph(session, lambda entities: any(e.node_name == "cvxnav_bridge" and e.topic == "/robot9/odom"
                                                 for e in entities))
        time.sleep(0.3)  # the bridge's subscriptions reach the robot's publishers
        try:
            yield robot
        finally:
            stop.set()
            thread.join(WAIT_S)
            node.close()
            for subscriber in subscribers:
                subscriber.undeclare()


def tokens(session: zenoh.Session) -> dict:
    """The ROS graph of the domain: each liveliness token's key and what it says."""
    keys = [str(reply.ok.key_expr) for reply in session.liveliness().get(f"@ros2_lv/{DOMAIN}/**", timeout=2.0)
            if reply.ok]
    return {token: parse_token(token) for token in keys}


def graph(session: zenoh.Session) -> list:
    return list(tokens(session).values())


def wait_graph(session: zenoh.Session, predicate) -> list:
    deadline = time.monotonic() + WAIT_S
    while time.monotonic() < deadline:
        entities = graph(session)
        if predicate(entities):
            return entities
        time.sleep(0.05)
    pytest.fail("the bridge's node did not appear in the ROS graph")


def path_to_the_goals(*, scan_seq: int, plan_id: int = 1) -> SmoothPath:
    """The pipeline's answer: the straight line from the start through (10, 10) to (15, 15)."""
    s = np.linspace(0.0, 15.0, 301)
    return SmoothPath(header=Header(stamp_s=0.0, seq=scan_seq), scan_seq=scan_seq, status="ok", goal_index=0,
                      points=[(float(v), float(v)) for v in s], max_curvature=0.0, min_level=2.0, plan_id=plan_id)


def publish_path(robot: Robot, message: SmoothPath) -> None:
    """The pipeline's answer to a scan: the ellipsoid stage's (no obstacles), then the smoother's."""
    empty = Ellipsoids(header=message.header, scan_seq=message.scan_seq, inflation_m=SCENARIO.inflation_m,
                       ellipsoids=[])
    for topic, answer in (("ellipsoids", empty), ("smooth_path", message)):
        robot.session.put(key(PREFIX, topic), answer.model_dump_json(), encoding=zenoh.Encoding(answer.encoding()))


def scan_and_plan(robot: Robot, *, t_s: float, plan_id: int = 1) -> object:
    """Odometry and a scan of nothing (every ray no return), the pipeline's path for it; the /plan the
    bridge publishes. (The odometry keeps the watchdog, which drops the path, quiet meanwhile.)"""
    robot.odom(t_s=t_s)
    scans, plans = robot.count("scan"), robot.count("plan")
    robot.put("scan", laser_scan(np.full(SCENARIO.sensor.rays, np.inf), t_s=t_s, angle_min=-math.pi / 2,
                                 angle_increment=math.pi / SCENARIO.sensor.rays))
    scan = robot.wait("scan", after=scans)
    publish_path(robot, path_to_the_goals(scan_seq=scan.header.seq, plan_id=plan_id))
    return robot.wait("plan", after=plans)


def test_the_bridge_is_a_ros_node_that_turns_the_robots_topics_into_the_pipelines_and_back(robot) -> None:
    entities = [e for e in graph(robot.session) if e.node_name == "cvxnav_bridge"]
    by_topic = {(e.kind, e.topic): e for e in entities if e.kind != EntityKind.NODE}
    assert {e.node_fqn for e in entities} == {"/robot9/cvxnav_bridge"}
    assert set(by_topic) == {(EntityKind.PUBLISHER if t.direction == "out" else EntityKind.SUBSCRIPTION,
                              f"/robot9/{t.name}") for t in BRIDGE_TOPICS.values()}
    for (_, topic), entity in by_topic.items():
        spec = BRIDGE_TOPICS[topic.rsplit("/", 1)[1]]
        assert (entity.msgtype, entity.type_hash) == (spec.msgtype, spec.type_hash)

    # Odometry: the robot state for the planner, and a command (zero: no plan yet) with rmw's attachment.
    twist, attachment, cmd_key = robot.odom(t_s=100.0, x=0.0, y=0.0)
    state = robot.wait("state")
    assert (state.pose.x_m, state.pose.y_m, state.pose.theta_rad) == pytest.approx((0.0, 0.0, math.pi / 4))
    assert cmd_key == topic_key(domain_id=DOMAIN, topic="/robot9/cmd_vel", msgtype="geometry_msgs/msg/Twist",
                                type_hash=BRIDGE_TOPICS["cmd_vel"].type_hash)
    (publisher,) = [token for token, e in tokens(robot.session).items() if e.topic == "/robot9/cmd_vel"
                    and e.kind == EntityKind.PUBLISHER]
    assert attachment.source_gid == gid_of(publisher)
    numbers = [a.sequence_number for _, a, _ in robot.received["cmd_vel"]]
    assert numbers == list(range(numbers[0], numbers[0] + len(numbers)))  # every command, in order
    assert (twist.linear.x, twist.angular.z) == (0.0, 0.0)

    # A scan becomes the pipeline's; the pipeline's verified path becomes /plan, stamped with the scan.
    # (A wall to the left of the path: the guard refuses a path into the robot's own hits.)
    robot.put("scan", laser_scan([2.0, 2.0], t_s=100.05, angle_min=1.0, angle_increment=0.1))
    scan = robot.wait("scan")
    angles = (math.pi / 4 + 1.0, math.pi / 4 + 1.1)
    np.testing.assert_allclose(scan.points, [(2 * math.cos(a), 2 * math.sin(a)) for a in angles], atol=1e-6)
    plan, _, plan_key = scan_and_plan(robot, t_s=100.1)
    assert plan_key.startswith(f"{DOMAIN}/robot9/plan/nav_msgs::msg::dds_::Path_/RIHS01_")
    assert plan.header.frame_id == "odom" and (plan.header.stamp.sec, plan.header.stamp.nanosec) == (100, 100_000_000)
    ends = [(p.pose.position.x, p.pose.position.y) for p in (plan.poses[0], plan.poses[-1])]
    assert ends == [pytest.approx((0.0, 0.0)), pytest.approx((15.0, 15.0))]

    # Now the robot is driven along it, within the speed bound, on the plan's straight line.
    for k in range(1, 6):
        speed, turn = cmd(robot.odom(t_s=100.1 + 0.1 * k, speed=0.3))
        assert 0.0 < speed <= SCENARIO.robot.max_speed and turn == pytest.approx(0.0, abs=1e-9)


def test_bad_input_is_an_error_on_the_status_key_the_robot_brakes_and_the_bridge_carries_on(robot) -> None:
    robot.odom(t_s=10.0)
    scan_and_plan(robot, t_s=10.0)
    other_hash = BRIDGE_TOPICS["odom"].type_hash
    impostor = robot.node.publisher(topic="scan", msgtype="sensor_msgs/msg/LaserScan", type_hash=other_hash)
    time.sleep(0.3)
    good_scan = laser_scan(np.full(SCENARIO.sensor.rays, np.inf), t_s=10.1, angle_min=-1.5, angle_increment=0.01)
    bad = [
        (lambda: robot.put("scan", good_scan[:40]), "scan", "malformed CDR"),
        (lambda: impostor.put(good_scan), "scan", f"type hash {other_hash} is not sensor_msgs/msg/LaserScan's"),
        (lambda: robot.put("scan", laser_scan(np.full(100_000, 2.0), t_s=10.1, angle_min=-1.5, angle_increment=3e-5)),
         "scan", "rays (the scenario's sensor.rays): 100000 exceeds the limit of"),
        (lambda: robot.put("odom", odometry(x=math.nan, y=0.0, yaw=0.0, t_s=10.1)), "odom", "not finite: x=nan"),
        (lambda: robot.put("odom", odometry(x=0.0, y=0.0, yaw=0.0, t_s=10.1, frame="map")), "odom",
         "header.frame_id changed from 'odom' to 'map' mid-run"),
    ]
    for k, (send, topic, reason) in enumerate(bad):
        speed, _ = cmd(robot.odom(t_s=10.2 + k))  # driving on the plan ...
        assert speed > 0.0
        before, statuses = robot.count("cmd_vel"), robot.count("status")
        send()
        status = robot.error(reason, after=statuses)  # ... a clear error on the bridge's status key ...
        assert status.stage == "ros2" and status.reason.startswith(f"{topic}: ") and "\n" not in status.reason
        assert status.input_key.startswith(f"{DOMAIN}/robot9/{topic}/")
        assert cmd(robot.wait("cmd_vel", after=before)) == (0.0, 0.0)  # ... the robot brakes at once ...
        assert cmd(robot.odom(t_s=10.3 + k)) == (0.0, 0.0)  # ... and stands until the next verified plan ...
        scan_and_plan(robot, t_s=10.4 + k, plan_id=2 + k)  # ... which the bridge, still running, follows.
    # Nothing else was lost: every good scan reached the pipeline, numbered without a gap, and the goal stands.
    assert [s.header.seq for s in robot.received["scan"]] == list(range(1 + len(bad)))
    assert robot.received["state"][-1].goal_index == 0 and not robot.received["goals"]


def test_a_payload_over_its_topics_cap_is_refused_undecoded(robot) -> None:
    robot.odom(t_s=1.0)
    statuses = robot.count("status")
    side = math.isqrt(MAX_MAP_CELLS) + 64  # a grid past the /map cap
    robot.put("map", occupancy_grid(np.zeros(side * side), width=side, height=side, resolution_m=0.05,
                                    origin=(0.0, 0.0)))
    status = robot.error("exceeds max_payload_bytes=", after=statuses)
    assert status.input_key.startswith(f"{DOMAIN}/robot9/map/nav_msgs::msg::dds_::OccupancyGrid_/")
    # A map within the cap is taken: no error; the next odometry goes through.
    robot.put("map", occupancy_grid([0, 100, -1, 0], width=2, height=2, resolution_m=0.05, origin=(0.0, 0.0)))
    robot.odom(t_s=1.1)
    time.sleep(0.2)
    assert [s for s in robot.received["status"][statuses:] if "exceeds" not in s.reason] == []


def test_a_goal_pose_becomes_the_pipelines_goals_and_a_restarted_stage_gets_them(robot) -> None:
    robot.odom(t_s=5.0)
    robot.put("goal_pose", goal_pose(x=4.0, y=1.0, t_s=5.0))
    goals = robot.wait("goals")
    assert goals.goals == [(4.0, 1.0)]
    (reply,) = [r.ok for r in robot.session.get(key(PREFIX, "goals"), timeout=2.0) if r.ok is not None]
    assert decode(Goals, reply.payload.to_bytes()).goals == [(4.0, 1.0)]
    # The scenario's path no longer ends at the goal: it is not published on /plan, nor followed.
    scans, plans = robot.count("scan"), robot.count("plan")
    robot.put("scan", laser_scan([np.inf], t_s=5.1, angle_min=0.0, angle_increment=0.0))
    publish_path(robot, path_to_the_goals(scan_seq=robot.wait("scan", after=scans).header.seq))
    assert cmd(robot.odom(t_s=5.2)) == (0.0, 0.0) and robot.count("plan") == plans


def test_a_lost_stage_or_silent_odometry_brakes_the_robot(robot) -> None:
    robot.odom(t_s=20.0)
    scan_and_plan(robot, t_s=20.0)
    assert cmd(robot.odom(t_s=20.1))[0] > 0.0
    robot.stage_tokens.pop("planner").undeclare()
    time.sleep(0.3)
    assert cmd(robot.odom(t_s=20.2)) == (0.0, 0.0)
    # The odometry falls silent: the timer commands zero, over and over, until it is back.
    before = robot.count("cmd_vel")
    time.sleep(2.0)
    silent = robot.received["cmd_vel"][before:]
    assert len(silent) >= 5 and all(cmd(c) == (0.0, 0.0) for c in silent)


def test_stopping_leaves_the_robot_a_zero_command_and_the_graph_without_the_bridge(robot) -> None:
    robot.odom(t_s=30.0)
    scan_and_plan(robot, t_s=30.0)
    assert cmd(robot.odom(t_s=30.1))[0] > 0.0
    before = robot.count("cmd_vel")
    robot.stop.set()
    robot.thread.join(WAIT_S)
    assert not robot.thread.is_alive()
    assert cmd(robot.wait("cmd_vel", after=before)) == (0.0, 0.0)
    assert not [e for e in graph(robot.session) if e.node_name == "cvxnav_bridge"]
