"""The monitor stage: every key under the prefix, logged to rerun on a tree that mirrors the pipeline.

    world/obstacles, world/bounds, goals      the true map (from the sim's World message), static
    world/map                                 a known map's occupied cells (a robot's /map), static
    sensing/scan, sensing/clusters            what the sensor saw and how it was grouped
    ellipsoids/grown                          the inflated ellipses the planner avoids
    planner/raw_path, smoother/path           the plan before and after smoothing
    sim/robot, sim/trail                      the footprint and where it has been
    status/<stage>/processing_ms              per-stage processing time (Scalars); errors as TextLog
    status/sim/speed_mps, status/smoother/*   the car's speed, the published curve's checks
    latency/scan_to_path_ms                   scan seen → smoothed path for that scan seen, here

Time is the message stamp on the ``sim_time`` timeline (``rr.set_time(duration=stamp_s)``), so a
recording replays on the pipeline's clock whatever the monitor's own delays. `MonitorCore` is the
wiring table's sink: the shell hands it every topic's messages and every status, in arrival order,
from a queue its subscriber callbacks only fill (they never slow a publisher that uses congestion
control BLOCK), and `stop` flushes the recording.

Rerun's analytics are switched off for this process and any viewer it spawns: the SDK has no
opt-out variable, but its pipeline skips analytics whenever ``CI`` is set
(``re_analytics/src/native/pipeline.rs``); ``disable_rerun_analytics`` sets it before rerun loads.
"""

from __future__ import annotations

import logging
import os
import shutil
import socket
import sysconfig
import time
import uuid
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from pydantic import BaseModel

from schemas.messages import Clusters, Ellipsoids, Goals, Map, RawPath, RobotState, Scan, SmoothPath, StageStatus, World
from schemas.scenario import Scenario
from services.contract import Outputs
from services.convert import grid_from_msg
from services.monitor.shapes import circle_outline, closed, ellipse_outline, footprint_outline

logger = logging.getLogger(__name__)

APPLICATION_ID = "cvxnav"
TIMELINE = "sim_time"
TRAIL_MAX_POINTS = 5_000
VIEWER_PORT = 9876  # where a spawned viewer listens (rerun's default; a viewer already there is reused)
# Each stream's flush at stop, at most: well within the grace the supervisor gives a stage to stop
# (`cvxnav.supervisor`'s 5 s) before it kills it mid-file.
_FLUSH_TIMEOUT_S = 2.0


def disable_rerun_analytics() -> None:
    """Turn rerun's usage analytics off in this process and its children (the viewer it spawns)."""
    os.environ.setdefault("CI", "1")


class ViewerError(Exception):
    """The viewer asked for cannot be shown and nothing else would receive the recording: one line."""


@dataclass(frozen=True)
class RerunTargets:
    """Where the recording goes: a file, a spawned viewer, a remote viewer's gRPC URL (any mix)."""

    record_path: Path | None = None
    spawn_viewer: bool = False
    viewer_url: str | None = None

    @property
    def any(self) -> bool:
        return self.record_path is not None or self.spawn_viewer or self.viewer_url is not None


class Recording:
    """One recording sent to each target on a rerun stream of its own (the same recording id). A stream
    is flushed and closed as a whole: on one stream with the file, a viewer that accepts the connection
    and then reads nothing (a spawned one that cannot open its window may linger so) keeps the file's
    flush waiting until the stage is killed, and the file is left without its footer. The file's stream
    is closed first."""

    def __init__(self, streams: list) -> None:
        self.streams = streams  # the file's first, where there is one

    def set_time(self, timeline: str, **time) -> None:
        for stream in self.streams:
            stream.set_time(timeline, **time)

    def log(self, entity: str, archetype, *, static: bool = False) -> None:
        for stream in self.streams:
            stream.log(entity, archetype, static=static)

    def close(self, *, timeout_s: float) -> None:
        """Flush each stream (at most `timeout_s` each) and disconnect it; a viewer that went away is
        a warning, the other targets keep their data."""
        for stream in self.streams:
            try:
                stream.flush(timeout_sec=timeout_s)
            except RuntimeError as error:
                logger.warning("monitor: %s", str(error).splitlines()[0])
            stream.disconnect()


def open_recording(*, targets: RerunTargets, recording_id: str | None = None) -> Recording:
    """The recording sent to every target, with the pipeline layout as its blueprint."""
    disable_rerun_analytics()
    import rerun as rr

    recording_id = recording_id or uuid.uuid4().hex
    sinks = []
    if targets.record_path is not None:
        sinks.append(rr.FileSink(str(targets.record_path)))
    if targets.spawn_viewer:
        try:
            rr.spawn(port=VIEWER_PORT, connect=False, executable_path=viewer_executable())
            reason = "" if viewer_listening() else "it exited (no display?)"
        except RuntimeError as error:  # no `rerun` executable
            reason = str(error).splitlines()[0]
        if not reason:
            sinks.append(rr.GrpcSink(f"rerun+http://127.0.0.1:{VIEWER_PORT}/proxy"))
        elif targets.record_path is None and targets.viewer_url is None:
            raise ViewerError(f"the rerun viewer did not start: {reason}; use --record or --viewer-url instead")
        else:
            logger.warning("monitor: the rerun viewer did not start: %s; sending to the other targets only", reason)
    if targets.viewer_url is not None:
        sinks.append(rr.GrpcSink(targets.viewer_url))
    streams = []
    for sink in sinks:
        stream = rr.RecordingStream(APPLICATION_ID, recording_id=recording_id)
        stream.set_sinks(sink, default_blueprint=blueprint())
        streams.append(stream)
    return Recording(streams)


