"""Sessions for the TLS tests: an inbox that records what a subscriber hears, the outsiders' configs, and
what the wiring table allows each certificate, written out from the table independently of `cvxnav.certs`.

Shared by tests/integration/test_tls.py (a bare TLS router) and tests/e2e/test_secure_run.py (a whole
`cvxnav run --tls`): a client without a certificate, one presenting a certificate from another CA, and
one with a valid certificate whose name is no stage.
"""

from __future__ import annotations

import json
import threading
from pathlib import Path

import zenoh

from cvxnav.certs import OPERATOR, client_config
from schemas.wiring import PROCESSES, TOPICS, alive_key, every_key, key, publishers_of, status_key

INTRUDER = "intruder"  # a name the certificates are issued for, but that access control does not list


def open_session(doc: dict) -> zenoh.Session:
    return zenoh.open(zenoh.Config.from_json5(json.dumps(doc)))


class Inbox:
    """A subscriber callback keeping every sample's key and payload."""

    def __init__(self) -> None:
        self.samples: list[tuple[str, bytes]] = []
        self.lock = threading.Lock()

    def __call__(self, sample: zenoh.Sample) -> None:
        with self.lock:
            self.samples.append((str(sample.key_expr), sample.payload.to_bytes()))

    def keys(self) -> list[str]:
        with self.lock:
            return [k for k, _ in self.samples]


def outsider_configs(ours: Path, theirs: Path, endpoint: str) -> dict[str, dict]:
    """Client configs for the router at ``endpoint`` that must get nothing through (label -> config).

    ``ours`` holds this deployment's certificates, including one for INTRUDER; ``theirs`` another CA's.
    """
    no_cert = client_config(cert_dir=ours, name="sensing", connect=[endpoint])
    tls = no_cert["transport"]["link"]["tls"]
    del tls["connect_certificate"], tls["connect_private_key"]
    other_ca = client_config(cert_dir=ours, name="sensing", connect=[endpoint])  # trusts our router...
    other_ca["transport"]["link"]["tls"].update(  # ...but presents a "sensing" certificate from another CA
        connect_certificate=str(theirs / "sensing.pem"), connect_private_key=str(theirs / "sensing.key"))
    return {"no certificate": no_cert, "another CA": other_ca,
            "valid certificate, name not allowed": client_config(cert_dir=ours, name=INTRUDER, connect=[endpoint])}


def connect_outsiders(ours: Path, theirs: Path, endpoint: str, *, prefix: str,
                      liveliness: bool = False) -> dict[str, tuple[zenoh.Session | None, Inbox]]:
    """Each outsider of ``outsider_configs`` connected and subscribed to everything under ``prefix``
    (and to its liveliness tokens, if asked), with the inbox it fills; None where the handshake
    refuses it. The caller closes the sessions."""
    outsiders: dict[str, tuple[zenoh.Session | None, Inbox]] = {}
    for label, config in outsider_configs(ours, theirs, endpoint).items():
        inbox = Inbox()
        try:
            session = open_session(config)
        except zenoh.ZError:
            session = None  # refused at the handshake: nothing can pass
        else:
            session.declare_subscriber(every_key(prefix), inbox)
            if liveliness:
                session.liveliness().declare_subscriber(alive_key(prefix), inbox)
        outsiders[label] = (session, inbox)
    return outsiders


def table_keys(prefix: str, names) -> dict[tuple[str, str], str]:
    """The keys under ``prefix`` by what they are: ("topic", name) or ("status", the name of its process)."""
    return {**{("topic", topic): key(prefix, topic) for topic in TOPICS},
            **{("status", name): status_key(prefix, name) for name in names}}


def may_put(name: str, what: tuple[str, str]) -> bool:
    """Only the table's publishers put a topic (the sim, or for a ROS 2 robot the bridge); only a process puts its own status."""
    kind, which = what
    return name in publishers_of(which) if kind == "topic" else name == which and name in PROCESSES


def may_read(name: str, what: tuple[str, str]) -> bool:
    """The operator reads everything; a process reads the topics it subscribes to, and statuses if it hears them."""
    if name == OPERATOR:
        return True
    spec = PROCESSES.get(name)
    if spec is None:
        return False
    kind, which = what
    return which in spec.subscribes if kind == "topic" else spec.hears_statuses


def may_ask(name: str, what: tuple[str, str]) -> bool:
    """Who may ask a latched topic's publisher for its last message: a process that subscribes to it."""
    kind, which = what
    return kind == "topic" and TOPICS[which].latched and name in PROCESSES and which in PROCESSES[name].subscribes


def may_answer(name: str, what: tuple[str, str]) -> bool:
    """Who may answer queries on a key: a latched topic's publisher, with its last message."""
    kind, which = what
    return kind == "topic" and TOPICS[which].latched and name in publishers_of(which)
