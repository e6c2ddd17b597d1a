"""Obstacle ellipses: Löwner–John fits (eq. 1), tight covers, and gaps between ellipses (eq. 3)."""

from services.ellipsoids.cover import cover_points, cover_polygon, excess_over_points, excess_over_polygon
from services.ellipsoids.gap import Gap, GapError, ellipse_gap, group_ellipses
from services.ellipsoids.mvee import FitError, mvee, mvee_fast

__all__ = [
    "FitError",
    "Gap",
    "GapError",
    "cover_points",
    "cover_polygon",
    "ellipse_gap",
    "excess_over_points",
    "excess_over_polygon",
    "group_ellipses",
    "mvee",
    "mvee_fast",
]