def viewer_listening(*, timeout_s: float = 1.0) -> bool:
    """Whether the spawned viewer accepts connections (one that cannot open a window exits at once)."""
    try:
        socket.create_connection(("127.0.0.1", VIEWER_PORT), timeout=timeout_s).close()
    except OSError:
        return False
    return True


def viewer_executable() -> str | None:
    """The `rerun` that rerun-sdk installed beside this Python (an un-activated venv is not on PATH), else PATH's."""
    return shutil.which("rerun", path=sysconfig.get_path("scripts")) or shutil.which("rerun")


def blueprint():
    """The map on the left, the time series (latency, per-stage processing, speed) on the right."""
    import rerun.blueprint as rrb

    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Spatial2DView(
                name="map", origin="/",
                contents=["world/**", "goals/**", "sensing/**", "ellipsoids/**", "planner/**", "smoother/**",
                          "sim/**"],
            ),
            rrb.Vertical(
                rrb.TimeSeriesView(name="latency", origin="latency"),
                rrb.TimeSeriesView(name="stages", origin="status"),
            ),
            column_shares=[3, 2],
        ),
    )


class RerunLogger:
    """Turns one decoded pipeline message into rerun log calls on the entity tree (module docstring)."""

    def __init__(self, *, recording) -> None:
        import rerun as rr

        self._rr = rr
        self._rec = recording
        self._robot_size_m: tuple[float, float] | None = None
        self._trail: list[tuple[float, float]] = []
        self._scan_seen_s: dict[int, float] = {}  # scan seq -> monotonic time the monitor saw it

    def log(self, *, topic: str | None, stage: str | None, message: BaseModel) -> None:
        header = getattr(message, "header", None)
        if header is not None:
            self._rec.set_time(TIMELINE, duration=header.stamp_s)
        if isinstance(message, StageStatus):
            self._status(stage=stage or message.stage, status=message)
            return
        handler = getattr(self, f"_{topic}")
        handler(message)

    # -- one method per topic of the wiring table (MONITOR.subscribes)

    def _world(self, world: World) -> None:
        rr, rec = self._rr, self._rec
        outlines = [closed(np.asarray(p)) for p in world.polygons]
        outlines += [circle_outline(center=np.asarray(c.center), radius_m=c.radius_m) for c in world.circles]
        rec.log("world/obstacles", rr.LineStrips2D(outlines, colors=[40, 40, 40], radii=0.04), static=True)
        lo, hi = np.asarray(world.bounds_min), np.asarray(world.bounds_max)
        rec.log("world/bounds", rr.Boxes2D(mins=[lo], sizes=[hi - lo], colors=[160, 160, 160]), static=True)
        rec.log("goals", rr.Points2D(world.goals, radii=world.goal_tolerance_m, colors=[0, 160, 0],
                                     labels=[f"goal {i + 1}" for i in range(len(world.goals))]), static=True)
        self._robot_size_m = (world.robot_width_m, world.robot_length_m)

    def _goals(self, goals: Goals) -> None:
        """Goals that replace the scenario's (a robot's /goal_pose): drawn where the world's were."""
        self._rec.log("goals", self._rr.Points2D(goals.goals, colors=[0, 160, 0],
                                                 labels=[f"goal {i + 1}" for i in range(len(goals.goals))]),
                      static=True)

    def _map(self, known: Map) -> None:
        """A known map (a robot's /map): its occupied cells, as few rectangles."""
        outlines = [closed(box) for box in grid_from_msg(known).rectangles()]
        self._rec.log("world/map", self._rr.LineStrips2D(outlines, colors=[90, 90, 90], radii=0.02), static=True)

    def _scan(self, scan: Scan) -> None:
        self._scan_seen_s[scan.header.seq] = time.monotonic()
        if len(self._scan_seen_s) > 1000:
            self._scan_seen_s.pop(min(self._scan_seen_s))
        self._rec.log("sensing/scan", self._rr.Points2D(scan.points or np.zeros((0, 2)), radii=0.03,
                                                         colors=[230, 120, 0]))

    def _clusters(self, clusters: Clusters) -> None:
        points = [p for c in clusters.clusters for p in c.points]
        ids = [c.cluster_id for c in clusters.clusters for _ in c.points]
        self._rec.log("sensing/clusters", self._rr.Points2D(points or np.zeros((0, 2)), class_ids=ids or None,
                                                             radii=0.05))

    def _ellipsoids(self, ellipsoids: Ellipsoids) -> None:
        outlines = [ellipse_outline(A=np.asarray(e.A), b=np.asarray(e.b)) for e in ellipsoids.ellipsoids]
        groups = [e.group for e in ellipsoids.ellipsoids]
        self._rec.log("ellipsoids/grown", self._rr.LineStrips2D(outlines, class_ids=groups or None, radii=0.03))

    def _raw_path(self, path: RawPath) -> None:
        strips = [path.points] if len(path.points) >= 2 else []
        self._rec.log("planner/raw_path", self._rr.LineStrips2D(strips, colors=[200, 0, 200], radii=0.03))
        if path.status == "no_path":
            self._rec.log("planner/log", self._rr.TextLog(f"no_path: {path.reason}", level="WARN"))

    def _smooth_path(self, path: SmoothPath) -> None:
        rr, rec = self._rr, self._rec
        strips = [path.points] if len(path.points) >= 2 else []
        rec.log("smoother/path", rr.LineStrips2D(strips, colors=[0, 90, 220], radii=0.05))
        rec.log("status/smoother/max_curvature", rr.Scalars(path.max_curvature))
        seen_s = self._scan_seen_s.pop(path.scan_seq, None)
        if seen_s is not None:
            rec.log("latency/scan_to_path_ms", rr.Scalars((time.monotonic() - seen_s) * 1e3))

    def _state(self, state: RobotState) -> None:
        rr, rec = self._rr, self._rec
        pose = state.pose
        self._trail.append((pose.x_m, pose.y_m))
        del self._trail[:-TRAIL_MAX_POINTS]
        width_m, length_m = self._robot_size_m or (0.3, 0.6)
        outline = footprint_outline(x_m=pose.x_m, y_m=pose.y_m, theta_rad=pose.theta_rad, width_m=width_m,
                                    length_m=length_m)
        rec.log("sim/robot", rr.LineStrips2D([outline], colors=[220, 0, 0], radii=0.03))
        if len(self._trail) >= 2:
            rec.log("sim/trail", rr.LineStrips2D([self._trail], colors=[220, 80, 80], radii=0.02))
        rec.log("status/sim/speed_mps", rr.Scalars(state.speed_mps))

    def _status(self, *, stage: str, status: StageStatus) -> None:
        rr, rec = self._rr, self._rec
        rec.log(f"status/{stage}/processing_ms", rr.Scalars(status.processing_ms))
        if status.state == "error":
            rec.log(f"status/{stage}/log", rr.TextLog(status.reason, level="ERROR"))


