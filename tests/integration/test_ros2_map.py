"""A robot's /map through the pipeline, over real Zenoh sessions on loopback: the bridge and the four
pipeline stages each in their own thread and session, joined through a router as `cvxnav run --ros2`
joins the robot's. The robot's side is a ROS node that publishes the depot's map_server map on /map
(transient local, before the bridge is up), odometry at depot-1's start and scans with no return, so the
map's walls are the only obstacles; /plan is decoded with mcap-ros2-support. The ellipsoid stage starts
only once the map has gone out on the pipeline's key: it gets it as a latched topic's late subscriber."""

from __future__ import annotations

import dataclasses
import math
import threading
import time
from collections.abc import Callable

import numpy as np
import pytest
import zenoh

from cvxnav.supervisor import free_ports
from ros2_bag import independent_decoder
from ros2_messages import laser_scan, map_server_grid, odometry
from schemas.messages import Ellipsoids, Map, decode
from schemas.occupancy import load_map
from schemas.scenario import load_scenario
from schemas.wiring import PIPELINE, ROS2, default_prefix, key
from services.convert import ellipses_from_msgs, grid_from_msg
from services.ellipsoids.stage import MAP_CLUSTER_ID, EllipsoidsStage
from services.geometry import EllipseStack
from services.planner.stage import PlannerStage
from services.ros2.interface import BRIDGE_TOPICS
from services.ros2.stage import BridgeStage
from services.sensing.stage import SensingStage
from services.shell.ros2 import RosNode
from services.shell.stage import run_stage
from services.shell.zenoh_config import build_zenoh_config
from services.smoother.stage import SmootherStage

WAIT_S = 60.0  # a first plan on a loaded 2-core machine: the map's tiles fitted, a route round the shelves
DOMAIN = 5
PREFIX = default_prefix(robot_id="maprobot")
START = (9.675, 5.875, 0.1573)  # depot-1's start
GOAL = (16.89, 2.57)  # 8 m on: the straight line runs through the depot's shelves
CORES = {"sensing": SensingStage, "ellipsoids": EllipsoidsStage, "planner": PlannerStage, "smoother": SmootherStage}


def wait_for(items: list, match: Callable[[object], bool], *, what: str, tick: Callable[[], None]) -> object:
    deadline = time.monotonic() + WAIT_S
    while time.monotonic() < deadline:
        for item in list(items):
            if match(item):
                return item
        tick()
    pytest.fail(f"no {what} within {WAIT_S} s")


