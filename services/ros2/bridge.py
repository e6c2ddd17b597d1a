"""The ROS 2 bridge core: a robot's ROS topics in, the pipeline's messages out, and back (no I/O).

It takes the place of the sim for a real robot (CONTRACTS.md §6). In: ``/scan`` (LaserScan), ``/odom``
(Odometry), ``/goal_pose`` (PoseStamped), ``/map`` (OccupancyGrid), each as the raw sample rmw_zenoh
delivers (key expression + CDR payload), and from the pipeline ``smooth_path`` and ``ellipsoids``.
Out: the pipeline's ``scan`` and ``state``, and ``/plan`` (nav_msgs/Path) and ``/cmd_vel`` (Twist).

- A scan becomes world-frame hits from the robot's pose at its stamp, interpolated between the
  odometry on either side (each within `BridgeConfig.max_pose_age_s`; a scan that arrives before the
  odometry after it waits for it as long, as tf's message filter waits for a transform): the laser
  sits at the robot's reference point looking along its heading (no TF), ray i at
  ``angle_min + i·angle_increment``. A ray with no return is
  dropped: inf or NaN, below ``range_min``, above ``range_max``, or beyond the scenario sensor's range
  (the range the planner's memory and checks assume).
- Each odometry message gives the robot state and one ``/cmd_vel``, so commands flow at the odometry
  rate: the sim's path tracker (`services.drive.controller.PurePursuit`) on the verified path, turned
  into the body twist that drives the footprint centre on the same arc, or zero when braking. The
  robot brakes with no verified path, on a plan older than `BridgeConfig.stale_after_s` (robot time),
  while a stage is down (then until a plan answers a scan sent after it is back), when the odometry
  falls silent (`tick`), and after any rejected input, until the next verified plan.
- Every path is checked before it is followed by the sim's guard (`services.drive.guard.PathGuard`:
  the map's bounds, the robot's own scan hits, the newest grown ellipses) from where the robot is, and
  re-checked when a scan or newer ellipses arrive. A path waits (`held`) until the guard knows the
  ellipses of its own scan and of every scan received `BridgeConfig.guard_window_s` before: a robot that
  has driven into view of an obstacle for that long is not handed a path checked only against older
  ellipses. The bounds and the robot's own hits need no message: no forged ellipse set can blind them.

Rejected, with a one-line reason in `BridgeOutput.error` (the bridge brakes and carries on): a key
whose type or hash is not the topic's, malformed CDR, a scan with more rays than the scenario's sensor,
non-finite poses or twists, an odometry frame that changes mid-run, a goal or map in another frame.

A /map (OccupancyGrid) becomes the pipeline's ``map`` (`schemas.messages.Map`, for the ellipsoid stage):
cells free, occupied or unknown by map_server's default thresholds (`OccupancyGrid.from_values`), sent
once the odometry's frame is known and equal to the map's.
"""

from __future__ import annotations

import math
from collections import OrderedDict, deque
from dataclasses import dataclass, field

import numpy as np

from schemas.messages import Ellipsoids, Header, Map, Point, Pose2D, RobotState, Scan, SmoothPath
from schemas.occupancy import MapError, OccupancyGrid
from schemas.scenario import Scenario
from services.contract import StageInputError
from services.convert import grid_to_msg
from services.drive.controller import GoalTracker, PurePursuit
from services.drive.guard import PathGuard, ahead
from services.drive.vehicle import VehicleLimits, VehicleState
from services.limits import DEFAULT_MAX_PAYLOAD_BYTES, Reach, check_count
from services.ros2 import typesupport
from services.ros2.interface import BRIDGE_TOPICS, MAX_MAP_CELLS
from services.ros2.wire import node_namespace, resolve_topic, topic_key

_SCANS_KEPT = 256  # recent scans' stamps and receive times, by seq (the paths that answer them)
_ODOMETRY_KEPT = 256  # recent odometry, to place a scan at the pose of its stamp


