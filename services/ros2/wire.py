"""rmw_zenoh's wire format (ROS 2 Jazzy and later), without ROS: names, keys, QoS, liveliness tokens, GIDs.

Everything here follows ros2/rmw_zenoh, `rolling` as of ``docs/design.md`` at commit 99a6a2bd
("Topic and Service name mapping to Zenoh key expressions", "Graph Cache", "Publishers") and the code
it describes, `rmw_zenoh_cpp/src/detail/`:

- data key (``liveliness_utils.cpp``, ``TopicInfo``): ``<domain_id>/<fully qualified name without its
  leading slash>/<DDS type name>/<type hash>``, the DDS type name ``<pkg>::msg::dds_::<Name>_``
  (``type_support_common.cpp``, ``_create_type_name``), the hash the type's RIHS01 string;
- liveliness tokens (``Entity::Entity``): ``@ros2_lv/<domain_id>/<zid>/<node_id>/<entity_id>/<kind>/
  <enclave>/<namespace>/<node name>`` and, for a publisher or subscription,
  ``/<topic>/<type>/<hash>/<qos>``; names "mangled" with each ``/`` replaced by ``%``; node, publisher
  and subscription ids come from one counter per context (the node's entity id is its node id);
- the QoS chunk (``qos_to_keyexpr``): ``R:D:H,depth:deadline_s,ns:lifespan_s,ns:liveliness,lease_s,ns``,
  each field left empty where it equals rmw_zenoh's default profile (``qos.cpp``);
- an entity's GID (``Entity::Entity``): the XXH3-128 hash of its liveliness key, low 64 bits then high
  64 bits, each little-endian (16 bytes, ``RMW_GID_STORAGE_SIZE``);
- the attachment of every sample, serialized with zenoh-ext, is the shell's (``services.shell.ros2``):
  this module is pure.

Types are the message types of rosbags' typestore (``services.ros2.typesupport``).
"""

from __future__ import annotations

import re
from dataclasses import dataclass, replace
from enum import Enum, IntEnum

import xxhash

ADMIN_SPACE = "@ros2_lv"
SLASH_REPLACEMENT = "%"
GID_BYTES = 16  # RMW_GID_STORAGE_SIZE from Jazzy on (Humble's was 24)
_QOS_DELIMITER = ":"
_QOS_COMPONENT_DELIMITER = ","
# A ROS name token: letters, digits and underscores, not starting with a digit (design article "Topic
# and Service Names"); rcl rejects the rest, and so do we rather than emit a key no ROS node could use.
_TOKEN = re.compile(r"[A-Za-z_][A-Za-z0-9_]*\Z")
_ROS_TYPE = re.compile(r"(?P<package>[A-Za-z][A-Za-z0-9_]*)/(?P<kind>msg|srv)/(?P<name>[A-Za-z][A-Za-z0-9_]*)\Z")
_DDS_TYPE = re.compile(r"(?P<package>[A-Za-z][A-Za-z0-9_]*)::(?P<kind>msg|srv)::dds_::(?P<name>[A-Za-z][A-Za-z0-9_]*)_\Z")
_RIHS01 = re.compile(r"RIHS01_[0-9a-f]{64}\Z")


class RosNameError(ValueError):
    """A ROS name, namespace or type name that no ROS 2 node would accept; the text is one line."""


class TokenError(ValueError):
    """A liveliness key that is not one of rmw_zenoh's entity tokens; the text is one line."""


# --------------------------------------------------------------------------- names


def node_namespace(namespace: str) -> str:
    """The absolute namespace for ``--namespace NS``: '' or '/' is the root '/', 'robot1' is '/robot1'."""
    text = namespace.strip()
    if text in ("", "/"):
        return "/"
    absolute = text if text.startswith("/") else "/" + text
    tokens = absolute[1:].split("/")
    for token in tokens:
        if not _TOKEN.match(token):
            raise RosNameError(f"namespace {namespace!r}: {token!r} is not a ROS name token "
                               "(letters, digits, underscores, not starting with a digit)")
    return absolute


def resolve_topic(name: str, *, namespace: str) -> str:
    """The fully qualified name of topic ``name`` in a node's ``namespace`` (absolute names stay as they are)."""
    if name.startswith("/"):
        tokens = name[1:].split("/")
        absolute = name
    else:
        tokens = name.split("/")
        absolute = (namespace.rstrip("/") + "/" + name) if namespace != "/" else "/" + name
    for token in tokens:
        if not _TOKEN.match(token):
            raise RosNameError(f"topic {name!r}: {token!r} is not a ROS name token")
    return absolute


