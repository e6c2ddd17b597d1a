"""The sim as a ticking core: `SimCore` (``sim.core``) driven by what the shell hears, in one of two modes.

- lockstep (default): at each sensor tick the sim publishes the state and the scan, then waits (up to
  `answer_timeout_s` of wall time) for the pipeline's answer to that scan before integrating the next
  sensor period. The answer is the SmoothPath carrying the scan's `scan_seq` that the car drives on, or
  the pipeline's no_path verdict for it. An error status of a pipeline stage for that scan, or an answer
  the car will not drive on (refused by the guard, or planned for a goal already passed), settles the
  scan only when nothing better for it arrives within `VERDICT_WAIT_S`: then no path could be verified
  against what the car now knows, and the car brakes rather than drive on a path checked only against
  older obstacles. So a forged error or path, sent the moment the scan goes out, never pre-empts the
  pipeline's real answer. Sim time then depends only on the scenario and the seed, so two runs give the
  same trajectory, and a run goes as fast as the pipeline answers. Scan and state are dropped, not
  queued, on a congested link (a subscriber that stops reading must not stall the loop), so the sim
  sends the scan it waits for again until the sensing stage reports it.
- realtime: sim time follows the wall clock; scans go out at the sensor rate and the newest path is
  used whenever it arrives, as on a real robot.

The shell hands the core its inputs (paths, ellipses), the pipeline stages' liveliness and every
stage's status as they arrive (a status counts only on the key of the pipeline stage it names: see
docs/security.md for who can put there); the core keeps them and acts on them when it ticks, in the
order one pass of its loop always takes: liveliness and ellipses, then the paths, then the statuses.
In lockstep it asks for a tick as soon as anything arrived (or at the answer's deadline, when a doubt
settles, or when the scan is due again); in realtime once per integration step of the wall clock,
where a stage's error brakes the car once VERDICT_WAIT_S has passed with no answer for that scan or a
later one.

A smooth_path it cannot use (answering a scan it never sent) is rejected, and reported by the shell
on ``<prefix>/status/sim`` with a one-line reason, like any stage's rejected input; so is a path it
will not drive on (a `Refusal`). Two watchdogs:

- liveliness: the sim follows the pipeline stages' tokens. When one disappears (its process died)
  the car brakes at once, and it drives again only on an answer to a scan sent after the loss, once
  every stage is back. In lockstep the sim then stops waiting for the answer to the current scan
  (none will come) and runs on the wall clock, braking and standing, until the stage is back; so a
  restart costs the car the restart time, never the answer timeout. Scan hits taken while the sensing
  stage was down ride along with the following scans, as many as keep each a valid scan, until a scan
  that carried them is answered, so the restarted stage's memory misses nothing the car saw (its point
  memory dedupes them).
- the path check (`services.drive.guard`): every path, and the path being driven whenever a scan or
  newer ellipses arrive, is checked against the map's bounds, the car's own scan hits and the newest
  grown ellipses from the ellipsoid stage; a path that fails any is not driven. For a received path the
  sim says why on its status key; a driven path that newer obstacles cross is routine (the planner
  replans on them), so it is only logged.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable
from collections import deque
from dataclasses import dataclass, field

from pydantic import BaseModel

from schemas.files import RunFile
from schemas.messages import Ellipsoids, SmoothPath, StageStatus
from schemas.scenario import Scenario
from schemas.wiring import SIM, subscribers_of
from services.contract import Outputs, Refusal, StageInputError
from services.limits import Reach
from sim.core import SimConfig, SimCore
from sim.truth import world_message

logger = logging.getLogger(__name__)

# Lockstep: a scan not answered within this wall time (or twice the sensing stage's newest processing
# time, if longer) is sent again while the sensing stage has not reported it (scan and state are
# dropped, not queued, on a congested link), and while routes to fresh (or restarted) peers may not
# have been up for it: the first scan, and any within this long of a stage's return.
RESEND_S = 1.0
REJOIN_RESEND_S = 5.0
_SCAN_READERS = subscribers_of("scan")
# Lockstep: the ellipses of a scan come straight from their stage, its path two stages later; a path is
# held this long at most for them, so it is checked against the same obstacles in every run.
ELLIPSOIDS_WAIT_S = 1.0
# A stage's error for a scan, or an answer the car will not drive on, counts only if no answer it drives
# on (or the pipeline's no_path verdict) arrives within this long: a forged one sent the moment the scan
# goes out must not pre-empt the real answer, which the pipeline's latency puts well inside it.
VERDICT_WAIT_S = 1.0
ANSWERS_KEPT = 64  # answers to one scan held at most (a flood of forged ones cannot grow the sim)


@dataclass
class _Waiting:
    """Lockstep: the scan sent, and what its answer has come to so far."""

    seq: int
    stamp_s: float
    started_s: float
    deadline_s: float
    resend_s: float
    delivered: bool = False  # the sensing stage reported it: no need to send it again
    held: list[SmoothPath] = field(default_factory=list)  # its answers, waiting for the scan's ellipses
    held_until_s: float = math.inf
    doubt: str | None = None  # why the car would brake if nothing better arrives (None: keep the path)
    doubt_until_s: float = math.inf  # when that settles the scan


class SimStage:
    """The car, its sensor and controller closing the loop with the pipeline; `result()` is run.json."""

    def __init__(self, *, scenario: Scenario, config: SimConfig, stage_wait_s: float = 30.0,
                 latency_clock: Callable[[], float] = time.perf_counter) -> None:
        """`latency_clock` times each scan from the moment it is first sensed to the arrival of the first
        answer to it or to a later scan, or to the run's end if none came (run.json's latency: a stall
        counts in full); everything else runs on the shell's `now_s`."""
        self.core = SimCore(scenario=scenario, config=config)
        self.latency_clock = latency_clock
        self.config = config
        self.reach = Reach.of(scenario)
        self.stage_wait_s = stage_wait_s
        self.done = False
        self.alive: set[str] = set()  # pipeline stages whose token is up
        self.published_at: dict[int, float] = {}  # unanswered scan seq -> latency_clock when first sensed
        self.stamps: dict[int, float] = {}  # scan seq -> its sim stamp
        self.latencies_ms: list[float] = []
        self._ended_at: float | None = None  # latency_clock when the run stopped
        self.rejected: dict[float, tuple[str, float]] = {}  # scan stamp -> (a stage's reason it has no path
        # for it, clock time it was heard)
        self._settled_stamp_s = -math.inf  # realtime: the newest scan an answer was driven on (or no_path) for
        self.back_at_s = -math.inf  # clock time a stage last came back
        self._started_s: float | None = None  # the first tick (the world goes out)
        self._running_s: float | None = None  # the loop started (every stage up, or the wait over)
        self._changes: list[tuple[str, bool]] = []  # liveliness changes not yet acted on
        self._ellipsoids: Ellipsoids | None = None  # the newest not yet acted on
        self._paths: deque[SmoothPath] = deque(maxlen=ANSWERS_KEPT)  # answers not yet acted on, in arrival order
        self._heard = False  # anything arrived since the last tick
        self._waiting: _Waiting | None = None
        self._next_s = 0.0
        self._sleeping = False  # lockstep: standing for a stage that is down; inputs wait for the next tick
        self._resend_after_s = RESEND_S

    @classmethod
    def from_scenario(cls, scenario: Scenario, **options) -> SimStage:
        """`options` are `SimConfig`'s fields (`cvxnav service sim --realtime --seed ...`)."""
        return cls(scenario=scenario, config=SimConfig(**options))

    # -- what the shell hands the core

    def process(self, *, topic: str, message: BaseModel, now_s: float) -> Outputs:
        if isinstance(message, SmoothPath):
            self._check_answers_a_sent_scan(message.scan_seq)
            now = self.latency_clock()
            for seq in [seq for seq in self.published_at if seq <= message.scan_seq]:  # this one and skipped ones
                self.latencies_ms.append((now - self.published_at.pop(seq)) * 1e3)
            self._paths.append(message)
        elif isinstance(message, Ellipsoids):
            # The guard keeps the newest set by scan; a forged one numbered past every real scan would
            # otherwise blind it to the real obstacles for the rest of the run.
            self._check_answers_a_sent_scan(message.scan_seq)
            self.reach.check_ellipses(message.ellipsoids, what="ellipsoids")
            if self._ellipsoids is None or message.scan_seq >= self._ellipsoids.scan_seq:
                self._ellipsoids = message
        else:
            raise StageInputError(f"sim does not handle {topic!r}")
        self._heard = True
        return []

    def stage_alive(self, *, stage: str, alive: bool, now_s: float) -> Outputs:
        (self.alive.add if alive else self.alive.discard)(stage)
        if self._running_s is not None:
            self._changes.append((stage, alive))
            self._heard = True
        return []

    def hear_status(self, *, stage: str, status: StageStatus, now_s: float) -> Outputs:
        """A pipeline stage's error for a scan; a status on another key, or naming another stage, counts for nothing."""
        if (status.state == "error" and stage in SIM.watches and status.stage == stage
                and status.input_stamp_s is not None):
            self.rejected.setdefault(status.input_stamp_s, (f"{stage}: {status.reason}", now_s))
            self._heard = True
        if stage in _SCAN_READERS and status.stage == stage:
            self._resend_after_s = max(RESEND_S, 2e-3 * status.processing_ms)
            wait, stamp_s = self._waiting, status.input_stamp_s
            if wait is not None and stamp_s is not None and abs(stamp_s - wait.stamp_s) <= 1e-9:
                wait.delivered = True
        return []

    def next_tick_s(self, *, now_s: float) -> float | None:
        if self._started_s is None:
            return now_s
        if self._running_s is None:
            return now_s if self.alive >= set(SIM.watches) else self._started_s + self.stage_wait_s
        if self._heard and not self.config.realtime and not self._sleeping:
            return now_s
        return self._next_s

    def tick(self, *, now_s: float) -> Outputs:
        if self._started_s is None:
            self._started_s = now_s
            return [("world", world_message(self.core.scenario))]  # latched: a monitor that joins later has it
        if self._running_s is None:
            self._start(now_s)
            if self.config.realtime:
                return self._publish(now_s) if self.core.scan_due else []
        self._heard = False
        return self._realtime(now_s) if self.config.realtime else self._lockstep(now_s)

    def stop(self, *, now_s: float) -> Outputs:
        self._ended_at = self.latency_clock()
        return [("state", self.core.robot_state())]  # done=True once the run is over

    def result(self) -> RunFile:
        """The run file; a scan never answered counts in the latency until the run stopped."""
        ended = self.latency_clock() if self._ended_at is None else self._ended_at
        unanswered = [(ended - sent) * 1e3 for sent in self.published_at.values()]
        return self.core.result(latencies_ms=self.latencies_ms + unanswered)

    # -- the loops

    def _start(self, now_s: float) -> None:
        missing = set(SIM.watches) - self.alive
        if missing:
            logger.warning("stages not alive after %.0f s: %s", self.stage_wait_s, ", ".join(sorted(missing)))
        for stage in sorted(missing):
            self.core.stage_lost(stage)
        self._running_s = now_s
        self._next_s = now_s + self.config.dt_s

    def _lockstep(self, now_s: float) -> Outputs:
        core, out = self.core, []
        self._sleeping = False
        while True:
            if self._waiting is None:
                if core.outcome is not None:
                    self.done = True
                    return out
                while not core.scan_due and core.outcome is None:  # backing out, with no scan to wait for
                    core.advance()
                if core.outcome is not None:
                    continue
                seq = core.scan_seq
                out += self._publish(now_s)
                self._waiting = _Waiting(seq=seq, stamp_s=core.t_s, started_s=now_s,
                                         deadline_s=now_s + self.config.answer_timeout_s,
                                         resend_s=now_s + self._resend_after_s)
            wait = self._waiting
            if now_s >= wait.deadline_s:
                taken, settled = self._take_held(wait, now_s)
                out += taken
                if not settled and wait.doubt is not None:
                    core.no_plan(wait.doubt)
                self._end_scan(now_s, answered=settled or wait.doubt_until_s < math.inf, stalled=False)
                continue
            self._watch(now_s)
            answers = [answer for answer in self._paths if answer.scan_seq == wait.seq]  # older ones: too late
            self._paths.clear()
            if answers and not wait.held:
                wait.held_until_s = min(wait.deadline_s, now_s + ELLIPSOIDS_WAIT_S)
            wait.held = (wait.held + answers)[-ANSWERS_KEPT:]
            if core.missing:  # no answer will come: brake on the wall clock until the stage is back
                answered = bool(wait.held)
                out += self._take_held(wait, now_s)[0]
                if self._end_scan(now_s, answered=answered, stalled=True):
                    return out
                continue
            if wait.held:
                if core.guard.scan_seq < wait.seq and now_s < wait.held_until_s:
                    self._next_s = min(wait.held_until_s, wait.deadline_s)
                    return out
                taken, settled = self._take_held(wait, now_s)
                out += taken
                if settled:
                    self._end_scan(now_s, answered=True, stalled=False)
                    continue
            reasons = [reason for stamp_s, reason in self.rejected.items() if abs(stamp_s - wait.stamp_s) <= 1e-9]
            if reasons and wait.doubt_until_s == math.inf:
                (reason, heard_s), = reasons[:1]
                wait.doubt, wait.doubt_until_s = reason, heard_s + VERDICT_WAIT_S
            if now_s >= wait.doubt_until_s:
                if wait.doubt is not None:
                    core.no_plan(wait.doubt)  # no verified path for what the car now knows: brake
                self._end_scan(now_s, answered=True, stalled=False)
                continue
            resending = wait.seq == 0 or now_s - self.back_at_s < REJOIN_RESEND_S or not wait.delivered
            if resending and now_s >= wait.resend_s:
                out += self._publish(now_s)  # dropped, or routes to fresh (or restarted) peers were not up for it
                wait.resend_s = now_s + self._resend_after_s
            self._next_s = min(wait.deadline_s, wait.doubt_until_s, wait.resend_s if resending else math.inf)
            return out

    def _end_scan(self, now_s: float, *, answered: bool, stalled: bool) -> bool:
        """Integrate the sensor period after a scan; True when the next scan waits on the wall clock."""
        core, wait = self.core, self._waiting
        assert wait is not None
        self._waiting = None
        self.rejected.clear()
        if not answered and not stalled:
            logger.warning("no answer to scan %d within %.1f s; driving on what the car has", wait.seq,
                           self.config.answer_timeout_s)
        for _ in range(core.steps_per_scan):
            if core.advance() is not None:
                return False
        if stalled:
            self._next_s = wait.started_s + core.steps_per_scan * self.config.dt_s
            self._sleeping = True
            return True
        return False

    def _realtime(self, now_s: float) -> Outputs:
        core = self.core
        core.advance()
        if core.outcome is not None:
            self.done = True
            return []
        out = self._publish(now_s) if core.scan_due else []
        self._watch(now_s)
        answers = sorted(self._paths, key=lambda answer: answer.scan_seq)  # stable: the newest scan's taken last
        self._paths.clear()
        for answer in answers:
            taken, settled = self._settle(answer)
            out += taken
            if settled:
                self._settled_stamp_s = max(self._settled_stamp_s, self.stamps.get(answer.scan_seq, -math.inf))
        published = {stamp for seq, stamp in self.stamps.items() if seq >= core.resume_seq}
        self.rejected = {stamp: heard for stamp, heard in self.rejected.items()
                         if stamp in published and stamp > self._settled_stamp_s}
        due = [reason for reason, heard_s in self.rejected.values() if now_s >= heard_s + VERDICT_WAIT_S]
        if due:
            # A stage could not verify a path for a scan the car sent (since a stage's loss or its last
            # back-out), and no answer for it or a later scan came since: brake until a verified one
            # arrives. Errors about anything else (a malformed message on a key) leave the plan in force.
            core.no_plan(due[0])
            self.rejected.clear()
        self._next_s = self._running_s + (core.step_index + 1) * self.config.dt_s
        return out

    # -- one pass's parts

    def _publish(self, now_s: float) -> Outputs:
        state, scan = self.core.sense()
        self.published_at.setdefault(scan.header.seq, self.latency_clock())  # a re-sent scan waits since the first
        self.stamps[scan.header.seq] = scan.header.stamp_s
        return [("state", state), ("scan", scan)]

    def _watch(self, now_s: float) -> None:
        """Pass liveliness changes and the newest ellipses to the core; log a path the ellipses dropped."""
        core = self.core
        for stage, alive in self._changes:
            if not alive:
                if stage not in core.missing:
                    logger.warning("stage %s is down at t = %.2f s: braking until it is back and a fresh plan arrives",
                                   stage, core.t_s)
                core.stage_lost(stage)
            elif stage in core.missing:
                logger.warning("stage %s is back at t = %.2f s", stage, core.t_s)
                core.stage_back(stage)
                self.back_at_s = now_s
        self._changes.clear()
        newest, self._ellipsoids = self._ellipsoids, None
        if newest is not None:
            dropped = core.know(newest)
            if dropped is not None:  # the planner replans on the same ellipses: routine, not an error
                logger.info("newer obstacles cross the path being driven; braking until the replan: %s", dropped)

    def _take_held(self, wait: _Waiting, now_s: float) -> tuple[Outputs, bool]:
        """Lockstep: hand the core the scan's answers in arrival order until one settles the scan; one
        refused (the car brakes) or planned for a goal already passed (it keeps its path) before that is
        the doubt, which settles the scan only if nothing better arrives within VERDICT_WAIT_S."""
        out: Outputs = []
        held, wait.held = wait.held, []
        for answer in held:
            taken, settled = self._settle(answer)
            out += taken
            if settled:
                return out, True
            if wait.doubt_until_s == math.inf:
                wait.doubt = self.core.no_path_reason if taken else None
                wait.doubt_until_s = now_s + VERDICT_WAIT_S
        return out, False

    def _settle(self, answer: SmoothPath) -> tuple[Outputs, bool]:
        """Hand the core an answer; if it will not drive on it, refuse it on the sim's status key. Whether the
        answer settles its scan: the car drives on it (the core took a new path), or it is no_path."""
        before = self.core.path
        reason = self.core.accept(answer)
        if reason is not None:
            return [("smooth_path", Refusal(f"plan {answer.plan_id} for scan {answer.scan_seq} not driven: "
                                            f"{reason}"))], False
        return [], answer.status == "no_path" or self.core.path is not before

    def _check_answers_a_sent_scan(self, scan_seq: int) -> None:
        if scan_seq not in self.stamps:
            raise StageInputError(f"answers scan {scan_seq}, which the sim never sent")
