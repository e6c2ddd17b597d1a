"""The ACES laser log (`../shared/external/carmen/aces-bag`) read by the second, independent ROS 2 stack:
mcap's reader with mcap-ros2-support's decoder (schemas from the file), never rosbags, so a test that
compares what cvxnav produced with rosbags against these messages checks two implementations."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory

BAG_PARTS = ("external", "carmen", "aces-bag")
TOPIC_COUNTS = {"/scan": 440, "/odom": 440}


@dataclass(frozen=True)
class Recorded:
    topic: str
    schema_name: str  # e.g. sensor_msgs/msg/LaserScan
    log_time_ns: int
    data: bytes  # the CDR payload as recorded
    message: object  # decoded by mcap-ros2-support


def aces_bag_dir(shared_dir: Path) -> Path:
    return shared_dir.joinpath(*BAG_PARTS)


def read_mcap(path: Path) -> list[Recorded]:
    """Every message of an MCAP file in log-time order, decoded with the file's own schemas."""
    with path.open("rb") as stream:
        reader = make_reader(stream, decoder_factories=[DecoderFactory()])
        return [Recorded(topic=channel.topic, schema_name=schema.name, log_time_ns=message.log_time,
                         data=bytes(message.data), message=decoded)
                for schema, channel, message, decoded in reader.iter_decoded_messages(log_time_order=True)]


def independent_decoder(msgtype: str):
    """A decoder of ``msgtype`` CDR from mcap-ros2-support, given the type's .msg text.

    The text is the standard definition as rosbags writes it out (comments dropped); parsing it and
    decoding the bytes is all mcap-ros2-support's own code.
    """
    from mcap.records import Schema

    from services.ros2.typesupport import jazzy

    text, _ = jazzy().generate_msgdef(msgtype, ros_version=2)
    schema = Schema(id=1, name=msgtype, encoding="ros2msg", data=text.encode())
    return DecoderFactory().decoder_for("cdr", schema)