def mangle(name: str) -> str:
    """A name as one key chunk: each '/' becomes '%' (``liveliness::mangle_name``)."""
    return name.replace("/", SLASH_REPLACEMENT)


def demangle(chunk: str) -> str:
    return chunk.replace(SLASH_REPLACEMENT, "/")


def dds_type_name(msgtype: str) -> str:
    """``sensor_msgs/msg/LaserScan`` → ``sensor_msgs::msg::dds_::LaserScan_`` (as rosidl_typesupport_fastrtps)."""
    match = _ROS_TYPE.match(msgtype)
    if match is None:
        raise RosNameError(f"type {msgtype!r} is not a ROS 2 interface name like 'sensor_msgs/msg/LaserScan'")
    return f"{match['package']}::{match['kind']}::dds_::{match['name']}_"


def ros_type_name(dds_name: str) -> str:
    """The inverse of `dds_type_name`."""
    match = _DDS_TYPE.match(dds_name)
    if match is None:
        raise RosNameError(f"type {dds_name!r} is not a DDS type name like 'sensor_msgs::msg::dds_::LaserScan_'")
    return f"{match['package']}/{match['kind']}/{match['name']}"


def topic_key(*, domain_id: int, topic: str, msgtype: str, type_hash: str) -> str:
    """The data key of a fully qualified ``topic`` carrying ``msgtype`` with RIHS01 ``type_hash``."""
    if not _RIHS01.match(type_hash):
        raise RosNameError(f"type hash {type_hash!r} is not 'RIHS01_' and 64 lowercase hex digits")
    return f"{domain_id}/{topic.strip('/')}/{dds_type_name(msgtype)}/{type_hash}"


def topic_key_any_type(*, domain_id: int, topic: str) -> str:
    """Every data key of ``topic``, whatever its type and hash: a subscriber that tells a wrong type apart.

    A topic's keys are exactly its name's chunks plus two (type, hash); a deeper topic such as
    ``/scan/front`` has one chunk more, so it never matches.
    """
    return f"{domain_id}/{topic.strip('/')}/*/*"


# --------------------------------------------------------------------------- QoS


class Reliability(IntEnum):  # rmw/types.h, rmw_qos_reliability_policy_e
    SYSTEM_DEFAULT = 0
    RELIABLE = 1
    BEST_EFFORT = 2
    UNKNOWN = 3
    BEST_AVAILABLE = 4


class Durability(IntEnum):  # rmw_qos_durability_policy_e
    SYSTEM_DEFAULT = 0
    TRANSIENT_LOCAL = 1
    VOLATILE = 2
    UNKNOWN = 3
    BEST_AVAILABLE = 4


class History(IntEnum):  # rmw_qos_history_policy_e
    SYSTEM_DEFAULT = 0
    KEEP_LAST = 1
    KEEP_ALL = 2
    UNKNOWN = 3


class Liveliness(IntEnum):  # rmw_qos_liveliness_policy_e
    SYSTEM_DEFAULT = 0
    AUTOMATIC = 1
    MANUAL_BY_TOPIC = 3
    UNKNOWN = 4
    BEST_AVAILABLE = 5


@dataclass(frozen=True)
class RmwDuration:
    sec: int
    nsec: int


INFINITE = RmwDuration(sec=9223372036, nsec=854775807)  # RMW_DURATION_INFINITE


