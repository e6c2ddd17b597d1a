"""Mutual TLS + access control on loopback, with certificates from `cvxnav certs`.

A router configured as `cvxnav certs` writes it; the pipeline's certificates talk (a real sensing
stage process answers a scan), while a client without a certificate, one with a certificate from
another CA, and one with a valid certificate whose name is not a stage get no message in or out.
Every certificate then tries every verb on every key: exactly what the wiring table gives it gets
through (`test_the_router_grants_exactly_the_wiring_tables_least_privilege`).
"""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
import zenoh
from tls_clients import (
    INTRUDER,
    Inbox,
    connect_outsiders,
    may_answer,
    may_ask,
    may_put,
    may_read,
    open_session,
    table_keys,
)

from cvxnav.certs import OPERATOR, client_config, pipeline_names, router_config, write_deployment
from cvxnav.supervisor import free_ports
from schemas.messages import Clusters, Header, Pose2D, Scan, decode
from schemas.wiring import (
    MONITOR,
    PROCESSES,
    alive_key,
    default_prefix,
    key,
    stage_of_alive_key,
)

PREFIX = default_prefix()
SETTLE_S = 1.0
QUERY_TIMEOUT_S = 8.0  # what a query may wait for its replies here


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
        for topic in MONITOR.subscribes:  # as the monitor's shell does: the wiring table's keys, each on its own
            monitor.declare_subscriber(key(PREFIX, topic), monitor_inbox)
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


def test_the_router_grants_exactly_the_wiring_tables_least_privilege(deployment):
    """Every certificate (the pipeline's, the monitor's, the operator's, a signed outsider's) puts,
    deletes, subscribes, queries, answers queries, holds tokens, watches and asks tokens on every key
    at once; what arrives is exactly what the table allows, and a refused query gets only its own
    session's timeout."""
    ours, _, endpoint = deployment
    names = (*pipeline_names(), INTRUDER)
    keys = table_keys(PREFIX, names)
    lock = threading.Lock()
    heard: dict[tuple, set[tuple[str, str]]] = {}  # (receiver, key) -> {(kind, sender)}
    replies: dict[tuple, set[str]] = {}  # (asker, key) -> {"ok:<replier>" | "err:<payload>"}
    tokens: dict[str, set[str]] = {}  # watcher -> names whose token it was sent

    def on_sample(receiver: str, what: tuple[str, str]):
        def callback(sample: zenoh.Sample) -> None:
            with lock:
                heard.setdefault((receiver, what), set()).add((str(sample.kind), sample.payload.to_bytes().decode()))
        return callback

    def on_reply(asker: str, what: tuple[str, str]):
        def callback(reply: zenoh.Reply) -> None:
            with lock:
                replies.setdefault((asker, what), set()).add(
                    f"ok:{reply.ok.payload.to_bytes().decode()}" if reply.ok is not None
                    else f"err:{reply.err.payload.to_bytes().decode()}")
        return callback

    def on_token(watcher: str):
        def callback(sample: zenoh.Sample) -> None:
            if sample.kind == zenoh.SampleKind.PUT:
                with lock:
                    tokens.setdefault(watcher, set()).add(stage_of_alive_key(PREFIX, str(sample.key_expr)))
        return callback

    finished = threading.Semaphore(0)  # released as each query ends
    asked_queries = 0
    sessions = {name: open_session(client_config(cert_dir=ours, name=name, connect=[endpoint])) for name in names}
    try:
        publishers = {}  # declared, as the shell declares them: they send only towards subscribers they are told of
        for name, session in sessions.items():
            for what, key_expr in keys.items():
                publishers[name, what] = session.declare_publisher(key_expr)
                session.declare_subscriber(key_expr, on_sample(name, what))
                session.declare_queryable(key_expr, lambda query, name=name: query.reply(query.key_expr, name))
            session.liveliness().declare_subscriber(alive_key(PREFIX), on_token(name), history=True)
        time.sleep(SETTLE_S)
        for name, session in sessions.items():
            for what, key_expr in keys.items():
                publishers[name, what].put(name)
                publishers[name, what].delete()
                # Every session asks every key at once: an answer may take longer than a settle (on a
                # loaded machine, seconds), so the replies are read only once every query has finished.
                # Every reply counts, not the one per key that consolidation would keep (its own
                # queryable's local reply, on the same key, would hide another's at random).
                session.get(key_expr, zenoh.handlers.Callback(on_reply(name, what), drop=finished.release),
                            consolidation=zenoh.ConsolidationMode.NONE, timeout=QUERY_TIMEOUT_S)
                asked_queries += 1
        # Tokens under every other name: none may reach anyone (a session sees its own locally).
        foreign = [session.liveliness().declare_token(alive_key(PREFIX, other))
                   for name, session in sessions.items() for other in names if other != name]
        time.sleep(2 * SETTLE_S)
        with lock:
            assert {name: seen - (set(names) - {name}) for name, seen in tokens.items() if seen - (set(names) - {name})} \
                == {}, "a token under another's name got through"
        for token in foreign:
            token.undeclare()
        time.sleep(SETTLE_S)
        with lock:
            tokens.clear()
        own = [session.liveliness().declare_token(alive_key(PREFIX, name)) for name, session in sessions.items()]
        time.sleep(SETTLE_S)
        # Every session asks at once, and each is read once its query has ended (at the timeout at the
        # latest): on a loaded machine an answer may take seconds.
        asking = {name: session.liveliness().get(alive_key(PREFIX), timeout=QUERY_TIMEOUT_S)
                  for name, session in sessions.items()}
        asked = {name: {stage_of_alive_key(PREFIX, str(reply.ok.key_expr)) for reply in answers if reply.ok is not None}
                 for name, answers in asking.items()}
        with lock:
            watched = {name: tokens.get(name, set()) for name in names}
        for token in own:
            token.undeclare()
        for _ in range(asked_queries):  # a refused query ends at its timeout, an allowed one with its replies
            assert finished.acquire(timeout=2 * QUERY_TIMEOUT_S), "a query never finished"
    finally:
        for session in sessions.values():
            session.close()

    for receiver in names:
        for what in keys:
            got = heard.get((receiver, what), set()) - {("SampleKind.PUT", receiver), ("SampleKind.DELETE", "")}
            expected = {("SampleKind.PUT", sender) for sender in names
                        if sender != receiver and may_put(sender, what) and may_read(receiver, what)}
            assert got == expected, f"{receiver} on {keys[what]}"
            answers = replies.get((receiver, what), set()) - {f"ok:{receiver}"}  # its own queryable, locally
            expected_answers = ({f"ok:{name}" for name in names if name != receiver and may_answer(name, what)}
                                if may_ask(receiver, what) else set())
            assert answers - {"err:Timeout"} == expected_answers, f"{receiver} asking {keys[what]}"
    # Deletes: nobody may delete, so none arrives from another session (their payload is empty).
    # Tokens: each process's own, to those that watch (the sim) or ask (the operator), and nobody else's.
    # (A watcher's own session answers its asking from the tokens it was sent.)
    holders = set(PROCESSES)
    for name in names:
        watching = bool(getattr(PROCESSES.get(name), "watches", ()))
        assert watched[name] - {name} == (holders - {name} if watching else set()), f"{name} watching tokens"
        assert asked[name] - {name} == (holders - {name} if watching or name == OPERATOR else set()), \
            f"{name} asking tokens"