def test_a_map_on_rmw_zenohs_key_reaches_the_ellipsoid_stage_and_the_plans_keep_clear_of_its_walls(shared_dir):
    depot_yaml = shared_dir / "maps" / "depot.yaml"
    depot = load_map(depot_yaml)
    base = load_scenario(shared_dir / "map-scenarios" / "depot-1.json")
    scenario = base.model_copy(update={"obstacles": [], "goals": [GOAL],
                                       "sensor": base.sensor.model_copy(update={"range": 10.0})})
    endpoint = f"tcp/127.0.0.1:{free_ports(1)[0]}"
    stop = threading.Event()
    received: dict[str, list] = {"plan": [], "ellipsoids": [], "map": []}
    plan_decoder = independent_decoder(BRIDGE_TOPICS["plan"].msgtype)
    with zenoh.open(build_zenoh_config(listen=[endpoint], mode="router")), \
            zenoh.open(build_zenoh_config(connect=[endpoint])) as session:
        subscribers = [
            session.declare_subscriber(f"{DOMAIN}/plan/**",
                                       lambda s: received["plan"].append(plan_decoder(s.payload.to_bytes()))),
            session.declare_subscriber(key(PREFIX, "ellipsoids"), lambda s: received["ellipsoids"].append(
                decode(Ellipsoids, s.payload.to_bytes(), encoding=str(s.encoding)))),
            session.declare_subscriber(key(PREFIX, "map"), lambda s: received["map"].append(
                decode(Map, s.payload.to_bytes(), encoding=str(s.encoding)))),
        ]
        node = RosNode(session, name="map_server", domain_id=DOMAIN)
        publishers = {name: node.publisher(topic=topic.name, msgtype=topic.msgtype, type_hash=topic.type_hash,
                                           qos=topic.qos)
                      for name, topic in BRIDGE_TOPICS.items() if topic.direction == "in"}
        publishers["map"].put(map_server_grid(depot_yaml))  # latched: the bridge, not up yet, queries it

        cores = {name: CORES[name].from_scenario(scenario) for name in PIPELINE}
        # The map's walls within 10 m: the whole way to the goal 8 m on.
        cores["ellipsoids"].config = dataclasses.replace(cores["ellipsoids"].config, map_window_m=10.0)
        cores[ROS2.name] = BridgeStage.from_scenario(scenario, domain_id=DOMAIN)
        threads = {name: threading.Thread(target=run_stage, name=f"stage-{name}", daemon=True, kwargs=dict(
            stage=name, core=core, session_config=build_zenoh_config(connect=[endpoint]), prefix=PREFIX,
            stop_event=stop)) for name, core in cores.items()}
        for name, thread in threads.items():
            if name != "ellipsoids":
                thread.start()
        clock = {"t_s": 100.0}

        def robot_tick() -> None:
            """One odometry at the start and a scan of nothing (every ray no return), at 5 Hz."""
            clock["t_s"] += 0.2
            x, y, yaw = START
            publishers["odom"].put(odometry(x=x, y=y, yaw=yaw, t_s=clock["t_s"]))
            publishers["scan"].put(laser_scan(np.full(scenario.sensor.rays, np.inf), t_s=clock["t_s"],
                                              angle_min=-math.pi / 2, angle_increment=math.pi / scenario.sensor.rays))
            time.sleep(0.2)

        try:
            sent = wait_for(received["map"], lambda m: True, what="map on the pipeline's key", tick=robot_tick)
            np.testing.assert_array_equal(grid_from_msg(sent).state, depot.state)
            threads["ellipsoids"].start()
            walls = wait_for(received["ellipsoids"], lambda e: any(x.cluster_id == MAP_CLUSTER_ID for x in e.ellipsoids),
                             what="ellipsoids with the map's walls", tick=robot_tick)
            # A plan of a scan answered before the walls came (the stage's ask of the latched map may go
            # before its session's routes are up: then the map comes with its next message) knew none.
            plan = wait_for(received["plan"], lambda p: len(p.poses) > 1 and p.header.stamp.sec
                            + 1e-9 * p.header.stamp.nanosec >= walls.header.stamp_s - 1e-6, what="plan", tick=robot_tick)
        finally:
            stop.set()
            for thread in threads.values():
                if thread.is_alive():
                    thread.join(10.0)
            node.close()
            for subscriber in subscribers:
                subscriber.undeclare()

    # The ellipsoid stage sent the map's walls round the robot: the shelves the straight line meets among them.
    stack = EllipseStack.of(ellipses_from_msgs([e for e in walls.ellipsoids if e.cluster_id == MAP_CLUSTER_ID]))
    straight = np.linspace(START[:2], GOAL, 200)
    blocked = straight[depot.clearance(straight) == 0.0]
    assert len(blocked) and np.all(stack.levels(blocked).min(axis=1) < 1.0)
    # The robot's /plan goes round them: from the robot to the goal, the margin kept from every wall.
    points = np.array([(p.pose.position.x, p.pose.position.y) for p in plan.poses])
    assert plan.header.frame_id == "odom"
    assert np.linalg.norm(points[0] - START[:2]) < 0.05 and np.linalg.norm(points[-1] - GOAL) <= scenario.goal_tolerance
    assert depot.clearance(points).min() >= scenario.inflation_m
