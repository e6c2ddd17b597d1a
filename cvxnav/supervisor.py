"""The supervisor of `cvxnav run`: every stage its own OS process, peered over Zenoh on loopback.

It it picks free loopback ports, starts each pipeline stage as
`python -m cvxnav service NAME --config FILE` (or the external command a `stages` config names), every
process listening on its own port and connecting to all the others' with multicast scouting off (a
full mesh on 127.0.0.1: no router, no stray sessions from the LAN), waits until every stage's
liveliness token is up, then starts the sim. It follows the sim's state and paths for the progress
bar, and when the sim exits (it writes run.json itself) prints the summary and stops every child:
SIGTERM, then SIGKILL after a grace period.

Each child's Zenoh settings are a config file the supervisor writes into the run's log directory.
`connect` endpoints are added to every process of the run (a router there relays the whole run to
`cvxnav status` or a monitor elsewhere), `listen` endpoints to the supervisor's own session (a client
connecting there hears the whole mesh). A run that connects somewhere is refused before it starts when a
pipeline with its robot id is already up there (its liveliness tokens are visible): two would cross-talk.

With `tls_dir` the run is the secure deployment on one machine: the supervisor's session is the
router of `cvxnav certs` (mutual TLS, access control by certificate name) on a free loopback port
plus the `listen` endpoints, and every stage is a TLS client of it presenting its own certificate
from `tls_dir`. Nothing listens in plain TCP; a session without a certificate of that CA gets no
link, one whose certificate names no stage gets a link that carries nothing.

A pipeline stage (or the monitor) that exits during the run is restarted on the same port, after a
backoff that doubles with each recent restart (`RunOptions.restart_backoff_s`, capped at
`restart_backoff_max_s`); more than `max_restarts` restarts of one stage within `restart_window_s`
end the run (exit 4) with a line naming the stage and its log tail. The new process declares its
liveliness token when it is up, and the sim, which brakes while a stage's token is gone, drives on
once the restarted pipeline answers. Stages that keep state no later input restores (the sensing
stage's point memory, the planner's plan) checkpoint it under `--state-dir` (`services.shell.checkpoint`),
one directory per stage, which outlives the process. The sim is not restarted: its exit ends the run.
With `RunOptions.warm_spares` (`cvxnav run --warm-spares`, always in a robot run) the supervisor keeps,
once the pipeline is up, a spare of each pipeline stage (`cvxnav service NAME --standby`: imported,
its core built, off the network), started one at a time; a restart hands the stage to its spare (a
line on its standard input: it restores the checkpoint and joins) instead of starting an interpreter,
and a new spare is started behind it.

A stage is swapped by naming, in a JSON `stages` file, either a Python entry point
`"module:factory"` (called with the scenario, returning a StageCore), or
`{"command": ["prog", "arg", ...]}`: any process that speaks the stage's keys. Its arguments may use
`{config}` (its Zenoh config file, the only complete one under TLS), `{listen}`, `{connect}`
(comma-separated endpoints; under TLS `{listen}` is empty), `{prefix}`, `{scenario}` (a file path) and
`{state_dir}` (the stage's own directory for state that must survive a restart).

The supervisor's own session is a peer of every stage (under TLS, their router).
`--record-messages FILE` has that session record every message under the prefix (`cvxnav.record`).

Hangs are faults too. Every process the supervisor starts is told of a watchdog as systemd tells a
service (``NOTIFY_SOCKET``, ``WATCHDOG_USEC``: `services.shell.watchdog`), and the run's own stages
send keep-alives while their worker makes progress. A process whose keep-alives stop for longer than
`RunOptions.watchdog_s` (stopped by SIGSTOP, frozen, or stuck on one input past its stall limit) is
killed with SIGKILL, and then restarted like a crashed one, as is a stage that sent none within
`RunOptions.startup_timeout_s` of its start; a swapped command that never sends one (it does not speak
the protocol) is watched for its exit only. A hung sim ends the run.

Every child gets SIGTERM when the supervisor dies, however it dies (Linux ``PR_SET_PDEATHSIG``): no
stage outlives a `cvxnav run` killed with SIGKILL, and the sim, stopping, writes its run file as
`interrupted`. SIGINT and SIGTERM of the supervisor stop the run the same way.

The run's directory of stage logs, Zenoh configs and checkpoints is removed when every goal is
reached or the run was interrupted, unless `RunOptions.keep_logs`; a run that failed keeps it, and
its path is logged.

`cvxnav run --ros2` (`run_robot`) drives a ROS 2 robot instead: the bridge (`cvxnav service ros2`, the
wiring table's ROS2) takes the sim's place, started once the pipeline is alive and restarted like a
stage if it exits, and the run goes on until SIGINT/SIGTERM (`stop_event`): then every process is
stopped and the exit code is 0. Every process also connects to the robot's rmw_zenohd (`connect`).
"""