@dataclass(frozen=True)
class QosProfile:
    """A QoS profile as rmw_zenoh holds it after ``best_available_qos`` (no SYSTEM_DEFAULT left)."""

    reliability: Reliability = Reliability.RELIABLE
    durability: Durability = Durability.VOLATILE
    history: History = History.KEEP_LAST
    depth: int = 10  # rclcpp's default depth
    deadline: RmwDuration = INFINITE
    lifespan: RmwDuration = INFINITE
    liveliness: Liveliness = Liveliness.AUTOMATIC
    liveliness_lease: RmwDuration = INFINITE

    @property
    def transient_local(self) -> bool:
        return self.durability == Durability.TRANSIENT_LOCAL

    def to_keyexpr(self) -> str:
        """The token's QoS chunk: every field equal to rmw_zenoh's default profile left empty."""
        d = RMW_ZENOH_DEFAULT_QOS

        def field(value: object, default: object) -> str:
            return "" if value == default else str(int(value))

        c, s = _QOS_COMPONENT_DELIMITER, _QOS_DELIMITER
        return (field(self.reliability, d.reliability) + s + field(self.durability, d.durability) + s
                + field(self.history, d.history) + c + field(self.depth, d.depth) + s
                + field(self.deadline.sec, d.deadline.sec) + c + field(self.deadline.nsec, d.deadline.nsec) + s
                + field(self.lifespan.sec, d.lifespan.sec) + c + field(self.lifespan.nsec, d.lifespan.nsec) + s
                + field(self.liveliness, d.liveliness) + c
                + field(self.liveliness_lease.sec, d.liveliness_lease.sec) + c
                + field(self.liveliness_lease.nsec, d.liveliness_lease.nsec))

    @classmethod
    def from_keyexpr(cls, chunk: str) -> QosProfile:
        """Parse a token's QoS chunk (``keyexpr_to_qos``); empty fields take rmw_zenoh's defaults."""
        parts = chunk.split(_QOS_DELIMITER)
        groups = [part.split(_QOS_COMPONENT_DELIMITER) for part in parts[2:6]] if len(parts) >= 6 else []
        if len(groups) != 4 or any(len(g) < n for g, n in zip(groups, (2, 2, 2, 3))):
            raise TokenError(f"QoS {chunk!r} is not R:D:H,depth:s,ns:s,ns:L,s,ns")
        (history, depth), deadline, lifespan, (liveliness, lease_s, lease_ns) = (
            groups[0][:2], groups[1][:2], groups[2][:2], groups[3][:3])
        d = RMW_ZENOH_DEFAULT_QOS
        try:
            return cls(
                reliability=Reliability(_number(parts[0], d.reliability)),
                durability=Durability(_number(parts[1], d.durability)),
                history=History(_number(history, d.history)),
                depth=_number(depth, d.depth),
                deadline=RmwDuration(sec=_number(deadline[0], d.deadline.sec), nsec=_number(deadline[1], d.deadline.nsec)),
                lifespan=RmwDuration(sec=_number(lifespan[0], d.lifespan.sec), nsec=_number(lifespan[1], d.lifespan.nsec)),
                liveliness=Liveliness(_number(liveliness, d.liveliness)),
                liveliness_lease=RmwDuration(sec=_number(lease_s, d.liveliness_lease.sec),
                                             nsec=_number(lease_ns, d.liveliness_lease.nsec)),
            )
        except ValueError as error:
            raise TokenError(f"QoS {chunk!r}: {error}") from None


def _number(text: str, default: int) -> int:
    if text == "":
        return int(default)
    if not text.isdigit():
        raise ValueError(f"{text!r} is not a non-negative integer")
    return int(text)


# rmw_zenoh's default profile (qos.cpp): the fields a token's QoS chunk leaves empty.
RMW_ZENOH_DEFAULT_QOS = QosProfile(depth=42)
# rclcpp's SensorDataQoS (what laser drivers and Nav2's costmaps use for /scan).
SENSOR_DATA_QOS = QosProfile(reliability=Reliability.BEST_EFFORT, depth=5)
# A latched topic such as map_server's /map: late joiners get the last sample.
LATCHED_QOS = QosProfile(durability=Durability.TRANSIENT_LOCAL, depth=1)


# --------------------------------------------------------------------------- graph entities


class EntityKind(Enum):
    NODE = "NN"
    PUBLISHER = "MP"
    SUBSCRIPTION = "MS"
    SERVICE = "SS"
    CLIENT = "SC"


@dataclass(frozen=True)
class NodeInfo:
    """A node of one Zenoh session (a ROS context): its graph identity."""

    domain_id: int
    zid: str  # the Zenoh session id as zenoh prints it (rmw_zenoh: ``zenoh::Id::to_string``)
    node_id: int
    name: str
    namespace: str = "/"
    enclave: str = "/"  # rcl's default security enclave

    def __post_init__(self) -> None:
        if not _TOKEN.match(self.name):
            raise RosNameError(f"node name {self.name!r} is not a ROS name token")
        object.__setattr__(self, "namespace", node_namespace(self.namespace))

    @property
    def token(self) -> str:
        """The node's liveliness key (its node id is also its entity id)."""
        return _join(self, entity_id=self.node_id, kind=EntityKind.NODE)


