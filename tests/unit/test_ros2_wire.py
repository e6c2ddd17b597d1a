"""rmw_zenoh's wire format, checked against the values rmw_zenoh itself documents and the ACES bag records.

Expected strings below are copied from ros2/rmw_zenoh ``docs/design.md`` at commit
99a6a2bd10b949052f4f12c5854825dc005e95a5 ("Topic and Service name mapping to Zenoh key expressions",
"Graph Cache", "Publishers"); rmw_zenoh_cpp's ``liveliness_utils.cpp``, ``attachment_helpers.cpp`` and
``qos.cpp`` at that time are what the docs describe. Every type hash is computed by rosbags.
"""

from __future__ import annotations

import struct

import pytest
import xxhash
from ruamel.yaml import YAML

from ros2_bag import aces_bag_dir
from services.ros2.interface import BRIDGE_TOPICS
from services.ros2.typesupport import type_hash
from services.ros2.wire import (
    LATCHED_QOS,
    RMW_ZENOH_DEFAULT_QOS,
    SENSOR_DATA_QOS,
    Durability,
    Endpoint,
    EntityKind,
    NodeInfo,
    QosProfile,
    RosNameError,
    TokenError,
    dds_type_name,
    gid_of,
    node_namespace,
    parse_token,
    resolve_topic,
    ros_type_name,
    topic_key,
)
from services.shell.ros2 import Attachment

# design.md: the demo_nodes_cpp chatter topic's type, std_msgs/msg/String.
STRING_HASH = "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18"
ADD_TWO_INTS_HASH = "RIHS01_e118de6bf5eeb66a2491b5bda11202e7b68f198d6f67922cf30364858239c81a"
LISTENER_ZID = "aac3178e146ba6f1fc6e6a4085e77f21"
TALKER_ZID = "8b20917502ee955ac4476e0266340d5c"


def test_rosbags_computes_the_rihs01_hash_rmw_zenoh_documents_for_std_msgs_string() -> None:
    assert type_hash("std_msgs/msg/String") == STRING_HASH


def test_data_keys_are_rmw_zenohs_examples() -> None:
    # design.md, "Topic and Service name mapping": chatter, chatter in /robot1, add_two_ints in domain 2.
    chatter = resolve_topic("chatter", namespace="/")
    assert topic_key(domain_id=0, topic=chatter, msgtype="std_msgs/msg/String", type_hash=STRING_HASH) == \
        f"0/chatter/std_msgs::msg::dds_::String_/{STRING_HASH}"
    namespaced = resolve_topic("chatter", namespace=node_namespace("robot1"))
    assert namespaced == "/robot1/chatter"
    assert topic_key(domain_id=0, topic=namespaced, msgtype="std_msgs/msg/String", type_hash=STRING_HASH) == \
        f"0/robot1/chatter/std_msgs::msg::dds_::String_/{STRING_HASH}"
    assert topic_key(domain_id=2, topic="/add_two_ints", msgtype="example_interfaces/srv/AddTwoInts",
                     type_hash=ADD_TWO_INTS_HASH) == \
        f"2/add_two_ints/example_interfaces::srv::dds_::AddTwoInts_/{ADD_TWO_INTS_HASH}"


def test_the_bridges_keys_carry_the_hashes_the_aces_bag_records(shared_dir) -> None:
    metadata = YAML(typ="safe").load((aces_bag_dir(shared_dir) / "metadata.yaml").read_text())
    recorded = {entry["topic_metadata"]["type"]: entry["topic_metadata"]["type_description_hash"]
                for entry in metadata["rosbag2_bagfile_information"]["topics_with_message_count"]}
    assert recorded["sensor_msgs/msg/LaserScan"] == \
        "RIHS01_64c191398013af96509d518dac71d5164f9382553fce5c1f8cca5be7924bd828"
    assert recorded["nav_msgs/msg/Odometry"].startswith("RIHS01_3cc97dc7")
    for topic in ("scan", "odom"):
        spec = BRIDGE_TOPICS[topic]
        assert spec.type_hash == recorded[spec.msgtype]
    key = topic_key(domain_id=0, topic="/scan", msgtype="sensor_msgs/msg/LaserScan",
                    type_hash=BRIDGE_TOPICS["scan"].type_hash)
    assert key == f"0/scan/sensor_msgs::msg::dds_::LaserScan_/{recorded['sensor_msgs/msg/LaserScan']}"