from __future__ import annotations

import ctypes
import json
import logging
import os
import random
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import zenoh

from cvxnav.certs import client_config, missing_files, pipeline_names, router_config, write_deployment
from cvxnav.exits import EXIT_BY_STATUS, EXIT_INTERRUPTED
from cvxnav.record import MessageRecorder
from cvxnav.stages import RunError, StageChoice, load_stages
from schemas.files import OutputFileError, RunFile
from schemas.messages import DecodeError, RobotState, SmoothPath, decode
from schemas.scenario import Scenario
from schemas.wiring import DEFAULT_ROBOT_ID, MONITOR, PIPELINE, ROS2, SIM, STAGES, default_prefix, key
from services.ros2.bridge import BridgeConfig
from services.shell.peers import alive_stages, wait_for_stages
from services.shell.watchdog import STALL_LIMIT_S, NotifySocket, notify_socket_in, watchdog_supported
from services.shell.zenoh_config import config_from_doc, endpoints_config, zenoh_reason

logger = logging.getLogger(__name__)
_PR_SET_PDEATHSIG = 1  # <linux/prctl.h>
_SPARE_STAGGER_S = 1.0  # between the starts of two warm spares: each spends about a second of CPU
_PORTS_FROM = 20_000  # free_ports draws from here to the ephemeral range: above the well-known services


class PipelineError(Exception):
    """The pipeline itself failed (a stage died or never came up): one line, exit code 4."""


def _ephemeral_low() -> int:
    """The first port of the kernel's ephemeral range (Linux's default where it cannot be read)."""
    try:
        return int(Path("/proc/sys/net/ipv4/ip_local_port_range").read_text().split()[0])
    except (OSError, ValueError, IndexError):
        return 32768


def free_ports(count: int) -> list[int]:
    """Distinct free TCP ports on 127.0.0.1 for the stages to listen on, held open together so none is
    handed out twice, drawn at random below the kernel's ephemeral range.

    A port the kernel hands out (bind to port 0) is an ephemeral one, and between this check and the
    stage binding it any outgoing connection on the machine may be given it (a suite's other worker
    took one so: the stage could not listen). Below the range only an explicit bind takes a port. Where
    none is free there, the kernel's choice is the fallback.
    """
    pool = range(_PORTS_FROM, max(_PORTS_FROM + 1, _ephemeral_low()))
    candidates = random.SystemRandom().sample(pool, k=min(len(pool), 4 * count + 64))
    probes: list[socket.socket] = []
    try:
        for port in candidates:
            if len(probes) == count:
                break
            probe = socket.socket()
            try:
                probe.bind(("127.0.0.1", port))
            except OSError:
                probe.close()
                continue
            probes.append(probe)
        while len(probes) < count:
            probes.append(socket.socket())
            probes[-1].bind(("127.0.0.1", 0))
        return [probe.getsockname()[1] for probe in probes]
    finally:
        for probe in probes:
            probe.close()


@dataclass
class Child:
    name: str
    process: subprocess.Popen
    log_path: Path
    last_beat_s: float | None = None  # monotonic time of its newest keep-alive; None: none yet
    # When its first keep-alive is due (monotonic s); None: a swapped command, watched for its exit only.
    first_beat_by_s: float | None = None
    hung: str | None = None  # why the watchdog killed it

    def log_tail(self, *, lines: int = 5) -> str:
        try:
            text = self.log_path.read_text(encoding="utf-8", errors="replace").strip().splitlines()
        except OSError:
            return ""
        return " | ".join(text[-lines:])


@dataclass(frozen=True)
class RobotOptions:
    """`cvxnav run --ros2`: the robot's ROS graph, which the bridge joins in the sim's place."""

    domain_id: int = 0
    namespace: str = "/"


