"""The pipeline's one wiring table: which stage publishes which key carrying which model.

Keys are relative to a prefix (default ``cvxnav/robot1``, CONTRACTS.md §5). Services, compose.yaml
and the monitor read this table; no stage names a key of its own.

    sim        --scan, state-->   sensing (scan), planner (state)
    sensing    --clusters-->      ellipsoids
    ellipsoids --ellipsoids-->    planner
    planner    --raw_path-->      smoother
    smoother   --smooth_path-->   sim
    ellipsoids --ellipsoids-->    sim (which checks every path against them before driving on it)
    sim        --world-->         monitor only (the true map; no planning stage may read it)

The monitor (``MONITOR``) is a sink outside ``STAGES``: it reads every topic and every status, and
the pipeline never waits for it.
"""

from __future__ import annotations

from dataclasses import dataclass
from types import MappingProxyType
from typing import Mapping

from schemas.messages import (
    Clusters,
    Ellipsoids,
    Message,
    RawPath,
    RobotState,
    Scan,
    SmoothPath,
    StageStatus,
    World,
)

DEFAULT_ROBOT_ID = "robot1"


@dataclass(frozen=True)
class Topic:
    """One key of the pipeline: its name relative to the prefix, its model and its one publisher."""

    name: str
    model: type[Message]
    publisher: str


@dataclass(frozen=True)
class StageSpec:
    """What one stage reads and writes (topic names, in the order the stage handles them)."""

    name: str
    subscribes: tuple[str, ...]
    publishes: tuple[str, ...]


TOPICS: Mapping[str, Topic] = MappingProxyType(
    {
        topic.name: topic
        for topic in (
            Topic(name="scan", model=Scan, publisher="sim"),
            Topic(name="state", model=RobotState, publisher="sim"),
            Topic(name="clusters", model=Clusters, publisher="sensing"),
            Topic(name="ellipsoids", model=Ellipsoids, publisher="ellipsoids"),
            Topic(name="raw_path", model=RawPath, publisher="planner"),
            Topic(name="smooth_path", model=SmoothPath, publisher="smoother"),
            Topic(name="world", model=World, publisher="sim"),
        )
    }
)

STAGES: Mapping[str, StageSpec] = MappingProxyType(
    {
        spec.name: spec
        for spec in (
            StageSpec(name="sim", subscribes=("smooth_path", "ellipsoids"), publishes=("scan", "state", "world")),
            StageSpec(name="sensing", subscribes=("scan",), publishes=("clusters",)),
            StageSpec(name="ellipsoids", subscribes=("clusters",), publishes=("ellipsoids",)),
            StageSpec(name="planner", subscribes=("ellipsoids", "state"), publishes=("raw_path",)),
            StageSpec(name="smoother", subscribes=("raw_path",), publishes=("smooth_path",)),
        )
    }
)

STATUS_MODEL: type[Message] = StageStatus

# The observer: subscribes to every topic (and every status), publishes nothing.
MONITOR = StageSpec(name="monitor", subscribes=tuple(TOPICS), publishes=())


def default_prefix(*, robot_id: str = DEFAULT_ROBOT_ID) -> str:
    return f"cvxnav/{robot_id}"


def key(prefix: str, topic: str) -> str:
    """The absolute Zenoh key of ``topic`` under ``prefix``; unknown topics are an error."""
    if topic not in TOPICS:
        raise KeyError(f"unknown topic {topic!r}; known: {', '.join(TOPICS)}")
    return f"{prefix}/{topic}"


def status_key(prefix: str, stage: str) -> str:
    """Where ``stage`` publishes its ``StageStatus`` after every input."""
    return f"{prefix}/status/{stage}"


def alive_key(prefix: str, stage: str) -> str:
    """The liveliness token ``stage`` holds while it runs."""
    return f"{prefix}/alive/{stage}"


def topic_of(prefix: str, key_expr: str) -> str | None:
    """The topic name of an absolute key under ``prefix`` (None for status, liveliness or foreign keys)."""
    head = prefix + "/"
    if not key_expr.startswith(head):
        return None
    name = key_expr[len(head):]
    return name if name in TOPICS else None


def model_for(topic: str) -> type[Message]:
    return TOPICS[topic].model


def subscribers_of(topic: str) -> tuple[str, ...]:
    return tuple(spec.name for spec in STAGES.values() if topic in spec.subscribes)
