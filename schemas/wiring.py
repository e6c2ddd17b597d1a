"""The pipeline's one wiring table: per process, what it reads and writes and the factory of its core.

Keys are relative to a prefix (default ``cvxnav/robot1``, CONTRACTS.md §5) and built and parsed only
by the helpers below. `cvxnav run`, `cvxnav service`, compose.yaml, the monitor, `cvxnav status` and
the closed-loop bench read this table; no core names a key of its own.

    sim        --scan, state-->   sensing (scan), planner (state), ellipsoids (state: where the robot is)
    sensing    --clusters-->      ellipsoids
    ellipsoids --ellipsoids-->    planner
    planner    --raw_path-->      smoother
    smoother   --smooth_path-->   sim
    ellipsoids --ellipsoids-->    sim (which checks every path against them before driving on it)
    sim        --world-->         monitor only (the true map; no planning stage may read it)

For a ROS 2 robot (``cvxnav run --ros2``) the bridge ``ros2`` takes the sim's place: it publishes
scan and state from the robot's /scan and /odom, reads smooth_path and ellipsoids as the sim does, and
publishes ``goals`` (read by the ellipsoid stage, the planner and the smoother) when the robot is given
a /goal_pose, and ``map`` (read by the ellipsoid stage, which adds the map's walls near the robot to the
sensed obstacles) when it is given a /map. It is
also a ROS 2 node (``StageSpec.ros2``): its topics are rmw_zenoh's keys outside the prefix
(``services.ros2.interface``), declared by the shell (``services.shell.ros2``).

Three roles, one shell (``services.shell``): a ``stage`` works on the newest input of each key and
reports a status after every input; the ``source`` (the sim) ticks, follows the pipeline stages'
liveliness and every stage's status, and ends the run; the ``sink`` (the monitor) reads every topic
and every status, and the pipeline never waits for it. Sources and sinks handle every input in
arrival order and report only the inputs they reject.

A factory is an entry point ``"module:attr[.attr]"`` (a string, so the table imports nothing it
wires): called with the scenario (and the process's options, for the sim and the monitor), it
returns the core.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from types import MappingProxyType
from typing import Literal, Mapping

from schemas.messages import Clusters, Ellipsoids, Goals, Map, Message, RawPath, RobotState, Scan, SmoothPath, World

DEFAULT_ROBOT_ID = "robot1"
# A robot id is a name: one key chunk, never a pattern (`*` in a key would reach every robot's keys).
ROBOT_ID_PATTERN = re.compile(r"[A-Za-z0-9_-]+")
PREFIX_PATTERN = re.compile(r"[A-Za-z0-9_-]+(/[A-Za-z0-9_-]+)*")

Role = Literal["stage", "source", "sink"]


@dataclass(frozen=True)
class Topic:
    """One key of the pipeline: its name relative to the prefix and its model.

    ``latched``: the publisher answers gets with the last message (a late subscriber still has the
    world). Every topic is dropped rather than queued on a congested link (``services.shell``).
    """

    name: str
    model: type[Message]
    latched: bool = False


@dataclass(frozen=True)
class StageSpec:
    """One process of the pipeline: what it reads and writes (topic names, in the order it handles
    them), whose liveliness and statuses it follows, and the factory of its core."""

    name: str
    factory: str
    subscribes: tuple[str, ...]
    publishes: tuple[str, ...] = ()
    role: Role = "stage"
    watches: tuple[str, ...] = ()  # processes whose liveliness the core is told of
    hears_statuses: bool = False  # the core is handed every process's StageStatus
    ros2: bool = False  # also a ROS 2 node: raw CDR on rmw_zenoh's keys and its own liveliness tokens

    @property
    def every_input(self) -> bool:
        """Every input in arrival order (source, sink), rather than the newest of each key (stage)."""
        return self.role != "stage"

    @property
    def reports_ok(self) -> bool:
        """A status after every input (a stage); a source or sink reports only what it rejects."""
        return self.role == "stage"


TOPICS: Mapping[str, Topic] = MappingProxyType(
    {
        topic.name: topic
        for topic in (
            Topic(name="scan", model=Scan),
            Topic(name="state", model=RobotState),
            Topic(name="clusters", model=Clusters),
            Topic(name="ellipsoids", model=Ellipsoids),
            Topic(name="raw_path", model=RawPath),
            Topic(name="smooth_path", model=SmoothPath),
            Topic(name="world", model=World, latched=True),
            Topic(name="goals", model=Goals, latched=True),
            Topic(name="map", model=Map, latched=True),
        )
    }
)

_PIPELINE = (
    StageSpec(name="sensing", factory="services.sensing.stage:SensingStage.from_scenario",
              subscribes=("scan",), publishes=("clusters",)),
    StageSpec(name="ellipsoids", factory="services.ellipsoids.stage:EllipsoidsStage.from_scenario",
              subscribes=("map", "state", "goals", "clusters"), publishes=("ellipsoids",)),
    StageSpec(name="planner", factory="services.planner.stage:PlannerStage.from_scenario",
              subscribes=("goals", "ellipsoids", "state"), publishes=("raw_path",)),
    StageSpec(name="smoother", factory="services.smoother.stage:SmootherStage.from_scenario",
              subscribes=("goals", "raw_path"), publishes=("smooth_path",)),
)
PIPELINE: tuple[str, ...] = tuple(spec.name for spec in _PIPELINE)  # started first, in this order; then the sim

SIM = StageSpec(name="sim", factory="sim.stage:SimStage.from_scenario", subscribes=("smooth_path", "ellipsoids"),
                publishes=("scan", "state", "world"), role="source", watches=PIPELINE, hears_statuses=True)

# The sim's place for a ROS 2 robot (`cvxnav run --ros2`): the robot's topics in and out, its goals and map.
ROS2 = StageSpec(name="ros2", factory="services.ros2.stage:BridgeStage.from_scenario",
                 subscribes=("smooth_path", "ellipsoids"), publishes=("scan", "state", "goals", "map"), role="source",
                 watches=PIPELINE, ros2=True)

# The observer: subscribes to every topic (and every status), publishes nothing.
MONITOR = StageSpec(name="monitor", factory="services.monitor.rerun:MonitorCore.from_scenario",
                    subscribes=tuple(TOPICS), role="sink", hears_statuses=True)

# The sim and the pipeline stages: every process of a sim run but the observer.
STAGES: Mapping[str, StageSpec] = MappingProxyType({spec.name: spec for spec in (SIM, *_PIPELINE)})
# Every process the table wires, the monitor last.
PROCESSES: Mapping[str, StageSpec] = MappingProxyType({**STAGES, ROS2.name: ROS2, MONITOR.name: MONITOR})


def check_robot_id(robot_id: str) -> str:
    """`robot_id` if it is a name (letters, digits, `_`, `-`), else ValueError saying so."""
    if not ROBOT_ID_PATTERN.fullmatch(robot_id):
        raise ValueError(f"must be letters, digits, '_' or '-' (a name, not a key pattern), got {robot_id!r}")
    return robot_id


def check_prefix(prefix: str) -> str:
    """`prefix` if it is a key of such names joined by `/`, else ValueError saying so."""
    if not PREFIX_PATTERN.fullmatch(prefix):
        raise ValueError(f"must be names of letters, digits, '_' or '-' joined by '/' (a key, not a pattern), "
                         f"got {prefix!r}")
    return prefix


def default_prefix(*, robot_id: str = DEFAULT_ROBOT_ID) -> str:
    return f"cvxnav/{check_robot_id(robot_id)}"


def key(prefix: str, topic: str) -> str:
    """The absolute Zenoh key of ``topic`` under ``prefix``; unknown topics are an error."""
    if topic not in TOPICS:
        raise KeyError(f"unknown topic {topic!r}; known: {', '.join(TOPICS)}")
    return f"{prefix}/{topic}"


def every_key(prefix: str) -> str:
    """The key expression of everything under ``prefix`` (topics, statuses)."""
    return f"{prefix}/**"


def status_key(prefix: str, stage: str = "*") -> str:
    """Where ``stage`` publishes its ``StageStatus`` after every input (``*``: every stage's)."""
    return f"{prefix}/status/{stage}"


def alive_key(prefix: str, stage: str = "*") -> str:
    """The liveliness token ``stage`` holds while it runs (``*``: every stage's)."""
    return f"{prefix}/alive/{stage}"


def _last_part(prefix: str, head: str, key_expr: str) -> str | None:
    start = f"{prefix}/{head}/"
    if not key_expr.startswith(start) or "/" in key_expr[len(start):]:
        return None
    return key_expr[len(start):] or None


def stage_of_status_key(prefix: str, key_expr: str) -> str | None:
    """The stage a status key under ``prefix`` belongs to (None for any other key)."""
    return _last_part(prefix, "status", key_expr)


def stage_of_alive_key(prefix: str, key_expr: str) -> str | None:
    """The stage a liveliness token under ``prefix`` belongs to (None for any other key)."""
    return _last_part(prefix, "alive", key_expr)


def topic_of(prefix: str, key_expr: str) -> str | None:
    """The topic name of an absolute key under ``prefix`` (None for status, liveliness or foreign keys)."""
    head = prefix + "/"
    if not key_expr.startswith(head):
        return None
    name = key_expr[len(head):]
    return name if name in TOPICS else None


def model_for(topic: str) -> type[Message]:
    return TOPICS[topic].model


def publishers_of(topic: str) -> tuple[str, ...]:
    """The processes that publish ``topic``: one in a run, the sim or, for a ROS 2 robot, the bridge."""
    return tuple(spec.name for spec in PROCESSES.values() if topic in spec.publishes)


def subscribers_of(topic: str) -> tuple[str, ...]:
    """The sim and pipeline stages that read ``topic`` (the monitor reads every one)."""
    return tuple(spec.name for spec in STAGES.values() if topic in spec.subscribes)
