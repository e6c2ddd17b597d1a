"""Real scans through the bridge into the sensing stage: the ACES corridors, people, glass and all.

The log's first 120 scans (its first ~230 s: the robot leaves its start room and drives the first
corridor) go through the bridge and the sensing core as the pipeline would run them.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from ros2_bag import aces_bag_dir, read_mcap
from schemas.scenario import load_scenario
from services.ros2.bridge import BridgeConfig, Ros2Bridge
from services.sensing.stage import SensingStage

SCENARIO = Path(__file__).resolve().parents[1] / "data" / "aces-bridge.json"
SCANS = 120


@pytest.fixture(scope="module")
def sensed(shared_dir):
    scenario = load_scenario(SCENARIO)
    bridge = Ros2Bridge(config=BridgeConfig.from_scenario(scenario))
    sensing = SensingStage.from_scenario(scenario)
    scans, cluster_sets = [], []
    for recorded in read_mcap(aces_bag_dir(shared_dir) / "aces-bag.mcap"):
        topic = recorded.topic.strip("/")
        output = bridge.receive(topic=topic, key_expr=bridge.keys[topic], payload=recorded.data, received_s=0.0)
        assert output.error is None
        for name, message in output.pipeline:
            if name == "scan":
                scans.append(message)
                ((_, clusters),) = sensing.process(topic="scan", message=message, now_s=0.0)  # raises if rejected
                cluster_sets.append(clusters)
        if len(scans) == SCANS:
            break
    return scenario, scans, cluster_sets, sensing


def test_the_sensing_stage_takes_every_real_scan(sensed) -> None:
    scenario, scans, cluster_sets, sensing = sensed
    assert len(cluster_sets) == SCANS
    assert all(0 < len(scan.points) <= scenario.sensor.rays for scan in scans)
    final = cluster_sets[-1].clusters
    assert len(final) >= 10 and sum(len(c.points) for c in final) == len(sensing.memory)
    # Isolated returns (people, glass, spurious points) stay in as small clusters of their own.
    assert any(len(c.points) == 1 for c in final)


def test_what_is_remembered_was_seen_within_the_sensors_range(sensed) -> None:
    scenario, scans, _, sensing = sensed
    poses = np.array([(s.pose.x_m, s.pose.y_m) for s in scans])
    points = sensing.memory.points()
    nearest = np.min(np.linalg.norm(points[:, None, :] - poses[None, :, :], axis=2), axis=1)
    assert nearest.max() <= scenario.sensor.range + 1e-9