@dataclass
class RunOptions:
    scenario_path: Path | None  # None: the bundled paper scenario
    out_path: Path
    realtime: bool = False
    time_limit_s: float | None = None  # sim time
    stages: dict[str, StageChoice] = field(default_factory=lambda: load_stages(None))
    robot_id: str = DEFAULT_ROBOT_ID
    noise_std_m: float = 0.0
    seed: int = 0
    startup_timeout_s: float = 60.0
    stop_grace_s: float = 5.0
    show_progress: bool = True
    monitor_args: tuple[str, ...] | None = None  # start the rerun monitor with these service options
    connect: tuple[str, ...] = ()  # every process of the run also connects to these Zenoh endpoints
    listen: tuple[str, ...] = ()  # the supervisor's session (under TLS: the run's router) also listens here
    tls_dir: Path | None = None  # mutual TLS + access control with the certificates of `cvxnav certs` here
    record_messages: Path | None = None  # MCAP file of every message under the prefix
    robot: RobotOptions | None = None  # a ROS 2 robot's graph: the bridge runs in the sim's place
    planner_budget_ms: float | None = None  # a live run's planner budget per scan (None: its default share)
    # A stage that exits is restarted after restart_backoff_s, doubled for each of its restarts within
    # restart_window_s, at most restart_backoff_max_s; more than max_restarts of them end the run.
    restart_backoff_s: float = 0.5
    restart_backoff_max_s: float = 5.0
    max_restarts: int = 4
    restart_window_s: float = 60.0
    # A process whose keep-alives stop for this long is killed (then restarted); Nav2's bond allows 4 s.
    watchdog_s: float = 3.0
    stall_limit_s: float = STALL_LIMIT_S  # a stage stops its keep-alives when one input takes longer
    keep_logs: bool = False  # keep the run's directory of logs, configs and checkpoints whatever the outcome
    warm_spares: bool = False  # a standby process per pipeline stage, ready to replace it (see the module's notes)

    @property
    def source(self) -> str:
        """The process that closes the loop: the sim, or the bridge to a ROS 2 robot."""
        return SIM.name if self.robot is None else ROS2.name

    @property
    def process_names(self) -> list[str]:
        """Every process the run starts, in start order."""
        return [*PIPELINE, *([MONITOR.name] if self.monitor_args is not None else []), self.source]


@dataclass(frozen=True)
class Restart:
    """One restart: which stage exited, with what code, and when it was found dead (monotonic s)."""

    stage: str
    exit_code: int
    found_s: float


@dataclass
class _Progress:
    sim_time_s: float = 0.0
    goals_reached: int = 0
    plan_ids: set[int] = field(default_factory=set)

    @property
    def replans(self) -> int:
        return max(0, len(self.plan_ids) - 1)


def prepare_tls(options: RunOptions) -> bool:
    """Check `options.tls_dir` has every certificate the run needs; make a deployment there if it does not exist.

    True when the certificates were made now. Raises RunError naming what is missing, and for
    `connect` endpoints (the run's stages are clients of its own router only).
    """
    if options.tls_dir is None:
        return False
    if options.connect:
        raise RunError("--connect cannot be combined with --tls: under TLS the stages are clients of the run's own "
                       "router; let others join it with --listen tls/HOST:PORT")
    created = not options.tls_dir.exists()
    if created:
        write_deployment(out_dir=options.tls_dir)
    missing = missing_files(cert_dir=options.tls_dir, names=options.process_names)
    if missing:
        raise RunError(f"{options.tls_dir}: missing {', '.join(path.name for path in missing)} "
                       f"(make them with: cvxnav certs --out {options.tls_dir})")
    return created


# Asked twice, this far apart, whether the robot id is up where the run connects: a peer may still be
# linking to the others' processes when the first answer comes.
IN_USE_ASKS_S = 0.3


def refuse_a_robot_id_in_use(options: RunOptions) -> None:
    """RunError if a pipeline under this robot id is already up at the `connect` endpoints (its tokens are
    visible there): a second one would read and answer the first one's keys."""
    if not options.connect:
        return  # the run's own mesh on fresh loopback ports: no one else is in it yet
    prefix = default_prefix(robot_id=options.robot_id)
    try:
        opened = zenoh.open(config_from_doc(endpoints_config(connect=list(options.connect))))
    except zenoh.ZError as error:
        raise RunError(f"cannot open a Zenoh session to {', '.join(options.connect)}: {zenoh_reason(error)}") from None
    with opened as session:
        alive = alive_stages(session, prefix=prefix)
        if not alive:
            time.sleep(IN_USE_ASKS_S)
            alive = alive_stages(session, prefix=prefix)
    if alive:
        raise RunError(f"robot id {options.robot_id!r} is already up at {', '.join(options.connect)} (alive under "
                       f"{prefix}: {', '.join(sorted(alive))}): a second pipeline would cross-talk with it; "
                       f"choose another --robot-id")


def plain_layout(options: RunOptions) -> tuple[dict, dict[str, dict]]:
    """The supervisor's and each process's Zenoh config: a full mesh on free loopback ports."""
    names = options.process_names
    ports = free_ports(len(names) + 1)
    endpoints = {name: f"tcp/127.0.0.1:{port}" for name, port in zip(names, ports)}
    own = f"tcp/127.0.0.1:{ports[-1]}"
    session = endpoints_config(listen=[own, *options.listen], connect=[*endpoints.values(), *options.connect])
    children = {name: endpoints_config(listen=[endpoint], connect=[*(ep for other, ep in endpoints.items()
                                                                       if other != name), own, *options.connect])
                for name, endpoint in endpoints.items()}
    return session, children


