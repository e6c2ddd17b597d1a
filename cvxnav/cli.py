"""The `cvxnav` command line (CONTRACTS §3). Every error is one line; exit codes are the contract's."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path

from cvxnav.exits import (EXIT_BAD_INPUT, EXIT_DIFFERS, EXIT_INTERRUPTED, EXIT_NO_PATH, EXIT_OK,
                          EXIT_TIMEOUT_OR_COLLISION, CliError)


def _load(scenario: Path | None):
    from schemas.scenario import ScenarioError, bundled_scenario, load_scenario

    try:
        return bundled_scenario() if scenario is None else load_scenario(scenario)
    except ScenarioError as error:
        raise CliError(str(error)) from None


@contextmanager
def _plan_progress() -> Iterator[Callable[[int, int], None]]:
    """A spinner on a terminal's stderr while `cvxnav plan` works (a building's map may take several
    plans, and a `no_path` seconds to prove), cleared when it is done; nothing where stderr is not one.
    Yields what `plan_scenario` tells as each plan starts."""
    if not sys.stderr.isatty():  # nothing to show: not even rich's import (some 40 ms)
        yield lambda rounds, ellipses: None
        return
    from rich.console import Console
    from rich.progress import Progress, SpinnerColumn, TextColumn, TimeElapsedColumn

    columns = (SpinnerColumn(), TextColumn("[bold]cvxnav plan[/bold]  {task.fields[doing]}"), TimeElapsedColumn())
    with Progress(*columns, console=Console(stderr=True), transient=True) as bar:
        task = bar.add_task("plan", total=None, doing="reading the files")
        yield lambda rounds, ellipses: bar.update(task, doing=f"plan {rounds} among {ellipses} ellipses")


def _cmd_plan(args: argparse.Namespace) -> int:
    import time

    import numpy as np

    from cvxnav.plan import plan_scenario
    from schemas.occupancy import map_readers
    from services.geometry import polyline_length

    map_readers()  # imported before the clock starts, as the planner is: `load` is reading the files
    with _plan_progress() as on_round:
        started = time.perf_counter()
        scenario = _load(args.scenario)  # the scenario and any map it names: counted in the plan's time
        plan = plan_scenario(scenario, load_ms=1e3 * (time.perf_counter() - started), on_round=on_round)
    plan.write(args.out)
    if plan.status != "ok":
        print(f"{scenario.name}: no path to the goals: {plan.reason} ({plan.timings_ms.total:.0f} ms) -> {args.out}")
        return EXIT_NO_PATH
    path = np.array(plan.path)
    clearance = float(np.min(scenario.clearance(path))) if scenario.obstacles else float("inf")
    print(
        f"{scenario.name}: path {polyline_length(path):.2f} m, clearance {clearance:.3f} m "
        f"(needs {scenario.inflation_m:.3f}), planned in {plan.timings_ms.total:.0f} ms -> {args.out}"
    )
    return EXIT_OK


def _cmd_service(args: argparse.Namespace) -> int:
    import zenoh

    from cvxnav.service import serve
    from cvxnav.stages import RunError
    from schemas.wiring import MONITOR, ROS2, SIM, default_prefix
    from services.limits import DEFAULT_MAX_PAYLOAD_BYTES
    from services.monitor.rerun import ViewerError
    from services.shell.zenoh_config import zenoh_config_from_args, zenoh_reason

    _output_path(args.out, flag="--out", scenario=args.scenario)
    scenario = _load(args.scenario)
    if args.name == ROS2.name:
        _join_ros_graph(args)
    options = {
        SIM.name: dict(realtime=args.realtime, time_limit_s=args.time_limit_s, noise_std_m=args.noise_std_m,
                       seed=args.seed),
        MONITOR.name: dict(record=args.record, viewer=args.viewer, viewer_url=args.viewer_url),
        ROS2.name: dict(domain_id=args.domain_id, namespace=_ros_namespace(args.namespace)),
        # A swapped planner's factory takes the scenario alone.
        "planner": dict(deadline=True, budget_ms=args.budget_ms) if args.deadline else {},
    }.get(args.name, {})
    try:
        return serve(name=args.name, scenario=scenario, session_config=zenoh_config_from_args(args),
                     prefix=args.prefix or default_prefix(robot_id=args.robot_id), entry_point=args.entry,
                     options=options, out_path=args.out, state_dir=args.state_dir,
                     max_payload_bytes=args.max_payload_bytes or DEFAULT_MAX_PAYLOAD_BYTES,
                     stall_limit_s=args.stall_limit_s, standby=args.standby)
    except (RunError, ViewerError) as error:
        raise CliError(str(error)) from None
    except zenoh.ZError as error:  # the session did not open: an endpoint it cannot listen on or reach
        raise CliError(f"cannot open a Zenoh session: {zenoh_reason(error)}") from None


def _output_path(path: Path | None, *, flag: str, scenario: Path | None = None) -> None:
    """Refuse an output file whose folder does not exist, that is a folder, or that is the `scenario` it
    would overwrite (a run removes a stale output as it starts), before anything runs."""
    if path is None:
        return
    if path.is_dir():
        raise CliError(f"{flag} {path}: is a folder, not a file")
    if not path.parent.is_dir():
        raise CliError(f"{flag} {path}: folder {path.parent} does not exist")
    if scenario is not None and path.exists() and path.samefile(scenario):
        raise CliError(f"{flag} {path}: is the scenario file")


def _cmd_run(args: argparse.Namespace) -> int:
    import signal
    import time

    from cvxnav.stages import RunError, load_stages
    from cvxnav.supervisor import PipelineError, RobotOptions, RunOptions, prepare_tls, run_pipeline, summary

    signal.signal(signal.SIGTERM, signal.default_int_handler)  # kill, systemd and docker stop: like Ctrl-C
    for path, flag in ((args.out, "--out"), (args.record, "--record"), (args.record_messages, "--record-messages")):
        _output_path(path, flag=flag, scenario=args.scenario)
    scenario = _load(args.scenario)
    robot = None
    if args.ros2:
        if args.tls:
            raise CliError("--ros2 cannot run under --tls: the bridge joins the robot's rmw_zenohd, which the run's "
                           "access control does not cover")
        robot = RobotOptions(domain_id=args.domain_id, namespace=_ros_namespace(args.namespace))
        args.connect = args.connect or [ROS2_ROUTER]
    try:
        stages = load_stages(args.stages)
        options = RunOptions(scenario_path=args.scenario, out_path=args.out, realtime=args.realtime,
                             time_limit_s=args.timeout_s, stages=stages, robot_id=args.robot_id,
                             noise_std_m=args.noise_std_m, seed=args.seed, show_progress=not args.quiet,
                             monitor_args=_monitor_args(args), connect=tuple(args.connect),
                             listen=tuple(args.listen), tls_dir=args.tls.resolve() if args.tls else None,
                             record_messages=args.record_messages, keep_logs=args.keep_logs, robot=robot,
                             warm_spares=args.warm_spares or robot is not None, planner_budget_ms=args.budget_ms)
        if prepare_tls(options):
            print(f"made a CA and certificates for every stage in {options.tls_dir}", file=sys.stderr)
    except RunError as error:
        raise CliError(str(error)) from None
    if robot is not None:
        return _run_robot(options, scenario=scenario)
    started = time.monotonic()
    try:
        code, result, restarts = run_pipeline(options=options, scenario=scenario)
    except RunError as error:  # e.g. the robot id is already up on the network
        raise CliError(str(error)) from None
    except PipelineError as error:
        print(f"cvxnav: error: {error}", file=sys.stderr)
        return EXIT_TIMEOUT_OR_COLLISION
    except RunError as error:  # before any stage started
        raise CliError(str(error)) from None
    if result is None and code == EXIT_INTERRUPTED:
        print(f"{scenario.name}: interrupted before the sim wrote a run file", file=sys.stderr)
        return code
    if result is None:
        print(f"{scenario.name}: timeout: the pipeline did not finish within the wall-clock guard", file=sys.stderr)
        return code
    print(summary(result, wall_s=time.monotonic() - started, out_path=args.out, restarts=restarts))
    return code


def _run_robot(options, *, scenario) -> int:
    """`cvxnav run --ros2`: until SIGINT/SIGTERM, then every process stopped; 0, or 4 if the pipeline failed."""
    import threading

    from cvxnav.supervisor import PipelineError, run_robot
    from services.shell.stage import install_signal_handlers

    stop = threading.Event()
    install_signal_handlers(stop)
    robot = options.robot
    print(f"{scenario.name}: driving the ROS 2 robot on domain {robot.domain_id}, namespace {robot.namespace}, via "
          f"{', '.join(options.connect)}; Ctrl-C stops", file=sys.stderr, flush=True)
    try:
        run = run_robot(options=options, scenario=scenario, stop_event=stop)
    except PipelineError as error:
        print(f"cvxnav: error: {error}", file=sys.stderr)
        return EXIT_TIMEOUT_OR_COLLISION
    print(f"{scenario.name}: stopped after {run.wall_s:.1f} s: {run.plans} verified paths on /plan, stage restarts "
          f"{run.restarts}")
    return EXIT_OK


def _monitor_args(args: argparse.Namespace) -> tuple[str, ...] | None:
    """`cvxnav service monitor` options for `run --record/--viewer/--viewer-url`; None: no monitor."""
    from services.monitor.rerun import monitor_arguments

    if args.record is None and not args.viewer and args.viewer_url is None:
        return None
    record = args.record.resolve() if args.record is not None else None
    return tuple(monitor_arguments(record=record, viewer=args.viewer, viewer_url=args.viewer_url))


def _cmd_replay(args: argparse.Namespace) -> int:
    from cvxnav.record import RecordingError, read_recording
    from cvxnav.replay import replay_stage
    from cvxnav.stages import RunError, load_factory

    try:
        recording = read_recording(args.file)
        if args.entry is not None:
            load_factory(args.entry)
    except (RecordingError, RunError) as error:
        raise CliError(str(error)) from None
    report = replay_stage(recording, stage=args.stage, entry_point=args.entry, rtol=args.rtol, atol=args.atol)
    print(report.summary())
    return EXIT_OK if report.reproduced else EXIT_DIFFERS


def _positive_float(text: str) -> float:
    import math

    value = float(text)
    if not (math.isfinite(value) and value > 0.0):
        raise argparse.ArgumentTypeError(f"must be a positive number, got {text!r}")
    return value


def _cmd_plot(args: argparse.Namespace) -> int:
    from cvxnav.plot import PlotError, plot_result, read_result
    from schemas.scenario import bundled_scenario

    try:
        result = read_result(args.file)
    except PlotError as error:
        raise CliError(str(error)) from None
    if args.scenario is not None:
        scenario = _load(args.scenario)
    elif result.scenario == bundled_scenario().name:
        scenario = bundled_scenario()
    else:
        raise CliError(f"{args.file}: scenario {result.scenario!r} is not the bundled one; name its file with --scenario")
    if scenario.name != result.scenario:
        raise CliError(f"{args.file} is for scenario {result.scenario!r}, but --scenario is {scenario.name!r}")
    plot_result(result=result, scenario=scenario, png_path=args.png, width_px=args.width_px, height_px=args.height_px)
    print(f"{result.scenario}: {result.status} -> {args.png} ({args.width_px}x{args.height_px})")
    return EXIT_OK


def _cmd_status(args: argparse.Namespace) -> int:
    import zenoh

    from cvxnav.status import observe
    from schemas.wiring import default_prefix
    from services.shell.zenoh_config import zenoh_config_from_args, zenoh_reason

    prefix = args.prefix or default_prefix(robot_id=args.robot_id)
    try:
        session = zenoh.open(zenoh_config_from_args(args))
    except zenoh.ZError as error:  # e.g. nothing listens at --connect, or a TLS port without --config
        raise CliError(f"cannot open a Zenoh session: {zenoh_reason(error)}") from None
    with session:
        report = observe(session, prefix=prefix, window_s=args.window_s)
    print(report.to_json() if args.json else report.table())
    return EXIT_OK


ROS2_ROUTER = "tcp/localhost:7447"  # where rmw_zenoh's sessions find the rmw_zenohd router by default
MAX_DOMAIN_ID = 232  # the largest ROS_DOMAIN_ID ROS 2 allows


def _ros_namespace(text: str) -> str:
    from services.ros2.wire import RosNameError, node_namespace

    try:
        return node_namespace(text)
    except RosNameError as error:
        raise CliError(str(error)) from None


def _join_ros_graph(args: argparse.Namespace) -> None:
    """With no endpoints of its own, a process joins the ROS graph as rmw_zenoh does: the local router."""
    if not (args.connect or args.listen or args.zenoh_config):
        args.connect, args.mode = [ROS2_ROUTER], args.mode or "client"


def _cmd_ros2_play(args: argparse.Namespace) -> int:
    import threading

    import zenoh

    from cvxnav.ros2_play import BagError, bag_topics, open_bag, play
    from services.shell.stage import install_signal_handlers
    from services.shell.zenoh_config import zenoh_config_from_args, zenoh_reason

    namespace = _ros_namespace(args.namespace)
    _join_ros_graph(args)
    stop = threading.Event()
    install_signal_handlers(stop)
    try:
        with open_bag(args.bag) as reader:
            topics = bag_topics(reader)
            try:
                session = zenoh.open(zenoh_config_from_args(args))
            except zenoh.ZError as error:
                raise CliError(f"cannot open a Zenoh session: {zenoh_reason(error)}") from None
            with session:
                print(f"playing {args.bag} at {args.rate:g}x{' (loop)' if args.loop else ''} on domain "
                      f"{args.domain_id}: " + ", ".join(f"{t.topic} {t.msgtype} ({t.message_count})"
                                                         for t in topics.values()), flush=True)
                count = play(reader=reader, session=session, rate=args.rate, loop=args.loop,
                             domain_id=args.domain_id, namespace=namespace, stop_event=stop, delay_s=args.delay)
    except BagError as error:
        raise CliError(str(error)) from None
    print(f"published {count} messages")
    return EXIT_OK


def _non_negative_float(text: str) -> float:
    import math

    value = float(text)
    if not (math.isfinite(value) and value >= 0.0):
        raise argparse.ArgumentTypeError(f"must be a non-negative number, got {text!r}")
    return value


def _domain_id(text: str) -> int:
    value = int(text)
    if not 0 <= value <= MAX_DOMAIN_ID:
        raise argparse.ArgumentTypeError(f"must be a ROS domain id in 0..{MAX_DOMAIN_ID}, got {text!r}")
    return value


def _cmd_router(args: argparse.Namespace) -> int:
    import threading

    import zenoh

    from cvxnav.status import run_router
    from services.shell.stage import install_signal_handlers
    from services.shell.zenoh_config import zenoh_config_from_args, zenoh_reason

    if not args.listen and args.zenoh_config is None:
        args.listen = ["tcp/0.0.0.0:7447"]
    stop = threading.Event()
    install_signal_handlers(stop)
    ready = threading.Event()
    failed: list[str] = []

    def serve_router() -> None:
        try:
            run_router(session_config=zenoh_config_from_args(args), stop_event=stop, ready_event=ready)
        except zenoh.ZError as error:  # e.g. an address no interface has, or a port in use
            failed.append(zenoh_reason(error))

    thread = threading.Thread(target=serve_router)
    thread.start()
    while thread.is_alive() and not ready.wait(0.1):
        pass
    if ready.is_set():
        print(f"cvxnav router listening on {', '.join(args.listen) or 'the config file endpoints'}", flush=True)
    thread.join()
    if failed:
        raise CliError(f"the router cannot listen: {failed[0]}")
    return EXIT_OK if ready.is_set() else EXIT_BAD_INPUT


def _positive_int(text: str) -> int:
    value = int(text)
    if value <= 0:
        raise argparse.ArgumentTypeError(f"must be a positive integer, got {text!r}")
    return value


def _cmd_certs(args: argparse.Namespace) -> int:
    from cvxnav.certs import DEFAULT_ROUTER_HOSTS, write_deployment

    hosts = tuple(dict.fromkeys([*args.router_host, *DEFAULT_ROUTER_HOSTS]))
    written = write_deployment(out_dir=args.out, router_hosts=hosts, port=args.port)
    print(f"wrote a CA, the router's and {len(written) // 2 - 1} client certificates with Zenoh configs to {args.out} "
          f"(router names: {', '.join(hosts)})")
    return EXIT_OK


def _cmd_schemas(args: argparse.Namespace) -> int:
    from schemas.export import export_json_schemas

    written = export_json_schemas(args.out)
    print(f"wrote {len(written)} JSON Schemas to {args.out}")
    return EXIT_OK


class _Parser(argparse.ArgumentParser):
    def error(self, message: str) -> None:  # one line, exit 2, like every other bad input
        self.exit(EXIT_BAD_INPUT, f"{self.prog}: error: {message}\n")


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="cvxnav", description="Mobile-robot motion planning by convex optimisation.")
    commands = parser.add_subparsers(dest="command", required=True, parser_class=_Parser)

    plan = commands.add_parser("plan", help="plan once on a known map, in one process")
    plan.add_argument("scenario", nargs="?", type=Path, help="scenario file (default: the paper's)")
    plan.add_argument("--out", type=Path, default=Path("plan.json"), help="plan file to write")
    plan.set_defaults(handler=_cmd_plan)

    from schemas.wiring import DEFAULT_ROBOT_ID, PIPELINE, PROCESSES, check_prefix, check_robot_id
    from services.shell.watchdog import STALL_LIMIT_S
    from services.shell.zenoh_config import add_zenoh_arguments, argument_type, endpoint_argument

    robot_id, prefix = argument_type(check_robot_id), argument_type(check_prefix)

    run = commands.add_parser("run", help="the whole pipeline, each stage its own process, with the sim")
    run.add_argument("scenario", nargs="?", type=Path, help="scenario file (default: the paper's)")
    run.add_argument("--out", type=Path, default=Path("run.json"), help="run file to write")
    run.add_argument("--realtime", action="store_true", help="run the sim on the wall clock (default: lockstep)")
    run.add_argument("--budget-ms", type=_positive_float, default=None,
                     help="the planner's budget per scan in a live run (--realtime, --ros2; default 15 %% of the "
                          "sensor's period)")
    run.add_argument("--timeout-s", type=_positive_float, default=None,
                     help="sim-time limit in seconds (default: from the scenario's tour length)")
    run.add_argument("--stages", type=Path, default=None,
                     help='JSON file swapping stages: {"smoother": "module:factory" | {"command": [...]}}')
    run.add_argument("--robot-id", type=robot_id, default=DEFAULT_ROBOT_ID,
                     help="key prefix is cvxnav/<robot-id>; refused if a pipeline with this id is up at --connect")
    run.add_argument("--noise-std-m", type=float, default=0.0, help="range noise (seeded)")
    run.add_argument("--seed", type=int, default=0, help="seed of the sensor noise")
    run.add_argument("--quiet", action="store_true", help="no progress bar")
    run.add_argument("--warm-spares", action="store_true",
                     help="keep a started spare process per pipeline stage, so a crashed stage is replaced at once "
                          "(always on with --ros2)")
    run.add_argument("--keep-logs", action="store_true",
                     help="keep the run's folder of stage logs, configs and checkpoints (by default removed "
                          "unless the run failed)")
    run.add_argument("--record", type=Path, default=None, metavar="FILE.rrd",
                     help="start the monitor stage and save a rerun recording")
    run.add_argument("--viewer", action="store_true", help="start the monitor stage and spawn a rerun viewer")
    run.add_argument("--viewer-url", default=None, metavar="URL",
                     help="start the monitor stage and stream to a rerun viewer or server at URL "
                          "(e.g. rerun+http://127.0.0.1:9876/proxy)")
    run.add_argument("--record-messages", type=Path, default=None, metavar="FILE.mcap",
                     help="record every message of the run (key, encoding, payload, receive time) as MCAP")
    network = run.add_argument_group("zenoh")
    network.add_argument("--connect", "-e", metavar="ENDPOINT", action="append", default=[], type=endpoint_argument,
                         help="every process of the run also connects here, e.g. a router others reach: "
                              "tcp/HOST:7447 (repeatable)")
    network.add_argument("--listen", "-l", metavar="ENDPOINT", action="append", default=[], type=endpoint_argument,
                         help="the run (under --tls: its router) also listens here for cvxnav status or a monitor "
                              "(repeatable)")
    network.add_argument("--tls", type=Path, default=None, metavar="DIR",
                         help="mutual TLS + access control with the certificates of `cvxnav certs --out DIR`; "
                              "made there first when DIR does not exist")
    robot = run.add_argument_group("ROS 2 robot (CONTRACTS §6)")
    robot.add_argument("--ros2", action="store_true",
                       help="drive a ROS 2 robot (rmw_zenoh): the bridge in the sim's place, until Ctrl-C or SIGTERM; "
                            f"every process joins the robot's rmw_zenohd (--connect, default {ROS2_ROUTER}); the "
                            "sim's options and --out do not apply")
    robot.add_argument("--domain-id", type=_domain_id, default=0, help="--ros2: ROS_DOMAIN_ID of the robot's graph")
    robot.add_argument("--namespace", default="/", help="--ros2: the robot's namespace (its topics under it)")
    run.set_defaults(handler=_cmd_run)

    service = commands.add_parser("service", help="run one stage as a standalone process")
    service.add_argument("name", choices=list(PROCESSES), help="the stage to run (monitor: the rerun sink)")
    service.add_argument("--scenario", type=Path, default=None, help="scenario file (default: the paper's)")
    service.add_argument("--robot-id", type=robot_id, default=DEFAULT_ROBOT_ID, help="key prefix is cvxnav/<robot-id>")
    service.add_argument("--prefix", type=prefix, default=None, help="key prefix (overrides --robot-id)")
    service.add_argument("--entry", default=None, metavar="MODULE:FACTORY",
                         help="an alternative implementation: a factory taking the scenario")
    service.add_argument("--max-payload-bytes", type=_positive_int, default=None, metavar="N",
                         help="reject (and report) an input message larger than N bytes (default 1 MiB)")
    service.add_argument("--state-dir", type=Path, default=None, metavar="DIR",
                         help="keep state that must survive a restart here (sensing: point memory; planner: plan)")
    service.add_argument("--stall-limit-s", type=_positive_float, default=STALL_LIMIT_S, metavar="S",
                         help="under a watchdog (NOTIFY_SOCKET, WATCHDOG_USEC: systemd or cvxnav run), stop the "
                              f"keep-alives when one input takes longer than this (default {STALL_LIMIT_S:g})")
    service.add_argument("--standby", action="store_true",
                         help="a warm spare: build the core, then wait for a line on standard input before joining "
                              "the network (end of input: exit 0)")
    planner = service.add_argument_group("planner")
    planner.add_argument("--deadline", action="store_true",
                         help="planner: answer each scan within its budget, with the best verified path at hand, "
                              "replanning in the background (live runs; lockstep runs wait for the best)")
    planner.add_argument("--budget-ms", type=_positive_float, default=None,
                         help="planner, with --deadline: each answer's budget (default 15 %% of the sensor's period, "
                              "15 ms at 10 Hz)")
    sim = service.add_argument_group("sim")
    sim.add_argument("--out", type=Path, default=None, help="sim: run file to write when the run ends")
    sim.add_argument("--realtime", action="store_true", help="sim: run on the wall clock")
    sim.add_argument("--time-limit-s", type=_positive_float, default=None, help="sim: sim-time limit")
    sim.add_argument("--noise-std-m", type=float, default=0.0, help="sim: range noise std")
    sim.add_argument("--seed", type=int, default=0, help="sim: noise seed")
    monitor = service.add_argument_group("monitor (rerun; default: --record cvxnav-monitor.rrd)")
    monitor.add_argument("--record", type=Path, default=None, metavar="FILE.rrd", help="monitor: save a recording")
    monitor.add_argument("--viewer", action="store_true", help="monitor: spawn a rerun viewer")
    monitor.add_argument("--viewer-url", default=None, metavar="URL",
                         help="monitor: stream to a viewer, e.g. rerun+http://host:9876/proxy")
    bridge = service.add_argument_group("ros2 (the ROS 2 bridge; without --connect, --listen or --config it joins "
                                        f"rmw_zenohd at {ROS2_ROUTER} as a client)")
    bridge.add_argument("--domain-id", type=_domain_id, default=0, help="ros2: ROS_DOMAIN_ID of the robot's graph")
    bridge.add_argument("--namespace", default="/", help="ros2: the robot's namespace (its topics under it)")
    add_zenoh_arguments(service)
    service.set_defaults(handler=_cmd_service)

    status = commands.add_parser("status", help="which stages are alive, their last status, message rates")
    status.add_argument("--robot-id", type=robot_id, default=DEFAULT_ROBOT_ID, help="key prefix is cvxnav/<robot-id>")
    status.add_argument("--prefix", type=prefix, default=None, help="key prefix (overrides --robot-id)")
    status.add_argument("--window-s", type=_positive_float, default=2.0, help="how long to measure rates")
    status.add_argument("--json", action="store_true", help="print JSON instead of a table")
    add_zenoh_arguments(status)
    status.set_defaults(handler=_cmd_status)

    ros2 = commands.add_parser("ros2", help="ROS 2 robots over rmw_zenoh, no ROS install (CONTRACTS §6)")
    ros2_commands = ros2.add_subparsers(dest="ros2_command", required=True, parser_class=_Parser)
    play = ros2_commands.add_parser("play", help="publish a rosbag2 (MCAP or sqlite3) on rmw_zenoh's keys, in "
                                                 "real time")
    play.add_argument("bag", type=Path, help="the bag's directory (or its .mcap / .db3 file)")
    play.add_argument("--rate", type=_positive_float, default=1.0, help="playback speed, times real time")
    play.add_argument("--loop", action="store_true", help="start over after the last message")
    play.add_argument("--delay", type=_non_negative_float, default=0.0, metavar="S",
                      help="seconds between joining the graph and the first message (and each loop)")
    play.add_argument("--domain-id", type=_domain_id, default=0, help="ROS_DOMAIN_ID of the graph to join")
    play.add_argument("--namespace", default="/", help="play the bag's topics under this namespace")
    add_zenoh_arguments(play)
    play.epilog = f"Without --connect, --listen or --config it joins the rmw_zenohd router at {ROS2_ROUTER} as a client."
    play.set_defaults(handler=_cmd_ros2_play)

    router = commands.add_parser("router", help="a Zenoh router in this process (default listen tcp/0.0.0.0:7447)")
    add_zenoh_arguments(router)
    router.set_defaults(handler=_cmd_router)

    certs = commands.add_parser("certs", help="a CA, router and per-stage certificates and Zenoh configs (mutual TLS "
                                             "+ access control)")
    certs.add_argument("--out", type=Path, default=Path("certs"), help="directory to write")
    certs.add_argument("--router-host", action="append", default=[], metavar="NAME_OR_IP",
                       help="a name the stages reach the router by (repeatable; the first is in the stage configs)")
    certs.add_argument("--port", type=int, default=7447, help="the router's TLS port")
    certs.set_defaults(handler=_cmd_certs)

    plot = commands.add_parser("plot", help="draw a plan.json or run.json as a PNG (like the paper's Fig. 5)")
    plot.add_argument("file", type=Path, help="a cvxnav.plan/2 (or /1) or cvxnav.run/2 (or /1) file")
    plot.add_argument("--png", type=Path, default=Path("plot.png"), help="image to write")
    plot.add_argument("--scenario", type=Path, default=None,
                      help="the scenario file (default: the bundled paper scenario, when the file names it)")
    plot.add_argument("--width-px", type=_positive_int, default=1200, help="image width in pixels")
    plot.add_argument("--height-px", type=_positive_int, default=900, help="image height in pixels")
    plot.set_defaults(handler=_cmd_plot)

    replay = commands.add_parser("replay", help="re-run one stage on a message recording; compare its outputs")
    replay.add_argument("file", type=Path, help="an MCAP file from `cvxnav run --record-messages`")
    replay.add_argument("--stage", required=True, choices=list(PIPELINE),
                        help="the stage whose recorded inputs are replayed")
    replay.add_argument("--entry", default=None, metavar="MODULE:FACTORY",
                        help="an alternative implementation: a factory taking the scenario")
    replay.add_argument("--rtol", type=_positive_float, default=1e-6, help="relative tolerance on numbers")
    replay.add_argument("--atol", type=_positive_float, default=1e-9, help="absolute tolerance on numbers")
    replay.set_defaults(handler=_cmd_replay)

    schemas = commands.add_parser("schemas", help="write every message model as JSON Schema")
    schemas.add_argument("--out", type=Path, default=Path("schemas-json"), help="directory to write")
    schemas.set_defaults(handler=_cmd_schemas)

    from cvxnav.bench.command import add_bench_parser  # light: the benchmark's imports are inside its handler

    add_bench_parser(commands)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return args.handler(args)
    except CliError as error:
        print(f"cvxnav: error: {error}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except KeyboardInterrupt:
        return EXIT_INTERRUPTED


if __name__ == "__main__":
    sys.exit(main())
