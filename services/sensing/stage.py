"""The sensing stage core: Scan → Clusters.

Every scan's hits go into a `PointMemory` (obstacles behind the 180° sensor stay known), and all the
remembered points are clustered anew by single linkage. Each cluster's points are sorted, and the
clusters ordered by their first point, so the same memory always yields the same message: the next
stage can then recognise an unchanged cluster by its content and skip refitting it. A scan that
occupies no new voxel leaves the memory's point set, and so its clusters, as they were: they are reused.

A scan is checked before it is remembered (``services.limits``): at most one hit per ray, the pose
inside the map, every hit within the sensor's range of it (10 % slack for range noise). Anything
else would stay in the memory for good, so it is rejected whole.

The memory is the one state of the pipeline that no later input restores (a point out of view is not
seen again): it is the core's `state()`, which the shell checkpoints after every scan that adds to it,
before the clusters that depend on it are published, and hands a restarted stage's `restore()`.
"""

from __future__ import annotations

import io
from dataclasses import dataclass

import numpy as np
from pydantic import BaseModel

from schemas.messages import ClusterMsg, Clusters, Scan
from schemas.scenario import Scenario
from services.contract import Outputs, StageInputError, StateError
from services.convert import answer_header
from services.geometry import PointMemory
from services.limits import MAX_SENSED_POINTS, Reach, check_count
from services.sensing.core import cluster_points

RANGE_SLACK = 1.1  # a hit may be measured this factor beyond the sensor's range (noise)


@dataclass(frozen=True)
class SensingConfig:
    link_m: float  # single-linkage distance: points closer than this share an obstacle
    reach: Reach
    max_scan_points: int  # the sensor's rays: one hit each at most
    max_range_m: float  # farthest a hit may lie from the scan's pose
    voxel_m: float = 0.05
    max_points: int = MAX_SENSED_POINTS

    @classmethod
    def from_scenario(cls, scenario: Scenario) -> SensingConfig:
        """Link at the robot's inflation, half its passage width 2·(width/2 + safety_distance).

        Any link up to the passage width loses no path (see `cluster_points`); half of it keeps
        clusters small, so a new hit changes (and forces a refit of) less of the map, while gaps
        between half and the full passage width are still closed by the ellipsoid stage's grouping.
        """
        return cls(link_m=scenario.inflation_m, reach=Reach.of(scenario), max_scan_points=scenario.sensor.rays,
                   max_range_m=RANGE_SLACK * float(scenario.sensor.range))


class SensingStage:
    def __init__(self, *, config: SensingConfig) -> None:
        self.config = config
        self.memory = PointMemory(voxel_m=config.voxel_m, max_points=config.max_points)
        # Reused while a scan adds no voxel (a still robot, a re-sent scan): the clusters cannot change.
        self._clusters: list[ClusterMsg] | None = None
        self._seq = 0
        self._state: bytes | None = None  # the memory as `state()` last saw it; None once it changed

    @classmethod
    def from_scenario(cls, scenario: Scenario) -> SensingStage:
        return cls(config=SensingConfig.from_scenario(scenario))

    def state(self) -> bytes:
        """The remembered points least recently observed first, as `.npy` bytes: adding them back in that
        order rebuilds the same voxels (each point is its voxel's representative) in the same age order.

        Taken when a scan adds to the memory, so a scan that only re-observes points changes nothing to save.
        """
        if self._state is None:
            buffer = io.BytesIO()
            np.save(buffer, self.memory.points(), allow_pickle=False)
            self._state = buffer.getvalue()
        return self._state

    def restore(self, data: bytes) -> None:
        try:
            points = np.load(io.BytesIO(data), allow_pickle=False)
        except (ValueError, EOFError) as error:
            raise StateError(f"not a point checkpoint: {error}") from None
        if points.ndim != 2 or points.shape[1] != 2 or not np.all(np.isfinite(points)):
            raise StateError(f"expected finite (n, 2) points, got shape {points.shape}")
        self.memory.add(points)
        self._state = None

    def process(self, *, topic: str, message: BaseModel, now_s: float) -> Outputs:
        if not isinstance(message, Scan):
            raise StageInputError(f"sensing does not handle {topic!r}")
        if message.header.frame_id != "map":
            raise StageInputError(f"scan points must be in the map frame, got frame_id={message.header.frame_id!r}")
        if self.memory.add(self._checked_hits(message)) or self._clusters is None:
            self._state = None
            self._clusters = self._clustered()
        out = Clusters(
            header=answer_header(scan_header=message.header, seq=self._seq),
            scan_seq=message.header.seq,
            clusters=self._clusters,
        )
        self._seq += 1
        return [("clusters", out)]

    def _clustered(self) -> list[ClusterMsg]:
        """The memory's clusters, in canonical order (independent of the order points were remembered)."""
        clusters = []
        for points in cluster_points(self.memory.points(), link_m=self.config.link_m):
            ordered = points[np.lexsort((points[:, 1], points[:, 0]))]
            clusters.append(ordered)
        clusters.sort(key=lambda c: (c[0, 0], c[0, 1]))
        return [ClusterMsg(cluster_id=index, points=[(float(x), float(y)) for x, y in points], solid=False)
                for index, points in enumerate(clusters)]

    def _checked_hits(self, scan: Scan) -> np.ndarray:
        config = self.config
        check_count(len(scan.points), limit=config.max_scan_points, what="scan points")
        config.reach.check_pose(scan.pose, what="scan")
        hits = np.asarray(scan.points, dtype=float).reshape(-1, 2)
        if len(hits):
            distance = np.hypot(hits[:, 0] - scan.pose.x_m, hits[:, 1] - scan.pose.y_m)
            k = int(np.argmax(distance))
            if distance[k] > config.max_range_m:
                raise StageInputError(f"scan point {k} lies {distance[k]:.6g} m from the pose, beyond the "
                                      f"sensor's range ({config.max_range_m:g} m with slack)")
        return hits
