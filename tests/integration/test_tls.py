"""Mutual TLS + access control on loopback, with certificates from `cvxnav certs`.

A router configured as `cvxnav certs` writes it; the pipeline's certificates talk (a real sensing
stage process answers a scan), while a client without a certificate, one with a certificate from
another CA, and one with a valid certificate whose name is not a stage get no message in or out.
"""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import zenoh
from tls_clients import INTRUDER, Inbox, connect_outsiders, open_session

from cvxnav.certs import client_config, pipeline_names, router_config, write_deployment
from cvxnav.supervisor import free_ports
from schemas.messages import Clusters, Header, Pose2D, Scan, decode
from schemas.wiring import default_prefix, every_key, key

PREFIX = default_prefix()
SETTLE_S = 1.0


def _scan(seq: int) -> str:
    return Scan(header=Header(stamp_s=0.1 * seq, seq=seq), pose=Pose2D(x_m=0.0, y_m=0.0, theta_rad=0.0),
                points=[(2.0, 0.0), (2.0, 0.1), (2.1, 0.05)]).model_dump_json()


@pytest.fixture(scope="module")
def deployment(tmp_path_factory):
    """Certificates (ours, plus an outsider's CA), and a TLS router with access control on a free port."""
    ours = tmp_path_factory.mktemp("certs")
    theirs = tmp_path_factory.mktemp("other-ca")
    try:
        write_deployment(out_dir=ours, names=(*pipeline_names(), INTRUDER))  # intruder: signed, not allowed
        write_deployment(out_dir=theirs)
    except Exception as error:  # pragma: no cover - only where the cryptography wheel is broken
        pytest.skip(f"cannot make certificates here: {error}")
    (port,) = free_ports(1)
    endpoint = f"tls/localhost:{port}"
    try:
        router = open_session(router_config(cert_dir=ours.resolve(), listen=[endpoint], names=pipeline_names()))
    except zenoh.ZError as error:
        pytest.skip(f"this zenoh wheel cannot open a TLS listener: {error}")
    yield ours.resolve(), theirs.resolve(), endpoint
    router.close()


def test_only_pipeline_certificates_exchange_messages(deployment, tmp_path):
    ours, theirs, endpoint = deployment
    monitor_inbox = Inbox()
    with open_session(client_config(cert_dir=ours, name="monitor", connect=[endpoint])) as monitor, \
            open_session(client_config(cert_dir=ours, name="sim", connect=[endpoint])) as sim:
        monitor.declare_subscriber(every_key(PREFIX), monitor_inbox)
        outsiders = connect_outsiders(ours, theirs, endpoint, prefix=PREFIX)
        time.sleep(SETTLE_S)
        assert outsiders["valid certificate, name not allowed"][0] is not None, "a signed client gets a link"
        sim.put(key(PREFIX, "scan"), _scan(1))
        for label, (session, _) in outsiders.items():
            if session is not None:
                session.put(key(PREFIX, "state"), f"from {label}")
        time.sleep(SETTLE_S)
        assert monitor_inbox.keys() == [key(PREFIX, "scan")], "the pipeline hears the sim and nobody else"
        for label, (session, inbox) in outsiders.items():
            heard = [k for k, payload in inbox.samples if payload != f"from {label}".encode()]  # not its own put
            assert heard == [], f"{label} received {heard}"
            if session is not None:
                session.close()

    # A real stage process on its generated config answers over TLS through the router's ACL.
    stage = subprocess.Popen([sys.executable, "-m", "cvxnav", "service", "sensing", "--config",
                              str(ours / "sensing.json5"), "--connect", endpoint],
                             stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    try:
        answers = Inbox()
        with open_session(client_config(cert_dir=ours, name="monitor", connect=[endpoint])) as monitor, \
                open_session(client_config(cert_dir=ours, name="sim", connect=[endpoint])) as sim:
            monitor.declare_subscriber(key(PREFIX, "clusters"), answers)
            deadline, seq = time.monotonic() + 60.0, 1
            while not answers.samples and time.monotonic() < deadline and stage.poll() is None:
                sim.put(key(PREFIX, "scan"), _scan(seq))  # until the stage is up and subscribed
                seq += 1
                time.sleep(0.3)
            assert answers.samples, f"no clusters from the TLS stage (exit {stage.poll()})"
            clusters = decode(Clusters, answers.samples[0][1])
            assert clusters.clusters and clusters.scan_seq >= 1
    finally:
        stage.send_signal(signal.SIGTERM)
        _, stderr = stage.communicate(timeout=20)
    assert stage.returncode == 0, stderr[-2000:]


def test_documented_configs_match_what_certs_writes():
    """deploy/*.json5 parse as Zenoh configs and grant exactly what `cvxnav certs` grants."""
    from cvxnav.certs import access_control

    deploy = Path(__file__).resolve().parents[2] / "deploy"
    router = zenoh.Config.from_file(str(deploy / "zenoh-tls-router.json5"))
    generated = zenoh.Config()
    generated.insert_json5("access_control", json.dumps(access_control(names=pipeline_names())))
    assert json.loads(router.get_json("access_control")) == json.loads(generated.get_json("access_control"))
    assert json.loads(router.get_json("transport/link/tls/enable_mtls")) is True
    stage = zenoh.Config.from_file(str(deploy / "zenoh-tls-stage.json5"))
    assert json.loads(stage.get_json("transport/link/tls/verify_name_on_connect")) is True
