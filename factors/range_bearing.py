"""Planar range-bearing observation of a point landmark (generic landmark datasets).

The measurement is ordered like GTSAM's ``BearingRangeFactor2D``: ``z = [bearing,
range]`` with the bearing in ``(-pi, pi]`` measured in the sensor frame (counter-
clockwise from the sensor's ``x`` axis) and the range in metres. With no sensor offset
``range_bearing(pose, l)`` equals ``(pose.bearing(l).theta(), pose.range(l))`` of
``gtsam.Pose2``; pose Jacobians are w.r.t. GTSAM's right tangent (conventions.md).

The bearing is singular when the landmark coincides with the sensor (range 0);
range-bearing sensors never report that, and the functions raise :class:`FactorError`
below 1e-9 m.
"""

from __future__ import annotations

import math

import numpy as np

from lampsam.arrays import FloatArray
from lampsam.factors.geometry import FactorError, rot2, wrap_angle

__all__ = ["range_bearing"]


def range_bearing(
    pose: FloatArray,
    landmark: FloatArray,
    body_T_sensor: FloatArray | None = None,
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Predicted bearing and range of a planar landmark, with Jacobians.

    With ``p = R(theta)^T (l - t)`` the landmark in the body frame and, for a sensor
    mounted at ``body_T_sensor = (o_x, o_y, o_theta)``, ``q = R(o_theta)^T (p - o)``
    in the sensor frame: ``bearing = atan2(q_y, q_x)``, ``range = |q|``.
    Derivation: under the right perturbation ``(d_xy, d_theta)`` of the pose,
    ``dp = -d_xy + d_theta (p_y, -p_x)``; ``d bearing / dq = (-q_y, q_x) / r^2`` and
    ``d range / dq = (q_x, q_y) / r``.

    Args:
        pose: (3,) ``world_T_body = (x, y, theta)``; m, m, rad.
        landmark: (2,) ``world_t_landmark``, metres.
        body_T_sensor: optional (3,) sensor pose in the body frame; None = identity.

    Returns:
        z: (2,) ``[bearing (rad, (-pi, pi]), range (m)]``.
        z_D_pose: (2, 3) w.r.t. the pose's right tangent.
        z_D_landmark: (2, 2) w.r.t. the world landmark coordinates.

    Raises:
        FactorError: the landmark is at the sensor (range < 1e-9 m).
    """
    c, s = math.cos(pose[2]), math.sin(pose[2])
    dx, dy = landmark[0] - pose[0], landmark[1] - pose[1]
    p = np.array([c * dx + s * dy, -s * dx + c * dy])
    p_D_pose = np.array([[-1.0, 0.0, p[1]], [0.0, -1.0, -p[0]]])
    p_D_landmark = np.array([[c, s], [-s, c]])
    if body_T_sensor is None:
        q, q_D_pose, q_D_landmark = p, p_D_pose, p_D_landmark
    else:
        r_o_t = rot2(float(body_T_sensor[2])).T
        q = r_o_t @ (p - np.asarray(body_T_sensor[:2], dtype=float))
        q_D_pose = r_o_t @ p_D_pose
        q_D_landmark = r_o_t @ p_D_landmark
    r2 = float(q[0] * q[0] + q[1] * q[1])
    r = math.sqrt(r2)
    if r < 1e-9:
        raise FactorError("range-bearing landmark coincides with the sensor (range 0)")
    z = np.array([wrap_angle(math.atan2(q[1], q[0])), r])
    z_D_q = np.array([[-q[1] / r2, q[0] / r2], [q[0] / r, q[1] / r]])
    return z, z_D_q @ q_D_pose, z_D_q @ q_D_landmark
