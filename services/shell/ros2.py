"""A ROS 2 node on a Zenoh session, declared as rmw_zenoh declares one (Jazzy and later), and the rmw
attachment every sample carries.

One Zenoh session is one ROS context: its node gets the first id of the context's counter and each
publisher or subscription the next (``rmw_context_impl_s``), each holds its liveliness token
(``services.ros2.wire``) while it exists, and every sample goes out with the rmw attachment. Publishers
and subscriptions are zenoh-ext's advanced ones, configured as ``rmw_publisher_data.cpp`` and
``rmw_subscription_data.cpp`` configure them: for a transient-local topic the publisher keeps a cache of
``depth`` samples and announces itself (with sporadic heartbeats when reliable), and the subscription
detects late publishers and queries their caches, so a latched /map reaches a bridge that starts later.

Subscriptions listen to every type and hash of their topic (`wire.topic_key_any_type`) so that a
publisher of a different definition is reported rather than silently never heard.

The bridge's node (`BridgePorts`) is the one the shell declares for a process that is also a ROS 2 node
(``StageSpec.ros2``), with the bridge's interface (``services.ros2.interface``).

The attachment of every sample (``attachment_helpers.cpp``): sequence number (int64), source timestamp
(int64 ns since the epoch), GID (16 bytes), written with the Zenoh serialization format (zenoh-ext),
so 8 + 8 + 1 (the GID's LEB128 length, 16) + 16 bytes, all little-endian. rmw_zenoh's subscriptions
drop a sample that has none.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass

import zenoh
import zenoh.ext

from services.ros2.interface import BRIDGE_NODE, BRIDGE_TOPICS
from services.ros2.wire import (
    GID_BYTES,
    EntityKind,
    Endpoint,
    History,
    NodeInfo,
    QosProfile,
    Reliability,
    resolve_topic,
    topic_key_any_type,
)

# Period of the sample-miss heartbeats of a reliable transient-local publisher (rmw_publisher_data.cpp).
_HEARTBEAT_S = 0.5


@dataclass(frozen=True)
class Attachment:
    """The metadata rmw_zenoh sends with every sample and its subscriptions require."""

    sequence_number: int  # the publisher's, from 1
    source_timestamp_ns: int  # when it was published, ns since the Unix epoch
    source_gid: bytes  # the publisher's GID

    def __post_init__(self) -> None:
        if len(self.source_gid) != GID_BYTES:
            raise ValueError(f"a GID has {GID_BYTES} bytes, got {len(self.source_gid)}")

    def to_bytes(self) -> bytes:
        """Serialised as rmw_zenoh's ``AttachmentData::serialize_to_zbytes`` (zenoh-ext format)."""
        value = (zenoh.ext.Int64(self.sequence_number), zenoh.ext.Int64(self.source_timestamp_ns),
                 bytes(self.source_gid))
        return zenoh.ext.z_serialize(value).to_bytes()

    @classmethod
    def from_bytes(cls, data: bytes) -> Attachment:
        """Parse an attachment; ValueError (one line) if it is not rmw_zenoh's."""
        try:
            sequence, stamp, gid = zenoh.ext.z_deserialize(tuple[zenoh.ext.Int64, zenoh.ext.Int64, bytes],
                                                           zenoh.ZBytes(bytes(data)))
        except zenoh.ext.ZDeserializeError as error:
            raise ValueError(f"not an rmw_zenoh attachment ({len(data)} bytes): {error}") from None
        return cls(sequence_number=int(sequence), source_timestamp_ns=int(stamp), source_gid=bytes(gid))


@dataclass
class RosPublisher:
    endpoint: Endpoint
    publisher: zenoh.ext.AdvancedPublisher
    token: zenoh.LivelinessToken
    sequence_number: int = 1  # rmw_zenoh's first sample is number 1

    def put(self, payload: bytes, *, source_timestamp_ns: int | None = None) -> Attachment:
        """Publish CDR bytes with the attachment rmw_zenoh's subscriptions require; returns that attachment."""
        attachment = Attachment(sequence_number=self.sequence_number,
                                source_timestamp_ns=time.time_ns() if source_timestamp_ns is None
                                else source_timestamp_ns,
                                source_gid=self.endpoint.gid)
        self.publisher.put(payload, attachment=attachment.to_bytes())
        self.sequence_number += 1
        return attachment

    def undeclare(self) -> None:
        self.token.undeclare()
        self.publisher.undeclare()


@dataclass
class RosSubscription:
    endpoint: Endpoint
    subscriber: zenoh.ext.AdvancedSubscriber
    token: zenoh.LivelinessToken

    def undeclare(self) -> None:
        self.token.undeclare()
        self.subscriber.undeclare()


