"""One helper that builds the Zenoh session config from ``--connect/--listen/--config/--mode``.

Mirrors zenoh-python's ``examples/common/common.py``. When explicit endpoints are given, multicast
scouting is turned off: the peers find each other through those endpoints, so processes on one
machine (and tests on loopback) need no router and do not see unrelated sessions on the LAN.
"""

from __future__ import annotations

import argparse
import json
from collections.abc import Sequence
from pathlib import Path
from typing import Literal

import zenoh

Mode = Literal["peer", "client", "router"]
MODES: tuple[Mode, ...] = ("peer", "client", "router")
# How often a session tries its `connect` endpoints again once a link is lost: Zenoh's default backs off
# to 4 s, so a client found a restarted router up to 4 s after it was back (and the car stood as long).
RECONNECT = {"period_init_ms": 250, "period_max_ms": 1000, "period_increase_factor": 2}


def build_zenoh_config(
    *,
    connect: Sequence[str] = (),
    listen: Sequence[str] = (),
    config_file: Path | None = None,
    mode: Mode | None = None,
) -> zenoh.Config:
    """Start from ``config_file`` (or Zenoh's defaults, mode ``peer``) and apply the overrides; ``connect``
    endpoints are retried every second at most (``RECONNECT``).

    ``mode=None`` keeps the file's mode (or Zenoh's default, ``peer``) rather than overriding it.
    """
    config = zenoh.Config.from_file(str(config_file)) if config_file else zenoh.Config()
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
    """A whole Zenoh config as a document (for a file a child process reads): these endpoints, no scouting."""
    return {"mode": mode, "listen": {"endpoints": list(listen)}, "connect": {"endpoints": list(connect)},
            "scouting": {"multicast": {"enabled": False}}}


def config_from_doc(doc: dict) -> zenoh.Config:
    """The session config for a document like ``endpoints_config`` or ``cvxnav.certs`` returns."""
    return zenoh.Config.from_json5(json.dumps(doc))


def add_zenoh_arguments(parser: argparse.ArgumentParser) -> None:
    group = parser.add_argument_group("zenoh")
    group.add_argument(
        "--connect", "-e", metavar="ENDPOINT", action="append", default=[],
        help="endpoint to connect to, e.g. tcp/127.0.0.1:7447 (repeatable)",
    )
    group.add_argument(
        "--listen", "-l", metavar="ENDPOINT", action="append", default=[],
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
