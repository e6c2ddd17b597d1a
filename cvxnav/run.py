"""`cvxnav run` and `cvxnav service`: every stage its own OS process, peered over Zenoh on loopback.

`run` supervises: it picks free loopback ports, starts each pipeline stage as
`python -m cvxnav service NAME --config FILE` (or the external command a `stages` config names), every
process listening on its own port and connecting to all the others' with multicast scouting off (a
full mesh on 127.0.0.1: no router, no stray sessions from the LAN), waits until every stage's
liveliness token is up, then starts the sim. It follows the sim's state and paths for the progress
bar, and when the sim exits (it writes run.json itself) prints the summary and stops every child:
SIGTERM, then SIGKILL after a grace period.

Each child's Zenoh settings are a config file the supervisor writes into the run's log directory.
`connect` endpoints are added to every process of the run (a router there relays the whole run to
`cvxnav status` or a monitor elsewhere), `listen` endpoints to the supervisor's own session (a client
connecting there hears the whole mesh).

With `tls_dir` the run is the secure deployment on one machine: the supervisor's session is the
router of `cvxnav certs` (mutual TLS, access control by certificate name) on a free loopback port
plus the `listen` endpoints, and every stage is a TLS client of it presenting its own certificate
from `tls_dir`. Nothing listens in plain TCP; a session without a certificate of that CA gets no
link, one whose certificate names no stage gets a link that carries nothing.

A stage is swapped by naming, in a JSON `stages` file, either a Python entry point
`"module:factory"` (called with the scenario, returning a StageCore), or
`{"command": ["prog", "arg", ...]}`: any process that speaks the stage's keys. Its arguments may use
`{config}` (its Zenoh config file, the only complete one under TLS), `{listen}`, `{connect}`
(comma-separated endpoints; under TLS `{listen}` is empty), `{prefix}` and `{scenario}` (a file path).
"""

from __future__ import annotations

import importlib
import json
import logging
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import zenoh

from cvxnav.certs import client_config, missing_files, pipeline_names, router_config, write_deployment
from cvxnav.runtime import StageCore, install_signal_handlers, run_stage
from cvxnav.zenoh_config import config_from_doc, endpoints_config
from schemas.files import OutputFileError, RunFile
from schemas.messages import DecodeError, RobotState, SmoothPath, decode
from schemas.scenario import Scenario
from schemas.wiring import STAGES, default_prefix, key

logger = logging.getLogger(__name__)

PIPELINE = ("sensing", "ellipsoids", "planner", "smoother")  # started first; then the sim
DEFAULT_FACTORIES: Mapping[str, str] = {
    "sensing": "services.sensing.stage:SensingStage.from_scenario",
    "ellipsoids": "services.ellipsoids.stage:EllipsoidsStage.from_scenario",
    "planner": "services.planner.stage:PlannerStage.from_scenario",
    "smoother": "services.smoother.stage:SmootherStage.from_scenario",
}
EXIT_BY_STATUS = {"reached": 0, "no_path": 3, "timeout": 4, "collision": 4}


class RunError(Exception):
    """Bad input to `run`/`service` (a stages file, an entry point): one line, exit code 2."""


class PipelineError(Exception):
    """The pipeline itself failed (a stage died or never came up): one line, exit code 4."""


# --------------------------------------------------------------------------- stage selection


def load_factory(entry_point: str) -> Callable[[Scenario], StageCore]:
    """`module:attr[.attr]` → the callable it names (a factory taking the scenario)."""
    module_name, sep, attr_path = entry_point.partition(":")
    if not sep or not module_name or not attr_path:
        raise RunError(f"entry point {entry_point!r} must look like 'package.module:factory'")
    try:
        target: Any = importlib.import_module(module_name)
    except ImportError as error:
        raise RunError(f"entry point {entry_point!r}: cannot import {module_name}: {error}") from None
    for attr in attr_path.split("."):
        if not hasattr(target, attr):
            raise RunError(f"entry point {entry_point!r}: {module_name} has no {attr_path}")
        target = getattr(target, attr)
    if not callable(target):
        raise RunError(f"entry point {entry_point!r} is not callable")
    return target


