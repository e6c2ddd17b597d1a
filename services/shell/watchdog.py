"""A process proves it is making progress: the keep-alive of systemd's watchdog, sent by every stage.

A stopped (SIGSTOP) or hung process keeps its Zenoh session and its liveliness token: its links stay
up, so nothing on the network tells it from a slow one. A heartbeat from inside the process does, as
Nav2's lifecycle manager holds a bond with each server (a heartbeat every 0.1 s, the bond broken after
``bond_timeout``, 4 s by default, checked every 0.2 s). The heartbeat here is the one systemd's
watchdog hears (sd_notify(3), sd_watchdog_enabled(3)): a ``WATCHDOG=1`` datagram to the unix socket
named by ``NOTIFY_SOCKET``, several times per ``WATCHDOG_USEC``; so `cvxnav run` (``NotifySocket``)
and a unit with ``WatchdogSec=`` and ``Restart=on-watchdog`` watch a stage alike.

The beat comes from a thread of its own (``keep_alive``), so a long solve, which releases the GIL,
does not silence it; but only while the worker's current pass (one input, one tick or one idle wait,
``Progress``) is younger than ``stall_limit_s``: a core stuck on one input stops the beat, and says
``WATCHDOG=trigger`` once, as surely as a stopped process falls silent. Over a local socket, not
Zenoh: a hang is a process fault, told apart from a network fault (a cut link, a dead router), which
the liveliness tokens report.
"""

from __future__ import annotations

import logging
import os
import socket
import struct
import threading
import time
from collections.abc import MutableMapping
from dataclasses import dataclass
from pathlib import Path

logger = logging.getLogger(__name__)

# A pass of the worker longer than this is a hang: no input takes a stage this long (the sim gives up
# waiting for an answer after 10 s).
STALL_LIMIT_S = 20.0
BEATS_PER_INTERVAL = 4  # keep-alives per WATCHDOG_USEC (sd_watchdog_enabled(3) asks for at least two)
_UCRED = struct.Struct("3i")  # struct ucred: pid, uid, gid


class Progress:
    """When the worker's current pass began (monotonic s); None until its loop runs.

    Written by the worker at the top of every pass, read by the heartbeat thread: one float, no lock.
    """

    def __init__(self) -> None:
        self.pass_started_s: float | None = None

    def beat(self) -> None:
        self.pass_started_s = time.monotonic()


def _socket_address(address: str) -> str:
    """A ``NOTIFY_SOCKET`` value as a socket address: ``@name`` (Linux's abstract namespace) leads with NUL."""
    return "\0" + address[1:] if address.startswith("@") else address


@dataclass(frozen=True)
class Watchdog:
    """Where this process sends its keep-alives, and the interval within which one must arrive."""

    address: str  # a socket path, or an abstract name starting with NUL
    interval_s: float

    @classmethod
    def from_environment(cls, environ: MutableMapping[str, str]) -> Watchdog | None:
        """The watchdog systemd (or `cvxnav run`) set up for this process, if any.

        As sd_watchdog_enabled(3) with ``unset_environment``: the variables are taken out of
        `environ`, so processes this one starts (the monitor's viewer) do not send for it; a
        ``WATCHDOG_PID`` naming another process means the watchdog is not this one's.
        """
        address = environ.pop("NOTIFY_SOCKET", None)
        usec = environ.pop("WATCHDOG_USEC", None)
        pid = environ.pop("WATCHDOG_PID", None)
        if not address or not usec or (pid is not None and pid != str(os.getpid())):
            return None
        try:
            interval_s = int(usec) / 1e6
        except ValueError:
            logger.warning("ignoring WATCHDOG_USEC=%r: not a number of microseconds", usec)
            return None
        if interval_s <= 0.0:
            return None
        return cls(address=_socket_address(address), interval_s=interval_s)


def keep_alive(*, watchdog: Watchdog, progress: Progress, stall_limit_s: float,
               stop_event: threading.Event) -> threading.Thread:
    """Start the daemon thread that sends ``WATCHDOG=1`` every `interval_s`/4 while the worker makes progress.

    Silent before the worker's loop runs (start-up is watched by the caller's own timeout) and once
    `stop_event` is set; after a pass older than `stall_limit_s` it sends ``WATCHDOG=trigger`` once
    and nothing more until the pass ends.
    """
    period_s = watchdog.interval_s / BEATS_PER_INTERVAL

    def beat() -> None:
        stalled = False
        with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as sock:
            while not stop_event.wait(period_s):
                started_s = progress.pass_started_s
                if started_s is None:
                    continue
                age_s = time.monotonic() - started_s
                if age_s <= stall_limit_s:
                    message, stalled = b"WATCHDOG=1", False
                elif not stalled:
                    logger.error("the worker has been in one pass for %.1f s (stall limit %.1f s): heartbeat "
                                 "stopped", age_s, stall_limit_s)
                    message, stalled = b"WATCHDOG=trigger", True
                else:
                    continue
                try:
                    sock.sendto(message, watchdog.address)
                except OSError as error:  # the watcher is gone: nothing to tell
                    logger.debug("keep-alive not sent to %r: %s", watchdog.address, error)

    thread = threading.Thread(target=beat, name="watchdog-keep-alive", daemon=True)
    thread.start()
    return thread


class NotifySocket:
    """The receiving end: a unix datagram socket that tells each message's sender by its pid (Linux).

    The kernel attaches the sender's credentials to every datagram (``SO_PASSCRED``), so a child is
    known by the pid its supervisor started, not by anything it says about itself. `address` is a
    path, or ``@name`` for Linux's abstract namespace (as ``NOTIFY_SOCKET`` writes it): no file, and no
    108-byte bound on a path.
    """

    def __init__(self, *, address: str) -> None:
        self.address = address
        self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        try:
            self._sock.setsockopt(socket.SOL_SOCKET, socket.SO_PASSCRED, 1)
            # OSError for a path longer than sun_path (108 bytes), or a name already bound.
            self._sock.bind(_socket_address(address))
        except OSError:
            self._sock.close()
            raise
        self._sock.setblocking(False)

    def receive(self) -> list[tuple[int, str]]:
        """Every datagram that arrived since the last call: (sender pid, text)."""
        received = []
        while True:
            try:
                data, ancillary, _flags, _address = self._sock.recvmsg(4096, socket.CMSG_SPACE(_UCRED.size))
            except (BlockingIOError, InterruptedError):
                return received
            pid = next((_UCRED.unpack(cdata[:_UCRED.size])[0] for level, kind, cdata in ancillary
                        if level == socket.SOL_SOCKET and kind == socket.SCM_CREDENTIALS), None)
            if pid is not None:
                received.append((pid, data.decode("utf-8", errors="replace")))

    def close(self) -> None:
        self._sock.close()
        if not self.address.startswith("@"):
            Path(self.address).unlink(missing_ok=True)


def notify_socket_in(folder: Path) -> NotifySocket:
    """A `NotifySocket` at ``folder/notify.sock``; where that path is too long for a unix socket (a deep
    TMPDIR), one named after the folder in the abstract namespace (a name taken is an OSError too)."""
    try:
        return NotifySocket(address=str(folder / "notify.sock"))
    except OSError:
        return NotifySocket(address=f"@{folder.name}/notify")


def watchdog_supported() -> bool:
    """Whether this system tells a datagram's sender (``SO_PASSCRED``: Linux)."""
    return hasattr(socket, "SO_PASSCRED") and hasattr(socket, "SCM_CREDENTIALS")
