"""`cvxnav run --tls`: a whole paper run under mutual TLS + access control, with every certificate misbehaving.

The run's router (the supervisor) also listens on a port the test chose. While the car drives:

- a client without a certificate and one with another CA's certificate are refused at the handshake;
- every certificate of the deployment (each stage's, the monitor's, the operator's, and a signed
  `intruder`) connects and tries every (key, verb) the wiring table does not give it: puts on the keys
  it does not publish, deletes (nobody may), subscribes to the keys it does not read, asks every key it
  may not ask, answers queries on every key it may not answer, holds tokens under every other name,
  watches and asks the tokens unless it may;
- with the operator's and the monitor's certificates, issue 27's attacker answers every scan with an
  empty ellipse set, a path into a wall or off the map, and error statuses on the planner's key.

The run must reach its goals, above the hard floor, and nothing refused may get through: no certificate
receives a message or a token it may not read (its own puts, answers and tokens aside, which its session
delivers to itself), a refused query gets no answer (its only reply is its own session's Timeout error,
so only `reply.ok` counts), an allowed query is answered only by the key's publisher, and the operator,
who reads every key, never hears a forged message, a delete, a refusal of a forged path, or a token
under a name no process holds.
"""

from __future__ import annotations

import subprocess
import sys
import threading
import time

import pytest
import zenoh
from attacker import FORGED_PLAN, Attacker
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

from cvxnav.certs import OPERATOR, client_config, pipeline_names, write_deployment
from cvxnav.supervisor import free_ports, stop_processes
from schemas.files import RunFile
from schemas.messages import DecodeError, RobotState, SmoothPath, decode
from schemas.scenario import bundled_scenario
from schemas.wiring import MONITOR, PROCESSES, STAGES, alive_key, default_prefix, every_key, key, stage_of_alive_key

pytestmark = pytest.mark.slow
PREFIX = default_prefix()
SCENARIO = bundled_scenario()
NAMES = (*pipeline_names(), INTRUDER)
ROUND_S = 1.0  # between the probes' rounds of refused puts and queries
RUN_S = 600.0  # only a guard against a hung run: a lockstep run's wall time follows the machine's load


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