@dataclass(frozen=True)
class StageChoice:
    """How one pipeline stage runs: a Python entry point in `cvxnav service`, or an external command."""

    entry_point: str | None = None
    command: tuple[str, ...] | None = None


def load_stages(path: Path | None) -> dict[str, StageChoice]:
    """The stages config (JSON: name → "module:factory" or {"command": [...]}) over the defaults."""
    choices = {name: StageChoice(entry_point=entry) for name, entry in DEFAULT_FACTORIES.items()}
    if path is None:
        return choices
    try:
        doc = json.loads(Path(path).read_text(encoding="utf-8"))
    except OSError as error:
        raise RunError(f"{path}: cannot read: {error.strerror}") from None
    except json.JSONDecodeError as error:
        raise RunError(f"{path}: invalid JSON: {error.msg} (line {error.lineno})") from None
    stages = doc.get("stages", doc) if isinstance(doc, dict) else None
    if not isinstance(stages, dict):
        raise RunError(f"{path}: expected an object mapping stage names to entry points")
    for name, spec in stages.items():
        if name not in PIPELINE:
            raise RunError(f"{path}: stages.{name}: unknown stage; swappable: {', '.join(PIPELINE)}")
        if isinstance(spec, str):
            load_factory(spec)  # fail now, in one line, rather than in a child process
            choices[name] = StageChoice(entry_point=spec)
        elif (isinstance(spec, dict) and set(spec) == {"command"} and isinstance(spec["command"], list)
              and spec["command"] and all(isinstance(a, str) for a in spec["command"])):
            choices[name] = StageChoice(command=tuple(spec["command"]))
        else:
            raise RunError(f"{path}: stages.{name}: expected 'module:factory' or {{\"command\": [...]}}")
    return choices


# --------------------------------------------------------------------------- one stage as a process


def serve(
    *,
    name: str,
    scenario: Scenario,
    session_config: zenoh.Config,
    prefix: str,
    entry_point: str | None = None,
    sim_options: Mapping[str, Any] | None = None,
) -> int:
    """Run stage `name` until SIGINT/SIGTERM (the sim: until its run ends); the process exit code."""
    stop = threading.Event()
    install_signal_handlers(stop)
    if name == "sim":
        from sim.service import SimConfig, run_sim

        options = dict(sim_options or {})
        out_path = options.pop("out_path", None)
        result = run_sim(scenario=scenario, config=SimConfig(**options), session_config=session_config,
                         prefix=prefix, stop_event=stop, out_path=out_path)
        return EXIT_BY_STATUS[result.status]
    if name not in STAGES:
        raise RunError(f"unknown stage {name!r}; known: {', '.join(STAGES)}")
    core = load_factory(entry_point or DEFAULT_FACTORIES[name])(scenario)
    run_stage(stage=name, core=core, session_config=session_config, prefix=prefix, stop_event=stop)
    return 0


# --------------------------------------------------------------------------- the supervisor


def free_ports(count: int) -> list[int]:
    """Distinct free TCP ports on 127.0.0.1 (held open together so none is handed out twice)."""
    probes = [socket.socket() for _ in range(count)]
    try:
        for probe in probes:
            probe.bind(("127.0.0.1", 0))
        return [probe.getsockname()[1] for probe in probes]
    finally:
        for probe in probes:
            probe.close()


@dataclass
class Child:
    name: str
    process: subprocess.Popen
    log_path: Path

    def log_tail(self, *, lines: int = 5) -> str:
        try:
            text = self.log_path.read_text(encoding="utf-8", errors="replace").strip().splitlines()
        except OSError:
            return ""
        return " | ".join(text[-lines:])


