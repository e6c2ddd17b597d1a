"""ROS 2 message types, their RIHS01 hashes and CDR, all from rosbags' typestore (no hand-written CDR).

The types are ROS 2 Jazzy's (rosbags ``Stores.ROS2_JAZZY``): rmw_zenoh exists from Jazzy on, and its
keys carry each type's RIHS01 hash (REP-2016: SHA-256 of the type description), which only a
subscriber with the same definition matches. For the interfaces the bridge speaks (LaserScan,
Odometry, PoseStamped, OccupancyGrid, Path, Twist) the Humble, Jazzy and Kilted definitions are the
same and so are their hashes, so a Humble robot's recording replays onto Jazzy keys unchanged.
"""

from __future__ import annotations

import functools

from rosbags.serde import SerdeError
from rosbags.typesys import Stores, get_typestore
from rosbags.typesys.store import Typestore

from services.ros2.wire import RosNameError

DISTRO = Stores.ROS2_JAZZY


class CdrError(ValueError):
    """A payload that is not a valid CDR message of the expected type; the text is one line."""


@functools.cache
def jazzy() -> Typestore:
    return get_typestore(DISTRO)


def type_hash(msgtype: str, *, store: Typestore | None = None) -> str:
    """The RIHS01 hash of ``msgtype`` in ``store`` (default: Jazzy's standard interfaces)."""
    store = store or jazzy()
    if msgtype not in store.fielddefs:
        raise RosNameError(f"unknown message type {msgtype!r} (not among the {DISTRO.value} standard interfaces)")
    return store.hash_rihs01(msgtype)


def decode(payload: bytes | memoryview, msgtype: str, *, store: Typestore | None = None) -> object:
    """Deserialize a CDR payload (with its encapsulation header) as ``msgtype``; `CdrError` if it is not one."""
    store = store or jazzy()
    try:
        # rosbags checks the encapsulation header, every length against the bytes left and the size.
        return store.deserialize_cdr(payload, msgtype)
    except (SerdeError, IndexError) as error:
        reason = (str(error).splitlines() or [type(error).__name__])[0]
        raise CdrError(f"{msgtype}: malformed CDR ({len(payload)} bytes): {reason[:160]}") from None


def encode(message: object, msgtype: str, *, store: Typestore | None = None) -> bytes:
    """Serialize a message of ``msgtype`` as little-endian CDR with its encapsulation header."""
    return bytes((store or jazzy()).serialize_cdr(message, msgtype, little_endian=True))


def message_class(msgtype: str) -> type:
    """The Jazzy dataclass of ``msgtype`` (to build messages to publish)."""
    return jazzy().types[msgtype]

