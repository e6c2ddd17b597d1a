"""`cvxnav replay FILE --stage NAME [--entry module:factory]`: re-run one stage's core on a recording.

The recording (`cvxnav.record`) holds every message of a run in the order the recorder received it.
Replay feeds the stage's inputs (its keys in the wiring table) to a fresh core, the default one or the
factory named by ``--entry`` (the same entry points `cvxnav run --stages` takes), through the same
decode step as the Zenoh shell, and compares what it returns with what the stage published in the run.

The inputs are fed in the order the stage handled them, not the order the recorder received them:
the two differ on a loaded machine (the sim's state for the next scan can reach the recorder before
the planner's input from the scan before, which the planner had long handled). A stage publishes a
status after every input it handles, naming the input's key and stamp (`StageStatus`), so the
statuses give that order; inputs the stage never handled (superseded in its ring) are not fed. A
recording without such statuses (a stage that publishes none) is replayed in receive order.

Outputs are matched by topic, ``scan_seq`` and their order among the outputs for that scan, and
compared field by field (numbers within ``rtol``/``atol``; the header's sequence number included, so
an output missing earlier shows up too). Inputs the recorded stage rejected are rejected again and
counted. A lockstep run is deterministic per scan, so the default core reproduces its recording; a
swapped one shows where it departs.
"""

from __future__ import annotations

import math
from collections import defaultdict
from dataclasses import dataclass, field
from typing import Any

from cvxnav.record import Recorded, Recording
from cvxnav.stages import load_factory
from schemas.messages import DecodeError, Message, StageStatus, decode
from schemas.wiring import STAGES, key, model_for, status_key
from services.contract import StageCore, StageInputError
from services.convert import LocalFrame

RTOL = 1e-6
ATOL = 1e-9
MatchKey = tuple[str, int, int]  # topic, scan_seq, k-th output for that scan


@dataclass
class ReplayReport:
    stage: str
    inputs: int = 0
    rejected: dict[str, int] = field(default_factory=dict)  # reason kind -> count
    compared: int = 0
    differences: list[str] = field(default_factory=list)  # one line each, in output order
    missing: list[MatchKey] = field(default_factory=list)  # recorded, not reproduced
    extra: list[MatchKey] = field(default_factory=list)  # reproduced, not recorded

    @property
    def reproduced(self) -> bool:
        return not (self.differences or self.missing or self.extra)

    def summary(self, *, limit: int = 5) -> str:
        rejected = sum(self.rejected.values())
        head = (f"{self.stage}: {self.inputs} inputs ({rejected} rejected), {self.compared} outputs compared: "
                + ("reproduced" if self.reproduced else
                   f"{len(self.differences)} differ, {len(self.missing)} missing, {len(self.extra)} extra"))
        lines = [head]
        lines += [f"  differs: {d}" for d in self.differences[:limit]]
        lines += [f"  missing: {t} for scan {s} (#{k})" for t, s, k in self.missing[:limit]]
        lines += [f"  extra: {t} for scan {s} (#{k})" for t, s, k in self.extra[:limit]]
        return "\n".join(lines)


def replay_stage(recording: Recording, *, stage: str, entry_point: str | None = None,
                 rtol: float = RTOL, atol: float = ATOL) -> ReplayReport:
    """Feed the stage's recorded inputs to a fresh core; compare its outputs with the recorded ones."""
    spec = STAGES[stage]
    frame = LocalFrame.of(recording.scenario)  # as the shell ran the core (`cvxnav.service.serve`)
    core: StageCore = load_factory(entry_point or spec.factory)(frame.scenario_to_local(recording.scenario))
    inputs = {key(recording.prefix, topic): topic for topic in spec.subscribes}
    outputs = {key(recording.prefix, topic): topic for topic in spec.publishes}
    report = ReplayReport(stage=stage)
    recorded: dict[MatchKey, Message] = {}
    replayed: dict[MatchKey, Message] = {}
    counts_rec: defaultdict[tuple[str, int], int] = defaultdict(int)
    counts_rep: defaultdict[tuple[str, int], int] = defaultdict(int)
    for item in recording.messages:
        if item.key in outputs:
            message = _decoded(outputs[item.key], item)
            if message is not None:
                _index(recorded, counts_rec, outputs[item.key], message)
    for item, message in handling_order(recording, stage=stage, inputs=inputs):
        report.inputs += 1
        for topic, output in _process(core, inputs[item.key], item, message and frame.to_local(message), report):
            _index(replayed, counts_rep, topic, frame.to_world(output))
    for match in sorted(recorded.keys() | replayed.keys(), key=lambda m: (m[1], m[0], m[2])):
        if match not in replayed:
            report.missing.append(match)
        elif match not in recorded:
            report.extra.append(match)
        else:
            report.compared += 1
            where = _first_difference(recorded[match].model_dump(mode="json"),
                                      replayed[match].model_dump(mode="json"), rtol=rtol, atol=atol)
            if where is not None:
                topic, scan_seq, k = match
                report.differences.append(f"{topic} for scan {scan_seq} (#{k}): {where}")
    return report


