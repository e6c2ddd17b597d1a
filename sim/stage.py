"""The sim as a ticking core: `SimCore` (``sim.core``) driven by what the shell hears, in one of two modes.

- lockstep (default): at each sensor tick the sim publishes the state and the scan, then waits (up to
  `answer_timeout_s` of wall time) for the pipeline's answer to that scan before integrating the next
  sensor period. The answer is the SmoothPath carrying the scan's `scan_seq` (status ok or no_path), or
  an error status of any stage for that scan: then no path could be verified against what the car now
  knows, and the car brakes rather than drive on a path checked only against older obstacles.
  Sim time then depends only on the scenario and the seed, so two runs give the same trajectory, and a
  run goes as fast as the pipeline answers. Scan and state are dropped, not queued, on a congested
  link (a subscriber that stops reading must not stall the loop), so the sim sends the scan it waits
  for again until the sensing stage reports it.
- realtime: sim time follows the wall clock; scans go out at the sensor rate and the newest path is
  used whenever it arrives, as on a real robot.

The shell hands the core its inputs (paths, ellipses), the pipeline stages' liveliness and every
stage's status as they arrive; the core keeps them and acts on them when it ticks, in the order one
pass of its loop always takes: liveliness and ellipses, then the path, then the statuses. In lockstep
it asks for a tick as soon as anything arrived (or at the answer's deadline, or when the scan is due
again); in realtime once per integration step of the wall clock.

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
- the path check (`services.drive.guard`): every path, and the path being driven whenever newer
  ellipses arrive, is checked against the newest grown ellipses from the ellipsoid stage; a path that
  enters one is not driven. For a received path the sim says why on its status key; a driven path that newer ellipses
  cross is routine (the planner replans on the same ellipses), so it is only logged.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass

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


@dataclass
class _Waiting:
    """Lockstep: the scan sent, and what its answer has come to so far."""

    seq: int
    stamp_s: float
    started_s: float
    deadline_s: float
    resend_s: float
    delivered: bool = False  # the sensing stage reported it: no need to send it again
    held: SmoothPath | None = None  # its answer, waiting for the scan's ellipses
    held_until_s: float = math.inf


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
        self.rejected: dict[float, str] = {}  # scan stamp -> a stage's reason it has no path for it
        self.back_at_s = -math.inf  # clock time a stage last came back
        self._started_s: float | None = None  # the first tick (the world goes out)
        self._running_s: float | None = None  # the loop started (every stage up, or the wait over)
        self._changes: list[tuple[str, bool]] = []  # liveliness changes not yet acted on
        self._ellipsoids: Ellipsoids | None = None  # the newest not yet acted on
        self._path: SmoothPath | None = None  # likewise
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
            if self._path is None or message.scan_seq >= self._path.scan_seq:
                self._path = message
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
        if status.state == "error" and status.stage != SIM.name and status.input_stamp_s is not None:
            self.rejected[status.input_stamp_s] = f"{status.stage}: {status.reason}"
            self._heard = True
        if status.stage in _SCAN_READERS:
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
                if wait.held is not None:
                    out += self._take(wait.held)
                    self._end_scan(now_s, answered=True, stalled=False)
                else:
                    self._end_scan(now_s, answered=False, stalled=False)
                continue
            self._watch(now_s)
            if core.missing:  # no answer will come: brake on the wall clock until the stage is back
                if wait.held is not None:
                    out += self._take(wait.held)
                if self._end_scan(now_s, answered=wait.held is not None, stalled=True):
                    return out
                continue
            if wait.held is not None:
                if core.guard.scan_seq < wait.seq and now_s < wait.held_until_s:
                    self._next_s = min(wait.held_until_s, wait.deadline_s)
                    return out
                out += self._take(wait.held)
                self._end_scan(now_s, answered=True, stalled=False)
                continue
            answer, self._path = self._path, None
            if answer is not None and answer.scan_seq == wait.seq:
                wait.held, wait.held_until_s = answer, min(wait.deadline_s, now_s + ELLIPSOIDS_WAIT_S)
                continue
            reasons = [reason for stamp_s, reason in self.rejected.items() if abs(stamp_s - wait.stamp_s) <= 1e-9]
            if reasons:
                core.no_plan(reasons[0])  # no verified path for what the car now knows: brake
                self._end_scan(now_s, answered=True, stalled=False)
                continue
            resend = wait.seq == 0 or now_s - self.back_at_s < REJOIN_RESEND_S or not wait.delivered
            if resend and now_s >= wait.resend_s:
                out += self._publish(now_s)  # dropped, or routes to fresh (or restarted) peers were not up for it
                wait.resend_s = now_s + self._resend_after_s
            self._next_s = min(wait.deadline_s, wait.resend_s) if resend else wait.deadline_s
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
        answer, self._path = self._path, None
        if answer is not None:
            out += self._take(answer)
        published = {stamp for seq, stamp in self.stamps.items() if seq >= core.resume_seq}
        concerning = [reason for stamp, reason in self.rejected.items() if stamp in published]
        if concerning:
            # A stage could not verify a path for a scan the car sent (since a stage's loss or its last
            # back-out): brake until a verified one arrives. Errors about anything else (a malformed
            # message on a key) leave the plan in force.
            core.no_plan(concerning[0])
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
                    logger.warning("stage %s is down: braking until it is back and a fresh plan arrives", stage)
                core.stage_lost(stage)
            elif stage in core.missing:
                logger.warning("stage %s is back", stage)
                core.stage_back(stage)
                self.back_at_s = now_s
        self._changes.clear()
        newest, self._ellipsoids = self._ellipsoids, None
        if newest is not None:
            dropped = core.know(newest)
            if dropped is not None:  # the planner replans on the same ellipses: routine, not an error
                logger.info("newer obstacles cross the path being driven; braking until the replan: %s", dropped)

    def _take(self, answer: SmoothPath) -> Outputs:
        """Hand the core an answer; if it will not drive on it, refuse it on the sim's status key."""
        reason = self.core.accept(answer)
        if reason is None:
            return []
        return [("smooth_path", Refusal(f"plan {answer.plan_id} for scan {answer.scan_seq} not driven: {reason}"))]

    def _check_answers_a_sent_scan(self, scan_seq: int) -> None:
        if scan_seq not in self.stamps:
            raise StageInputError(f"answers scan {scan_seq}, which the sim never sent")