@dataclass
class RunOptions:
    scenario_path: Path | None  # None: the bundled paper scenario
    out_path: Path
    realtime: bool = False
    time_limit_s: float | None = None  # sim time
    stages: dict[str, StageChoice] = field(default_factory=lambda: load_stages(None))
    robot_id: str = "robot1"
    noise_std_m: float = 0.0
    seed: int = 0
    startup_timeout_s: float = 60.0
    stop_grace_s: float = 5.0
    show_progress: bool = True
    monitor_args: tuple[str, ...] | None = None  # start the rerun monitor with these service options
    connect: tuple[str, ...] = ()  # every process of the run also connects to these Zenoh endpoints
    listen: tuple[str, ...] = ()  # the supervisor's session (under TLS: the run's router) also listens here
    tls_dir: Path | None = None  # mutual TLS + access control with the certificates of `cvxnav certs` here

    @property
    def process_names(self) -> list[str]:
        """Every process the run starts, in start order."""
        return list(PIPELINE) + (["monitor"] if self.monitor_args is not None else []) + ["sim"]


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
    """Starts, watches and stops the stage processes of one run."""

    def __init__(self, *, options: RunOptions, scenario: Scenario) -> None:
        self.options = options
        self.scenario = scenario
        self.prefix = default_prefix(robot_id=options.robot_id)
        self.session_doc, self.child_docs = (tls_layout if options.tls_dir else plain_layout)(options)
        self.children: list[Child] = []
        self.log_dir = Path(tempfile.mkdtemp(prefix="cvxnav-run-"))

    def _config_file(self, name: str) -> Path:
        path = self.log_dir / f"{name}.json5"
        path.write_text(json.dumps(self.child_docs[name], indent=1) + "\n", encoding="utf-8")
        return path

    def _command(self, name: str) -> list[str]:
        doc, config = self.child_docs[name], str(self._config_file(name))
        scenario_arg = str(self.options.scenario_path) if self.options.scenario_path else ""
        choice = self.options.stages.get(name)
        if choice is not None and choice.command is not None:
            fields = dict(config=config, listen=",".join(doc.get("listen", {}).get("endpoints", [])),
                          connect=",".join(doc["connect"]["endpoints"]), prefix=self.prefix, scenario=scenario_arg)
            return [arg.format(**fields) for arg in choice.command]
        cmd = [sys.executable, "-m", "cvxnav", "service", name, "--config", config, "--robot-id", self.options.robot_id]
        if self.options.scenario_path:
            cmd += ["--scenario", scenario_arg]
        if choice is not None and choice.entry_point is not None and choice.entry_point != DEFAULT_FACTORIES[name]:
            cmd += ["--entry", choice.entry_point]
        if name == "monitor":
            cmd += list(self.options.monitor_args or ())
        if name == "sim":
            cmd += ["--out", str(self.options.out_path), "--seed", str(self.options.seed),
                    "--noise-std-m", repr(self.options.noise_std_m)]
            if self.options.realtime:
                cmd += ["--realtime"]
            if self.options.time_limit_s is not None:
                cmd += ["--time-limit-s", repr(self.options.time_limit_s)]
        return cmd

    def start(self, name: str) -> Child:
        log_path = self.log_dir / f"{name}.log"
        with open(log_path, "wb") as log:
            process = subprocess.Popen(self._command(name), stdin=subprocess.DEVNULL, stdout=log,
                                       stderr=subprocess.STDOUT, start_new_session=True)
        child = Child(name=name, process=process, log_path=log_path)
        self.children.append(child)
        return child

    def check_alive(self, *, except_name: str | None = None) -> None:
        for child in self.children:
            if child.name != except_name and child.process.poll() is not None:
                raise PipelineError(f"stage {child.name} exited with code {child.process.returncode}: "
                                    f"{child.log_tail(lines=2)}")

    def stop(self) -> None:
        """SIGTERM every child, SIGKILL those still running after the grace period."""
        killed = stop_processes([child.process for child in self.children], grace_s=self.options.stop_grace_s)
        for child in self.children:
            if child.process in killed:
                logger.warning("stage %s ignored SIGTERM; it was killed", child.name)


def stop_processes(processes: list[subprocess.Popen], *, grace_s: float) -> list[subprocess.Popen]:
    """SIGTERM every running process, SIGKILL those still running after `grace_s`; the killed ones."""
    for process in processes:
        if process.poll() is None:
            process.send_signal(signal.SIGTERM)
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


