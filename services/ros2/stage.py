"""The ROS 2 bridge as a stage core, in the sim's place for a real robot (``schemas.wiring.ROS2``).

`Ros2Bridge` does the work; this is what the one shell (``services.shell``) asks of a core: the robot's
topics come in as raw CDR (``Bridging.receive``), the pipeline's paths and ellipses as messages
(``process``), the pipeline stages' liveliness as ``stage_alive`` and a timer as ``tick``. Out go the
pipeline's scan and state, the goals of a /goal_pose, the map of a /map, and /plan and /cmd_vel as CDR
(``Raw``). A
rejected input is a ``Refusal`` on the input's port, so the shell reports it on the bridge's status
key, next to the zero /cmd_vel the robot brakes on; nothing else the bridge holds is lost.

- Until every pipeline stage's liveliness token has been seen, the bridge counts it as lost: the robot
  stands until the whole pipeline is up and has answered a scan.
- Commands follow the odometry, one per message; the timer (`TICK_S`) repeats the last one when none
  has gone out for `BridgeConfig.command_period_s` (a base times its command out, often after 0.5 s),
  and is the odometry watchdog: with no odometry for `BridgeConfig.odom_timeout_s`, a zero /cmd_vel on
  every tick.
- On stop, a last zero /cmd_vel: the robot is not left driving on the bridge's last command.
- A stage that reads the map gets it again whenever its token (re)appears.
"""

from __future__ import annotations

import logging
import math

import numpy as np
from pydantic import BaseModel

from schemas.messages import Ellipsoids, Goals, Header, SmoothPath
from schemas.scenario import Scenario
from schemas.wiring import ROS2, subscribers_of
from services.contract import Outputs, Raw, Refusal, StageInputError
from services.ros2 import typesupport
from services.ros2.bridge import BridgeConfig, BridgeOutput, Ros2Bridge
from services.ros2.interface import BRIDGE_TOPICS

logger = logging.getLogger(__name__)

TICK_S = 0.1  # the odometry watchdog's period


class BridgeStage:
    """`Ros2Bridge` behind the stage contract: ``Bridging``, ``Scheduled``, ``Watching``, ``Stopping``."""

    done = False  # a robot's run ends on SIGINT/SIGTERM, never by itself

    def __init__(self, *, config: BridgeConfig, tick_period_s: float = TICK_S) -> None:
        self.bridge = Ros2Bridge(config=config)
        self.tick_period_s = tick_period_s
        self._next_tick_s: float | None = None
        self._goals_seq = 0
        for stage in ROS2.watches:  # down until its token is seen
            self.bridge.stage_lost(stage, now_s=-math.inf)

    @classmethod
    def from_scenario(cls, scenario: Scenario, *, domain_id: int = 0, namespace: str = "/") -> BridgeStage:
        """`cvxnav service ros2 --domain-id N --namespace NS`: the robot's ROS domain and namespace."""
        return cls(config=BridgeConfig.from_scenario(scenario, domain_id=domain_id, namespace=namespace))

    @property
    def domain_id(self) -> int:
        return self.bridge.config.domain_id

    @property
    def namespace(self) -> str:
        return self.bridge.config.namespace

    # -- what the shell hands the core

    def receive(self, *, port: str, key_expr: str, payload: bytes, now_s: float) -> Outputs:
        return self._outputs(self.bridge.receive(topic=port, key_expr=key_expr, payload=payload, received_s=now_s))

    def process(self, *, topic: str, message: BaseModel, now_s: float) -> Outputs:
        if isinstance(message, SmoothPath):
            return self._outputs(self.bridge.take_path(message, received_s=now_s))
        if isinstance(message, Ellipsoids):
            return self._outputs(self.bridge.take_ellipsoids(message, received_s=now_s))
        raise StageInputError(f"the ROS 2 bridge does not handle {topic!r}")

    def stage_alive(self, *, stage: str, alive: bool, now_s: float) -> Outputs:
        if alive:
            back = stage in self.bridge.missing
            if back:
                logger.info("stage %s is up", stage)
            self.bridge.stage_back(stage)
            # The map again for a stage that reads it: its query of the latched key, one second at start,
            # may have gone unanswered on a busy machine (a map it has is ignored).
            if back and stage in subscribers_of("map") and self.bridge.map_sent:
                return [("map", self.bridge.map)]
            return []
        logger.warning("stage %s is down: the robot brakes until it is back and a fresh plan arrives", stage)
        return self._outputs(self.bridge.stage_lost(stage, now_s=now_s))

    def next_tick_s(self, *, now_s: float) -> float:
        return now_s if self._next_tick_s is None else self._next_tick_s

    def tick(self, *, now_s: float) -> Outputs:
        self._next_tick_s = now_s + self.tick_period_s
        return self._outputs(self.bridge.tick(received_s=now_s))

    def stop(self, *, now_s: float) -> Outputs:
        latencies = np.asarray(self.bridge.latencies_ms)
        if latencies.size:
            logger.info("bridge: %d answers to %d scans, scan -> path latency p50 %.0f / max %.0f ms",
                        latencies.size, self.bridge.scan_seq, np.median(latencies), latencies.max())
        return self._outputs(self.bridge.stopped(now_s=now_s))

    # -- what the core hands the shell

    def _outputs(self, out: BridgeOutput) -> Outputs:
        """The bridge's answer as the shell publishes it: pipeline messages, goals, CDR, a refusal."""
        outputs: Outputs = list(out.pipeline)
        if out.goals is not None:
            stamp_s = max(self.bridge.odom.stamp_s, 0.0) if self.bridge.odom is not None else 0.0
            outputs.append(("goals", Goals(header=Header(stamp_s=stamp_s, seq=self._goals_seq), goals=list(out.goals))))
            self._goals_seq += 1
        outputs += [(name, Raw(typesupport.encode(message, BRIDGE_TOPICS[name].msgtype))) for name, message in out.ros]
        if out.error is not None:
            outputs.append((out.refused, Refusal(out.error)))
        return outputs