class MonitorCore:
    """The sink: each message and status it is handed, logged to rerun; the recording flushed at stop."""

    def __init__(self, *, targets: RerunTargets, recording_id: str | None = None) -> None:
        self.recording = open_recording(targets=targets, recording_id=recording_id)
        self.sink = RerunLogger(recording=self.recording)
        self.logged: dict[str, int] = {}  # by topic, and by status/<stage>

    @classmethod
    def from_scenario(cls, scenario: Scenario, *, record: Path | None = None, viewer: bool = False,
                      viewer_url: str | None = None) -> MonitorCore:
        """The targets a command line asked for (`monitor_targets`); the scenario's map comes as the World."""
        return cls(targets=monitor_targets(record=record, viewer=viewer, viewer_url=viewer_url))

    def process(self, *, topic: str, message: BaseModel, now_s: float) -> Outputs:
        self.sink.log(topic=topic, stage=None, message=message)
        self.logged[topic] = self.logged.get(topic, 0) + 1
        return []

    def hear_status(self, *, stage: str, status: StageStatus, now_s: float) -> Outputs:
        self.sink.log(topic=None, stage=stage, message=status)
        self.logged[f"status/{stage}"] = self.logged.get(f"status/{stage}", 0) + 1
        return []

    def stop(self, *, now_s: float) -> Outputs:
        self.recording.close(timeout_s=_FLUSH_TIMEOUT_S)
        logger.info("monitor logged %d messages", sum(self.logged.values()))
        return []


def monitor_targets(*, record: Path | None, viewer: bool, viewer_url: str | None) -> RerunTargets:
    """The targets a command line asked for; with none, a recording in the working directory."""
    targets = RerunTargets(record_path=record, spawn_viewer=viewer, viewer_url=viewer_url)
    return targets if targets.any else RerunTargets(record_path=Path("cvxnav-monitor.rrd"))


def monitor_arguments(*, record: Path | None, viewer: bool, viewer_url: str | None) -> Sequence[str]:
    """The `cvxnav service monitor` options for these targets (how `cvxnav run` starts it)."""
    args: list[str] = []
    if record is not None:
        args += ["--record", str(record)]
    if viewer:
        args += ["--viewer"]
    if viewer_url is not None:
        args += ["--viewer-url", viewer_url]
    return args
