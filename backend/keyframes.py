"""Keyframe policy of the factor-graph backends.

A frame with observations becomes a keyframe (a pose variable ``X(k)`` with its
observations' factors) when it is the first one, when the robot has moved
``keyframe_distance`` or turned ``keyframe_angle`` since the last keyframe, or always
with ``every_frame``. The smoothers use no other frame's observations; between
keyframes the pose is the last keyframe's estimate composed with the odometry
(:mod:`lampsam.backend.pose_cov`). Fewer keyframes keep iSAM2's updates small; the
measured trade-off of the defaults is in docs/graph-backend.md.
"""

from __future__ import annotations

import math

from lampsam.arrays import FloatArray
from lampsam.backend.config import Isam2Config


def is_keyframe(k: int, delta: FloatArray, config: Isam2Config) -> bool:
    """Whether a frame with observations becomes keyframe ``k + 1``.

    The first frame is always a keyframe: seen from the known start pose, it anchors
    the map's heading, which nothing later can observe.

    Args:
        k: index of the last keyframe (0: only the start pose so far).
        delta: (3,) odometry ``(x, y, theta)`` since keyframe ``k``, in its body frame,
            m and rad.
        config: ``every_frame``, ``keyframe_distance`` (m), ``keyframe_angle`` (rad).
    """
    if config.every_frame or k == 0:
        return True
    return bool(math.hypot(float(delta[0]), float(delta[1])) >= config.keyframe_distance
                or abs(float(delta[2])) >= config.keyframe_angle)
