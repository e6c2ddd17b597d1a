"""The monitor draws goals that replace the scenario's (a robot's /goal_pose) where it draws the world's."""

from __future__ import annotations

import numpy as np
from rerun.chunk import RrdReader

from schemas.messages import Goals, Header
from schemas.scenario import bundled_scenario
from services.monitor.rerun import MonitorCore


def test_new_goals_are_drawn_as_the_goals(tmp_path) -> None:
    path = tmp_path / "goals.rrd"
    monitor = MonitorCore.from_scenario(bundled_scenario(), record=path)
    monitor.process(topic="goals", message=Goals(header=Header(stamp_s=3.0, seq=0), goals=[(4.0, 1.0)]), now_s=0.0)
    monitor.stop(now_s=0.0)
    (entry,) = RrdReader(path).recordings()
    chunks = [chunk for chunk in RrdReader(path).stream() if chunk.entity_path == "/goals"]
    assert entry.application_id == "cvxnav" and len(chunks) == 1 and chunks[0].is_static
    positions = chunks[0].to_record_batch().column("Points2D:positions").to_pylist()
    np.testing.assert_allclose(np.asarray(positions[0]).reshape(-1, 2), [(4.0, 1.0)])
