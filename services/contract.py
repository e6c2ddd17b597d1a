"""The stage contract: what a core is, seen from the shell that runs it (``services.shell``).

A core is built from its configuration (a ``from_scenario`` factory named in the wiring table) and is
plain code: ``process`` takes one decoded input and returns the messages to publish, by topic; it
never opens a session, names a key or touches a file. A source (the sim) also ``tick``s; a core whose
output depends on more than its newest input also hands the shell its ``state()`` and takes it back
with ``restore()``, and the shell decides when and where it is persisted (after copper-rs's
``new`` + ``process`` tasks with ``Freezable`` state).
"""

from __future__ import annotations

from typing import Protocol, runtime_checkable

from pydantic import BaseModel

Outputs = list[tuple[str, BaseModel]]


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
class Stateful(Protocol):
    """A core with state no later input restores (the sensing memory, the planner's plan)."""

    def state(self) -> bytes:
        """A snapshot of what must survive a restart of the process."""
        ...

    def restore(self, data: bytes) -> None:
        """Take back a snapshot ``state`` made; ``StateError`` when ``data`` is not one."""
        ...