@dataclass(frozen=True)
class Endpoint:
    """A publisher or subscription of a node on one topic: its data key, liveliness key and GID."""

    node: NodeInfo
    entity_id: int
    kind: EntityKind
    topic: str  # fully qualified, e.g. /robot1/scan
    msgtype: str  # ROS name, e.g. sensor_msgs/msg/LaserScan
    type_hash: str  # RIHS01_...
    qos: QosProfile

    def __post_init__(self) -> None:
        if self.kind not in (EntityKind.PUBLISHER, EntityKind.SUBSCRIPTION):
            raise ValueError(f"an endpoint is a publisher or a subscription, not {self.kind.name}")
        if not self.topic.startswith("/"):
            raise RosNameError(f"topic {self.topic!r} must be fully qualified (resolve_topic)")

    @property
    def key_expr(self) -> str:
        return topic_key(domain_id=self.node.domain_id, topic=self.topic, msgtype=self.msgtype,
                         type_hash=self.type_hash)

    @property
    def token(self) -> str:
        tail = "/".join((mangle(self.topic), mangle(dds_type_name(self.msgtype)), mangle(self.type_hash),
                         self.qos.to_keyexpr()))
        return _join(self.node, entity_id=self.entity_id, kind=self.kind) + "/" + tail

    @property
    def gid(self) -> bytes:
        return gid_of(self.token)


def _join(node: NodeInfo, *, entity_id: int, kind: EntityKind) -> str:
    return "/".join((ADMIN_SPACE, str(node.domain_id), node.zid, str(node.node_id), str(entity_id), kind.value,
                     mangle(node.enclave), mangle(node.namespace), node.name))


def gid_of(token: str) -> bytes:
    """An entity's GID: XXH3-128 of its liveliness key, low then high 64 bits, each little-endian."""
    return xxhash.xxh3_128_intdigest(token.encode()).to_bytes(GID_BYTES, "little")


@dataclass(frozen=True)
class GraphEntity:
    """What a parsed liveliness token says (``Entity::make(keyexpr)``); topic fields only for endpoints."""

    domain_id: int
    zid: str
    node_id: int
    entity_id: int
    kind: EntityKind
    enclave: str
    namespace: str
    node_name: str
    topic: str | None = None
    msgtype: str | None = None  # the ROS name, e.g. sensor_msgs/msg/LaserScan
    type_hash: str | None = None
    qos: QosProfile | None = None

    @property
    def node_fqn(self) -> str:
        """``/robot1/cvxnav_bridge``: what ``ros2 node list`` prints."""
        return self.namespace.rstrip("/") + "/" + self.node_name


_TOKEN_CHUNKS_NODE = 9
_TOKEN_CHUNKS_ENDPOINT = 13


def parse_token(key_expr: str) -> GraphEntity:
    """Parse an ``@ros2_lv`` liveliness key, as rmw_zenoh's graph cache does; `TokenError` if it is not one."""
    parts = str(key_expr).split("/")
    if len(parts) < _TOKEN_CHUNKS_NODE or any(part == "" for part in parts):
        raise TokenError(f"{str(key_expr)[:120]!r}: expected at least {_TOKEN_CHUNKS_NODE} non-empty chunks")
    if parts[0] != ADMIN_SPACE:
        raise TokenError(f"{str(key_expr)[:120]!r}: not under {ADMIN_SPACE}")
    try:
        kind = EntityKind(parts[5])
    except ValueError:
        raise TokenError(f"{str(key_expr)[:120]!r}: unknown entity kind {parts[5]!r}") from None
    if not all(part.isdigit() for part in (parts[1], parts[3], parts[4])):
        raise TokenError(f"{str(key_expr)[:120]!r}: domain, node and entity ids must be integers")
    entity = GraphEntity(domain_id=int(parts[1]), zid=parts[2], node_id=int(parts[3]), entity_id=int(parts[4]),
                         kind=kind, enclave=demangle(parts[6]), namespace=demangle(parts[7]), node_name=parts[8])
    if kind == EntityKind.NODE:
        return entity
    if len(parts) < _TOKEN_CHUNKS_ENDPOINT:
        raise TokenError(f"{str(key_expr)[:120]!r}: a {kind.name.lower()} token needs topic, type, hash and QoS")
    try:
        msgtype = ros_type_name(demangle(parts[10]))
    except RosNameError as error:
        raise TokenError(str(error)) from None
    return replace(entity, topic=demangle(parts[9]), msgtype=msgtype, type_hash=demangle(parts[11]),
                   qos=QosProfile.from_keyexpr(parts[12]))
