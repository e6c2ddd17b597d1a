"""The heartbeat: a stage in the real shell on a real Zenoh session sends systemd's keep-alives over a
real unix datagram socket while its worker makes progress, and stops (after one WATCHDOG=trigger) while
one input holds the worker past the stall limit."""

from __future__ import annotations

import os
import threading
import time
import uuid
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

import pytest
import zenoh

from cvxnav.supervisor import free_ports
from schemas.messages import Header, Pose2D, Scan
from schemas.wiring import key
from services.shell.stage import run_stage
from services.shell.watchdog import NotifySocket, Progress, Watchdog, keep_alive, notify_socket_in
from services.shell.zenoh_config import build_zenoh_config

INTERVAL_S = 0.4  # WATCHDOG_USEC: a keep-alive every 0.1 s
STALL_LIMIT_S = 0.8
WAIT_S = 10.0  # a guard against a hung test, not a speed requirement


@dataclass
class HoldingSensing:
    """Stand-in sensing core that holds its worker on every scan until released (a hang, GIL released)."""

    entered: threading.Event = field(default_factory=threading.Event)
    release: threading.Event = field(default_factory=threading.Event)

    def process(self, *, topic: str, message: Scan, now_s: float) -> list:
        self.entered.set()
        self.release.wait(WAIT_S)
        return []


def listen(notify: NotifySocket, *, for_s: float) -> list[str]:
    """The keep-alives this process sent within the next `for_s` seconds, in order."""
    received, deadline = [], time.monotonic() + for_s
    while time.monotonic() < deadline:
        received += [text for pid, text in notify.receive() if pid == os.getpid()]
        time.sleep(0.01)
    return received


@contextmanager
def watched_stage(core: HoldingSensing, notify: NotifySocket) -> Iterator[tuple[zenoh.Session, str]]:
    endpoint = f"tcp/127.0.0.1:{free_ports(1)[0]}"
    prefix, stop, ready, progress = f"test/{uuid.uuid4().hex[:8]}", threading.Event(), threading.Event(), Progress()
    keep_alive(watchdog=Watchdog(address=notify.address, interval_s=INTERVAL_S), progress=progress,
               stall_limit_s=STALL_LIMIT_S, stop_event=stop)
    worker = threading.Thread(target=run_stage, daemon=True, kwargs=dict(
        stage="sensing", core=core, session_config=build_zenoh_config(listen=[endpoint]), prefix=prefix,
        stop_event=stop, ready_event=ready, progress=progress))
    worker.start()
    try:
        assert ready.wait(WAIT_S)
        with zenoh.open(build_zenoh_config(connect=[endpoint])) as session:
            yield session, prefix
    finally:
        core.release.set()
        stop.set()
        worker.join(WAIT_S)


def test_keep_alives_stop_while_one_input_holds_the_worker_past_the_stall_limit(tmp_path: Path):
    notify, core = NotifySocket(address=str(tmp_path / "notify.sock")), HoldingSensing()
    try:
        with watched_stage(core, notify) as (session, prefix):
            idle = listen(notify, for_s=0.5)
            assert idle and set(idle) == {"WATCHDOG=1"}  # idle, the worker passes its loop: alive
            scan = Scan(header=Header(stamp_s=0.0, seq=0), pose=Pose2D(x_m=0.0, y_m=0.0, theta_rad=0.0),
                        points=[(1.0, 1.0)])
            publisher = session.declare_publisher(key(prefix, "scan"))
            deadline = time.monotonic() + WAIT_S
            while not core.entered.wait(0.05) and time.monotonic() < deadline:  # until the route is up
                publisher.put(scan.model_dump_json())
            assert core.entered.is_set()
            held = listen(notify, for_s=STALL_LIMIT_S + 1.0)
            assert held.count("WATCHDOG=trigger") == 1  # once, when the pass grew past the limit ...
            assert "WATCHDOG=1" not in held[held.index("WATCHDOG=trigger"):]  # ... and silent after it
            assert held[0] == "WATCHDOG=1"  # a solve shorter than the limit is no hang
            core.release.set()
            assert "WATCHDOG=1" in listen(notify, for_s=0.5)  # the worker moved on: alive again
    finally:
        notify.close()


def test_the_watchdog_is_read_from_the_environment_as_systemd_sets_it_and_taken_out_of_it():
    environ = {"NOTIFY_SOCKET": "@cvxnav-test", "WATCHDOG_USEC": "3000000", "HOME": "/root"}
    assert Watchdog.from_environment(environ) == Watchdog(address="\0cvxnav-test", interval_s=3.0)
    assert environ == {"HOME": "/root"}  # a process it starts does not send for it
    other = {"NOTIFY_SOCKET": "/run/n.sock", "WATCHDOG_USEC": "3000000", "WATCHDOG_PID": str(os.getpid() + 1)}
    assert Watchdog.from_environment(other) is None  # the watchdog of another process
    assert Watchdog.from_environment({"NOTIFY_SOCKET": "/run/n.sock"}) is None  # notify, but no watchdog


def test_a_socket_path_too_long_for_unix_is_an_oserror_that_leaves_no_socket_open(tmp_path: Path):
    deep = tmp_path / ("d" * 120)  # sun_path holds 108 bytes: a long TMPDIR gives no watchdog, not a crash
    deep.mkdir()
    open_before = len(os.listdir("/proc/self/fd"))
    with pytest.raises(OSError):
        NotifySocket(address=str(deep / "notify.sock"))
    assert len(os.listdir("/proc/self/fd")) == open_before


def test_a_run_folder_too_deep_for_a_socket_path_gets_an_abstract_socket_that_hears_keep_alives(tmp_path: Path):
    # A TMPDIR deep enough that the run's notify.sock cannot be bound (sun_path holds 108 bytes) left the
    # run's stages without a watchdog, and a warning line before any error. The socket is named after the
    # run's folder in Linux's abstract namespace instead, as NOTIFY_SOCKET says it ("@name"), and a stage
    # reading that from its environment is heard, known by its pid.
    deep = tmp_path / ("d" * 120) / "cvxnav-run-test"
    deep.mkdir(parents=True)
    notify = notify_socket_in(deep)
    stop, progress = threading.Event(), Progress()
    try:
        assert notify.address == "@cvxnav-run-test/notify"
        watchdog = Watchdog.from_environment({"NOTIFY_SOCKET": notify.address, "WATCHDOG_USEC": str(int(INTERVAL_S * 1e6))})
        progress.beat()
        keep_alive(watchdog=watchdog, progress=progress, stall_limit_s=STALL_LIMIT_S, stop_event=stop)
        assert "WATCHDOG=1" in listen(notify, for_s=4 * INTERVAL_S)
        with pytest.raises(OSError):  # the name is the run's own while it is bound
            notify_socket_in(deep)
    finally:
        stop.set()
        notify.close()
    assert not list(deep.iterdir())  # no file was made for it