class Probe:
    """One certificate trying, on a live run, every (key, verb) the wiring table does not give it: it puts
    and deletes, subscribes, asks and answers queries, holds tokens under other names, watches and asks
    the tokens, wherever the table does not let it. Where it may ask, it asks too, and must hear only
    the key's publisher."""

    def __init__(self, session: zenoh.Session, name: str) -> None:
        self.session, self.name = session, name
        self.lock = threading.Lock()
        keys = table_keys(PREFIX, NAMES)
        self.puts = [key_expr for what, key_expr in keys.items() if not may_put(name, what)]
        self.deletes = list(keys.values())  # nobody may delete
        self.asks = [key_expr for what, key_expr in keys.items() if not may_ask(name, what)]
        self.allowed_asks = [key_expr for what, key_expr in keys.items() if may_ask(name, what)]
        self.marker = f"forged by {name}".encode()
        self.heard: list[tuple[str, bytes]] = []  # on keys it may not read
        self.answers: list[str] = []  # the keys of others' answers to its refused queries
        self.allowed_answers: list[bytes] = []  # the payloads answering the queries it may ask
        self.tokens: set[str] = set()  # names of the tokens it was sent
        self.reads = [key_expr for what, key_expr in keys.items() if not may_read(name, what)]
        for key_expr in self.reads:
            session.declare_subscriber(key_expr, self._on_sample)
        self.answered = [key_expr for what, key_expr in keys.items() if not may_answer(name, what)]
        for key_expr in self.answered:
            session.declare_queryable(key_expr, lambda query: query.reply(query.key_expr, self.marker))
        self.tries_watching = not getattr(PROCESSES.get(name), "watches", ())
        if self.tries_watching:
            session.liveliness().declare_subscriber(alive_key(PREFIX), self._on_token, history=True)
        self.asks_tokens = self.tries_watching and name != OPERATOR
        self.own_tokens = {other for other in NAMES if other != name}
        self.declared = [session.liveliness().declare_token(alive_key(PREFIX, other)) for other in self.own_tokens]

    def pairs(self) -> int:
        """How many (key, verb) pairs outside the table it tries."""
        return (len(self.puts) + len(self.deletes) + len(self.reads) + len(self.asks) + len(self.answered)
                + len(self.own_tokens) + self.tries_watching + self.asks_tokens)

    def _on_sample(self, sample: zenoh.Sample) -> None:
        if sample.kind == zenoh.SampleKind.PUT:  # its own deletes come back to it locally (the operator checks them)
            with self.lock:
                self.heard.append((str(sample.key_expr), sample.payload.to_bytes()))

    def _on_token(self, sample: zenoh.Sample) -> None:
        if sample.kind == zenoh.SampleKind.PUT:
            with self.lock:
                self.tokens.add(stage_of_alive_key(PREFIX, str(sample.key_expr)))

    def _on_reply(self, reply: zenoh.Reply) -> None:
        # A refused query's only reply is its own session's Timeout error, no answer; its own queryables
        # answer it locally.
        if reply.ok is not None and reply.ok.payload.to_bytes() != self.marker:
            with self.lock:
                self.answers.append(str(reply.ok.key_expr))

    def _on_allowed_reply(self, reply: zenoh.Reply) -> None:
        payload = reply.ok.payload.to_bytes() if reply.ok is not None else b""
        if payload and payload != self.marker:  # its own queryable answers it locally
            with self.lock:
                self.allowed_answers.append(payload)

    def _on_token_reply(self, reply: zenoh.Reply) -> None:
        if reply.ok is not None:
            with self.lock:
                self.tokens.add(stage_of_alive_key(PREFIX, str(reply.ok.key_expr)))

    def round(self) -> None:
        for key_expr in self.puts:
            self.session.put(key_expr, self.marker)
        for key_expr in self.deletes:
            self.session.delete(key_expr)
        for key_expr in self.asks:
            self.session.get(key_expr, self._on_reply, timeout=1.0)
        for key_expr in self.allowed_asks:
            self.session.get(key_expr, self._on_allowed_reply, timeout=1.0)
        if self.asks_tokens:
            self.session.liveliness().get(alive_key(PREFIX), self._on_token_reply, timeout=1.0)


