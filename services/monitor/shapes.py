"""Outlines to draw, computed from message fields: plain numpy, no rerun and no I/O."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]


def ellipse_outline(*, A: FloatArray, b: FloatArray, samples: int = 64) -> FloatArray:
    """Closed outline of {z : ||A z + b||_2 <= 1}: z = A^-1 (u - b) for u on the unit circle."""
    t = np.linspace(0.0, 2.0 * np.pi, samples + 1)
    u = np.column_stack([np.cos(t), np.sin(t)])
    return np.linalg.solve(np.asarray(A, dtype=float), (u - np.asarray(b, dtype=float)).T).T


def circle_outline(*, center: FloatArray, radius_m: float, samples: int = 64) -> FloatArray:
    t = np.linspace(0.0, 2.0 * np.pi, samples + 1)
    return np.asarray(center, dtype=float) + radius_m * np.column_stack([np.cos(t), np.sin(t)])


def closed(vertices: FloatArray) -> FloatArray:
    """The ring with its first vertex repeated at the end, so a line strip draws every edge."""
    v = np.asarray(vertices, dtype=float).reshape(-1, 2)
    return np.vstack([v, v[:1]]) if len(v) else v


def footprint_outline(*, x_m: float, y_m: float, theta_rad: float, width_m: float, length_m: float) -> FloatArray:
    """The robot's rectangle centred on the pose (CONTRACTS §1), closed, length along the heading."""
    half = np.array([[1, 1], [-1, 1], [-1, -1], [1, -1]], dtype=float) * [length_m / 2.0, width_m / 2.0]
    c, s = np.cos(theta_rad), np.sin(theta_rad)
    rotation = np.array([[c, -s], [s, c]])
    return closed(half @ rotation.T + [x_m, y_m])
