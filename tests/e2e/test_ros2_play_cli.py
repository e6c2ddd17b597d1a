"""`cvxnav ros2 play` as a user runs it: a real process publishing the ACES bag into a real Zenoh peer.

What arrives is decoded by mcap-ros2-support with the schemas the bag itself carries and compared with
the bag's messages read by mcap's own reader (``ros2_bag``), byte for byte and field by field.
"""

from __future__ import annotations

import signal
import subprocess
import sys
import threading
import time
from collections import defaultdict
from dataclasses import dataclass, field
from pathlib import Path

import pytest
import zenoh
from mcap.records import Schema
from mcap_ros2.decoder import DecoderFactory

from cvxnav.supervisor import free_ports, stop_processes
from ros2_bag import TOPIC_COUNTS, aces_bag_dir, read_mcap
from services.ros2.wire import EntityKind, gid_of, parse_token
from services.shell.ros2 import Attachment
from services.shell.zenoh_config import build_zenoh_config

RATE = 2000.0  # the 1318 s log in 0.66 s


@dataclass
class Listener:
    """A peer the player connects to: every data sample under a domain, and the graph's tokens."""

    session: zenoh.Session
    endpoint: str
    samples: list[tuple[str, bytes, bytes | None]] = field(default_factory=list)
    tokens: dict[str, bool] = field(default_factory=dict)  # key -> alive
    lock: threading.Lock = field(default_factory=threading.Lock)

    def on_sample(self, sample: zenoh.Sample) -> None:
        with self.lock:
            attachment = sample.attachment.to_bytes() if sample.attachment is not None else None
            self.samples.append((str(sample.key_expr), sample.payload.to_bytes(), attachment))

    def on_token(self, sample: zenoh.Sample) -> None:
        with self.lock:
            self.tokens[str(sample.key_expr)] = sample.kind == zenoh.SampleKind.PUT

    def wait(self, predicate, *, timeout_s: float) -> None:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            with self.lock:
                if predicate(self):
                    return
            time.sleep(0.02)
        pytest.fail("timed out waiting for the player")


@pytest.fixture
def listener():
    endpoint = f"tcp/127.0.0.1:{free_ports(1)[0]}"
    with zenoh.open(build_zenoh_config(listen=[endpoint])) as session:
        peer = Listener(session=session, endpoint=endpoint)
        session.declare_subscriber("*/**", peer.on_sample)
        session.liveliness().declare_subscriber("@ros2_lv/**", peer.on_token, history=True)
        yield peer


@pytest.fixture(scope="module")
def recorded(shared_dir):
    return read_mcap(aces_bag_dir(shared_dir) / "aces-bag.mcap")


def play(bag: Path, *args: str, cwd: Path) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "cvxnav", "ros2", "play", str(bag), *args], cwd=cwd,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def decoders(shared_dir) -> dict[str, object]:
    """mcap-ros2-support decoders by type, from the schemas stored in the bag."""
    from mcap.reader import make_reader

    with (aces_bag_dir(shared_dir) / "aces-bag.mcap").open("rb") as stream:
        summary = make_reader(stream).get_summary()
    factory = DecoderFactory()
    return {s.name: factory.decoder_for("cdr", Schema(id=s.id, name=s.name, encoding=s.encoding, data=s.data))
            for s in summary.schemas.values()}


def check_played(samples, recorded, *, decode, prefix: str) -> None:
    """Every recorded message arrived once, in order per topic, unchanged, with rmw_zenoh's attachment."""
    by_key = defaultdict(list)
    for key, payload, attachment in samples:
        by_key[key].append((payload, Attachment.from_bytes(attachment)))
    expected_keys = {f"{prefix}/scan/sensor_msgs::msg::dds_::LaserScan_/RIHS01_64c191398013af96509d518dac71d5164f"
                     "9382553fce5c1f8cca5be7924bd828",
                     f"{prefix}/odom/nav_msgs::msg::dds_::Odometry_/RIHS01_3cc97dc7fb7502f8714462c526d369e35b603cfc"
                     "34d946e3f2eda2766dfec6e0"}
    assert set(by_key) == expected_keys
    for key, arrived in by_key.items():
        topic = "/" + key.split("/")[-3]
        bag = [r for r in recorded if r.topic == topic]
        assert len(arrived) == len(bag) == TOPIC_COUNTS[topic]
        assert [a.sequence_number for _, a in arrived] == list(range(1, len(bag) + 1))
        assert len({a.source_gid for _, a in arrived}) == 1
        # Paced: the topic's messages span its recording's duration / rate (less 20 ms for the first one's
        # send), not faster.
        span_ns = arrived[-1][1].source_timestamp_ns - arrived[0][1].source_timestamp_ns
        assert span_ns >= (bag[-1].log_time_ns - bag[0].log_time_ns) / RATE - 20e6
        for (payload, _), message in zip(arrived, bag):
            assert payload == message.data
            mine, theirs = decode[message.schema_name](payload), message.message
            assert (mine.header.stamp.sec, mine.header.stamp.nanosec, mine.header.frame_id) == \
                (theirs.header.stamp.sec, theirs.header.stamp.nanosec, theirs.header.frame_id)
            if topic == "/scan":
                assert list(mine.ranges) == list(theirs.ranges) and mine.angle_min == theirs.angle_min
            else:
                assert mine.pose.pose.position.x == theirs.pose.pose.position.x


