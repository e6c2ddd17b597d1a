"""`cvxnav run --tls`: a whole paper run under mutual TLS + access control, with outsiders knocking during it.

The run's router (the supervisor) also listens on a port the test chose. While the car drives, a
client without a certificate, one with another CA's certificate and one with a valid certificate whose
name is no stage subscribe to every key and liveliness token, query, and publish a forged scan. The
run must reach its goals; none of them may receive a message or a reply, and the forged scan must never
reach the pipeline, while the operator's certificate hears the run the whole time.
"""

from __future__ import annotations

import subprocess
import sys
import time

import pytest
import zenoh
from tls_clients import INTRUDER, Inbox, connect_outsiders, open_session

from cvxnav.certs import client_config, pipeline_names, write_deployment
from cvxnav.supervisor import free_ports, stop_processes
from schemas.files import RunFile
from schemas.messages import DecodeError, Header, Pose2D, RobotState, Scan, decode
from schemas.wiring import alive_key, default_prefix, every_key, key

pytestmark = pytest.mark.slow
PREFIX = default_prefix()
FORGED_SEQ = 987_654  # a scan number the sim never reaches on this scenario


def _forged_scan() -> bytes:
    """A valid scan of a wall right in front of the start: it would change the plan if it got in."""
    points = [(2.0, -1.0 + 0.1 * i) for i in range(21)]
    return Scan(header=Header(stamp_s=0.1, seq=FORGED_SEQ), pose=Pose2D(x_m=0.0, y_m=0.0, theta_rad=0.0),
                points=points).model_dump_json().encode()


def _open_when_up(doc: dict, run: subprocess.Popen, *, timeout_s: float = 60.0) -> zenoh.Session:
    """A session to the run's router once it listens (the supervisor is still importing at first)."""
    deadline = time.monotonic() + timeout_s
    while True:
        try:
            return open_session(doc)
        except zenoh.ZError:
            if run.poll() is not None or time.monotonic() > deadline:
                raise
            time.sleep(0.2)


def test_tls_run_reaches_its_goals_and_outsiders_get_nothing(tmp_path):
    ours, theirs = tmp_path / "certs", tmp_path / "other-ca"
    write_deployment(out_dir=ours, names=(*pipeline_names(), INTRUDER))
    write_deployment(out_dir=theirs)
    (port,) = free_ports(1)
    endpoint = f"tls/127.0.0.1:{port}"
    with open(tmp_path / "run.log", "wb") as log:
        run = subprocess.Popen([sys.executable, "-m", "cvxnav", "run", "--quiet", "--tls", str(ours), "--listen",
                                endpoint, "--out", "run.json"], cwd=tmp_path, stdout=log, stderr=subprocess.STDOUT,
                               stdin=subprocess.DEVNULL)
    sessions: list[zenoh.Session] = []
    try:
        operator = _open_when_up(client_config(cert_dir=ours, name="operator", connect=[endpoint]), run)
        sessions.append(operator)
        heard = Inbox()
        operator.declare_subscriber(every_key(PREFIX), heard)
        outsiders = connect_outsiders(ours, theirs, endpoint, prefix=PREFIX, liveliness=True)
        sessions += [session for session, _ in outsiders.values() if session is not None]
        assert outsiders["valid certificate, name not allowed"][0] is not None, "a signed client gets a link"
        replies = {label: 0 for label in outsiders}
        forged = 0
        while run.poll() is None:
            for label, (session, _) in outsiders.items():
                if session is None:
                    continue
                session.put(key(PREFIX, "scan"), _forged_scan())
                forged += 1
                # A refused query's only reply is its own session's Timeout error: count the answers.
                replies[label] += sum(reply.ok is not None for reply in session.get(every_key(PREFIX), timeout=0.5))
                replies[label] += sum(reply.ok is not None
                                      for reply in session.liveliness().get(alive_key(PREFIX), timeout=0.5))
            time.sleep(0.2)
        assert run.wait() == 0, (tmp_path / "run.log").read_text()[-2000:]
    finally:
        stop_processes([run], grace_s=10.0)
        for session in sessions:
            session.close()

    result = RunFile.read(tmp_path / "run.json")
    assert result.status == "reached" and result.goals_reached == 2
    assert forged > 0, "the outsiders never got to publish during the run"
    for label, (_, inbox) in outsiders.items():
        received = [k for k, payload in inbox.samples if payload != _forged_scan()]  # not its own puts, delivered locally
        assert received == [], f"{label} received {len(received)} messages: {received[:5]}"
        assert replies[label] == 0, f"{label} got {replies[label]} answers"
    # The operator (a listed name) heard the run throughout, and never the forged scan.
    states = []
    for key_expr, payload in heard.samples:
        if key_expr == key(PREFIX, "state"):
            try:
                states.append(decode(RobotState, payload))
            except DecodeError:
                pass
        if key_expr == key(PREFIX, "scan"):
            assert decode(Scan, payload).header.seq != FORGED_SEQ, "a forged scan reached the pipeline"
    assert states and states[-1].goals_reached == 2