def tls_layout(options: RunOptions) -> tuple[dict, dict[str, dict]]:
    """The supervisor as the TLS + access-control router, each process a client with its own certificate."""
    assert options.tls_dir is not None
    cert_dir = options.tls_dir.resolve()
    (port,) = free_ports(1)
    router = f"tls/127.0.0.1:{port}"  # 127.0.0.1 is in the router certificate's subjectAltName
    session = router_config(cert_dir=cert_dir, listen=[router, *options.listen], names=pipeline_names())
    children = {name: client_config(cert_dir=cert_dir, name=name, connect=[router]) for name in options.process_names}
    return session, children


class Supervisor:
    """Starts, watches, restarts and stops the stage processes of one run."""

    def __init__(self, *, options: RunOptions, scenario: Scenario) -> None:
        self.options = options
        self.scenario = scenario
        self.prefix = default_prefix(robot_id=options.robot_id)
        self.session_doc, self.child_docs = (tls_layout if options.tls_dir else plain_layout)(options)
        self.children: dict[str, Child] = {}  # the newest process of each stage
        self.restarts: list[Restart] = []
        self._restart_due: dict[str, float] = {}  # stage -> monotonic time its restart is due
        self.spares: dict[str, subprocess.Popen] = {}  # stage -> its standby process
        self._sparing = False  # set by keep_spares once the pipeline is up
        self._unspared: set[str] = set()  # stages whose spare died in standby
        self._next_spare_s = 0.0
        self.log_dir = Path(tempfile.mkdtemp(prefix="cvxnav-run-"))
        self.state_dir = self.log_dir / "state"
        self.notify = self._notify_socket()
        self._exit_with_me = _exit_with_parent()

    def _notify_socket(self) -> NotifySocket | None:
        """Where the children send their keep-alives; None (no hang is seen) where it cannot be made."""
        if not watchdog_supported():
            return None
        try:
            return notify_socket_in(self.log_dir)
        except OSError as error:
            logger.warning("no watchdog for this run's stages (a hang will not be seen): %s", error)
            return None

    def _config_file(self, name: str) -> Path:
        path = self.log_dir / f"{name}.json5"
        path.write_text(json.dumps(self.child_docs[name], indent=1) + "\n", encoding="utf-8")
        return path

    def _command(self, name: str) -> list[str]:
        doc, config = self.child_docs[name], str(self._config_file(name))
        scenario_arg = str(self.options.scenario_path) if self.options.scenario_path else ""
        state_dir = str(self.state_dir / name)
        choice = self.options.stages.get(name)
        if choice is not None and choice.command is not None:
            fields = dict(config=config, listen=",".join(doc.get("listen", {}).get("endpoints", [])),
                          connect=",".join(doc["connect"]["endpoints"]), prefix=self.prefix, scenario=scenario_arg,
                          state_dir=state_dir)
            return [arg.format(**fields) for arg in choice.command]
        cmd = [sys.executable, "-m", "cvxnav", "service", name, "--config", config, "--robot-id", self.options.robot_id,
               "--stall-limit-s", repr(self.options.stall_limit_s)]
        if self.options.scenario_path:
            cmd += ["--scenario", scenario_arg]
        if name in PIPELINE:
            cmd += ["--state-dir", state_dir]
        swapped = choice is not None and choice.entry_point not in (None, STAGES[name].factory)
        if swapped:
            cmd += ["--entry", choice.entry_point]
        if name == "planner" and not swapped and (self.options.realtime or self.options.robot is not None):
            cmd += ["--deadline"]  # the world does not wait for the answer: each scan's within its period
            if self.options.planner_budget_ms is not None:
                cmd += ["--budget-ms", repr(self.options.planner_budget_ms)]
        if name == MONITOR.name:
            cmd += self._monitor_args()
        if name == SIM.name:
            cmd += ["--out", str(self.options.out_path), "--seed", str(self.options.seed),
                    "--noise-std-m", repr(self.options.noise_std_m)]
            if self.options.realtime:
                cmd += ["--realtime"]
            if self.options.time_limit_s is not None:
                cmd += ["--time-limit-s", repr(self.options.time_limit_s)]
        if name == ROS2.name:
            robot = self.options.robot
            cmd += ["--domain-id", str(robot.domain_id), "--namespace", robot.namespace]
        return cmd

    def _monitor_args(self) -> list[str]:
        """The monitor's options; a restarted monitor records to run.1.rrd, run.2.rrd, … (no overwrite)."""
        args = list(self.options.monitor_args or ())
        count = self.restart_count(MONITOR.name)
        if count and "--record" in args:
            where = args.index("--record") + 1
            record = Path(args[where])
            args[where] = str(record.with_name(f"{record.stem}.{count}{record.suffix}"))
            logger.warning("the monitor's recording continues in %s", args[where])
        return args

    def restart_count(self, name: str) -> int:
        return sum(1 for restart in self.restarts if restart.stage == name)

    def start(self, name: str) -> Child:
        count = self.restart_count(name)
        log_path = self.log_dir / (f"{name}.log" if count == 0 else f"{name}.{count}.log")
        process = self._called_up(name)
        if process is None:
            process = self._spawn(self._command(name), log_path=log_path)
        choice = self.options.stages.get(name)
        speaks_watchdog = self.notify is not None and (choice is None or choice.command is None)
        child = Child(name=name, process=process, log_path=log_path,
                      first_beat_by_s=time.monotonic() + self.options.startup_timeout_s if speaks_watchdog else None)
        self.children[name] = child
        return child

    def _spawn(self, command: list[str], *, log_path: Path, standby: bool = False) -> subprocess.Popen:
        env = dict(os.environ)
        if self.notify is not None:
            env.update(NOTIFY_SOCKET=self.notify.address, WATCHDOG_USEC=str(round(self.options.watchdog_s * 1e6)))
        with open(log_path, "wb") as log:
            return subprocess.Popen(command, stdin=subprocess.PIPE if standby else subprocess.DEVNULL, stdout=log,
                                    stderr=subprocess.STDOUT, start_new_session=True, env=env,
                                    preexec_fn=self._exit_with_me)

    def _called_up(self, name: str) -> subprocess.Popen | None:
        """`name`'s spare, told to join the network; None when it has none (or it has died)."""
        spare = self.spares.pop(name, None)
        if spare is None:
            return None
        try:
            spare.stdin.write(b"go\n")
            spare.stdin.close()
        except OSError:  # it died: its pipe is broken
            spare.wait()
            return None
        return spare

    def keep_spares(self) -> None:
        """With `warm_spares`, start a spare for one pipeline stage that has none (one a second at most,
        so they do not crowd the running stages' CPU). Called once the pipeline is up, then by `supervise`."""
        self._sparing = self.options.warm_spares
        now = time.monotonic()
        if not self._sparing or now < self._next_spare_s:
            return
        for name in PIPELINE:
            spare = self.spares.get(name)
            choice = self.options.stages.get(name)
            if spare is not None and spare.poll() is not None:  # its core failed to build: restarts start afresh
                logger.warning("stage %s: its warm spare exited with code %d; no more spares for it", name,
                               spare.returncode)
                self._unspared.add(name)
                del self.spares[name]
            if (spare is not None or name in self._unspared or name not in self.children
                    or (choice is not None and choice.command is not None)):
                continue
            # It will serve the next restart: its log is that restart's.
            log_path = self.log_dir / f"{name}.{self.restart_count(name) + 1}.log"
            self.spares[name] = self._spawn([*self._command(name), "--standby"], log_path=log_path, standby=True)
            self._next_spare_s = now + _SPARE_STAGGER_S
            return

    def watch(self) -> None:
        """Take the keep-alives that arrived; SIGKILL every child whose keep-alives stopped.

        A `cvxnav service` child must send its first keep-alive within `startup_timeout_s` of its start
        (one stopped before its loop ran never sends any); a swapped command is watched once it sends
        one. ``WATCHDOG=trigger`` (a stage stuck on one input) acts at once. A stopped process dies of
        SIGKILL too, so nothing stopped is left behind.
        """
        if self.notify is None:
            return
        now = time.monotonic()
        by_pid = {child.process.pid: child for child in self.children.values()}
        for pid, text in self.notify.receive():
            child = by_pid.get(pid)
            if child is None:
                continue
            states = text.split("\n")
            if "WATCHDOG=1" in states:
                child.last_beat_s = now
            if "WATCHDOG=trigger" in states:
                child.hung = "stuck on one input past its stall limit"
        for child in self.children.values():
            if child.process.poll() is not None:
                continue
            if child.hung is None and child.last_beat_s is not None:
                silent_s = now - child.last_beat_s
                if silent_s > self.options.watchdog_s:
                    child.hung = f"no keep-alive for {silent_s:.1f} s"
            elif child.hung is None and child.first_beat_by_s is not None and now > child.first_beat_by_s:
                child.hung = f"no keep-alive within {self.options.startup_timeout_s:.0f} s of its start"
            if child.hung is not None:
                logger.warning("stage %s hung (%s): killing pid %d", child.name, child.hung, child.process.pid)
                child.process.kill()
                child.process.wait()

    def supervise(self) -> None:
        """Kill the hung stages; restart every stage but the sim that has exited, once its backoff is over.

        Raises PipelineError when a stage has exited more than `max_restarts` times within
        `restart_window_s`: it keeps crashing, and restarting it again would not help.
        """
        self.watch()
        now = time.monotonic()
        for name, child in list(self.children.items()):
            if name == SIM.name or child.process.poll() is None:
                continue
            due = self._restart_due.get(name)
            if due is None:
                due = self._restart_due[name] = now + self._backoff(child, now=now)
            if now >= due:
                del self._restart_due[name]
                spare = self.spares.get(name)
                restarted = self.start(name)
                logger.warning("stage %s restarted (pid %d, restart %d%s)", name, restarted.process.pid,
                               self.restart_count(name), ", its warm spare" if restarted.process is spare else "")
        if self._sparing:
            self.keep_spares()

    def _backoff(self, child: Child, *, now: float) -> float:
        """Record the exit of `child`; the delay before its restart, or PipelineError if it keeps crashing."""
        options = self.options
        code = child.process.returncode
        recent = [r for r in self.restarts if r.stage == child.name and now - r.found_s <= options.restart_window_s]
        if len(recent) >= options.max_restarts:
            raise PipelineError(f"stage {child.name} keeps crashing ({len(recent) + 1} exits within "
                                f"{options.restart_window_s:.0f} s, last code {code}): {child.log_tail(lines=3)}")
        self.restarts.append(Restart(stage=child.name, exit_code=code, found_s=now))
        delay = min(options.restart_backoff_max_s, options.restart_backoff_s * 2.0 ** len(recent))
        if not recent and child.name in self.spares:
            delay = 0.0  # the first exit in the window: its spare takes over at once
        how = f"hung ({child.hung}) and was killed" if child.hung else f"exited with code {code}"
        logger.warning("stage %s %s; restarting it in %.1f s: %s", child.name, how, delay, child.log_tail(lines=1))
        return delay

    def stop(self) -> None:
        """SIGTERM every child, SIGKILL those still running after the grace period."""
        children = list(self.children.values())
        for spare in self.spares.values():
            if spare.stdin is not None and not spare.stdin.closed:
                spare.stdin.close()  # end of input: a spare leaves at once
        killed = stop_processes([child.process for child in children] + list(self.spares.values()),
                                grace_s=self.options.stop_grace_s)
        for child in children:
            if child.process in killed:
                logger.warning("stage %s ignored SIGTERM; it was killed", child.name)
        if self.notify is not None:
            self.notify.close()