def test_tls_run_refuses_every_pair_outside_the_wiring_table_and_forged_traffic_changes_nothing(tmp_path):
    ours, theirs = tmp_path / "certs", tmp_path / "other-ca"
    write_deployment(out_dir=ours, names=NAMES)
    write_deployment(out_dir=theirs)
    (port,) = free_ports(1)
    endpoint = f"tls/127.0.0.1:{port}"
    config = lambda name: client_config(cert_dir=ours, name=name, connect=[endpoint])  # noqa: E731
    with open(tmp_path / "run.log", "wb") as log:
        run = subprocess.Popen([sys.executable, "-m", "cvxnav", "run", "--quiet", "--tls", str(ours), "--listen",
                                endpoint, "--out", "run.json"], cwd=tmp_path, stdout=log, stderr=subprocess.STDOUT,
                               stdin=subprocess.DEVNULL)
    sessions: list[zenoh.Session] = []
    try:
        operator = _open_when_up(config(OPERATOR), run)
        sessions.append(operator)
        heard, deleted = Inbox(), []

        def on_delete(sample: zenoh.Sample) -> None:
            if sample.kind == zenoh.SampleKind.DELETE:
                deleted.append(str(sample.key_expr))

        operator.declare_subscriber(every_key(PREFIX), heard)
        operator.declare_subscriber(every_key(PREFIX), on_delete)
        outsiders = connect_outsiders(ours, theirs, endpoint, prefix=PREFIX)
        refused = {label: session is None for label, (session, _) in outsiders.items()}
        sessions += [session for session, _ in outsiders.values() if session is not None]
        probes = [Probe(open_session(config(name)), name) for name in NAMES]
        attackers = [Attacker(open_session(config(name)), prefix=PREFIX) for name in (OPERATOR, MONITOR.name)]
        sessions += [probe.session for probe in probes] + [attacker.session for attacker in attackers]
        rounds, alive = 0, set()  # the names of the tokens the operator was shown
        deadline = time.monotonic() + RUN_S
        while run.poll() is None:
            assert time.monotonic() < deadline, f"the run is still going after {RUN_S:g} s"
            for probe in probes:
                probe.round()
            alive |= {stage_of_alive_key(PREFIX, str(reply.ok.key_expr))
                      for reply in operator.liveliness().get(alive_key(PREFIX), timeout=1.0) if reply.ok is not None}
            rounds += 1
            time.sleep(ROUND_S)
        assert run.wait() == 0, (tmp_path / "run.log").read_text()[-2000:]
        time.sleep(1.5)  # the last queries' timeouts
    finally:
        stop_processes([run], grace_s=10.0)
        for session in sessions:
            session.close()

    result = RunFile.read(tmp_path / "run.json")
    assert result.status == "reached" and result.goals_reached == len(SCENARIO.goals)
    assert result.min_clearance >= SCENARIO.robot.safety_distance / 2.0  # the hard floor's promise
    assert refused == {"no certificate": True, "another CA": True, "valid certificate, name not allowed": False}
    assert rounds > 3 and all(attacker.scans > 20 and attacker.statuses_left == 0 for attacker in attackers)
    for label, (_, inbox) in outsiders.items():
        assert inbox.samples == [], f"{label} received {inbox.keys()[:5]}"
    for probe in probes:
        with probe.lock:
            got = [(key_expr, payload) for key_expr, payload in probe.heard if payload != probe.marker]
            assert got == [], f"{probe.name} received, on keys it may not read, {got[:3]}"
            assert probe.answers == [], f"{probe.name} was answered on {sorted(set(probe.answers))}"
            assert probe.tokens <= probe.own_tokens, f"{probe.name} was sent {probe.tokens - probe.own_tokens}"
            forged = [payload for payload in probe.allowed_answers if payload.startswith(b"forged by ")]
            assert forged == [], f"{probe.name} was answered by a queryable the table does not allow: {forged[:3]}"
    (monitor,) = (probe for probe in probes if probe.name == MONITOR.name)
    assert monitor.allowed_answers, "the monitor's certificate asked the world and the sim did not answer"
    print(f"{sum(probe.pairs() for probe in probes)} (certificate, key, verb) pairs outside the table tried "
          f"{rounds} times, all refused; {sum(attacker.scans for attacker in attackers)} scans answered by the attackers")
    # The operator, who reads every key, heard the run throughout and none of the refused traffic.
    states, paths, texts = [], [], []
    assert deleted == [], f"a refused delete got through on {sorted(set(deleted))}"
    for key_expr, payload in heard.samples:
        assert not payload.startswith(b"forged by "), f"a refused put got through on {key_expr}: {payload!r}"
        texts.append(payload)
        if key_expr == key(PREFIX, "state"):
            try:
                states.append(decode(RobotState, payload))
            except DecodeError:
                pass
        elif key_expr == key(PREFIX, "smooth_path"):
            paths.append(decode(SmoothPath, payload).plan_id)
    assert states and states[-1].goals_reached == len(SCENARIO.goals)
    assert paths and FORGED_PLAN not in paths, "a forged path reached the pipeline's key"
    assert not [text for text in texts if f"plan {FORGED_PLAN}".encode() in text or b'"input_key":"forged"' in text]
    assert alive == set(STAGES), "a token under another's name, or an outsider's, was shown"