def test_humble_jazzy_and_kilted_define_the_bridges_types_alike() -> None:
    """Why Jazzy's hashes serve a Humble robot's bag: the definitions (so the hashes) are the same."""
    from rosbags.typesys import Stores, get_typestore

    stores = [get_typestore(s) for s in (Stores.ROS2_HUMBLE, Stores.ROS2_JAZZY, Stores.ROS2_KILTED)]
    for spec in BRIDGE_TOPICS.values():
        assert len({type_hash(spec.msgtype, store=store) for store in stores}) == 1, spec.msgtype


def test_liveliness_tokens_are_rmw_zenohs_examples() -> None:
    # design.md, "Graph Cache": the listener node, its subscription (depth 10), the talker's publisher (depth 7).
    listener = NodeInfo(domain_id=2, zid=LISTENER_ZID, node_id=0, name="listener")
    assert listener.token == f"@ros2_lv/2/{LISTENER_ZID}/0/0/NN/%/%/listener"
    subscription = Endpoint(node=listener, entity_id=10, kind=EntityKind.SUBSCRIPTION, topic="/chatter",
                            msgtype="std_msgs/msg/String", type_hash=STRING_HASH, qos=QosProfile(depth=10))
    assert subscription.token == (f"@ros2_lv/2/{LISTENER_ZID}/0/10/MS/%/%/listener/%chatter/"
                                  f"std_msgs::msg::dds_::String_/{STRING_HASH}/::,10:,:,:,,")
    talker = NodeInfo(domain_id=2, zid=TALKER_ZID, node_id=0, name="talker")
    publisher = Endpoint(node=talker, entity_id=10, kind=EntityKind.PUBLISHER, topic="/chatter",
                         msgtype="std_msgs/msg/String", type_hash=STRING_HASH, qos=QosProfile(depth=7))
    assert publisher.token == (f"@ros2_lv/2/{TALKER_ZID}/0/10/MP/%/%/talker/%chatter/"
                               f"std_msgs::msg::dds_::String_/{STRING_HASH}/::,7:,:,:,,")


def test_namespaced_tokens_mangle_every_slash() -> None:
    node = NodeInfo(domain_id=0, zid=TALKER_ZID, node_id=0, name="cvxnav_bridge", namespace="/fleet/robot1")
    endpoint = Endpoint(node=node, entity_id=3, kind=EntityKind.PUBLISHER,
                        topic=resolve_topic("plan", namespace=node.namespace), msgtype="nav_msgs/msg/Path",
                        type_hash=type_hash("nav_msgs/msg/Path"), qos=QosProfile())
    assert endpoint.key_expr.startswith("0/fleet/robot1/plan/nav_msgs::msg::dds_::Path_/RIHS01_")
    assert endpoint.token.startswith(f"@ros2_lv/0/{TALKER_ZID}/0/3/MP/%/%fleet%robot1/cvxnav_bridge/"
                                     "%fleet%robot1%plan/nav_msgs::msg::dds_::Path_/RIHS01_")


@pytest.mark.parametrize("token", [
    f"@ros2_lv/2/{LISTENER_ZID}/0/0/NN/%/%/listener",
    f"@ros2_lv/2/{LISTENER_ZID}/0/10/MS/%/%/listener/%chatter/std_msgs::msg::dds_::String_/{STRING_HASH}/::,10:,:,:,,",
    f"@ros2_lv/2/{TALKER_ZID}/0/10/MP/%/%/talker/%chatter/std_msgs::msg::dds_::String_/{STRING_HASH}/::,7:,:,:,,",
])
def test_parsing_a_token_gives_back_the_entity_it_was_made_from(token: str) -> None:
    entity = parse_token(token)
    node = NodeInfo(domain_id=entity.domain_id, zid=entity.zid, node_id=entity.node_id, name=entity.node_name,
                    namespace=entity.namespace, enclave=entity.enclave)
    if entity.kind == EntityKind.NODE:
        assert node.token == token
        return
    assert entity.topic == "/chatter" and entity.msgtype == "std_msgs/msg/String"
    assert entity.type_hash == STRING_HASH and entity.node_fqn == f"/{entity.node_name}"
    rebuilt = Endpoint(node=node, entity_id=entity.entity_id, kind=entity.kind, topic=entity.topic,
                       msgtype=entity.msgtype, type_hash=entity.type_hash, qos=entity.qos)
    assert rebuilt.token == token


