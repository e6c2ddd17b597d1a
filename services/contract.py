"""The stage contract: what a core is, seen from the shell that runs it (``services.shell``).

A core is built from its configuration (a ``from_scenario`` factory named in the wiring table) and is
plain code: ``process`` takes one decoded input and returns the messages to publish, by topic; it
never opens a session, names a key or touches a file. A source (the sim) also ``tick``s, and says
when it next wants to; a core whose output depends on more than its newest input also hands the shell
its ``state()`` and takes it back with ``restore()``, and the shell decides when and where it is
persisted (after copper-rs's ``new`` + ``process`` tasks with ``Freezable`` state). What else a core
asks the wiring table for (``StageSpec.watches``, ``hears_statuses``) the shell hands it as calls of
``Watching`` and ``Listening``, as dora-rs hands a node its inputs and its peers' failures as events.
A process that is also a ROS 2 node (``StageSpec.ros2``) speaks keys outside the table's JSON key space
through ``Bridging``: raw bytes in, ``Raw`` bytes out, the codec (CDR) the core's own.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol, runtime_checkable

from pydantic import BaseModel

from schemas.messages import StageStatus


@dataclass(frozen=True)
class Refusal:
    """An earlier input the core decided not to act on, reported by the shell on the stage's status key."""

    reason: str


@dataclass(frozen=True)
class Notice:
    """Why an answer is not the best the core could give (a deadline cut its search short), reported by the
    shell as the reason on the stage's ``ok`` status for the input; the answer itself is published as usual."""

    reason: str


@dataclass(frozen=True)
class Raw:
    """Bytes for an output port outside the wiring table's key space (a ROS 2 topic's CDR), encoded by the
    core; the shell publishes them as they are."""

    payload: bytes


# By topic: a message to publish on an output topic, a Refusal of an input on an input topic, Raw
# bytes for a bridging core's output port, or a Notice on the answer published on an output topic.
Outputs = list[tuple[str, BaseModel | Refusal | Raw | Notice]]


class StageInputError(ValueError):
    """Raised by a core for an input it rejects (valid schema, unusable content); stage carries on."""


class StateError(ValueError):
    """Raised by ``restore`` for saved state it cannot take back: the stage must not start forgetful."""


class StageCore(Protocol):
    def process(self, *, topic: str, message: BaseModel, now_s: float) -> Outputs:
        """Handle one input message; return the messages to publish, by topic name."""
        ...


class TickingCore(StageCore, Protocol):
    """A core that also produces outputs on a timer (the sim publishing scans and state)."""

    def tick(self, *, now_s: float) -> Outputs:
        """Advance by one period; return the messages to publish, by topic name."""
        ...


@runtime_checkable
class Scheduled(Protocol):
    """A ticking core that says when it next wants to tick, and when it is done (the sim's run ends)."""

    done: bool

    def next_tick_s(self, *, now_s: float) -> float | None:
        """The clock time of the next tick (``now_s`` or earlier: at once); None: none until an input."""
        ...


@runtime_checkable
class Watching(Protocol):
    """A core told when a process it watches (``StageSpec.watches``) comes up or goes down."""

    def stage_alive(self, *, stage: str, alive: bool, now_s: float) -> Outputs:
        ...


@runtime_checkable
class Listening(Protocol):
    """A core handed every process's status (``StageSpec.hears_statuses``)."""

    def hear_status(self, *, stage: str, status: StageStatus, now_s: float) -> Outputs:
        ...


@runtime_checkable
class Bridging(Protocol):
    """A core that is also a ROS 2 node (``StageSpec.ros2``): the shell declares the node and its topics
    (``services.ros2.interface``) in ``domain_id`` under ``namespace``, hands the core every sample of an
    input port undecoded, and publishes its ``Raw`` outputs on the output ports."""

    domain_id: int
    namespace: str

    def receive(self, *, port: str, key_expr: str, payload: bytes, now_s: float) -> Outputs:
        """One sample of input ``port`` (a ROS topic), as received on ``key_expr``."""
        ...


@runtime_checkable
class Stopping(Protocol):
    """A core with last outputs, or resources to release, when its process stops."""

    def stop(self, *, now_s: float) -> Outputs:
        ...


@runtime_checkable
class Stateful(Protocol):
    """A core with state no later input restores (the sensing memory, the planner's plan)."""

    def state(self) -> bytes:
        """A snapshot of what must survive a restart of the process."""
        ...

    def restore(self, data: bytes) -> None:
        """Take back a snapshot ``state`` made; ``StateError`` when ``data`` is not one."""
        ...
