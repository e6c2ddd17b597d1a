"""`cvxnav run --ros2` as a robot's user runs it: real processes, a real router, real laser data.

`cvxnav router` plays rmw_zenohd's part; the run's processes join it, and so does the test, as one more
client of the robot's graph: it hears every ROS sample (decoded with mcap-ros2-support, never with
rosbags, which cvxnav encodes with), every liveliness token and every stage status.

- The ACES building log (`../shared/external/carmen/aces-bag`, 440 real scans, nobody's drawing) is
  played by `cvxnav ros2 play` at 3x into the run, up to where the recorded route reaches the
  scenario's goal: the plans must be the robot's (its frame, from its pose, to its goal), keep its
  margin from every real hit it had had for half a second, and the commands must flow.
- A synthetic robot's node publishes the inputs the issue names as breaking ones into a live run.
- A map server's map (Nav2's depot) on /map, published before the run starts, and a laser that sees
  nothing: every plan goes round the map's walls, which the straight way runs into, with the margin.
"""

from __future__ import annotations

import math
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pytest
import shapely
import zenoh

from cvxnav.supervisor import free_ports, stop_processes
from ros2_bag import aces_bag_dir, independent_decoder
from ros2_messages import laser_scan, map_server_grid, odometry
from schemas.messages import StageStatus, decode
from schemas.occupancy import load_map
from schemas.scenario import bundled_scenario, load_scenario
from schemas.wiring import PIPELINE, ROS2, default_prefix, key, status_key
from services.ros2.bridge import yaw_of
from services.ros2.interface import BRIDGE_NODE, BRIDGE_TOPICS
from services.ros2.wire import EntityKind, parse_token
from services.shell.ros2 import Attachment, RosNode
from services.shell.zenoh_config import build_zenoh_config
from stage_processes import alive, spare_pids, stage_pids

ACES = Path(__file__).resolve().parents[1] / "data" / "aces-bridge.json"
DEPOT = Path(__file__).resolve().parents[1] / "data" / "depot-bridge.json"
PREFIX = default_prefix()
STARTUP_S = 180.0  # five stage processes on a shared machine
RATE = 3.0  # the log's 2.2 s between scans become 0.73 s: odometry, and so commands, above 1 Hz
WINDOW_S = 0.5  # a plan keeps the margin from every hit received this long before it


@dataclass
class Graph:
    """The test's session, a client of the router: what the robot's graph carries, as it arrives."""

    session: zenoh.Session
    samples: list[tuple[float, str, object, Attachment]] = field(default_factory=list)  # (time, topic, msg, att)
    tokens: dict[str, bool] = field(default_factory=dict)  # liveliness key -> alive
    statuses: list[tuple[float, StageStatus]] = field(default_factory=list)
    lock: threading.Lock = field(default_factory=threading.Lock)

    def on_sample(self, sample: zenoh.Sample) -> None:
        topic = str(sample.key_expr).split("/")[-3]
        try:
            message = DECODERS[topic](sample.payload.to_bytes())
        except Exception:  # noqa: BLE001  # the broken messages a test sends the bridge
            return
        with self.lock:
            self.samples.append((time.monotonic(), topic, message, Attachment.from_bytes(sample.attachment.to_bytes())))

    def on_token(self, sample: zenoh.Sample) -> None:
        with self.lock:
            self.tokens[str(sample.key_expr)] = sample.kind == zenoh.SampleKind.PUT

    def on_status(self, sample: zenoh.Sample) -> None:
        with self.lock:
            self.statuses.append((time.monotonic(), decode(StageStatus, sample.payload.to_bytes())))

    def of(self, topic: str) -> list[tuple[float, object]]:
        with self.lock:
            return [(t, message) for t, name, message, _ in self.samples if name == topic]

    def bridge_entities(self) -> set[tuple[EntityKind, str | None, str | None, str | None]]:
        with self.lock:
            alive = [parse_token(key) for key, up in self.tokens.items() if up]
        return {(e.kind, e.topic, e.msgtype, e.type_hash) for e in alive if e.node_fqn == f"/{BRIDGE_NODE}"}

    def wait(self, predicate, *, timeout_s: float, what: str) -> None:
        deadline = time.monotonic() + timeout_s
        while not predicate():
            if time.monotonic() > deadline:
                pytest.fail(f"timed out after {timeout_s:.0f} s waiting for {what}")
            time.sleep(0.05)