@dataclass(frozen=True)
class BridgeConfig:
    domain_id: int
    namespace: str  # absolute, e.g. "/" or "/robot1"
    max_rays: int  # the scenario sensor's rays: a LaserScan with more is refused
    max_range_m: float  # the scenario sensor's range: farther returns are no return
    reach: Reach
    goals: tuple[Point, ...]
    goal_tolerance_m: float
    limits: VehicleLimits
    inflation_m: float
    keep_out_m: float
    stale_after_s: float = 1.5  # robot time: a plan answering an older scan is not followed
    max_pose_age_s: float = 0.5  # a scan is placed with odometry at most this far from it in time, and waits as long
    # Receive clock: a path waits for the ellipses of every scan received this long before (half a second,
    # less a tenth for the network between the robot's other nodes and the bridge).
    guard_window_s: float = 0.4
    odom_timeout_s: float = 1.0  # receive clock: odometry silent this long, the robot brakes
    command_period_s: float = 0.5  # receive clock: the longest between two /cmd_vel (a base's usual timeout)

    @classmethod
    def from_scenario(cls, scenario: Scenario, *, domain_id: int = 0, namespace: str = "/") -> BridgeConfig:
        """A plan stays in force three scan periods at least (a slow laser is not a stale plan)."""
        period_s = 1.0 / float(scenario.sensor.rate_hz)
        return cls(domain_id=domain_id, namespace=node_namespace(namespace), max_rays=scenario.sensor.rays,
                   max_range_m=float(scenario.sensor.range), reach=Reach.of(scenario),
                   goals=tuple(tuple(g) for g in scenario.goals), goal_tolerance_m=float(scenario.goal_tolerance),
                   limits=VehicleLimits.from_scenario(scenario), inflation_m=scenario.inflation_m,
                   keep_out_m=scenario.keep_out_m, stale_after_s=max(1.5, 3.0 * period_s))

    def key(self, topic: str) -> str:
        """The data key of one of the bridge's topics (`BRIDGE_TOPICS`) in this domain and namespace."""
        spec = BRIDGE_TOPICS[topic]
        return topic_key(domain_id=self.domain_id, topic=resolve_topic(spec.name, namespace=self.namespace),
                         msgtype=spec.msgtype, type_hash=spec.type_hash)


@dataclass
class BridgeOutput:
    """What one input produced: pipeline messages by topic, ROS messages by bridge topic, and a verdict."""

    pipeline: list[tuple[str, Scan | RobotState | Map]] = field(default_factory=list)
    ros: list[tuple[str, object]] = field(default_factory=list)  # (BRIDGE_TOPICS name, rosbags message)
    error: str | None = None  # why the input was rejected (one line); the robot brakes
    refused: str | None = None  # the input topic the error is about
    goals: tuple[Point, ...] | None = None  # new goals from /goal_pose, for the planner


@dataclass(frozen=True)
class _Odometry:
    pose: Pose2D
    speed_mps: float
    stamp_s: float
    received_s: float


@dataclass(frozen=True)
class _Waiting:
    """A scan not yet placed: the odometry from after its stamp has not arrived yet."""

    message: object
    stamp_s: float
    received_s: float


@dataclass(frozen=True)
class _ScanRecord:
    stamp: object  # the scan's builtin_interfaces/Time, reused for the /plan that answers it
    stamp_s: float
    received_s: float


def ros_time_s(stamp: object) -> float:
    return float(stamp.sec) + 1e-9 * float(stamp.nanosec)


def yaw_of(q: object) -> float:
    """Heading (rotation about z) of a unit quaternion; the robot is taken to drive on the plane."""
    return math.atan2(2.0 * (q.w * q.z + q.x * q.y), 1.0 - 2.0 * (q.y * q.y + q.z * q.z))


def scan_hits(scan: object, *, pose: Pose2D, max_range_m: float) -> np.ndarray:
    """World-frame hits (k, 2) of a LaserScan taken at ``pose``, no-return rays dropped."""
    ranges = np.asarray(scan.ranges, dtype=float)
    angles = scan.angle_min + scan.angle_increment * np.arange(len(ranges))
    with np.errstate(invalid="ignore"):  # NaN ranges compare false: no return
        valid = (np.isfinite(ranges) & (ranges >= scan.range_min) & (ranges <= scan.range_max)
                 & (ranges <= max_range_m))
    r, heading = ranges[valid], pose.theta_rad + angles[valid]
    return np.column_stack([pose.x_m + r * np.cos(heading), pose.y_m + r * np.sin(heading)])