def _exit_with_parent() -> Callable[[], None] | None:
    """A `preexec_fn` that has the child sent SIGTERM when this process dies, even by SIGKILL (Linux).

    ``prctl(PR_SET_PDEATHSIG)`` is kept across exec, so it holds for any command; a child whose parent
    died before the call goes at once. None where there is no prctl: children are then stopped only
    by a supervisor that lives to stop them.
    """
    if not sys.platform.startswith("linux"):
        return None
    prctl = ctypes.CDLL(None, use_errno=True).prctl  # looked up here: the child only calls it
    parent_pid = os.getpid()

    def in_child() -> None:
        prctl(_PR_SET_PDEATHSIG, signal.SIGTERM)
        if os.getppid() != parent_pid:
            os._exit(1)

    return in_child


def stop_processes(processes: list[subprocess.Popen], *, grace_s: float) -> list[subprocess.Popen]:
    """SIGTERM every running process, SIGKILL those still running after `grace_s`; the killed ones.

    A stopped (SIGSTOP) process is continued after the SIGTERM, so it can act on it.
    """
    for process in processes:
        if process.poll() is None:
            process.send_signal(signal.SIGTERM)
            process.send_signal(signal.SIGCONT)
    deadline = time.monotonic() + grace_s
    killed = []
    for process in processes:
        try:
            process.wait(timeout=max(0.0, deadline - time.monotonic()))
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait()
            killed.append(process)
    return killed