def test_the_aces_bag_arrives_whole_on_rmw_zenoh_keys(listener, recorded, shared_dir, tmp_path) -> None:
    process = play(aces_bag_dir(shared_dir), "--rate", str(RATE), "--delay", "1", "--connect", listener.endpoint,
                   cwd=tmp_path)
    out, err = process.communicate(timeout=60)
    assert process.returncode == 0, err
    assert out.splitlines()[-1] == "published 880 messages"
    listener.wait(lambda peer: len(peer.samples) == 880, timeout_s=10)
    check_played(listener.samples, recorded, decode=decoders(shared_dir), prefix="0")
    # The graph saw the player's node and one publisher per topic, each GID the hash of its token.
    entities = {parse_token(key): key for key in listener.tokens}
    assert {(e.kind, e.node_fqn, e.topic) for e in entities} == {
        (EntityKind.NODE, "/cvxnav_play", None),
        (EntityKind.PUBLISHER, "/cvxnav_play", "/scan"),
        (EntityKind.PUBLISHER, "/cvxnav_play", "/odom")}
    gids = {gid_of(key) for e, key in entities.items() if e.kind == EntityKind.PUBLISHER}
    assert gids == {Attachment.from_bytes(a).source_gid for _, _, a in listener.samples}
    listener.wait(lambda peer: not any(peer.tokens.values()), timeout_s=10)  # all undeclared at the end


def test_a_sqlite3_bag_plays_the_same_under_a_namespace_and_domain(listener, recorded, shared_dir, tmp_path) -> None:
    from rosbags.highlevel import AnyReader
    from rosbags.rosbag2 import StoragePlugin, Writer

    sqlite_bag = tmp_path / "aces-sqlite3"
    with AnyReader([aces_bag_dir(shared_dir)]) as reader, Writer(sqlite_bag, version=9,
                                                                 storage_plugin=StoragePlugin.SQLITE3) as writer:
        connections = {c.id: writer.add_connection(c.topic, c.msgtype, typestore=reader.typestore)
                       for c in reader.connections}
        for connection, stamp_ns, payload in reader.messages():
            writer.write(connections[connection.id], stamp_ns, payload)
    process = play(sqlite_bag, "--rate", str(RATE), "--delay", "1", "--namespace", "robot1", "--domain-id", "7",
                   "--connect", listener.endpoint, cwd=tmp_path)
    _, err = process.communicate(timeout=60)
    assert process.returncode == 0, err
    listener.wait(lambda peer: len(peer.samples) == 880, timeout_s=10)
    check_played(listener.samples, recorded, decode=decoders(shared_dir), prefix="7/robot1")
    assert {parse_token(key).node_fqn for key in listener.tokens} == {"/robot1/cvxnav_play"}


@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM])
def test_a_looping_player_stops_cleanly_on_a_signal(listener, shared_dir, tmp_path, signum) -> None:
    process = play(aces_bag_dir(shared_dir), "--rate", "500", "--loop", "--connect", listener.endpoint, cwd=tmp_path)
    try:
        listener.wait(lambda peer: len(peer.samples) > 880, timeout_s=30)  # into its second pass
        process.send_signal(signum)
        out, err = process.communicate(timeout=15)
    finally:
        stop_processes([process], grace_s=5.0)
    assert process.returncode == 0, err
    assert int(out.splitlines()[-1].split()[1]) > 880
    sequence = [Attachment.from_bytes(a).sequence_number for k, _, a in listener.samples if "/scan/" in k]
    assert sequence == list(range(1, len(sequence) + 1))  # the second pass continues the numbering


@pytest.mark.parametrize("make, message", [
    (lambda tmp: tmp / "absent", "absent: no such bag"),
    (lambda tmp: (tmp / "notes.txt").write_text("hello") and tmp / "notes.txt", "not a readable rosbag2"),
    (lambda tmp: _bag_without_definitions(tmp / "custom", "my_pkg/msg/Thing"),
     "unknown message type 'my_pkg/msg/Thing'"),
    (lambda tmp: _bag_without_definitions(tmp / "wrong", "sensor_msgs/msg/LaserScan"),
     f"records type hash RIHS01_{'0' * 64} for sensor_msgs/msg/LaserScan, but its definition hashes to RIHS01_64c19"),
])
def test_a_bag_that_cannot_be_played_is_one_line_and_exit_2(tmp_path, make, message) -> None:
    process = play(make(tmp_path), "--listen", f"tcp/127.0.0.1:{free_ports(1)[0]}", cwd=tmp_path)
    out, err = process.communicate(timeout=60)
    assert process.returncode == 2 and out == ""
    assert err.count("\n") == 1 and err.startswith("cvxnav: error: ") and message in err


def _bag_without_definitions(path: Path, msgtype: str) -> Path:
    """A sqlite3 bag of one ``msgtype`` message, its definition left out and its hash recorded as zeros."""
    import sqlite3

    from rosbags.rosbag2 import StoragePlugin, Writer

    with Writer(path, version=9, storage_plugin=StoragePlugin.SQLITE3) as writer:
        connection = writer.add_connection("/thing", msgtype, msgdef="", rihs01="RIHS01_" + "0" * 64)
        writer.write(connection, 1, b"\x00\x01\x00\x00")
    with sqlite3.connect(path / f"{path.name}.db3") as db:
        db.execute("DELETE FROM message_definitions")
    return path