@pytest.mark.parametrize("token, reason", [
    ("cvxnav/robot1/alive/sim", "chunks"),
    (f"@ros2_lv/0/{TALKER_ZID}/0/0/XX/%/%/talker", "entity kind"),
    (f"@ros2_lv/0/{TALKER_ZID}/zero/0/NN/%/%/talker", "integers"),
    (f"@ros2_lv/0/{TALKER_ZID}/0/1/MP/%/%/talker/%chatter", "needs topic"),
    (f"@ros2_lv/0/{TALKER_ZID}/0/1/MP/%/%/talker/%chatter/String/{STRING_HASH}/::,7:,:,:,,", "DDS type"),
    (f"@ros2_lv/0/{TALKER_ZID}/0/1/MP/%/%/talker/%chatter/std_msgs::msg::dds_::String_/{STRING_HASH}/1:2", "QoS"),
])
def test_a_token_that_is_not_rmw_zenohs_is_refused_with_a_reason(token: str, reason: str) -> None:
    with pytest.raises(TokenError, match=reason):
        parse_token(token)


def test_qos_chunks_leave_rmw_zenohs_defaults_empty_and_parse_back() -> None:
    assert RMW_ZENOH_DEFAULT_QOS.to_keyexpr() == "::,:,:,:,,"  # qos.cpp: reliable, volatile, keep last 42
    assert QosProfile().to_keyexpr() == "::,10:,:,:,,"
    assert SENSOR_DATA_QOS.to_keyexpr() == "2::,5:,:,:,,"  # best effort (2), depth 5
    assert LATCHED_QOS.to_keyexpr() == ":1:,1:,:,:,,"  # transient local (1), depth 1
    for profile in (RMW_ZENOH_DEFAULT_QOS, QosProfile(), SENSOR_DATA_QOS, LATCHED_QOS):
        assert QosProfile.from_keyexpr(profile.to_keyexpr()) == profile
    assert QosProfile.from_keyexpr(":1:,1:,:,:,,").durability == Durability.TRANSIENT_LOCAL


def test_a_gid_is_the_xxh3_128_of_the_token_low_then_high_half_little_endian() -> None:
    # XXH3_128bits("") = {low64 0x6001C324468D497F, high64 0x99AA06D3014798D8}: xxHash's sanity test vector.
    assert gid_of("") == bytes.fromhex("7f498d4624c30160") + bytes.fromhex("d8984701d306aa99")
    token = f"@ros2_lv/2/{TALKER_ZID}/0/10/MP/%/%/talker/%chatter/std_msgs::msg::dds_::String_/{STRING_HASH}/::,7:,:,:,,"
    value = xxhash.xxh3_128_intdigest(token.encode())
    assert gid_of(token) == struct.pack("<QQ", value & (2**64 - 1), value >> 64)


def test_the_attachment_is_laid_out_byte_for_byte_as_design_md_says() -> None:
    # design.md, "Publishers": 8 bytes sequence number, 8 bytes timestamp (both int64 little-endian),
    # 1 byte for the GID's length (16), then the 16 GID bytes.
    gid = bytes(range(16))
    attachment = Attachment(sequence_number=7, source_timestamp_ns=1_700_000_000_123_456_789, source_gid=gid)
    data = attachment.to_bytes()
    assert data == struct.pack("<qqB16s", 7, 1_700_000_000_123_456_789, 16, gid)
    assert len(data) == 33
    assert Attachment.from_bytes(data) == attachment
    with pytest.raises(ValueError, match="not an rmw_zenoh attachment"):
        Attachment.from_bytes(data[:20])
    with pytest.raises(ValueError, match="16 bytes"):
        Attachment(sequence_number=1, source_timestamp_ns=0, source_gid=bytes(24))  # Humble's GID size


def test_names_follow_ros_rules() -> None:
    assert node_namespace("") == node_namespace("/") == "/"
    assert node_namespace("robot1") == node_namespace("/robot1") == "/robot1"
    assert resolve_topic("scan", namespace="/robot1") == "/robot1/scan"
    assert resolve_topic("/scan", namespace="/robot1") == "/scan"
    assert dds_type_name("nav_msgs/msg/Odometry") == "nav_msgs::msg::dds_::Odometry_"
    assert ros_type_name("nav_msgs::msg::dds_::Odometry_") == "nav_msgs/msg/Odometry"
    for bad in ("9robot", "robot-1", "a//b", "robot1/"):
        with pytest.raises(RosNameError):
            node_namespace(bad)
    with pytest.raises(RosNameError):
        resolve_topic("scan topic", namespace="/")
    with pytest.raises(RosNameError):
        dds_type_name("LaserScan")
    with pytest.raises(RosNameError, match="RIHS01"):
        topic_key(domain_id=0, topic="/scan", msgtype="sensor_msgs/msg/LaserScan", type_hash="TypeHashNotSupported")
