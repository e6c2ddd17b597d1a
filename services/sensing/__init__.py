"""Sensing stage: scan hits → remembered map-frame points (`services.geometry.PointMemory`) → obstacle
clusters (core in `core`)."""

from services.sensing.core import cluster_points

__all__ = ["cluster_points"]