DECODERS = {topic.name: independent_decoder(topic.msgtype) for topic in BRIDGE_TOPICS.values()}
BRIDGE_GRAPH = {(EntityKind.NODE, None, None, None)} | {
    (EntityKind.PUBLISHER if t.direction == "out" else EntityKind.SUBSCRIPTION, f"/{t.name}", t.msgtype, t.type_hash)
    for t in BRIDGE_TOPICS.values()}


@contextmanager
def robot_graph(tmp_path: Path) -> Iterator[tuple[str, Graph]]:
    """`cvxnav router` in rmw_zenohd's place, and the test's client session of it."""
    endpoint = f"tcp/127.0.0.1:{free_ports(1)[0]}"
    router = subprocess.Popen([sys.executable, "-m", "cvxnav", "router", "--listen", endpoint], cwd=tmp_path,
                              stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        assert router.stdout.readline().startswith("cvxnav router listening"), router.stdout.read()
        with zenoh.open(build_zenoh_config(connect=[endpoint], mode="client")) as session:
            graph = Graph(session=session)
            declarations = [session.declare_subscriber("0/**", graph.on_sample),
                            session.liveliness().declare_subscriber("@ros2_lv/**", graph.on_token, history=True),
                            session.declare_subscriber(status_key(PREFIX), graph.on_status)]
            yield endpoint, graph
            for declaration in declarations:
                declaration.undeclare()
    finally:
        stop_processes([router], grace_s=5.0)


@contextmanager
def run_ros2(scenario: Path | None, *, endpoint: str, graph: Graph, cwd: Path) -> Iterator[subprocess.Popen]:
    """`cvxnav run --ros2 [SCENARIO] --connect EP`, once the bridge's node is in the robot's graph."""
    log = open(cwd / "run.log", "w+")
    process = subprocess.Popen([sys.executable, "-m", "cvxnav", "run", "--ros2", *([str(scenario)] if scenario else []),
                                "--connect", endpoint, "--quiet"], cwd=cwd, stdout=log, stderr=subprocess.STDOUT,
                               text=True)
    try:
        graph.wait(lambda: graph.bridge_entities() == BRIDGE_GRAPH or process.poll() is not None,
                   timeout_s=STARTUP_S, what="the bridge's node in the graph")
        assert process.poll() is None, (cwd / "run.log").read_text()[-3000:]
        time.sleep(0.5)  # its subscriptions reach the publishers about to start
        yield process
    finally:
        stop_processes([process], grace_s=30.0)
        log.close()


def stop_run(process: subprocess.Popen, *, cwd: Path) -> tuple[int, str]:
    """SIGTERM the run, as a service manager would: its exit code and output; every stage must be gone."""
    stages = stage_pids(process.pid)
    assert set(stages) == {*PIPELINE, ROS2.name}
    pids = [*stages.values(), *spare_pids(process.pid).values()]  # a robot run keeps warm spares
    process.send_signal(signal.SIGTERM)
    code = process.wait(timeout=60)
    deadline = time.monotonic() + 10.0
    while any(alive(pid) for pid in pids) and time.monotonic() < deadline:
        time.sleep(0.05)
    assert not any(alive(pid) for pid in pids)
    return code, (cwd / "run.log").read_text()


def stamp_s(message) -> float:
    return message.header.stamp.sec + 1e-9 * message.header.stamp.nanosec


def hits_of(scan, odom, *, max_range_m: float) -> np.ndarray:
    """A LaserScan's world-frame hits from the odometry stamped with it, computed here ray by ray."""
    p, yaw = odom.pose.pose.position, yaw_of(odom.pose.pose.orientation)
    r = np.asarray(scan.ranges, dtype=float)
    a = yaw + scan.angle_min + scan.angle_increment * np.arange(len(r))
    with np.errstate(invalid="ignore"):
        seen = np.isfinite(r) & (r >= scan.range_min) & (r <= min(scan.range_max, max_range_m))
    return np.column_stack([p.x + r[seen] * np.cos(a[seen]), p.y + r[seen] * np.sin(a[seen])])


@pytest.mark.slow
def test_a_real_laser_log_is_planned_through_with_the_robots_margin_and_commands_flow(shared_dir, tmp_path) -> None:
    scenario = load_scenario(ACES)
    goal = np.asarray(scenario.goals[-1])
    with robot_graph(tmp_path) as (endpoint, graph), run_ros2(ACES, endpoint=endpoint, graph=graph,
                                                              cwd=tmp_path) as run:
        player = subprocess.Popen([sys.executable, "-m", "cvxnav", "ros2", "play", str(aces_bag_dir(shared_dir)),
                                   "--rate", str(RATE), "--delay", "1", "--connect", endpoint], cwd=tmp_path,
                                  stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        try:
            # The recorded route reaches the goal 55.5 s into the log; then two more scans for the last plans.
            reached = lambda: any(  # noqa: E731
                math.dist((m.pose.pose.position.x, m.pose.pose.position.y), goal) <= scenario.goal_tolerance
                for _, m in graph.of("odom"))
            graph.wait(reached, timeout_s=60 / RATE + 60, what="the recorded route to reach the goal")
            time.sleep(2 * 2.2 / RATE)
            player.send_signal(signal.SIGINT)
            assert player.wait(timeout=30) == 0
        finally:
            stop_processes([player], grace_s=5.0)
        time.sleep(1.5)  # the watchdog's zeros once the odometry has stopped
        code, log = stop_run(run, cwd=tmp_path)
    assert code == 0, log[-3000:]
    assert "verified paths on /plan" in log.splitlines()[-1]

    # Every real scan and odometry was taken: the bridge placed every scan, the sensing stage took it.
    refused = [(s.stage, s.reason) for _, s in graph.statuses if s.state == "error"
               and (s.stage == "sensing" or s.reason.startswith(("scan:", "odom:")))]
    assert refused == []
    odoms, scans, plans, commands = (graph.of(topic) for topic in ("odom", "scan", "plan", "cmd_vel"))
    assert len(odoms) == len(scans) >= 31
    odom_at = {stamp_s(m): m for _, m in odoms}
    hits = [(t, hits_of(m, odom_at[stamp_s(m)], max_range_m=float(scenario.sensor.range))) for t, m in scans]
    scan_arrival = {stamp_s(m): t for t, m in scans}
    assert plans, f"no /plan; statuses: {[s.reason for _, s in graph.statuses][-10:]}"
    latencies_ms, clearances = [], []
    for arrived, plan in plans:
        # The robot's plan: in its odometry's frame, stamped with the scan it answers, from where the robot
        # was when it was planned (the newest pose the planner had, between that scan and the plan) to its goal.
        points = np.array([(p.pose.position.x, p.pose.position.y) for p in plan.poses])
        assert plan.header.frame_id == "odom" and {p.header.frame_id for p in plan.poses} == {"odom"}
        since = scan_arrival[stamp_s(plan)] - 0.1
        poses = [(m.pose.pose.position.x, m.pose.pose.position.y) for t, m in odoms if since <= t <= arrived]
        assert min(math.dist(points[0], pose) for pose in poses) <= 0.5  # the planner's max_cross_track_m
        assert np.linalg.norm(points[-1] - goal) <= 1e-6
        latencies_ms.append(1e3 * (arrived - scan_arrival[stamp_s(plan)]))
        # Its margin from every real hit the robot had had for half a second: the run's hard floor, or
        # what the robot itself had (where the plan starts, or where it was then), if it was closer.
        known = [h for t, h in hits if t <= arrived - WINDOW_S]
        if not known:
            continue
        cloud = shapely.points(np.vstack(known))
        clearance = float(shapely.distance(shapely.LineString(points), cloud).min())
        at_start = float(shapely.distance(shapely.points([points[0], poses[-1]]), cloud[:, None]).min())
        assert clearance >= min(scenario.keep_out_m, at_start) - 0.02, (clearance, at_start)
        clearances.append(clearance)

    # Commands: one per odometry message while the bag plays (above 1 Hz), within the speed bound, on
    # arcs the robot can drive; and a zero one last, when the bridge stops.
    during = [(t, c) for t, c in commands if odoms[0][0] <= t <= odoms[-1][0] + 0.1]
    gaps = np.diff([t for t, _ in during])
    assert len(during) >= len(odoms) and gaps.max() <= 1.0, gaps.max()
    speed = np.array([c.linear.x for _, c in commands])
    turn = np.array([c.angular.z for _, c in commands])
    assert np.all((speed >= 0.0) & (speed <= scenario.robot.max_speed + 1e-9))
    assert np.all(np.abs(turn) <= speed * scenario.centre_max_curvature + 1e-9)
    assert (commands[-1][1].linear.x, commands[-1][1].angular.z) == (0.0, 0.0)
    # The graph named the bridge's node and its topics while it ran, and none of them once it stopped.
    assert graph.bridge_entities() == set()
    print(f"\nACES at {RATE:g}x: {len(scans)} scans, {len(plans)} plans on /plan, scan -> /plan latency p50 "
          f"{np.median(latencies_ms):.0f} / max {max(latencies_ms):.0f} ms, min clearance {min(clearances):.3f} m, "
          f"{int(np.count_nonzero(speed))} of {len(speed)} commands moving")


@pytest.mark.slow
def test_bad_robot_input_is_an_error_on_the_bridges_status_key_and_the_robot_brakes(tmp_path) -> None:
    """Each input the issue names, into a live run: a clear error on ``status/ros2``, a zero /cmd_vel at
    once, the same bridge process going on to drive the robot again, and no other stage disturbed."""
    scenario = bundled_scenario()  # the robot stands at the start; its laser sees nothing: plans run to the goals
    with robot_graph(tmp_path) as (endpoint, graph), run_ros2(None, endpoint=endpoint, graph=graph,
                                                              cwd=tmp_path) as run:
        bridge_pid = stage_pids(run.pid)[ROS2.name]
        node = RosNode(graph.session, name="robot_base")
        publishers = {name: node.publisher(topic=t.name, msgtype=t.msgtype, type_hash=t.type_hash, qos=t.qos)
                      for name, t in BRIDGE_TOPICS.items() if t.direction == "in"}
        impostor = node.publisher(topic="scan", msgtype="sensor_msgs/msg/LaserScan",
                                  type_hash=BRIDGE_TOPICS["odom"].type_hash)
        start = scenario.start
        clock = {"t": 1000.0}

        def step(k: int) -> None:
            """0.1 s of the robot: its odometry, and every fifth step a scan (of nothing)."""
            clock["t"] += 0.1
            publishers["odom"].put(odometry(x=start.x, y=start.y, yaw=start.theta, t_s=clock["t"]))
            if k % 5 == 0:
                publishers["scan"].put(laser_scan(np.full(scenario.sensor.rays, np.inf), t_s=clock["t"],
                                                  angle_min=-math.pi / 2, angle_increment=math.pi / 180))
            time.sleep(0.1)

        def drive_until_moving(timeout_s: float = 60.0) -> None:
            deadline, k = time.monotonic() + timeout_s, 0
            while time.monotonic() < deadline:
                step(k)
                k += 1
                recent = graph.of("cmd_vel")[-1:]
                if recent and recent[0][1].linear.x > 0.0:
                    return
            pytest.fail(f"the robot was not driven again; statuses: {[s.reason for _, s in graph.statuses][-5:]}")

        good = laser_scan(np.full(scenario.sensor.rays, np.inf), t_s=0.0, angle_min=-1.5, angle_increment=0.01)
        bad = [
            (lambda: publishers["scan"].put(good[:40]), "scan: sensor_msgs/msg/LaserScan: malformed CDR"),
            (lambda: impostor.put(good), "is not sensor_msgs/msg/LaserScan's"),
            (lambda: publishers["scan"].put(laser_scan(np.full(100_000, 2.0), t_s=clock["t"], angle_min=-1.5,
                                                       angle_increment=3e-5)),
             "scan: rays (the scenario's sensor.rays): 100000 exceeds the limit of 181"),
            (lambda: publishers["odom"].put(odometry(x=math.nan, y=0.0, yaw=0.0, t_s=clock["t"])),
             "odom: pose/twist not finite: x=nan"),
            (lambda: publishers["odom"].put(odometry(x=0.0, y=0.0, yaw=0.0, t_s=clock["t"], frame="map")),
             "odom: header.frame_id changed from 'odom' to 'map' mid-run"),
        ]
        time.sleep(0.5)
        for send, reason in bad:
            drive_until_moving()
            commands, statuses = len(graph.of("cmd_vel")), len(graph.statuses)
            send()
            graph.wait(lambda: any(s.stage == ROS2.name and s.state == "error" and reason in s.reason
                                   for _, s in graph.statuses[statuses:]), timeout_s=10, what=reason)
            graph.wait(lambda: len(graph.of("cmd_vel")) > commands, timeout_s=10, what="a command")
            first = graph.of("cmd_vel")[commands][1]
            assert (first.linear.x, first.angular.z) == (0.0, 0.0)  # braking at once, before any odometry
        drive_until_moving()
        assert stage_pids(run.pid)[ROS2.name] == bridge_pid  # the same bridge, never restarted
        node.close()
        code, log = stop_run(run, cwd=tmp_path)
    assert code == 0, log[-3000:]
    errors = [(s.stage, s.reason) for _, s in graph.statuses if s.state == "error"]
    assert {stage for stage, _ in errors} == {ROS2.name}, errors  # nothing else was disturbed
    assert len(errors) == len(bad), errors


@pytest.mark.slow
def test_a_map_servers_map_on_map_is_planned_round_with_the_robots_margin(shared_dir, tmp_path) -> None:
    scenario = load_scenario(DEPOT)
    depot_yaml = shared_dir / "maps" / "depot.yaml"
    walls = load_map(depot_yaml)
    start, goal = scenario.start, np.asarray(scenario.goals[-1])
    straight = np.linspace((start.x, start.y), goal, 200)
    assert walls.clearance(straight).min() == 0.0  # the straight way runs into the depot's shelves
    with robot_graph(tmp_path) as (endpoint, graph):
        node = RosNode(graph.session, name="robot_base")
        publishers = {name: node.publisher(topic=t.name, msgtype=t.msgtype, type_hash=t.type_hash, qos=t.qos)
                      for name, t in BRIDGE_TOPICS.items() if t.direction == "in"}
        publishers["map"].put(map_server_grid(depot_yaml))  # latched: the bridge, not started yet, asks for it
        map_in = threading.Event()  # the bridge has sent the pipeline its Map
        map_key = graph.session.declare_subscriber(key(PREFIX, "map"), lambda sample: map_in.set())
        with run_ros2(DEPOT, endpoint=endpoint, graph=graph, cwd=tmp_path) as run:
            deadline, clock = time.monotonic() + 120.0, {"t": 1000.0}

            def stand(*, laser: bool) -> None:
                """A tenth of a second of the robot standing at the start: its odometry, and with the laser
                on a scan that sees nothing."""
                clock["t"] += 0.1
                publishers["odom"].put(odometry(x=start.x, y=start.y, yaw=start.theta, t_s=clock["t"]))
                if laser:
                    publishers["scan"].put(laser_scan(np.full(scenario.sensor.rays, np.inf), t_s=clock["t"],
                                                      angle_min=-math.pi / 2,
                                                      angle_increment=math.pi / scenario.sensor.rays))
                time.sleep(0.1)

            # The robot stands, its laser off, until the map is in the pipeline: a scan planned before then
            # (the latched /map reaches a bridge just started after a few scans on a loaded machine) is
            # planned on what the laser saw alone (docs/ros2.md). Then two more odometries, so the ellipsoid
            # stage knows where the robot is when the first scan arrives.
            while not map_in.is_set() and time.monotonic() < deadline:
                stand(laser=False)
            assert map_in.is_set(), "the bridge never sent the map"
            for _ in range(2):
                stand(laser=False)
            while len(graph.of("plan")) < 3 and time.monotonic() < deadline:
                stand(laser=True)
            code, log = stop_run(run, cwd=tmp_path)
        map_key.undeclare()
        node.close()
    assert code == 0, log[-3000:]
    plans = graph.of("plan")
    assert plans, f"no /plan; statuses: {[s.reason for _, s in graph.statuses][-10:]}"
    for _, plan in plans:
        points = np.array([(p.pose.position.x, p.pose.position.y) for p in plan.poses])
        assert plan.header.frame_id == "odom"
        assert math.dist(points[0], (start.x, start.y)) <= 0.05 and np.linalg.norm(points[-1] - goal) <= 1e-6
        assert walls.clearance(points).min() >= scenario.inflation_m


@pytest.mark.slow
def test_a_hung_stage_or_bridge_is_replaced_and_a_killed_run_leaves_nothing_running(tmp_path) -> None:
    """The faults of a sim run, driving a robot: a stage and the bridge each stopped with SIGSTOP (they keep
    their links and tokens) are killed by the watchdog and started again, the bridge's node back in the
    robot's graph; SIGKILL of `cvxnav run --ros2` then leaves no process of it running."""
    with robot_graph(tmp_path) as (endpoint, graph), run_ros2(None, endpoint=endpoint, graph=graph,
                                                              cwd=tmp_path) as run:
        graph.wait(lambda: graph.of("cmd_vel"), timeout_s=STARTUP_S, what="the bridge's first command")
        time.sleep(1.5)  # two keep-alive periods: its watchdog is armed (a silent start is given 60 s)
        stopped = {name: stage_pids(run.pid)[name] for name in ("planner", ROS2.name)}
        for pid in stopped.values():
            os.kill(pid, signal.SIGSTOP)
        graph.wait(lambda: all(stage_pids(run.pid).get(name, pid) != pid for name, pid in stopped.items()),
                   timeout_s=STARTUP_S, what="the stopped processes to be replaced")
        graph.wait(lambda: graph.bridge_entities() == BRIDGE_GRAPH, timeout_s=STARTUP_S,
                   what="the new bridge's node in the graph")
        assert not [pid for pid in stopped.values() if alive(pid)]  # nothing stopped is left behind
        stages = {**{f"{name} (spare)": pid for name, pid in spare_pids(run.pid).items()}, **stage_pids(run.pid)}
        run.kill()  # nothing of the supervisor runs: the stages and their spares notice their parent is gone
        run.wait()
        deadline = time.monotonic() + 10.0
        while any(alive(pid) for pid in stages.values()) and time.monotonic() < deadline:
            time.sleep(0.05)
        assert not [name for name, pid in stages.items() if alive(pid)]
    log = (tmp_path / "run.log").read_text()
    for name, pid in stopped.items():
        assert f"stage {name} hung (no keep-alive for" in log and f"killing pid {pid}" in log, log[-3000:]
