"""The monitor's recording file is whole when the viewer it also sends to stalls: a real rerun gRPC server
stopped with SIGSTOP (a viewer that accepted the connection and reads nothing more), the monitor's process
killed with SIGKILL at the supervisor's grace after it was told to stop, as `cvxnav run` does."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import time
import warnings
from pathlib import Path

from cvxnav.supervisor import free_ports

_SERVER = """
import sys, time
import rerun as rr
rr.init("stalled-viewer")
rr.serve_grpc(grpc_port=int(sys.argv[1]))
print("up", flush=True)
time.sleep(600)
"""

_MONITOR = """
import sys
from pathlib import Path
from schemas.messages import Header, Pose2D, Scan
from services.monitor.rerun import MonitorCore, RerunTargets
core = MonitorCore(targets=RerunTargets(record_path=Path(sys.argv[1]), viewer_url=sys.argv[2]))
for k in range(220):  # 22 s of scans at 10 Hz
    scan = Scan(header=Header(stamp_s=0.1 * k, seq=k), pose=Pose2D(x_m=0.0, y_m=0.0, theta_rad=0.0),
                points=[(0.001 * i, 1.0) for i in range(5000)])
    core.process(topic="scan", message=scan, now_s=0.1 * k)
print("stopping", flush=True)
core.stop(now_s=22.0)
print("stopped", flush=True)
"""


def test_a_stalled_viewer_costs_the_recording_file_nothing(tmp_path: Path):
    from rerun.chunk import RrdReader

    (port,) = free_ports(1)
    server = subprocess.Popen([sys.executable, "-c", textwrap.dedent(_SERVER), str(port)], stdout=subprocess.PIPE,
                              text=True)
    try:
        assert server.stdout.readline().strip() == "up"
        os.kill(server.pid, signal.SIGSTOP)
        record = tmp_path / "run.rrd"
        monitor = subprocess.Popen([sys.executable, "-c", textwrap.dedent(_MONITOR), str(record),
                                    f"rerun+http://127.0.0.1:{port}/proxy"], stdout=subprocess.PIPE, text=True)
        assert monitor.stdout.readline().strip() == "stopping"
        try:
            monitor.wait(timeout=5.0)  # the supervisor's grace for a stage to stop
        except subprocess.TimeoutExpired:
            monitor.kill()  # still flushing to the stalled viewer: killed, as the supervisor does
            monitor.wait()
    finally:
        os.kill(server.pid, signal.SIGCONT)
        server.kill()
        server.wait()
    with warnings.catch_warnings(record=True) as warned:
        warnings.simplefilter("always")
        reader = RrdReader(record)
        reader.recordings()
    assert not [w for w in warned if "no footer" in str(w.message)], "the file was cut off before its footer"
    stamps = sorted(value.as_py().total_seconds() if hasattr(value, "as_py") else value.value / 1e9
                    for chunk in reader.stream() if chunk.entity_path == "/sensing/scan"
                    for value in chunk.to_record_batch().column("sim_time"))
    assert len(stamps) == 220 and stamps[-1] >= 21.9
