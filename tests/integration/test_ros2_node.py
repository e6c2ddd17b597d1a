"""A ROS 2 node as rmw_zenoh declares it, over real Zenoh sessions: two peers on tcp/127.0.0.1, no scouting."""

from __future__ import annotations

import time
from collections.abc import Iterator

import pytest
import zenoh

from cvxnav.supervisor import free_ports
from services.ros2.typesupport import type_hash
from services.ros2.wire import LATCHED_QOS, EntityKind, parse_token
from services.shell.ros2 import Attachment, RosNode
from services.shell.zenoh_config import build_zenoh_config

WAIT_S = 5.0
GRID = "nav_msgs/msg/OccupancyGrid"


@pytest.fixture
def peers() -> Iterator[tuple[zenoh.Session, zenoh.Session]]:
    endpoint = f"tcp/127.0.0.1:{free_ports(1)[0]}"
    with zenoh.open(build_zenoh_config(listen=[endpoint])) as a, zenoh.open(build_zenoh_config(connect=[endpoint])) as b:
        yield a, b


def wait_until(predicate, *, timeout_s: float = WAIT_S) -> None:
    deadline = time.monotonic() + timeout_s
    while not predicate():
        if time.monotonic() > deadline:
            pytest.fail("timed out")
        time.sleep(0.01)


def graph(session: zenoh.Session, domain_id: int = 0) -> list:
    return [parse_token(str(reply.ok.key_expr)) for reply in session.liveliness().get(f"@ros2_lv/{domain_id}/**",
                                                                                      timeout=2.0) if reply.ok]


def test_samples_carry_rmw_zenohs_attachment_and_the_graph_shows_the_node(peers) -> None:
    a, b = peers
    node = RosNode(a, name="cvxnav_bridge", namespace="robot1", domain_id=3)
    publisher = node.publisher(topic="plan", msgtype="nav_msgs/msg/Path", type_hash=type_hash("nav_msgs/msg/Path"))
    node.subscription(topic="scan", msgtype="sensor_msgs/msg/LaserScan",
                      type_hash=type_hash("sensor_msgs/msg/LaserScan"), handler=lambda sample: None)
    received = []
    subscriber = b.declare_subscriber(publisher.endpoint.key_expr, received.append)
    wait_until(lambda: {e.kind for e in graph(b, 3)} == {EntityKind.NODE, EntityKind.PUBLISHER,
                                                         EntityKind.SUBSCRIPTION})
    entities = {entity.kind: entity for entity in graph(b, 3)}
    assert {e.node_fqn for e in entities.values()} == {"/robot1/cvxnav_bridge"}
    assert entities[EntityKind.NODE].zid == str(a.zid()) and entities[EntityKind.NODE].entity_id == 0
    assert (entities[EntityKind.PUBLISHER].topic, entities[EntityKind.PUBLISHER].msgtype) == \
        ("/robot1/plan", "nav_msgs/msg/Path")
    assert entities[EntityKind.SUBSCRIPTION].topic == "/robot1/scan"
    assert publisher.endpoint.key_expr.startswith("3/robot1/plan/nav_msgs::msg::dds_::Path_/RIHS01_")
    time.sleep(0.2)  # the subscriber's declaration reaches the publisher's session
    before_ns = time.time_ns()
    sent = [publisher.put(bytes([0, 1, 0, 0, k])) for k in range(3)]
    wait_until(lambda: len(received) == 3)
    for k, (sample, attachment) in enumerate(zip(received, sent)):
        assert str(sample.key_expr) == publisher.endpoint.key_expr
        assert sample.payload.to_bytes() == bytes([0, 1, 0, 0, k])
        parsed = Attachment.from_bytes(sample.attachment.to_bytes())
        assert parsed == attachment and parsed.sequence_number == k + 1
        assert parsed.source_gid == publisher.endpoint.gid
        assert before_ns <= parsed.source_timestamp_ns <= time.time_ns()
    subscriber.undeclare()
    node.close()
    wait_until(lambda: graph(b, 3) == [])


def test_a_latched_map_reaches_a_subscription_that_starts_later(peers) -> None:
    a, b = peers
    publisher = RosNode(a, name="map_server").publisher(topic="map", msgtype=GRID, type_hash=type_hash(GRID),
                                                        qos=LATCHED_QOS)
    publisher.put(b"\x00\x01\x00\x00grid")
    time.sleep(0.3)
    received = []
    RosNode(b, name="cvxnav_bridge").subscription(topic="map", msgtype=GRID, type_hash=type_hash(GRID),
                                                  handler=received.append, qos=LATCHED_QOS)
    wait_until(lambda: len(received) == 1)
    assert received[0].payload.to_bytes() == b"\x00\x01\x00\x00grid"
    assert Attachment.from_bytes(received[0].attachment.to_bytes()).source_gid == publisher.endpoint.gid


def test_a_subscription_hears_a_publisher_of_another_definition(peers) -> None:
    """So the bridge can say why it refuses it, rather than never hearing it."""
    a, b = peers
    received = []
    RosNode(b, name="cvxnav_bridge").subscription(topic="odom", msgtype="nav_msgs/msg/Odometry",
                                                  type_hash=type_hash("nav_msgs/msg/Odometry"), handler=received.append)
    other = RosNode(a, name="robot").publisher(topic="odom", msgtype="nav_msgs/msg/Odometry",
                                               type_hash="RIHS01_" + "0" * 64)
    deeper = RosNode(a, name="other").publisher(topic="odom/filtered", msgtype="nav_msgs/msg/Odometry",
                                                type_hash=type_hash("nav_msgs/msg/Odometry"))
    time.sleep(0.3)
    other.put(b"\x00\x01\x00\x00")
    deeper.put(b"\x00\x01\x00\x00")
    wait_until(lambda: len(received) >= 1)
    time.sleep(0.2)
    assert [str(s.key_expr) for s in received] == ["0/odom/nav_msgs::msg::dds_::Odometry_/RIHS01_" + "0" * 64]