def _wait_alive(session: zenoh.Session, supervisor: Supervisor, *, timeout_s: float,
                stop_event: threading.Event | None = None) -> None:
    deadline = time.monotonic() + timeout_s
    missing = set(supervisor.children)  # the pipeline, and the monitor if asked
    while missing and time.monotonic() < deadline and not (stop_event and stop_event.is_set()):
        supervisor.supervise()
        missing = wait_for_stages(session, prefix=supervisor.prefix, stages=tuple(missing), timeout_s=1.0,
                                  stop_event=stop_event)
    if missing and not (stop_event and stop_event.is_set()):
        raise PipelineError(f"stages not alive after {timeout_s:.0f} s: {', '.join(sorted(missing))}")


def run_pipeline(*, options: RunOptions, scenario: Scenario) -> tuple[int, RunFile | None, int]:
    """Run every stage as a process until the sim ends; the exit code, the run file and the restarts.

    SIGINT (KeyboardInterrupt; `cvxnav run` turns SIGTERM into one) stops the run: the sim, stopped,
    writes its run file as `interrupted`. Interrupted before the sim started, there is no run file.
    Raises RunError, before starting anything, if the robot id is already up where the run connects.
    """
    from sim.core import default_time_limit_s

    refuse_a_robot_id_in_use(options)
    supervisor = Supervisor(options=options, scenario=scenario)
    progress = _Progress()
    time_limit_s = options.time_limit_s or default_time_limit_s(scenario)
    recorder = (MessageRecorder(path=options.record_messages, prefix=supervisor.prefix, scenario=scenario)
                if options.record_messages is not None else None)
    sim_started = interrupted = False
    code: int | None = None
    try:
        try:
            opened = zenoh.open(config_from_doc(supervisor.session_doc))
        except zenoh.ZError as error:  # --listen on an address no interface has, a port in use
            shutil.rmtree(supervisor.log_dir, ignore_errors=True)  # nothing started: nothing to look into
            raise RunError(f"cannot open the run's Zenoh session: {zenoh_reason(error)}") from None
        with opened as session:
            if recorder is not None:
                recorder.subscribe(session)  # before any stage starts: the recording misses nothing

            def on_state(sample: zenoh.Sample) -> None:
                try:
                    state = decode(RobotState, sample.payload.to_bytes())
                except DecodeError:
                    return
                progress.sim_time_s, progress.goals_reached = state.header.stamp_s, state.goals_reached

            def on_path(sample: zenoh.Sample) -> None:
                try:
                    progress.plan_ids.add(decode(SmoothPath, sample.payload.to_bytes()).plan_id)
                except DecodeError:
                    return

            state_sub = session.declare_subscriber(key(supervisor.prefix, "state"), on_state)
            path_sub = session.declare_subscriber(key(supervisor.prefix, "smooth_path"), on_path)
            for name in PIPELINE:
                supervisor.start(name)
            if options.monitor_args is not None:
                supervisor.start(MONITOR.name)  # before the sim, so it sees the world and the first scan
            _wait_alive(session, supervisor, timeout_s=options.startup_timeout_s)
            supervisor.keep_spares()
            options.out_path.unlink(missing_ok=True)  # what is there after the run is this run's, or nothing
            sim = supervisor.start(SIM.name)
            sim_started = True
            wall_limit_s = time_limit_s * (1.5 if options.realtime else 1.0) + options.startup_timeout_s
            code = _follow(sim=sim, supervisor=supervisor, progress=progress, time_limit_s=time_limit_s,
                           wall_limit_s=wall_limit_s, goals=len(scenario.goals), show=options.show_progress)
            state_sub.undeclare()
            path_sub.undeclare()
    except KeyboardInterrupt:
        interrupted = True
        logger.warning("interrupted: stopping the run")
    except PipelineError:
        logger.warning("stage logs kept in %s", supervisor.log_dir)
        raise
    finally:
        supervisor.stop()
        if recorder is not None:
            recorder.close()
    restarts = len(supervisor.restarts)
    if interrupted and not sim_started:
        _clean_up(supervisor, keep=options.keep_logs)
        return EXIT_INTERRUPTED, None, restarts
    if code is None and not interrupted:
        return EXIT_BY_STATUS["timeout"], None, restarts
    try:
        result = RunFile.read(options.out_path)
    except OutputFileError as error:
        if interrupted:  # the sim did not stop in time to write it
            _clean_up(supervisor, keep=options.keep_logs)
            return EXIT_INTERRUPTED, None, restarts
        raise PipelineError(f"the sim wrote no usable run file: {error}") from None
    _clean_up(supervisor, keep=options.keep_logs or result.status not in ("reached", "interrupted"))
    return EXIT_BY_STATUS[result.status], result, restarts


