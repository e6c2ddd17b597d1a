"""Machines apart on one machine, for the e2e tests: Linux network namespaces joined only through a router's.

`network(hosts)` makes a router namespace and one namespace per host, each host on its own veth link to
the router's (10.77.<n>.0/24); the router namespace does not forward IP, so hosts reach each other only
through a Zenoh router listening there. A host's link can be cut (`Network.cut`: the veth goes down, so
packets are lost without a word, as when a cable is pulled or Wi-Fi drops) and restored. Made and
removed by the caller; skipped where namespaces cannot be made (not root, no `ip`, a container without
CAP_SYS_ADMIN).

Run as a script in a host's namespace (`Network.observe`), this module is an observer: a Zenoh client
of the router that writes each state of the sim and each liveliness change, with its monotonic arrival
time, one JSON object a line.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import time
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import pytest

ROUTER_PORT = 7447
LISTENING = "cvxnav router listening"


def _ip(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(["ip", *args], capture_output=True, text=True)


def _must(*args: str) -> None:
    proc = _ip(*args)
    if proc.returncode != 0:
        raise RuntimeError(f"ip {' '.join(args)}: {proc.stderr.strip()}")


@dataclass(frozen=True)
class Network:
    tag: str
    hosts: tuple[str, ...]

    @property
    def router_ns(self) -> str:
        return f"{self.tag}r"

    def ns(self, host: str) -> str:
        return f"{self.tag}{host}"

    def _index(self, host: str) -> int:
        return self.hosts.index(host) + 1

    def _inner(self, host: str) -> str:
        return f"{self.tag}{self._index(host)}h"

    def router_ip(self, host: str) -> str:
        """The router's address on `host`'s link."""
        return f"10.77.{self._index(host)}.1"

    def host_ip(self, host: str) -> str:
        return f"10.77.{self._index(host)}.2"

    def router_endpoint(self, host: str) -> str:
        """Where the stages on `host` reach the router."""
        return f"tcp/{self.router_ip(host)}:{ROUTER_PORT}"

    def start(self, host: str | None, args: Sequence[str], *, log: Path) -> subprocess.Popen:
        """`python ARGS` in `host`'s namespace (None: the router's), output to `log`."""
        with open(log, "ab") as out:
            return subprocess.Popen(["ip", "netns", "exec", self.ns(host) if host else self.router_ns,
                                     sys.executable, *args], stdout=out, stderr=subprocess.STDOUT,
                                    stdin=subprocess.DEVNULL, cwd=log.parent)

    def cvxnav(self, host: str | None, *args: str, log: Path) -> subprocess.Popen:
        return self.start(host, ["-m", "cvxnav", *args], log=log)

    def router(self, *, log: Path) -> subprocess.Popen:
        """`cvxnav router` in the router's namespace (again, after a kill: the log is appended), once it listens."""
        said = log.read_text().count(LISTENING) if log.exists() else 0
        process = self.cvxnav(None, "router", "--listen", f"tcp/0.0.0.0:{ROUTER_PORT}", log=log)
        deadline = time.monotonic() + 30.0  # clients give up if the router is not listening yet
        while log.read_text().count(LISTENING) == said:
            assert process.poll() is None and time.monotonic() < deadline, log.read_text()
            time.sleep(0.05)
        return process

    def observe(self, host: str, *, log: Path, out: Path) -> subprocess.Popen:
        """The observer (this module as a script) in `host`'s namespace, writing to `out`."""
        return self.start(host, [__file__, self.router_endpoint(host), str(out)], log=log)

    def cut(self, host: str) -> None:
        """Pull `host`'s cable: its link to the router goes down, nothing is said to either end."""
        _must("-n", self.ns(host), "link", "set", self._inner(host), "down")

    def restore(self, host: str) -> None:
        _must("-n", self.ns(host), "link", "set", self._inner(host), "up")


