"""Signed distance functions of the simulated ceiling's planar shapes (rectangles, discs).

Shared by the renderer (anti-aliased edge coverage) and the truth labels (occlusion
tests) so that both see the same outline. Distances in metres, negative inside.
"""

from __future__ import annotations

import math

import numpy as np

from lampsam.arrays import FloatArray

__all__ = ["disc_sdf", "rect_sdf"]


def rect_sdf(x: FloatArray, y: FloatArray, center: tuple[float, float], half: tuple[float, float],
              yaw: float) -> FloatArray:  # fmt: skip
    """Signed distance (m, negative inside) to a rotated rectangle."""
    c, s = math.cos(yaw), math.sin(yaw)
    dx, dy = x - center[0], y - center[1]
    qx = np.abs(c * dx + s * dy) - half[0]
    qy = np.abs(-s * dx + c * dy) - half[1]
    outside = np.hypot(np.maximum(qx, 0.0), np.maximum(qy, 0.0))
    inside = np.minimum(np.maximum(qx, qy), 0.0)
    return outside + inside


def disc_sdf(
    x: FloatArray, y: FloatArray, center: tuple[float, float], radius: float
) -> FloatArray:
    """Signed distance (m, negative inside) to a disc."""
    return np.hypot(x - center[0], y - center[1]) - radius
