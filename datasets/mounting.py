"""Camera mounting: a tilted or offset ceiling camera from roll, pitch and yaw.

The paper's camera looks straight up (DESIGN.md sec. 1). A real robot's camera
sits tilted by a few degrees and off the rotation centre. The rig keeps the
full mounting: ``body_R_camera`` (camera axes -> body axes) and
``body_t_camera`` (the optical centre in the body frame, m). A world YAML may
give the tilt as angles instead of a matrix::

    rig:
      camera: {..., body_R_camera: [[0, -1, 0], [1, 0, 0], [0, 0, 1]],
               mount_rpy_deg: [roll, pitch, yaw], body_t_camera: [x, y, z]}

``body_R_camera = R_z(yaw) R_y(pitch) R_x(roll) body_R_camera_upward``: the
upward mounting (given, or the camera model's default) turned about the body
axes (x forward, y left, z up): roll about x tilts the optical axis to the
right, pitch about y tilts it forward, yaw about z turns the image. The frontend
and the measurement models use the whole rotation (normalised ceiling
coordinates are defined in body axes, docs/conventions.md), so a tilted camera
changes no interface.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from lampsam.arrays import FloatArray


def rotation_rpy(roll: float, pitch: float, yaw: float) -> FloatArray:
    """``R_z(yaw) R_y(pitch) R_x(roll)``, shape (3, 3); angles in rad."""
    cr, sr = math.cos(roll), math.sin(roll)
    cp, sp = math.cos(pitch), math.sin(pitch)
    cy, sy = math.cos(yaw), math.sin(yaw)
    rx = np.array([[1.0, 0.0, 0.0], [0.0, cr, -sr], [0.0, sr, cr]])
    ry = np.array([[cp, 0.0, sp], [0.0, 1.0, 0.0], [-sp, 0.0, cp]])
    rz = np.array([[cy, -sy, 0.0], [sy, cy, 0.0], [0.0, 0.0, 1.0]])
    return rz @ ry @ rx


def mounted(body_R_camera_up: FloatArray, rpy_deg: Sequence[float]) -> FloatArray:
    """The tilted mounting ``R_z R_y R_x body_R_camera_up`` for ``[roll, pitch, yaw]`` in degrees."""
    r, p, y = (math.radians(float(a)) for a in rpy_deg)
    return rotation_rpy(r, p, y) @ np.asarray(body_R_camera_up, dtype=np.float64)


def tilt_deg(body_R_camera: FloatArray) -> float:
    """Angle between the optical axis and the body's up axis, degrees."""
    axis = np.asarray(body_R_camera, dtype=np.float64) @ np.array([0.0, 0.0, 1.0])
    return math.degrees(math.acos(max(-1.0, min(1.0, float(axis[2])))))