def _wait_alive(session: zenoh.Session, supervisor: Supervisor, *, timeout_s: float) -> None:
    from sim.service import wait_for_stages

    deadline = time.monotonic() + timeout_s
    missing = {child.name for child in supervisor.children}  # the pipeline, and the monitor if asked
    while missing and time.monotonic() < deadline:
        supervisor.check_alive()
        missing = wait_for_stages(session, prefix=supervisor.prefix, stages=tuple(missing), timeout_s=1.0)
    if missing:
        raise PipelineError(f"stages not alive after {timeout_s:.0f} s: {', '.join(sorted(missing))}")


def run_pipeline(*, options: RunOptions, scenario: Scenario) -> tuple[int, RunFile | None]:
    """Run every stage as a process until the sim ends; the exit code and the run file."""
    from sim.service import default_time_limit_s

    supervisor = Supervisor(options=options, scenario=scenario)
    progress = _Progress()
    time_limit_s = options.time_limit_s or default_time_limit_s(scenario)
    try:
        with zenoh.open(config_from_doc(supervisor.session_doc)) as session:
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
                supervisor.start("monitor")  # before the sim, so it sees the world and the first scan
            _wait_alive(session, supervisor, timeout_s=options.startup_timeout_s)
            sim = supervisor.start("sim")
            wall_limit_s = time_limit_s * (1.5 if options.realtime else 1.0) + options.startup_timeout_s
            code = _follow(sim=sim, supervisor=supervisor, progress=progress, time_limit_s=time_limit_s,
                           wall_limit_s=wall_limit_s, goals=len(scenario.goals), show=options.show_progress)
            state_sub.undeclare()
            path_sub.undeclare()
    finally:
        supervisor.stop()
    if code is None:
        return EXIT_BY_STATUS["timeout"], None
    try:
        result = RunFile.read(options.out_path)
    except OutputFileError as error:
        raise PipelineError(f"the sim wrote no usable run file: {error}") from None
    return EXIT_BY_STATUS[result.status], result


def _follow(*, sim: Child, supervisor: Supervisor, progress: _Progress, time_limit_s: float,
            wall_limit_s: float, goals: int, show: bool) -> int | None:
    """Show progress until the sim exits; None when it ran past the wall-clock guard."""
    from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

    columns = (TextColumn("[bold]cvxnav run"), BarColumn(),
               TextColumn("sim {task.fields[sim_s]:6.1f} s  goals {task.fields[goals]}  replans {task.fields[replans]}"),
               TimeElapsedColumn())
    deadline = time.monotonic() + wall_limit_s
    with Progress(*columns, disable=not show) as bar:
        task = bar.add_task("run", total=time_limit_s, sim_s=0.0, goals=f"0/{goals}", replans=0)
        while sim.process.poll() is None:
            supervisor.check_alive(except_name="sim")
            if time.monotonic() > deadline:
                sim.process.kill()
                sim.process.wait()
                return None
            bar.update(task, completed=progress.sim_time_s, sim_s=progress.sim_time_s,
                       goals=f"{progress.goals_reached}/{goals}", replans=progress.replans)
            time.sleep(0.1)
        bar.update(task, completed=progress.sim_time_s, sim_s=progress.sim_time_s,
                   goals=f"{progress.goals_reached}/{goals}", replans=progress.replans)
    return sim.process.returncode


def summary(result: RunFile, *, wall_s: float, out_path: Path) -> str:
    """One line: outcome, goals, sim and wall time, replans, latency, clearance, file."""
    t_end = result.trajectory[-1][0] if result.trajectory else 0.0
    lat = result.latency_ms
    return (f"{result.scenario}: {result.status}, goals {result.goals_reached}, sim {t_end:.1f} s in "
            f"{wall_s:.1f} s wall, replans {result.replans}, scan->path latency p50 {lat.p50:.0f} / "
            f"p99 {lat.p99:.0f} / max {lat.max:.0f} ms, min clearance {result.min_clearance:.3f} m -> {out_path}")
