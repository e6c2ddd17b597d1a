"""The Zenoh configs cvxnav builds: shared memory off in every one (services.shell.zenoh_config)."""

import json
from pathlib import Path

import pytest
import zenoh

from cvxnav.certs import client_config, router_config
from services.shell.zenoh_config import build_zenoh_config, config_from_doc, endpoints_config

DEPLOY = Path(__file__).resolve().parents[2] / "deploy"
CONFIGS = {
    "defaults": lambda: build_zenoh_config(),
    "endpoints": lambda: build_zenoh_config(connect=["tcp/127.0.0.1:7447"], listen=["tcp/127.0.0.1:7448"]),
    "a run's stage": lambda: config_from_doc(endpoints_config(listen=["tcp/127.0.0.1:7448"])),
    "TLS router": lambda: config_from_doc(router_config(cert_dir=Path("/certs"), listen=["tls/127.0.0.1:7447"],
                                                        names=["sensing"])),
    "TLS stage": lambda: config_from_doc(client_config(cert_dir=Path("/certs"), name="sensing",
                                                       connect=["tls/127.0.0.1:7447"])),
    "deploy router": lambda: zenoh.Config.from_file(str(DEPLOY / "zenoh-tls-router.json5")),
    "deploy stage": lambda: zenoh.Config.from_file(str(DEPLOY / "zenoh-tls-stage.json5")),
}


@pytest.mark.parametrize("name", CONFIGS)
def test_every_config_cvxnav_builds_has_shared_memory_off(name):
    """Zenoh's shared memory would set up its pool inside a process's first put over 3 KiB: a stall of
    tens of milliseconds on one scan, for messages too small to gain from it."""
    assert json.loads(CONFIGS[name]().get_json("transport/shared_memory/enabled")) is False


def test_a_config_file_is_taken_as_it_is(tmp_path):
    path = tmp_path / "zenoh.json5"
    path.write_text('{ mode: "peer", transport: { shared_memory: { enabled: true } } }')
    config = build_zenoh_config(config_file=path, connect=["tcp/127.0.0.1:7447"])
    assert json.loads(config.get_json("transport/shared_memory/enabled")) is True
