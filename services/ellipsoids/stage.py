"""The ellipsoid stage core: Clusters → Ellipsoids (fit, split, group, grow).

Each cluster is covered by a few tight ellipses (`cover_points`), the ellipses whose gap is
narrower than the robot's passage 2·inflation are grouped (the paper's eq. 3), and every ellipse is
grown by inflation = width/2 + safety_distance so the planner can treat the robot as a point.

Fits, and the grown ellipses, are cached by cluster content: the sensing stage sends unchanged clusters byte-identical, and
most of the map is unchanged from one scan to the next, so only new or grown clusters are refitted.

A Clusters message holds at most as many points as the sensing stage remembers, all within the
sensor's reach of the map (``services.limits``). Degenerate clusters (one point, all points equal,
collinear: a wall seen edge-on) are real obstacles and are covered like any other.
"""

from __future__ import annotations

import hashlib
from collections import OrderedDict
from dataclasses import dataclass

import numpy as np
from pydantic import BaseModel

from cvxnav.geometry import Ellipse
from cvxnav.runtime import Outputs, StageInputError
from schemas.messages import Clusters, Ellipsoids
from schemas.scenario import Scenario
from services.convert import answer_header, ellipse_to_msg
from services.ellipsoids.cover import cover_points
from services.ellipsoids.gap import group_ellipses
from services.limits import MAX_SENSED_POINTS, Reach, check_count


@dataclass(frozen=True)
class EllipsoidsConfig:
    inflation_m: float  # width/2 + safety_distance: how much each fitted ellipse is grown
    reach: Reach
    max_points: int = MAX_SENSED_POINTS  # over all clusters of one message
    tolerance_m: float = 0.1  # how far a fitted ellipse may stick out of its points
    max_pieces: int = 32  # ellipses per cluster at most
    cache_size: int = 1024  # clusters whose fits are remembered

    @property
    def min_gap_m(self) -> float:
        """Ellipses closer than the robot's passage width are one obstacle to the planner."""
        return 2.0 * self.inflation_m

    @classmethod
    def from_scenario(cls, scenario: Scenario) -> EllipsoidsConfig:
        return cls(inflation_m=scenario.inflation_m, reach=Reach.of(scenario))


class EllipsoidsStage:
    def __init__(self, *, config: EllipsoidsConfig) -> None:
        self.config = config
        self._fits: OrderedDict[bytes, list[tuple[Ellipse, Ellipse]]] = OrderedDict()  # (fitted, grown) pieces
        self._seq = 0

    @classmethod
    def from_scenario(cls, scenario: Scenario) -> EllipsoidsStage:
        return cls(config=EllipsoidsConfig.from_scenario(scenario))

    def _cover(self, points: np.ndarray) -> list[tuple[Ellipse, Ellipse]]:
        """The cluster's cover, each piece with its grown ellipse (both cached by the points' content)."""
        digest = hashlib.blake2b(points.tobytes(), digest_size=16).digest()
        if digest in self._fits:
            self._fits.move_to_end(digest)
            return self._fits[digest]
        fitted = [(piece, piece.grown(self.config.inflation_m)) for piece in
                  cover_points(points, tolerance_m=self.config.tolerance_m, max_pieces=self.config.max_pieces)]
        self._fits[digest] = fitted
        while len(self._fits) > self.config.cache_size:
            self._fits.popitem(last=False)
        return fitted

    def process(self, *, topic: str, message: BaseModel, now_s: float) -> Outputs:
        if not isinstance(message, Clusters):
            raise StageInputError(f"ellipsoids does not handle {topic!r}")
        check_count(sum(len(c.points) for c in message.clusters), limit=self.config.max_points,
                    what="cluster points")
        clouds = []
        for cluster in message.clusters:
            if not cluster.points:  # the schema forbids it; a hand-built message may not
                raise StageInputError(f"cluster {cluster.cluster_id} has no points")
            points = np.asarray(cluster.points, dtype=float).reshape(-1, 2)
            self.config.reach.check_points(points, what=f"cluster {cluster.cluster_id}")
            clouds.append((cluster.cluster_id, points))
        raw: list[Ellipse] = []
        grown: list[Ellipse] = []
        cluster_ids: list[int] = []
        for cluster_id, points in clouds:
            for piece, piece_grown in self._cover(points):
                raw.append(piece)
                grown.append(piece_grown)
                cluster_ids.append(cluster_id)
        # A cluster is one obstacle, so its pieces share a group from the start (the default sensing
        # links points closer than r, so adjacent pieces are closer than the passage 2 r anyway); only
        # pairs across clusters are examined.
        labels = group_ellipses(raw, min_gap_m=self.config.min_gap_m, connected=np.array(cluster_ids, dtype=int))
        out = Ellipsoids(
            header=answer_header(scan_header=message.header, seq=self._seq),
            scan_seq=message.scan_seq,
            inflation_m=self.config.inflation_m,
            ellipsoids=[
                ellipse_to_msg(ellipse, group=int(label), cluster_id=cid)
                for ellipse, label, cid in zip(grown, labels, cluster_ids)
            ],
        )
        self._seq += 1
        return [("ellipsoids", out)]