@contextmanager
def network(*, hosts: Sequence[str]) -> Iterator[Network]:
    """The namespaces and links for `hosts`, removed afterwards; skips the test where they cannot be made."""
    if shutil.which("ip") is None:
        pytest.skip("no `ip` command (iproute2) on this machine")
    net = Network(tag=f"cx{os.getpid() % 100000}", hosts=tuple(hosts))
    probe = _ip("netns", "add", net.router_ns)
    if probe.returncode != 0:
        pytest.skip(f"cannot create network namespaces here: {probe.stderr.strip()}")
    try:
        _must("-n", net.router_ns, "link", "set", "lo", "up")
        for host in net.hosts:
            ns, outer, inner = net.ns(host), f"{net.tag}{net._index(host)}r", net._inner(host)
            _must("netns", "add", ns)
            _must("-n", ns, "link", "set", "lo", "up")
            _must("link", "add", outer, "netns", net.router_ns, "type", "veth", "peer", "name", inner, "netns", ns)
            _must("-n", net.router_ns, "addr", "add", f"{net.router_ip(host)}/24", "dev", outer)
            _must("-n", ns, "addr", "add", f"{net.host_ip(host)}/24", "dev", inner)
            _must("-n", net.router_ns, "link", "set", outer, "up")
            _must("-n", ns, "link", "set", inner, "up")
        yield net
    finally:
        for ns in (net.router_ns, *(net.ns(host) for host in net.hosts)):
            _ip("netns", "del", ns)  # removes the veth pairs with them


@dataclass(frozen=True)
class Seen:
    """What the observer saw: (arrival s, sim stamp s, speed m/s) per state; (arrival s, stage, up) per token."""

    states: list[tuple[float, float, float]]
    tokens: list[tuple[float, str, bool]]

    @classmethod
    def read(cls, path: Path) -> Seen:
        states, tokens = [], []
        for line in path.read_text().splitlines():
            row = json.loads(line)
            if "stamp_s" in row:
                states.append((row["t"], row["stamp_s"], row["speed_mps"]))
            else:
                tokens.append((row["t"], row["stage"], row["up"]))
        return cls(states=states, tokens=tokens)

    def longest_gap_s(self, *, start_s: float, end_s: float) -> float:
        """The longest wall time without a state, between two arrival times."""
        times = [start_s, *(t for t, _, _ in self.states if start_s < t < end_s), end_s]
        return max(b - a for a, b in zip(times, times[1:]))


def _observe(endpoint: str, out: Path) -> None:
    import signal
    import threading

    import zenoh

    from schemas.messages import RobotState, decode
    from schemas.wiring import alive_key, default_prefix, key, stage_of_alive_key
    from services.shell.zenoh_config import build_zenoh_config

    prefix, lock, stop = default_prefix(), threading.Lock(), threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    config = build_zenoh_config(connect=[endpoint], mode="client")  # reconnects as the stages do
    with open(out, "w", encoding="utf-8") as file, zenoh.open(config) as session:

        def write(row: dict) -> None:
            with lock:
                file.write(json.dumps({"t": time.monotonic(), **row}) + "\n")
                file.flush()

        def on_state(sample: zenoh.Sample) -> None:
            state = decode(RobotState, sample.payload.to_bytes())
            write({"stamp_s": state.header.stamp_s, "speed_mps": state.speed_mps})

        def on_alive(sample: zenoh.Sample) -> None:
            write({"stage": stage_of_alive_key(prefix, str(sample.key_expr)),
                   "up": sample.kind == zenoh.SampleKind.PUT})

        subscribers = (session.declare_subscriber(key(prefix, "state"), on_state),
                       session.liveliness().declare_subscriber(alive_key(prefix), on_alive, history=True))
        stop.wait()
        for subscriber in subscribers:
            subscriber.undeclare()


if __name__ == "__main__":
    _observe(sys.argv[1], Path(sys.argv[2]))