def _clean_up(supervisor: Supervisor, *, keep: bool) -> None:
    """Remove the run's directory of logs, configs and checkpoints, or say where it was kept."""
    if keep:
        logger.warning("stage logs kept in %s", supervisor.log_dir)
    else:
        shutil.rmtree(supervisor.log_dir, ignore_errors=True)


def _follow(*, sim: Child, supervisor: Supervisor, progress: _Progress, time_limit_s: float,
            wall_limit_s: float, goals: int, show: bool) -> int | None:
    """Show progress and restart crashed stages until the sim exits; None when it ran past the wall-clock guard."""
    from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

    columns = (TextColumn("[bold]cvxnav run"), BarColumn(),
               TextColumn("sim {task.fields[sim_s]:6.1f} s  goals {task.fields[goals]}  replans "
                          "{task.fields[replans]}  restarts {task.fields[restarts]}"),
               TimeElapsedColumn())
    deadline = time.monotonic() + wall_limit_s
    with Progress(*columns, disable=not show) as bar:
        task = bar.add_task("run", total=time_limit_s, sim_s=0.0, goals=f"0/{goals}", replans=0, restarts=0)

        def update() -> None:
            bar.update(task, completed=progress.sim_time_s, sim_s=progress.sim_time_s,
                       goals=f"{progress.goals_reached}/{goals}", replans=progress.replans,
                       restarts=len(supervisor.restarts))

        while sim.process.poll() is None:
            supervisor.supervise()
            if time.monotonic() > deadline:
                sim.process.kill()
                sim.process.wait()
                return None
            update()
            time.sleep(0.1)
        update()
    if sim.hung is not None:
        raise PipelineError(f"the sim hung ({sim.hung}) and was killed: {sim.log_tail(lines=2)}")
    return sim.process.returncode


