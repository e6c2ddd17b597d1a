"""One helper that builds the Zenoh session config from ``--connect/--listen/--config/--mode``.

Mirrors zenoh-python's ``examples/common/common.py``. When explicit endpoints are given, multicast
scouting is turned off: the peers find each other through those endpoints, so processes on one
machine (and tests on loopback) need no router and do not see unrelated sessions on the LAN.

Every config built here (and the run's and the TLS run's documents) has Zenoh's shared-memory
transport off (``NO_SHARED_MEMORY``): Zenoh 1.x sends a payload over 3 KiB through shared memory when
both ends share a host, and a process's first such put sets up its pool inside the call — a one-off
stall of its stage on one scan (6 ms alone, 35–45 ms in a running pipeline; docs/closed-loop.md),
while cvxnav's messages, kilobytes each, gain nothing from not being copied. A ``--config`` file is
taken as it is.
"""

from __future__ import annotations

import argparse
import ipaddress
import json
import re
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Literal

import zenoh

Mode = Literal["peer", "client", "router"]
MODES: tuple[Mode, ...] = ("peer", "client", "router")
# How often a session tries its `connect` endpoints again once a link is lost: Zenoh's default backs off
# to 4 s, so a client found a restarted router up to 4 s after it was back (and the car stood as long).
RECONNECT = {"period_init_ms": 250, "period_max_ms": 1000, "period_increase_factor": 2}
NO_SHARED_MEMORY = {"shared_memory": {"enabled": False}}  # under "transport"

# Zenoh's link protocols (zenoh/io/zenoh-links): those whose address is host:port, and the rest.
IP_PROTOCOLS = ("tcp", "udp", "tls", "quic", "ws")
OTHER_PROTOCOLS = ("unixsock-stream", "unixpipe", "serial", "vsock")
_HOSTNAME = re.compile(r"(?=.{1,253}$)([A-Za-z0-9]([A-Za-z0-9-]{0,61}[A-Za-z0-9])?)(\.[A-Za-z0-9]([A-Za-z0-9-]{0,61}[A-Za-z0-9])?)*\.?")


def check_endpoint(text: str) -> str:
    """`text` if it is a Zenoh endpoint `<protocol>/<address>[?<metadata>][#<config>]` whose address can be
    one; else ValueError saying why, in one line.

    Zenoh takes any such string into its config and fails only when the session opens (with a
    traceback's worth of context); checked here, a typo is refused before anything starts. An IP
    protocol's address is host:port: a port 0–65535, and an IPv4 literal, a bracketed IPv6 literal or a
    host name (RFC 1123; one made of digits and dots is an IPv4 literal, so 999.1.1.1 is refused).
    """
    protocol, slash, rest = text.partition("/")
    address = re.split(r"[?#]", rest, maxsplit=1)[0]
    if not slash or not protocol or not address:
        raise ValueError(f"{text!r} is not <protocol>/<address>, e.g. tcp/127.0.0.1:7447")
    if protocol in OTHER_PROTOCOLS:
        return text
    if protocol not in IP_PROTOCOLS:
        raise ValueError(f"{text!r}: unknown protocol {protocol!r} (known: {', '.join(IP_PROTOCOLS + OTHER_PROTOCOLS)})")
    host, colon, port = address.rpartition(":")
    if not colon or not host or not port.isdigit() or int(port) > 65535:
        raise ValueError(f"{text!r}: the address must be HOST:PORT with a port in 0..65535, e.g. {protocol}/127.0.0.1:7447")
    try:
        if host.startswith("[") and host.endswith("]"):
            ipaddress.IPv6Address(host[1:-1])
        elif re.fullmatch(r"[0-9.]+", host):
            ipaddress.IPv4Address(host)
        elif not _HOSTNAME.fullmatch(host):
            raise ValueError(f"{host!r} is not a host name")
    except ValueError as error:
        raise ValueError(f"{text!r}: not an IP address or host name: {error}") from None
    return text


def argument_type(check: Callable[[str], str]) -> Callable[[str], str]:
    """A check that raises ValueError as an argparse type: a bad value is the usual one-line usage error
    (exit 2)."""
    def parse(text: str) -> str:
        try:
            return check(text)
        except ValueError as error:
            raise argparse.ArgumentTypeError(str(error)) from None
    return parse


endpoint_argument = argument_type(check_endpoint)


def zenoh_reason(error: Exception) -> str:
    """A Zenoh error's message without the Rust source locations it carries."""
    return re.sub(r"\s+at /\S+?\.rs:\d+\.?", "", str(error)).strip()


def build_zenoh_config(
    *,
    connect: Sequence[str] = (),
    listen: Sequence[str] = (),
    config_file: Path | None = None,
    mode: Mode | None = None,
) -> zenoh.Config:
    """Start from ``config_file`` (or Zenoh's defaults, mode ``peer``, with shared memory off) and apply the
    overrides; ``connect`` endpoints are retried every second at most (``RECONNECT``).

    ``mode=None`` keeps the file's mode (or Zenoh's default, ``peer``) rather than overriding it.
    """
    if config_file:
        config = zenoh.Config.from_file(str(config_file))
    else:
        config = zenoh.Config()
        config.insert_json5("transport", json.dumps(NO_SHARED_MEMORY))
    if mode is not None:
        config.insert_json5("mode", json.dumps(mode))
    if connect:
        config.insert_json5("connect/endpoints", json.dumps(list(connect)))
        config.insert_json5("connect/retry", json.dumps(RECONNECT))
    if listen:
        config.insert_json5("listen/endpoints", json.dumps(list(listen)))
    if connect or listen:
        config.insert_json5("scouting/multicast/enabled", json.dumps(False))
    return config


def endpoints_config(*, listen: Sequence[str] = (), connect: Sequence[str] = (), mode: Mode = "peer") -> dict:
    """A whole Zenoh config as a document (for a file a child process reads): these endpoints, no scouting,
    no shared memory."""
    return {"mode": mode, "listen": {"endpoints": list(listen)}, "connect": {"endpoints": list(connect)},
            "scouting": {"multicast": {"enabled": False}}, "transport": NO_SHARED_MEMORY}


def config_from_doc(doc: dict) -> zenoh.Config:
    """The session config for a document like ``endpoints_config`` or ``cvxnav.certs`` returns."""
    return zenoh.Config.from_json5(json.dumps(doc))


def add_zenoh_arguments(parser: argparse.ArgumentParser) -> None:
    group = parser.add_argument_group("zenoh")
    group.add_argument(
        "--connect", "-e", metavar="ENDPOINT", action="append", default=[], type=endpoint_argument,
        help="endpoint to connect to, e.g. tcp/127.0.0.1:7447 (repeatable)",
    )
    group.add_argument(
        "--listen", "-l", metavar="ENDPOINT", action="append", default=[], type=endpoint_argument,
        help="endpoint to listen on, e.g. tcp/0.0.0.0:7447 (repeatable)",
    )
    group.add_argument(
        "--config", "-c", dest="zenoh_config", metavar="FILE", type=Path, default=None,
        help="a Zenoh configuration file (zenoh.json5)",
    )
    group.add_argument(
        "--mode", "-m", choices=MODES, default=None,
        help="session mode (default: the config file's, else peer)",
    )


def zenoh_config_from_args(args: argparse.Namespace) -> zenoh.Config:
    """The config for arguments added by ``add_zenoh_arguments``."""
    return build_zenoh_config(
        connect=args.connect, listen=args.listen, config_file=args.zenoh_config, mode=args.mode
    )