def handling_order(recording: Recording, *, stage: str,
                   inputs: dict[str, str]) -> list[tuple[Recorded, Message | None]]:
    """The stage's recorded inputs (`inputs`: key → topic), each with its decoded message (None if it
    does not decode), in the order the stage's statuses say it handled them.

    Each status with an input names its key and, if the input decoded, its stamp; it is matched to the
    first recorded input not yet matched with that key and stamp. Without any such status, every
    input, in receive order.
    """
    received = [(item, _decoded(inputs[item.key], item)) for item in recording.messages if item.key in inputs]
    statuses = status_key(recording.prefix, stage)
    handled = []
    for item in recording.messages:
        if item.key == statuses:
            try:
                status = decode(StageStatus, item.payload, encoding=item.encoding or None)
            except DecodeError:
                continue
            if status.input_key in inputs:
                handled.append((status.input_key, status.input_stamp_s))
    if not handled:
        return received
    waiting: defaultdict[tuple[str, float | None], list[tuple[Recorded, Message | None]]] = defaultdict(list)
    for item, message in received:
        waiting[(item.key, message.header.stamp_s if message is not None else None)].append((item, message))
    return [waiting[match].pop(0) for match in handled if waiting[match]]


def _decoded(topic: str, item: Recorded) -> Message | None:
    try:
        return decode(model_for(topic), item.payload, encoding=item.encoding or None)
    except DecodeError:
        return None


def _process(core: StageCore, topic: str, item: Recorded, message: Message | None,
             report: ReplayReport) -> list[tuple[str, Message]]:
    if message is None:
        report.rejected["undecodable"] = report.rejected.get("undecodable", 0) + 1
        return []
    try:
        return core.process(topic=topic, message=message, now_s=item.log_time_ns * 1e-9)
    except StageInputError:
        report.rejected["rejected by the core"] = report.rejected.get("rejected by the core", 0) + 1
    except Exception:  # as the Zenoh shell does: a failing core is reported, the replay goes on
        report.rejected["core failed"] = report.rejected.get("core failed", 0) + 1
    return []


def _index(into: dict[MatchKey, Message], counts: defaultdict[tuple[str, int], int], topic: str,
           message: Message) -> None:
    scan_seq = getattr(message, "scan_seq", message.header.seq)
    k = counts[(topic, scan_seq)]
    counts[(topic, scan_seq)] += 1
    into[(topic, scan_seq, k)] = message


def _first_difference(a: Any, b: Any, *, rtol: float, atol: float, path: str = "") -> str | None:
    """Where two JSON trees first differ (numbers within tolerance), as `path: recorded vs replayed`."""
    if isinstance(a, dict) and isinstance(b, dict):
        for name in sorted(a.keys() | b.keys()):
            sub = f"{path}.{name}" if path else name
            if name not in a or name not in b:
                return f"{sub}: present in only one"
            found = _first_difference(a[name], b[name], rtol=rtol, atol=atol, path=sub)
            if found is not None:
                return found
        return None
    if isinstance(a, list) and isinstance(b, list):
        if len(a) != len(b):
            return f"{path}: {len(a)} items recorded vs {len(b)} replayed"
        for index, (x, y) in enumerate(zip(a, b)):
            found = _first_difference(x, y, rtol=rtol, atol=atol, path=f"{path}[{index}]")
            if found is not None:
                return found
        return None
    numbers = (int, float)
    if isinstance(a, numbers) and isinstance(b, numbers) and not isinstance(a, bool) and not isinstance(b, bool):
        return None if math.isclose(a, b, rel_tol=rtol, abs_tol=atol) else f"{path}: {a!r} recorded vs {b!r} replayed"
    return None if a == b else f"{path}: {a!r} recorded vs {b!r} replayed"