def body_twist(*, speed_mps: float, steering_rad: float, wheelbase_m: float) -> tuple[float, float]:
    """(forward speed, yaw rate) that drive the footprint centre on the arc the bicycle's steering gives.

    At steering δ the centre (L/2 ahead of the rear axle) turns with curvature 2 sin β / L, β =
    atan(tan δ / 2) (the slip angle at the centre): a robot that takes a body twist, a differential
    drive as much as a car's base controller, follows that arc with ω = v κ.
    """
    beta = math.atan(0.5 * math.tan(steering_rad))
    return speed_mps, speed_mps * 2.0 * math.sin(beta) / wheelbase_m


class Ros2Bridge:
    """The bridge's state: the odometry frame and pose, the goals, the guard, the path being followed."""

    def __init__(self, *, config: BridgeConfig) -> None:
        self.config = config
        self.keys = {name: config.key(name) for name, spec in BRIDGE_TOPICS.items() if spec.direction == "in"}
        self.tracker = PurePursuit.from_limits(config.limits)
        self.goals = GoalTracker(goals=config.goals, tolerance_m=config.goal_tolerance_m)
        self.guard = PathGuard(inflation_m=config.inflation_m, keep_out_m=config.keep_out_m,
                               bounds_min=config.reach.bounds_min, bounds_max=config.reach.bounds_max)
        self.frame_id: str | None = None  # the odometry's frame, latched from the first message
        self.odom: _Odometry | None = None  # the newest
        self.odometry: deque[_Odometry] = deque(maxlen=_ODOMETRY_KEPT)
        self.waiting: deque[_Waiting] = deque()  # scans in arrival order, waiting for their odometry
        self.steering_rad = 0.0  # the tracker's model of the wheels, moved at the steering rate limit
        self.scan_seq = 0  # the next scan's seq
        self.scans: OrderedDict[int, _ScanRecord] = OrderedDict()
        self.path: np.ndarray | None = None
        self.held: tuple[SmoothPath, _ScanRecord, np.ndarray] | None = None  # a path waiting for its ellipses
        self.path_stamp_s = -math.inf  # the stamp of the scan the path answers
        self.progress_m: float | None = None
        self.resume_seq = 0  # answers to earlier scans are not followed (after a lost stage, a new goal)
        self.missing: set[str] = set()  # pipeline stages whose liveliness token is gone
        self.braking_reason = "no verified path yet"
        self.last_command = self._twist(0.0, 0.0)  # the newest /cmd_vel, and when it went out
        self.commanded_s = -math.inf
        self.latencies_ms: list[float] = []  # scan received → its smooth path received
        self.map_frame_id: str | None = None  # the frame of the newest /map
        self.map: Map | None = None  # the newest /map, for the pipeline
        self.map_sent = False  # ... gone out (it waits for the odometry whose frame it must share)

    # ----------------------------------------------------------------------- ROS inputs

    def receive(self, *, topic: str, key_expr: str, payload: bytes, received_s: float) -> BridgeOutput:
        """One sample from ``topic`` (a `BRIDGE_TOPICS` input): check its key, decode it, act on it."""
        try:
            expected = self.keys[topic]
            if str(key_expr) != expected:
                raise StageInputError(_wrong_key(topic, str(key_expr), expected))
            message = typesupport.decode(payload, BRIDGE_TOPICS[topic].msgtype)
            handler = {"scan": self._on_scan, "odom": self._on_odom, "goal_pose": self._on_goal,
                       "map": self._on_map}[topic]
            return handler(message, received_s=received_s)
        except (StageInputError, typesupport.CdrError) as error:
            return self._rejected(topic, f"{topic}: {error}", now_s=received_s)

    def _rejected(self, topic: str, reason: str, *, now_s: float) -> BridgeOutput:
        self.held = None
        return BridgeOutput(ros=self._brake(reason, now_s=now_s), error=reason, refused=topic)

    def _on_odom(self, message: object, *, received_s: float) -> BridgeOutput:
        frame = message.header.frame_id
        if self.frame_id is None:
            if not frame:
                raise StageInputError("header.frame_id is empty: the plans need a frame")
            if self.map_frame_id is not None and self.map_frame_id != frame:
                raise StageInputError(f"frame {frame!r} is not the map's {self.map_frame_id!r}")
            self.frame_id = frame
        elif frame != self.frame_id:
            raise StageInputError(f"header.frame_id changed from {self.frame_id!r} to {frame!r} mid-run; the "
                                  f"plans are in {self.frame_id!r}")
        p, q = message.pose.pose.position, message.pose.pose.orientation
        speed = message.twist.twist.linear.x
        values = {"x": p.x, "y": p.y, "qx": q.x, "qy": q.y, "qz": q.z, "qw": q.w, "twist.linear.x": speed}
        bad = [name for name, value in values.items() if not math.isfinite(value)]
        if bad:
            raise StageInputError(f"pose/twist not finite: {', '.join(f'{n}={values[n]}' for n in bad)}")
        if q.x * q.x + q.y * q.y + q.z * q.z + q.w * q.w < 1e-12:
            raise StageInputError("pose.orientation is a zero quaternion")
        pose = Pose2D(x_m=float(p.x), y_m=float(p.y), theta_rad=yaw_of(q))
        self.config.reach.check_pose(pose, what="odom")
        stamp_s = ros_time_s(message.header.stamp)
        dt_s = stamp_s - self.odom.stamp_s if self.odom is not None else 0.0
        self.odom = _Odometry(pose=pose, speed_mps=float(speed), stamp_s=stamp_s, received_s=received_s)
        self.odometry.append(self.odom)
        self.goals.update(x_m=pose.x_m, y_m=pose.y_m)
        out = BridgeOutput(pipeline=self._map_out() + self._planning(self._state()),
                           ros=self._send(self._command(dt_s=min(max(dt_s, 0.0), 1.0), now_s=received_s),
                                          now_s=received_s))
        placed = self._place_scans(now_s=received_s)  # scans that waited for this odometry
        out.pipeline += placed.pipeline
        out.ros += placed.ros
        out.error, out.refused = placed.error, placed.refused
        return out

    def _on_scan(self, message: object, *, received_s: float) -> BridgeOutput:
        check_count(len(message.ranges), limit=self.config.max_rays, what="rays (the scenario's sensor.rays)")
        fields = {name: getattr(message, name) for name in ("angle_min", "angle_increment", "range_min", "range_max")}
        bad = [f"{name}={value}" for name, value in fields.items() if not math.isfinite(value)]
        if bad:
            raise StageInputError(f"not finite: {', '.join(bad)}")
        stamp_s = ros_time_s(message.header.stamp)
        if stamp_s < 0.0:
            raise StageInputError(f"header.stamp {stamp_s:.9g} s is negative")
        self.waiting.append(_Waiting(message=message, stamp_s=stamp_s, received_s=received_s))
        return self._place_scans(now_s=received_s)

    def _place_scans(self, *, now_s: float) -> BridgeOutput:
        """The waiting scans that the odometry now places, in order (`_pose_at`); the first that no
        odometry will place any more is rejected."""
        out = BridgeOutput()
        while self.waiting:
            scan = self.waiting[0]
            # Final once the odometry from after it has come (it comes in order) or it has waited long enough.
            final = (now_s - scan.received_s > self.config.max_pose_age_s
                     or (self.odom is not None and self.odom.stamp_s >= scan.stamp_s))
            pose = self._pose_at(scan.stamp_s, final=final)
            if pose is None and not final:
                break
            self.waiting.popleft()
            if pose is not None:
                out.pipeline += self._placed(scan, pose=pose)
                out.ros += self._recheck("its own scan", now_s=now_s)
                continue
            rejected = self._rejected("scan", f"scan: {self._unplaced(scan.stamp_s)}", now_s=now_s)
            rejected.pipeline = out.pipeline
            return rejected
        return out

    def _pose_at(self, stamp_s: float, *, final: bool) -> Pose2D | None:
        """The robot's pose at ``stamp_s``, interpolated between the odometry on either side of it, as tf
        looks a transform up at a scan's stamp; None while odometry from after it may still come.

        Both sides must lie within `max_pose_age_s` of it (one side only: its pose). Once no odometry
        nearer after it can come (``final``), the odometry from before it alone places it."""
        max_age_s = self.config.max_pose_age_s
        before = max((o for o in self.odometry if o.stamp_s <= stamp_s), key=lambda o: o.stamp_s, default=None)
        after = min((o for o in self.odometry if o.stamp_s >= stamp_s), key=lambda o: o.stamp_s, default=None)
        before = before if before is not None and stamp_s - before.stamp_s <= max_age_s else None
        after = after if after is not None and after.stamp_s - stamp_s <= max_age_s else None
        if after is None:
            return before.pose if final and before is not None else None
        if before is None or after.stamp_s == before.stamp_s:
            return after.pose
        w = (stamp_s - before.stamp_s) / (after.stamp_s - before.stamp_s)
        a, b = before.pose, after.pose
        turn = math.remainder(b.theta_rad - a.theta_rad, 2.0 * math.pi)
        return Pose2D(x_m=a.x_m + w * (b.x_m - a.x_m), y_m=a.y_m + w * (b.y_m - a.y_m),
                      theta_rad=math.remainder(a.theta_rad + w * turn, 2.0 * math.pi))

    def _unplaced(self, stamp_s: float) -> str:
        """Why no odometry places a scan stamped ``stamp_s``."""
        if not self.odometry:
            return "no odometry yet to place the scan"
        nearest = min(self.odometry, key=lambda o: abs(o.stamp_s - stamp_s))
        return (f"stamped {stamp_s:.3f} s but the nearest odometry is from {nearest.stamp_s:.3f} s "
                f"({abs(nearest.stamp_s - stamp_s):.3f} s apart > max_pose_age_s {self.config.max_pose_age_s:g})")

    def _placed(self, scan: _Waiting, *, pose: Pose2D) -> list[tuple[str, Scan | RobotState]]:
        message, stamp_s, received_s = scan.message, scan.stamp_s, scan.received_s
        hits = scan_hits(message, pose=pose, max_range_m=self.config.max_range_m)
        self.guard.sense(hits)  # the path being followed is re-checked against them (`_place_scans`)
        seq = self.scan_seq
        self.scan_seq += 1
        self.scans[seq] = _ScanRecord(stamp=message.header.stamp, stamp_s=stamp_s, received_s=received_s)
        while len(self.scans) > _SCANS_KEPT:
            self.scans.popitem(last=False)
        scan = Scan(header=Header(stamp_s=stamp_s, seq=seq), pose=pose,
                    points=[(float(x), float(y)) for x, y in hits])
        return [*self._planning(self._state(pose=pose)), ("scan", scan)]

    def _on_goal(self, message: object, *, received_s: float) -> BridgeOutput:
        if self.frame_id is None:
            raise StageInputError("no odometry yet: the goal's frame cannot be checked against it")
        if message.header.frame_id != self.frame_id:
            raise StageInputError(f"frame {message.header.frame_id!r} is not the odometry's {self.frame_id!r}")
        x, y = message.pose.position.x, message.pose.position.y
        if not (math.isfinite(x) and math.isfinite(y)):
            raise StageInputError(f"pose.position not finite: x={x}, y={y}")
        self.config.reach.check_pose(Pose2D(x_m=x, y_m=y, theta_rad=0.0), what="goal")
        self.goals = GoalTracker(goals=[(float(x), float(y))], tolerance_m=self.config.goal_tolerance_m)
        return BridgeOutput(ros=self._brake(f"new goal ({x:.2f}, {y:.2f}): waiting for a plan to it", now_s=received_s,
                                            from_next_scan=True), goals=tuple(self.goals.goals))

    def _on_map(self, message: object, *, received_s: float) -> BridgeOutput:
        """A /map becomes the pipeline's `Map` (its cells free, occupied or unknown as map_server's thresholds
        read them), sent once the odometry has shown that the map is in its frame."""
        frame = message.header.frame_id
        if self.frame_id is not None and frame != self.frame_id:
            raise StageInputError(f"frame {frame!r} is not the odometry's {self.frame_id!r}")
        info = message.info
        width, height = int(info.width), int(info.height)
        check_count(width * height, limit=MAX_MAP_CELLS, what="cells")
        if width * height == 0 or len(message.data) != width * height:
            raise StageInputError(f"{len(message.data)} cells of data for a {width} x {height} grid")
        o = info.origin
        values = (info.resolution, o.position.x, o.position.y, o.orientation.z, o.orientation.w)
        if not all(math.isfinite(v) for v in values) or not info.resolution > 0.0:
            raise StageInputError(f"resolution {info.resolution} and origin must be finite, resolution positive")
        try:
            grid = OccupancyGrid.from_values(message.data, width=width, height=height,
                                             resolution_m=float(info.resolution),
                                             origin=(float(o.position.x), float(o.position.y), yaw_of(o.orientation)))
        except MapError as error:
            raise StageInputError(str(error)) from None
        stamp_s = max(ros_time_s(message.header.stamp), 0.0)
        pipeline_map = grid_to_msg(grid, header=Header(stamp_s=stamp_s, seq=0))
        size = len(pipeline_map.to_json_bytes())
        if size > DEFAULT_MAX_PAYLOAD_BYTES:
            raise StageInputError(f"the grid's cells compress to {size} bytes, more than the pipeline's "
                                  f"{DEFAULT_MAX_PAYLOAD_BYTES} a message may have")
        self.map_frame_id, self.map, self.map_sent = frame, pipeline_map, False
        return BridgeOutput(pipeline=self._map_out())

    def _map_out(self) -> list[tuple[str, Map]]:
        """The newest /map for the pipeline, once, as soon as the odometry's frame is known (it is the map's)."""
        if self.map is None or self.map_sent or self.frame_id is None:
            return []
        self.map_sent = True
        return [("map", self.map)]

    # ----------------------------------------------------------------------- pipeline inputs

    def take_ellipsoids(self, message: Ellipsoids, *, received_s: float) -> BridgeOutput:
        """Newer grown ellipses for the guard; the path being followed is re-checked against them, and a
        path held for them is checked and, if clear, published."""
        try:
            self._answering(message.scan_seq)
            self.config.reach.check_ellipses(message.ellipsoids, what="ellipsoids")
        except StageInputError as error:
            return BridgeOutput(error=f"ellipsoids: {error}", refused="ellipsoids")
        self.guard.know(message)
        braked = self._recheck("newer obstacles", now_s=received_s)  # routine: the planner replans on them
        out = self._release(received_s)
        out.ros = braked + out.ros
        return out

    def _recheck(self, what: str, *, now_s: float) -> list[tuple[str, object]]:
        """Brake if the rest of the path being followed fails the guard's check on what it now knows;
        the zero command to publish, if it does."""
        if self.path is None or self.odom is None:
            return []
        position = (self.odom.pose.x_m, self.odom.pose.y_m)
        reason = self.guard.check(ahead(self.path, position=position), start=position)
        return self._brake(f"{what}: {reason}", now_s=now_s) if reason is not None else []

    def take_path(self, message: SmoothPath, *, received_s: float) -> BridgeOutput:
        """The pipeline's answer to a scan: a path to follow (published on /plan), or a reason to brake.
        The planner's no_path while it replans in the background (``replanning``) is neither: the robot
        goes on as if the answer were still to come, as the sim does.

        A path is held until the guard knows the ellipses of its own scan and of every scan received
        `BridgeConfig.guard_window_s` before now (`_release`)."""
        try:
            record = self._answering(message.scan_seq)
        except StageInputError as error:
            return BridgeOutput(error=f"smooth_path: {error}", refused="smooth_path")
        self.latencies_ms.append(1e3 * (received_s - record.received_s))
        if self.missing or message.scan_seq < self.resume_seq:
            return BridgeOutput()
        if message.status == "no_path" and message.replanning:
            return BridgeOutput()  # no verdict yet: the path stands while it is fresh and clear, as for a late answer
        if message.status == "no_path":  # nor is a path held for an older scan followed
            self.held = None
            return BridgeOutput(ros=self._brake(f"no path: {message.reason}", now_s=received_s))
        points = np.asarray(message.points, dtype=float).reshape(-1, 2)
        if (message.goal_index != self.goals.reached_count or len(points) < 2 or self.goals.done
                or math.dist(points[-1], self.goals.goals[-1]) > self.config.goal_tolerance_m):
            return BridgeOutput()  # planned for a goal passed or replaced: keep the current path until the replan
        self.held = (message, record, points)
        return self._release(received_s)

    def _release(self, now_s: float) -> BridgeOutput:
        """The held path checked by the guard and published, once the guard is current: it knows the
        ellipses of the path's scan and of the newest scan received `guard_window_s` ago. Before that the
        obstacles of a scan the robot has had a while may still be on their way through the pipeline."""
        if self.held is None:
            return BridgeOutput()
        message, record, points = self.held
        if self.guard.scan_seq < max(message.scan_seq, self._received_by(now_s - self.config.guard_window_s)):
            return BridgeOutput()
        self.held = None
        # From where the robot is now: the planner may have planned from a pose newer than the scan's.
        reason = self.guard.check(points, start=(self.odom.pose.x_m, self.odom.pose.y_m))
        heading = self.odom.pose.theta_rad if self.odom is not None else 0.0
        if reason is None and np.dot(points[1] - points[0], (math.cos(heading), math.sin(heading))) <= 0.0:
            reason = "the path starts against the robot's heading"
        if reason is not None:
            return BridgeOutput(ros=self._brake(reason, now_s=now_s), refused="smooth_path",
                                error=f"smooth_path: plan {message.plan_id} for scan {message.scan_seq} not "
                                      f"followed: {reason}")
        self.path, self.path_stamp_s, self.progress_m = points, record.stamp_s, None
        return BridgeOutput(ros=[("plan", self._plan_message(points, stamp=record.stamp))])

    def _received_by(self, t_s: float) -> int:
        """The newest scan received by time ``t_s`` (receive clock); -1 for none."""
        return max((seq for seq, record in self.scans.items() if record.received_s <= t_s), default=-1)

    def _answering(self, seq: int) -> _ScanRecord:
        record = self.scans.get(seq)
        if record is None:
            raise StageInputError(f"answers scan {seq}, which the bridge did not send (or long ago)")
        return record

    def stage_lost(self, stage: str, *, now_s: float) -> BridgeOutput:
        """A pipeline stage's token is gone: brake, and follow only answers to scans sent from now on."""
        self.missing.add(stage)
        return BridgeOutput(ros=self._brake(f"stage {stage} is down", now_s=now_s, from_next_scan=True))

    def stage_back(self, stage: str) -> None:
        self.missing.discard(stage)

    def tick(self, *, received_s: float) -> BridgeOutput:
        """A timer: odometry silent for `odom_timeout_s` means brake, now; no /cmd_vel for
        `command_period_s` means the last one again (zero if the robot brakes since), so the base hears
        one before it times its command out; a scan that waited for its odometry longer than
        `max_pose_age_s` is rejected."""
        out = self._place_scans(now_s=received_s)
        if self.odom is None or received_s - self.odom.received_s > self.config.odom_timeout_s:
            out.ros = self._brake("no odometry", now_s=received_s)
        elif not out.ros and received_s - self.commanded_s >= self.config.command_period_s:
            driving = self.path is not None and not self.goals.done and not self.missing
            out.ros = self._send(self.last_command if driving else self._twist(0.0, 0.0), now_s=received_s)
        return out

    def stopped(self, *, now_s: float) -> BridgeOutput:
        """The bridge is stopping: the zero twist to leave the robot with."""
        return BridgeOutput(ros=self._brake("the bridge stopped", now_s=now_s))

    # ----------------------------------------------------------------------- outputs

    def _brake(self, reason: str, *, now_s: float, from_next_scan: bool = False) -> list[tuple[str, object]]:
        """Drop the path; the zero command to publish now. ``from_next_scan``: answers to scans already
        sent no longer count either (they were planned for a lost stage's pipeline or an old goal)."""
        self.path = None
        self.braking_reason = reason
        if from_next_scan:
            self.resume_seq = self.scan_seq
            self.held = None
        return self._send(self._twist(0.0, 0.0), now_s=now_s)

    def _send(self, twist: object, *, now_s: float) -> list[tuple[str, object]]:
        """A /cmd_vel to publish, remembered for the timer to repeat."""
        self.last_command, self.commanded_s = twist, now_s
        return [("cmd_vel", twist)]

    def _planning(self, state: RobotState) -> list[tuple[str, RobotState]]:
        """The state for the planner, while there is a goal to plan for (the scans go on regardless: the
        sensing stage's memory keeps growing for the next goal)."""
        return [] if self.goals.done else [("state", state)]

    def _state(self, *, pose: Pose2D | None = None) -> RobotState:
        """The robot state for the planner; its seq is the newest scan's, which the planner pairs it with."""
        odom = self.odom
        goals = self.goals
        return RobotState(header=Header(stamp_s=max(odom.stamp_s, 0.0), seq=max(self.scan_seq - 1, 0)),
                          pose=pose or odom.pose, speed_mps=odom.speed_mps, steering_rad=self.steering_rad,
                          goal_index=min(goals.reached_count, len(goals.goals) - 1),
                          goals_reached=goals.reached_count, done=goals.done)

    def _command(self, *, dt_s: float, now_s: float) -> object:
        """The tracker's twist on a fresh path, else zero; the wheels' model follows at the rate limit."""
        odom = self.odom
        age_s = odom.stamp_s - self.path_stamp_s
        if self.path is not None and not (0.0 <= age_s <= self.config.stale_after_s):
            self._brake(f"the plan is {age_s:.2f} s old (stale_after_s {self.config.stale_after_s:g})", now_s=now_s)
        if self.path is None or self.goals.done or self.missing:
            return self._twist(0.0, 0.0)
        state = VehicleState(x_m=odom.pose.x_m, y_m=odom.pose.y_m, theta_rad=odom.pose.theta_rad,
                             speed_mps=odom.speed_mps, steering_rad=self.steering_rad)
        command = self.tracker.command(state, path=self.path, progress_m=self.progress_m)
        self.progress_m = command.progress_m
        limits = self.config.limits
        swing = limits.max_steering_rate_radps * dt_s
        target = max(-limits.max_steering_rad, min(limits.max_steering_rad, command.target_steering_rad))
        self.steering_rad += max(-swing, min(swing, target - self.steering_rad))
        speed = max(0.0, min(limits.max_speed_mps, command.target_speed_mps))
        return self._twist(*body_twist(speed_mps=speed, steering_rad=self.steering_rad,
                                       wheelbase_m=limits.wheelbase_m))

    @staticmethod
    def _twist(linear_mps: float, angular_radps: float) -> object:
        Twist, Vector3 = typesupport.message_class("geometry_msgs/msg/Twist"), typesupport.message_class(
            "geometry_msgs/msg/Vector3")
        return Twist(linear=Vector3(x=float(linear_mps), y=0.0, z=0.0), angular=Vector3(x=0.0, y=0.0,
                                                                                        z=float(angular_radps)))

    def _plan_message(self, points: np.ndarray, *, stamp: object) -> object:
        """nav_msgs/Path in the odometry's frame, stamped with the scan it answers; poses face along it."""
        cls = typesupport.message_class
        Header_, PoseStamped, Pose, Point_, Quaternion = (
            cls("std_msgs/msg/Header"), cls("geometry_msgs/msg/PoseStamped"), cls("geometry_msgs/msg/Pose"),
            cls("geometry_msgs/msg/Point"), cls("geometry_msgs/msg/Quaternion"))
        header = Header_(stamp=stamp, frame_id=self.frame_id or "")
        step = np.diff(points, axis=0)
        headings = np.arctan2(step[:, 1], step[:, 0])
        headings = np.append(headings, headings[-1])
        poses = [PoseStamped(header=header, pose=Pose(position=Point_(x=float(x), y=float(y), z=0.0),
                                                      orientation=Quaternion(x=0.0, y=0.0, z=math.sin(0.5 * h),
                                                                             w=math.cos(0.5 * h))))
                 for (x, y), h in zip(points.tolist(), headings.tolist())]
        return cls("nav_msgs/msg/Path")(header=header, poses=poses)


def _wrong_key(topic: str, key_expr: str, expected: str) -> str:
    got, want = key_expr.rsplit("/", 2), expected.rsplit("/", 2)
    if len(got) == 3 and got[0] == want[0] and got[1] == want[1]:
        return (f"type hash {got[2][:80]} is not {BRIDGE_TOPICS[topic].msgtype}'s {want[2]} (the publisher was "
                f"built with another definition of the type)")
    return f"key {key_expr[:160]} is not {expected}"
