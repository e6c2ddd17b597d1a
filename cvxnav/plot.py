"""`cvxnav plot`: a plan or run file drawn the way the paper's Figure 5 is, without a viewer.

Obstacles (from the scenario: the file carries only its name; a map as its cells, occupied black,
unknown grey, placed by its origin and yaw), the inflated ellipses and the raw and
smoothed paths (plan.json), the driven trajectory with the footprint every few seconds (run.json),
start and goals. Matplotlib with the Agg backend, so it runs headless and in CI.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from schemas.files import MAX_OUTPUT_BYTES, RUN_FORMAT, RUN_FORMATS, OutputFileError, PlanFile, RunFile
from schemas.scenario import Scenario, read_text
from services.monitor.shapes import closed, ellipse_outline, footprint_outline

FOOTPRINT_EVERY_S = 2.0


class PlotError(ValueError):
    """A file that cannot be plotted; one line."""


def read_result(path: Path) -> PlanFile | RunFile:
    """A plan or run file, chosen by its `format` field."""
    try:
        doc = json.loads(read_text(path, error=PlotError, max_bytes=MAX_OUTPUT_BYTES)[0])
    except json.JSONDecodeError as error:
        raise PlotError(f"{path}: invalid JSON: {error.msg} (line {error.lineno})") from None
    kind = doc.get("format") if isinstance(doc, dict) else None
    model = {"cvxnav.plan/1": PlanFile, "cvxnav.plan/2": PlanFile, **dict.fromkeys(RUN_FORMATS, RunFile)}.get(kind)
    if model is None:
        raise PlotError(f"{path}: format: expected cvxnav.plan/2 (or /1) or {RUN_FORMAT} (or /1), got {kind!r}")
    try:
        return model.read(path)
    except OutputFileError as error:
        raise PlotError(str(error)) from None


def _draw_grid(ax, grid) -> None:
    """The map's cells under everything else: free white, occupied black, unknown grey."""
    from matplotlib.transforms import Affine2D

    from schemas.occupancy import FREE, OCCUPIED

    shade = np.where(grid.state == FREE, 1.0, np.where(grid.state == OCCUPIED, 0.0, 0.72))
    width, height = grid.size_m
    place = Affine2D().rotate(grid.origin_yaw_rad).translate(grid.origin_x_m, grid.origin_y_m) + ax.transData
    ax.imshow(shade, origin="lower", extent=(0.0, width, 0.0, height), cmap="gray", vmin=0.0, vmax=1.0,
              interpolation="nearest", transform=place, zorder=0)


def plot_result(*, result: PlanFile | RunFile, scenario: Scenario, png_path: Path, width_px: int = 1200,
                height_px: int = 900, dpi: int = 100) -> None:
    """Write the figure to `png_path` at exactly `width_px` × `height_px`."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Circle, Polygon

    fig, ax = plt.subplots(figsize=(width_px / dpi, height_px / dpi), dpi=dpi)
    try:
        for obstacle in scenario.obstacles:
            if obstacle.type == "occupancy_grid":
                _draw_grid(ax, obstacle.grid)
            elif obstacle.type == "circle":
                ax.add_patch(Circle(obstacle.center, obstacle.radius, facecolor="0.35", edgecolor="black"))
            else:
                vertices = obstacle.vertices if obstacle.type == "polygon" else obstacle.cover_vertices()
                ax.add_patch(Polygon(np.asarray(vertices), closed=True, facecolor="0.35", edgecolor="black"))
        if isinstance(result, PlanFile):
            for index, ellipse in enumerate(result.ellipsoids):
                outline = ellipse_outline(A=np.asarray(ellipse.A), b=np.asarray(ellipse.b))
                ax.plot(outline[:, 0], outline[:, 1], color="tab:orange", lw=1.2,
                        label="inflated ellipses" if index == 0 else None)
            if len(result.raw_path) >= 2:
                raw = np.asarray(result.raw_path)
                ax.plot(raw[:, 0], raw[:, 1], "--", color="tab:purple", lw=1.2, label="raw path")
            if len(result.path) >= 2:
                path = np.asarray(result.path)
                ax.plot(path[:, 0], path[:, 1], color="tab:blue", lw=2.0, label="smoothed path")
        else:
            trajectory = np.asarray(result.trajectory, dtype=float).reshape(-1, 4)
            if len(trajectory):
                ax.plot(trajectory[:, 1], trajectory[:, 2], color="tab:red", lw=2.0, label="trajectory")
                next_s = 0.0
                for t_s, x_m, y_m, theta_rad in trajectory:
                    if t_s >= next_s:
                        box = footprint_outline(x_m=x_m, y_m=y_m, theta_rad=theta_rad, width_m=scenario.robot.width,
                                                length_m=scenario.robot.length)
                        ax.plot(box[:, 0], box[:, 1], color="tab:red", lw=0.8)
                        next_s = t_s + FOOTPRINT_EVERY_S
        ax.plot([scenario.start.x], [scenario.start.y], "o", color="black", label="start")
        goals = scenario.goals_array
        ax.plot(goals[:, 0], goals[:, 1], "*", color="tab:green", markersize=14, label="goals")
        lo, hi = np.asarray(scenario.bounds.min), np.asarray(scenario.bounds.max)
        frame = closed(np.array([lo, [hi[0], lo[1]], hi, [lo[0], hi[1]]]))
        ax.plot(frame[:, 0], frame[:, 1], color="0.6", lw=0.8)
        ax.set_aspect("equal")
        ax.set_xlabel("x [m]")
        ax.set_ylabel("y [m]")
        ax.set_title(f"{result.scenario}: {result.status}")
        ax.legend(loc="best", fontsize="small")
        fig.tight_layout()
        fig.savefig(png_path, dpi=dpi)  # no bbox_inches="tight": that would change the pixel size
    finally:
        plt.close(fig)
