"""The player's reading of a bag's recorded QoS, as rmw_zenoh adapts a profile (``best_available_qos``)."""

from __future__ import annotations

from rosbags.interfaces import Qos, QosDurability, QosHistory, QosLiveliness, QosReliability, QosTime

from cvxnav.ros2_play import recorded_qos
from services.ros2.wire import INFINITE, Durability, QosProfile, Reliability, RmwDuration


def qos(*, durability: QosDurability, reliability: QosReliability, depth: int, deadline: QosTime) -> Qos:
    return Qos(history=QosHistory.KEEP_LAST, depth=depth, reliability=reliability, durability=durability,
               deadline=deadline, lifespan=QosTime(sec=0, nsec=0), liveliness=QosLiveliness.SYSTEM_DEFAULT,
               liveliness_lease_duration=QosTime(sec=0, nsec=0), avoid_ros_namespace_conventions=False)


def test_a_latched_recording_plays_transient_local_and_system_defaults_take_rmw_zenohs() -> None:
    latched = recorded_qos([qos(durability=QosDurability.TRANSIENT_LOCAL, reliability=QosReliability.RELIABLE,
                                depth=1, deadline=QosTime(sec=0, nsec=0))])
    assert latched == QosProfile(durability=Durability.TRANSIENT_LOCAL, depth=1)
    assert latched.to_keyexpr() == ":1:,1:,:,:,,"
    defaults = recorded_qos([qos(durability=QosDurability.SYSTEM_DEFAULT, reliability=QosReliability.BEST_AVAILABLE,
                                 depth=0, deadline=QosTime(sec=2, nsec=500))])
    assert (defaults.reliability, defaults.durability, defaults.depth) == (Reliability.RELIABLE, Durability.VOLATILE, 42)
    assert defaults.deadline == RmwDuration(sec=2, nsec=500) and defaults.lifespan == INFINITE
    assert recorded_qos([]) == QosProfile()
