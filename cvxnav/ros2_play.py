"""`cvxnav ros2 play`: a recorded rosbag2 published on rmw_zenoh's keys, in real time, without ROS.

The bag is read by rosbags (``AnyReader``: MCAP or sqlite3 storage, with or without embedded message
definitions) and each message's CDR bytes go out unchanged on its topic's data key with the rmw
attachment, from one node (``cvxnav_play``) whose liveliness tokens show it and its publishers in the
ROS graph, as ``ros2 bag play`` would appear. A message recorded t seconds after the first is published
t / rate seconds after the start (rosbag2's receive time); ``loop`` starts over after the last.

A topic's type hash is computed from the definition the bag carries (rosbags' typestore of the bag,
else ROS 2 Jazzy's standard interfaces), so the key matches the bytes; a bag whose metadata records a
different hash for a topic is refused rather than published on a key its subscribers would not match.
Topic names are taken relative to ``namespace`` ("/scan" plays as "/robot1/scan" under ``robot1``).
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import zenoh
from rosbags.highlevel import AnyReader, AnyReaderError
from rosbags.interfaces import Connection, Qos
from rosbags.rosbag2 import ReaderError
from rosbags.typesys.store import Typestore

from services.ros2 import typesupport
from services.ros2.wire import (
    INFINITE,
    RMW_ZENOH_DEFAULT_QOS,
    Durability,
    History,
    Liveliness,
    QosProfile,
    Reliability,
    RmwDuration,
    RosNameError,
    resolve_topic,
)
from services.shell.ros2 import RosNode

logger = logging.getLogger(__name__)

PLAY_NODE = "cvxnav_play"
_WAIT_SLICE_S = 0.05  # the longest the player sleeps before looking at the stop event again


class BagError(ValueError):
    """A bag that cannot be played (missing, unreadable, a type no definition is known for); one line."""


@dataclass(frozen=True)
class BagTopic:
    """One recorded topic as it will be published."""

    topic: str  # as recorded, e.g. /scan
    msgtype: str
    type_hash: str
    qos: QosProfile
    message_count: int


@contextmanager
def open_bag(path: Path) -> Iterator[AnyReader]:
    """The opened bag; `BagError` with one line if it is missing or not a rosbag2 rosbags can read."""
    if not Path(path).exists():
        raise BagError(f"{path}: no such bag")
    try:
        reader = AnyReader([Path(path)], default_typestore=typesupport.jazzy())
        reader.open()
    except (AnyReaderError, OSError, ValueError, KeyError) as error:
        raise BagError(f"{path}: not a readable rosbag2 ({str(error).splitlines()[0] if str(error) else error!r})") \
            from None
    try:
        yield reader
    finally:
        reader.close()


def _store_for(reader: AnyReader, msgtype: str) -> Typestore:
    """The typestore that defines ``msgtype``: the bag's own definitions first, else Jazzy's."""
    if msgtype in reader.typestore.fielddefs:
        return reader.typestore
    if msgtype in typesupport.jazzy().fielddefs:
        return typesupport.jazzy()
    raise BagError(f"unknown message type {msgtype!r}: the bag carries no definition of it and it is not "
                   f"among the {typesupport.DISTRO.value} standard interfaces")


def recorded_qos(profiles: list[Qos]) -> QosProfile:
    """The first recorded QoS profile as rmw_zenoh adapts it (``best_available_qos``), else rclcpp's default.

    A policy left to the system (or unknown, or best available) takes rmw_zenoh's default; a zero
    duration or depth, likewise.
    """
    if not profiles:
        return QosProfile()
    q, default = profiles[0], RMW_ZENOH_DEFAULT_QOS

    def policy(enum, value: int, fallback):
        return enum(value) if value in _CONCRETE[enum] else fallback

    def duration(value) -> RmwDuration:
        return INFINITE if (value.sec, value.nsec) == (0, 0) else RmwDuration(sec=value.sec, nsec=value.nsec)

    return QosProfile(
        reliability=policy(Reliability, q.reliability.value, default.reliability),
        durability=policy(Durability, q.durability.value, default.durability),
        history=policy(History, q.history.value, default.history),
        depth=q.depth or default.depth,
        deadline=duration(q.deadline), lifespan=duration(q.lifespan),
        liveliness=policy(Liveliness, q.liveliness.value, default.liveliness),
        liveliness_lease=duration(q.liveliness_lease_duration))


_CONCRETE = {
    Reliability: {Reliability.RELIABLE, Reliability.BEST_EFFORT},
    Durability: {Durability.TRANSIENT_LOCAL, Durability.VOLATILE},
    History: {History.KEEP_LAST, History.KEEP_ALL},
    Liveliness: {Liveliness.AUTOMATIC, Liveliness.MANUAL_BY_TOPIC},
}


def bag_topics(reader: AnyReader) -> dict[int, BagTopic]:
    """Every connection of the bag by id, checked playable: CDR, a known type, a hash that matches."""
    topics = {}
    for connection in reader.connections:
        topics[connection.id] = _bag_topic(reader, connection)
    if not topics:
        raise BagError("the bag has no topics")
    return topics


def _bag_topic(reader: AnyReader, connection: Connection) -> BagTopic:
    fmt = getattr(connection.ext, "serialization_format", "cdr")
    if fmt != "cdr":
        raise BagError(f"{connection.topic}: serialization {fmt!r} is not CDR")
    store = _store_for(reader, connection.msgtype)
    try:
        computed = typesupport.type_hash(connection.msgtype, store=store)
    except RosNameError as error:
        raise BagError(f"{connection.topic}: {error}") from None
    recorded = connection.digest if str(connection.digest).startswith("RIHS01_") else None
    if recorded is not None and recorded != computed:
        raise BagError(f"{connection.topic}: the bag records type hash {recorded} for {connection.msgtype}, but its "
                       f"definition hashes to {computed}")
    return BagTopic(topic=connection.topic, msgtype=connection.msgtype, type_hash=computed,
                    qos=recorded_qos(list(connection.ext.offered_qos_profiles)), message_count=connection.msgcount)


def play(
    *,
    reader: AnyReader,
    session: zenoh.Session,
    rate: float,
    loop: bool,
    domain_id: int,
    namespace: str,
    stop_event: threading.Event,
    delay_s: float = 0.0,
) -> int:
    """Publish the bag until its end (or forever with ``loop``) or ``stop_event``; how many messages went out.

    ``delay_s`` passes between declaring the node and the first message (and before each loop), as
    ``ros2 bag play --delay``: time for subscribers to learn of the new publishers.
    """
    topics = bag_topics(reader)
    node = RosNode(session, name=PLAY_NODE, namespace=namespace, domain_id=domain_id)
    published = 0
    try:
        publishers = {}
        for connection_id, topic in topics.items():
            name = resolve_topic(topic.topic.lstrip("/"), namespace=node.info.namespace)
            publishers[connection_id] = node.publisher(topic=name, msgtype=topic.msgtype, type_hash=topic.type_hash,
                                                       qos=topic.qos)
        logger.info("playing %s on domain %d: %s", ", ".join(str(p) for p in reader.paths), domain_id,
                    ", ".join(p.endpoint.topic for p in publishers.values()))
        while not stop_event.wait(delay_s):
            start_wall = time.monotonic()
            start_bag_ns = None
            for connection, stamp_ns, payload in _messages(reader):
                start_bag_ns = stamp_ns if start_bag_ns is None else start_bag_ns
                due = start_wall + (stamp_ns - start_bag_ns) * 1e-9 / rate
                while not stop_event.is_set() and (wait := due - time.monotonic()) > 0.0:
                    stop_event.wait(min(wait, _WAIT_SLICE_S))
                if stop_event.is_set():
                    break
                publishers[connection.id].put(bytes(payload))
                published += 1
            if not loop:
                break
    finally:
        node.close()
    return published


def _messages(reader: AnyReader) -> Iterator[tuple[Connection, int, bytes]]:
    """The bag's messages in time order; a storage error part-way through is a `BagError`."""
    try:
        yield from reader.messages()
    except (AnyReaderError, ReaderError) as error:
        raise BagError(f"{', '.join(str(p) for p in reader.paths)}: unreadable part-way: {error}") from None