class RosNode:
    """A node, its publishers and its subscriptions on ``session``; ``close`` undeclares them all."""

    def __init__(self, session: zenoh.Session, *, name: str, namespace: str = "/", domain_id: int = 0) -> None:
        self.session = session
        self.info = NodeInfo(domain_id=domain_id, zid=str(session.zid()), node_id=0, name=name, namespace=namespace)
        self._next_id = self.info.node_id + 1
        self.token = session.liveliness().declare_token(self.info.token)
        self.publishers: list[RosPublisher] = []
        self.subscriptions: list[RosSubscription] = []

    def _endpoint(self, *, kind: EntityKind, topic: str, msgtype: str, type_hash: str, qos: QosProfile) -> Endpoint:
        endpoint = Endpoint(node=self.info, entity_id=self._next_id, kind=kind,
                            topic=resolve_topic(topic, namespace=self.info.namespace), msgtype=msgtype,
                            type_hash=type_hash, qos=qos)
        self._next_id += 1
        return endpoint

    def publisher(self, *, topic: str, msgtype: str, type_hash: str, qos: QosProfile = QosProfile()) -> RosPublisher:
        endpoint = self._endpoint(kind=EntityKind.PUBLISHER, topic=topic, msgtype=msgtype, type_hash=type_hash,
                                  qos=qos)
        reliable = qos.reliability == Reliability.RELIABLE
        options: dict = {}
        if qos.transient_local:
            options = dict(cache=zenoh.ext.CacheConfig(max_samples=qos.depth), publisher_detection=True)
            if reliable:
                options["sample_miss_detection"] = zenoh.ext.MissDetectionConfig(heartbeat=None,
                                                                                  sporadic_heartbeat=_HEARTBEAT_S)
        # A reliable keep-all publisher blocks rather than drop when the network cannot keep up.
        block = reliable and qos.history == History.KEEP_ALL
        publisher = zenoh.ext.declare_advanced_publisher(
            self.session, endpoint.key_expr,
            reliability=zenoh.Reliability.RELIABLE if reliable else zenoh.Reliability.BEST_EFFORT,
            congestion_control=zenoh.CongestionControl.BLOCK if block else zenoh.CongestionControl.DROP, **options)
        entity = RosPublisher(endpoint=endpoint, publisher=publisher,
                              token=self.session.liveliness().declare_token(endpoint.token))
        self.publishers.append(entity)
        return entity

    def subscription(self, *, topic: str, msgtype: str, type_hash: str, handler: Callable[[zenoh.Sample], None],
                     qos: QosProfile = QosProfile()) -> RosSubscription:
        """Subscribe ``handler`` to every sample on ``topic``, whatever type hash its key carries."""
        endpoint = self._endpoint(kind=EntityKind.SUBSCRIPTION, topic=topic, msgtype=msgtype, type_hash=type_hash,
                                  qos=qos)
        options: dict = {}
        if qos.transient_local:
            options = dict(history=zenoh.ext.HistoryConfig(detect_late_publishers=True, max_samples=qos.depth),
                           subscriber_detection=True)
            if qos.reliability == Reliability.RELIABLE:
                options["recovery"] = zenoh.ext.RecoveryConfig(periodic_queries=None, heartbeat=True)
        key = topic_key_any_type(domain_id=self.info.domain_id, topic=endpoint.topic)
        subscriber = zenoh.ext.declare_advanced_subscriber(self.session, key, handler, **options)
        entity = RosSubscription(endpoint=endpoint, subscriber=subscriber,
                                 token=self.session.liveliness().declare_token(endpoint.token))
        self.subscriptions.append(entity)
        return entity

    def close(self) -> None:
        """Undeclare every entity, then the node (the order rmw_zenoh's graph sees them leave)."""
        for entity in [*self.publishers, *self.subscriptions]:
            entity.undeclare()
        self.publishers.clear()
        self.subscriptions.clear()
        self.token.undeclare()


class BridgePorts:
    """The ROS 2 bridge's node on the shell's session (``StageSpec.ros2``), its topics the bridge interface's.

    Every sample of an input topic goes to ``deliver(port, sample)`` (the shell's queue, in arrival
    order with the process's other inputs); ``put`` publishes a core's ``Raw`` bytes on an output topic
    with the attachment. The node and its publishers and subscriptions hold their liveliness tokens
    until ``close``.
    """

    def __init__(self, session: zenoh.Session, *, domain_id: int, namespace: str,
                 deliver: Callable[[str, zenoh.Sample], None]) -> None:
        self.node = RosNode(session, name=BRIDGE_NODE, namespace=namespace, domain_id=domain_id)
        self._publishers: dict[str, RosPublisher] = {}
        self._subscriptions: dict[str, RosSubscription] = {}
        for port, topic in BRIDGE_TOPICS.items():
            common = dict(topic=topic.name, msgtype=topic.msgtype, type_hash=topic.type_hash, qos=topic.qos)
            if topic.direction == "out":
                self._publishers[port] = self.node.publisher(**common)
            else:
                self._subscriptions[port] = self.node.subscription(
                    handler=lambda sample, port=port: deliver(port, sample), **common)

    @property
    def inputs(self) -> tuple[str, ...]:
        return tuple(self._subscriptions)

    def publishes(self, port: str) -> bool:
        return port in self._publishers

    def key(self, port: str) -> str:
        """The data key of ``port`` (for an input, the one its type and hash are expected on)."""
        entity = self._publishers.get(port) or self._subscriptions[port]
        return entity.endpoint.key_expr

    def max_payload_bytes(self, port: str) -> int:
        return BRIDGE_TOPICS[port].max_payload_bytes

    def put(self, port: str, payload: bytes) -> None:
        self._publishers[port].put(payload)

    def close(self) -> None:
        self.node.close()
