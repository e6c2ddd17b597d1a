"""Sensing stage: scan hits → remembered map-frame points → obstacle clusters (core in `core`)."""

from services.sensing.core import PointMemory, cluster_points

__all__ = ["PointMemory", "cluster_points"]
