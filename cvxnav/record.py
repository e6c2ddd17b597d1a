"""Message recording: every message under the prefix, exactly as it went over the wire, in MCAP.

`cvxnav run --record-messages run.mcap` has the supervisor's own Zenoh session (already a peer of
every stage) subscribe to ``<prefix>/**`` and hand each sample to a `MessageRecorder`. The subscriber
callback only enqueues (key, encoding, payload, receive time) into a bounded queue, so it never slows
a publisher; one writer thread appends to the file; a full queue drops and counts.

The file is plain MCAP (https://mcap.dev), readable by any MCAP tool:

- one channel per (key, Zenoh encoding) seen: ``topic`` is the Zenoh key, ``message_encoding`` is
  ``json`` for JSON payloads (the raw bytes are stored, valid or not), and the channel's metadata
  keeps the exact Zenoh encoding; a channel whose encoding names a cvxnav model carries that model's
  JSON Schema (``jsonschema``), as `cvxnav schemas` exports it;
- ``log_time`` = ``publish_time`` = receive time at the recorder (ns since the epoch), and a
  sequence number giving the receive order across channels;
- attachment ``scenario.json`` (the run's scenario) and metadata ``cvxnav`` (prefix, scenario name,
  messages dropped), so `cvxnav replay` needs nothing but the file.

Rerun stays the monitor's business: this is a record of the messages, not a visualisation.
"""

from __future__ import annotations

import json
import logging
import queue
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import BinaryIO

import zenoh
from mcap.reader import make_reader
from mcap.writer import CompressionType, Writer

from schemas.export import json_schema
from schemas.messages import MESSAGE_MODELS
from schemas.scenario import Scenario

logger = logging.getLogger(__name__)

PROFILE = "cvxnav"
SCENARIO_ATTACHMENT = "scenario.json"
METADATA_NAME = "cvxnav"
QUEUE_CAPACITY = 10_000
_MODELS_BY_SCHEMA = {model.schema_id(): model for model in MESSAGE_MODELS}


@dataclass(frozen=True)
class Recorded:
    """One message as it was received: key, Zenoh encoding, payload bytes, receive time (ns)."""

    key: str
    encoding: str
    payload: bytes
    log_time_ns: int


class MessageRecorder:
    """Writes every sample it is handed to an MCAP file; `subscribe` wires it to a Zenoh session."""

    def __init__(self, *, path: Path, prefix: str, scenario: Scenario) -> None:
        self.path = path
        self.prefix = prefix
        self.dropped = 0
        self.written = 0
        self._inbox: queue.Queue[Recorded | None] = queue.Queue(maxsize=QUEUE_CAPACITY)
        self._file: BinaryIO = open(path, "wb")
        self._writer = Writer(self._file, compression=CompressionType.ZSTD)
        self._writer.start(profile=PROFILE, library="cvxnav")
        now = time.time_ns()
        self._writer.add_attachment(create_time=now, log_time=now, name=SCENARIO_ATTACHMENT,
                                    media_type="application/json", data=scenario.model_dump_json().encode())
        self._scenario_name = scenario.name
        self._schemas: dict[str, int] = {}
        self._channels: dict[tuple[str, str], int] = {}
        self._thread = threading.Thread(target=self._drain, name="mcap-recorder", daemon=True)
        self._thread.start()

    def on_sample(self, sample: zenoh.Sample) -> None:
        """Zenoh subscriber callback: enqueue only."""
        if sample.kind != zenoh.SampleKind.PUT:
            return
        item = Recorded(key=str(sample.key_expr), encoding=str(sample.encoding), payload=sample.payload.to_bytes(),
                        log_time_ns=time.time_ns())
        try:
            self._inbox.put_nowait(item)
        except queue.Full:
            self.dropped += 1

    def subscribe(self, session: zenoh.Session) -> zenoh.Subscriber:
        return session.declare_subscriber(f"{self.prefix}/**", self.on_sample)

    def close(self) -> None:
        """Write what is queued, the metadata, and the MCAP summary."""
        self._inbox.put(None)
        self._thread.join()
        self._writer.add_metadata(METADATA_NAME, {"prefix": self.prefix, "scenario": self._scenario_name,
                                                  "dropped": str(self.dropped)})
        self._writer.finish()
        self._file.close()
        logger.info("recorded %d messages to %s (%d dropped)", self.written, self.path, self.dropped)

    def _drain(self) -> None:
        while (item := self._inbox.get()) is not None:
            self._writer.add_message(channel_id=self._channel(item.key, item.encoding), log_time=item.log_time_ns,
                                     publish_time=item.log_time_ns, data=item.payload, sequence=self.written)
            self.written += 1

    def _channel(self, key: str, encoding: str) -> int:
        channel = self._channels.get((key, encoding))
        if channel is None:
            mime, _, schema = encoding.partition(";")
            channel = self._writer.register_channel(
                topic=key, message_encoding="json" if mime == "application/json" else mime,
                schema_id=self._schema(schema), metadata={"zenoh_encoding": encoding})
            self._channels[(key, encoding)] = channel
        return channel

    def _schema(self, schema_id: str) -> int:
        """The MCAP schema of a cvxnav model named in an encoding; 0 (none) for anything else."""
        model = _MODELS_BY_SCHEMA.get(schema_id)
        if model is None:
            return 0
        if schema_id not in self._schemas:
            self._schemas[schema_id] = self._writer.register_schema(
                name=schema_id, encoding="jsonschema", data=json.dumps(json_schema(model)).encode())
        return self._schemas[schema_id]


class RecordingError(Exception):
    """A message recording that cannot be read: one line."""


@dataclass(frozen=True)
class Recording:
    """What `cvxnav replay` needs from a file: prefix, scenario and the messages in receive order."""

    prefix: str
    scenario: Scenario
    messages: list[Recorded]


def read_recording(path: Path) -> Recording:
    """Read a file written by `MessageRecorder`; `RecordingError` in one line when it is not one."""
    from schemas.scenario import ScenarioError, parse_scenario

    try:
        with open(path, "rb") as stream:
            reader = make_reader(stream)
            metadata = {m.name: dict(m.metadata) for m in reader.iter_metadata()}
            attachments = {a.name: a.data for a in reader.iter_attachments()}
            messages = list(_messages(reader))
    except OSError as error:
        raise RecordingError(f"{path}: cannot read: {error.strerror}") from None
    except Exception as error:  # the mcap reader raises several kinds for a file that is not MCAP
        raise RecordingError(f"{path}: not an MCAP file: {type(error).__name__}: {error}".splitlines()[0]) from None
    if METADATA_NAME not in metadata or SCENARIO_ATTACHMENT not in attachments:
        raise RecordingError(f"{path}: not a cvxnav message recording (no {METADATA_NAME!r} metadata or scenario)")
    try:
        scenario = parse_scenario(attachments[SCENARIO_ATTACHMENT].decode(), source=f"{path}:{SCENARIO_ATTACHMENT}")
    except ScenarioError as error:
        raise RecordingError(str(error)) from None
    return Recording(prefix=metadata[METADATA_NAME]["prefix"], scenario=scenario, messages=messages)


def _messages(reader) -> Iterator[Recorded]:
    for _, channel, message in reader.iter_messages(log_time_order=True):
        yield Recorded(key=channel.topic, encoding=channel.metadata.get("zenoh_encoding", ""), payload=message.data,
                       log_time_ns=message.log_time)