@dataclass(frozen=True)
class RobotRun:
    """What `run_robot` saw: the paths it published on /plan, its restarts, how long it ran."""

    plans: int
    restarts: int
    wall_s: float


def run_robot(*, options: RunOptions, scenario: Scenario, stop_event: threading.Event) -> RobotRun:
    """Every stage as a process and the ROS 2 bridge in the sim's place, until `stop_event`; then all stopped.

    Stages (the bridge too) that exit or hang are restarted as in a sim run; PipelineError when one
    keeps crashing or the pipeline never comes up. The stage logs are kept when any stage was
    restarted, or when `options.keep_logs`.
    """
    assert options.robot is not None
    supervisor = Supervisor(options=options, scenario=scenario)
    bridge = BridgeConfig.from_scenario(scenario, domain_id=options.robot.domain_id,
                                        namespace=options.robot.namespace)
    recorder = (MessageRecorder(path=options.record_messages, prefix=supervisor.prefix, scenario=scenario)
                if options.record_messages is not None else None)
    plans = 0
    started = time.monotonic()
    try:
        with zenoh.open(config_from_doc(supervisor.session_doc)) as session:
            if recorder is not None:
                recorder.subscribe(session)

            def on_plan(_sample: zenoh.Sample) -> None:
                nonlocal plans
                plans += 1

            plan_sub = session.declare_subscriber(bridge.key("plan"), on_plan)
            for name in PIPELINE:
                supervisor.start(name)
            if options.monitor_args is not None:
                supervisor.start(MONITOR.name)
            _wait_alive(session, supervisor, timeout_s=options.startup_timeout_s, stop_event=stop_event)
            supervisor.keep_spares()
            if not stop_event.is_set():
                supervisor.start(ROS2.name)
                _follow_robot(supervisor=supervisor, stop_event=stop_event, plans=lambda: plans,
                              show=options.show_progress)
            plan_sub.undeclare()
    finally:
        supervisor.stop()
        if recorder is not None:
            recorder.close()
    _clean_up(supervisor, keep=options.keep_logs or bool(supervisor.restarts))
    return RobotRun(plans=plans, restarts=len(supervisor.restarts), wall_s=time.monotonic() - started)


def _follow_robot(*, supervisor: Supervisor, stop_event: threading.Event, plans, show: bool) -> None:
    """Show the paths published and restart crashed stages until `stop_event`."""
    from rich.progress import Progress, TextColumn, TimeElapsedColumn

    columns = (TextColumn("[bold]cvxnav run --ros2[/bold]  paths on /plan {task.fields[plans]}  restarts "
                          "{task.fields[restarts]}"), TimeElapsedColumn())
    with Progress(*columns, disable=not show) as bar:
        task = bar.add_task("robot", total=None, plans=0, restarts=0)
        while not stop_event.wait(0.1):
            supervisor.supervise()
            bar.update(task, plans=plans(), restarts=len(supervisor.restarts))


def summary(result: RunFile, *, wall_s: float, out_path: Path, restarts: int = 0) -> str:
    """One line: outcome, goals, sim and wall time, replans, back-outs, restarts, latency, clearance, file."""
    t_end = result.trajectory[-1][0] if result.trajectory else 0.0
    lat = result.latency_ms
    times, metres = result.backed_out()
    backed = f", backed out {times}x ({metres:.1f} m)" if times else ""
    clearance = "none (no obstacle)" if result.min_clearance is None else f"{result.min_clearance:.3f} m"
    return (f"{result.scenario}: {result.status}, goals {result.goals_reached}, sim {t_end:.1f} s in "
            f"{wall_s:.1f} s wall, replans {result.replans}{backed}, stage restarts {restarts}, scan->path latency "
            f"p50 {lat.p50:.0f} / p99 {lat.p99:.0f} / max {lat.max:.0f} ms, min clearance "
            f"{clearance} -> {out_path}")
