"""Stereo two-point relative pose: measurement and motion models (paper 3, eqs. 1-5).

Frames and signs (docs/stereo.md gives the full statement):

* Target frame ``{O}``: the two target points ``target_t_points`` (2, 2) are known
  in it, metres.
* Rig frame ``{C}`` (= robot frame; the paper assumes only a vertical offset
  between them): origin at the midpoint of the two optical centres, ``x`` along
  the optical axes (depth), ``y`` to the left, ``z`` up. The left camera is at
  ``y = +B/2``, the right one at ``y = -B/2``.
* State: ``target_T_camera = (x, y, theta)``, the rig's planar pose in the target
  frame (the paper's eq. 3-4 state, "the robot's x, y and heading relative to the
  target"). Eq. 1 ``c_p = T + R(theta_1) o_p`` is the same map written the other
  way round: ``c_p = R(theta)^T (o_p - t)``, i.e. ``theta_1 = -theta`` and
  ``T = -R(theta)^T t``. This choice makes the paper's motion model eq. 4 hold
  literally and makes the variable a ``gtsam.Pose2``.
* Image coordinate: the paper's horizontal coordinate in pixels from the
  principal point, **positive to the left** (towards ``+y``), so that eq. 2 holds
  as printed: ``x_l = (f/p)(c_y - B/2)/c_x``, ``x_r = (f/p)(c_y + B/2)/c_x``. With
  OpenCV columns ``u``: ``x = c_u - u``. Disparity ``x_r - x_l = (f/p) B / c_x > 0``.

Every model is a pure function returning ``(value, value_D_arg, ...)``; pose
Jacobians are in GTSAM's right-perturbation tangent of ``Pose2``
(docs/conventions.md). The EKF converts them with ``blockdiag(R(theta)^T, 1)``.
"""

from __future__ import annotations

from functools import partial

import gtsam
import numpy as np

from lampsam.angles import wrap_angle
from lampsam.arrays import FloatArray
from lampsam.errors import LampsamError
from lampsam.factors.geometry import rot2

#: Order of the four coordinates in a two-point measurement (eq. 5).
MEASUREMENT_ORDER = ("xl1", "xr1", "xl2", "xr2")


class StereoModelError(LampsamError):
    """A stereo model was called with an unusable argument (shape, non-finite)."""


def pose_vector(pose: gtsam.Pose2 | FloatArray) -> FloatArray:
    """(3,) ``(x, y, theta)`` of a ``Pose2`` or of an array-like."""
    if isinstance(pose, gtsam.Pose2):
        return np.array([pose.x(), pose.y(), pose.theta()])
    vec = np.asarray(pose, dtype=float).reshape(-1)
    if vec.shape != (3,):
        raise StereoModelError(f"pose must have 3 coordinates, got shape {np.shape(pose)}")
    return vec


def camera_point(
    target_T_camera: gtsam.Pose2 | FloatArray, target_t_point: FloatArray
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """A target point in the rig frame (eq. 1, written as ``R^T (o_p - t)``).

    Args:
        target_T_camera: rig pose in the target frame, ``(x, y, theta)`` m, rad.
        target_t_point: (2,) the point in the target frame, m.

    Returns:
        ``c`` (2,) the point in the rig frame ``(depth, left)``, m;
        ``c_D_pose`` (2, 3) w.r.t. the right-perturbation tangent;
        ``c_D_point`` (2, 2) w.r.t. ``target_t_point``.
    """
    x, y, theta = pose_vector(target_T_camera)
    rt = rot2(theta).T
    c = rt @ (np.asarray(target_t_point, dtype=float) - np.array([x, y]))
    # d c / d(dx, dy) = -I (the tangent translation is in the rig frame);
    # d c / d dtheta = -S c with S = [[0, -1], [1, 0]]  ->  (c_y, -c_x).
    c_D_pose = np.array([[-1.0, 0.0, c[1]], [0.0, -1.0, -c[0]]])
    return c, c_D_pose, rt


def stereo_project(
    camera_t_point: FloatArray, baseline: float, f_px: float
) -> tuple[FloatArray, FloatArray]:
    """Parallel-stereo horizontal image coordinates of one point (eq. 2).

    Args:
        camera_t_point: (2,) ``(c_x, c_y)`` in the rig frame, m; ``c_x`` is the
            depth and must be positive (checked by the callers, not here, so the
            Jacobian tests can probe any point).
        baseline: ``B``, m.
        f_px: ``f / p``, focal length over pixel pitch, px.

    Returns:
        ``x`` (2,) ``(x_l, x_r)`` px, positive to the left of the principal point;
        ``x_D_point`` (2, 2).
    """
    cx, cy = float(camera_t_point[0]), float(camera_t_point[1])
    half = 0.5 * baseline
    x_l = f_px * (cy - half) / cx
    x_r = f_px * (cy + half) / cx
    x_D_point = np.array([[-x_l / cx, f_px / cx], [-x_r / cx, f_px / cx]])
    return np.array([x_l, x_r]), x_D_point


def two_point_measurement(
    target_T_camera: gtsam.Pose2 | FloatArray,
    target_t_points: FloatArray,
    baseline: float,
    f_px: float,
) -> tuple[FloatArray, FloatArray]:
    """The four-coordinate measurement of eq. 5: ``[x_l1, x_r1, x_l2, x_r2]`` px.

    Args:
        target_T_camera: rig pose in the target frame ``(x, y, theta)``.
        target_t_points: (2, 2) the two target points (rows) in the target frame, m.
        baseline: ``B``, m.
        f_px: ``f / p``, px.

    Returns:
        ``z`` (4,) px in :data:`MEASUREMENT_ORDER`; ``z_D_pose`` (4, 3) w.r.t. the
        right-perturbation tangent of the pose.
    """
    points = np.asarray(target_t_points, dtype=float)
    if points.shape != (2, 2):
        raise StereoModelError(f"target_t_points must be (2, 2), got {points.shape}")
    z = np.empty(4)
    z_D_pose = np.empty((4, 3))
    for j in range(2):
        c, c_D_pose, _ = camera_point(target_T_camera, points[j])
        x, x_D_c = stereo_project(c, baseline, f_px)
        z[2 * j : 2 * j + 2] = x
        z_D_pose[2 * j : 2 * j + 2] = x_D_c @ c_D_pose
    return z, z_D_pose


def motion_model(
    state: FloatArray, v_dt: float, omega_dt: float
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """The paper's motion model (eq. 4) in plain coordinates.

    ``x += v_dt cos(theta)``, ``y += v_dt sin(theta)``, ``theta += omega_dt``.
    This equals ``Pose2(state).compose(Pose2(v_dt, 0, omega_dt))``, so the graph
    uses GTSAM's ``BetweenFactorPose2`` for it (tests show both agree).

    Args:
        state: (3,) ``(x, y, theta)`` in the target frame, m, rad.
        v_dt: distance driven along the heading during the step, m.
        omega_dt: heading change during the step, rad.

    Returns:
        ``next`` (3,) (heading wrapped); ``next_D_state`` (3, 3), the EKF's ``A``
        (eq. 7); ``next_D_input`` (3, 2) w.r.t. ``(v_dt, omega_dt)``.
    """
    x, y, theta = pose_vector(state)
    c, s = np.cos(theta), np.sin(theta)
    nxt = np.array([x + v_dt * c, y + v_dt * s, wrap_angle(theta + omega_dt)])
    next_D_state = np.array([[1.0, 0.0, -v_dt * s], [0.0, 1.0, v_dt * c], [0.0, 0.0, 1.0]])
    next_D_input = np.array([[c, 0.0], [s, 0.0], [0.0, 1.0]])
    return nxt, next_D_state, next_D_input


def triangulate_point(x_l: float, x_r: float, baseline: float, f_px: float) -> FloatArray:
    """Invert eq. 2 for one point: ``c_x = (f/p) B / d``, ``c_y = c_x (x_l + x_r) / (2 f/p)``.

    Args:
        x_l, x_r: image coordinates, px (positive left); disparity ``d = x_r - x_l``
            must be positive (the caller flags it otherwise).
        baseline: ``B``, m.
        f_px: ``f / p``, px.

    Returns:
        (2,) ``(c_x, c_y)`` in the rig frame, m.
    """
    d = x_r - x_l
    if not d > 0.0:
        raise StereoModelError(f"non-positive disparity {d} px")
    depth = f_px * baseline / d
    return np.array([depth, depth * 0.5 * (x_l + x_r) / f_px])


def _two_point_error(
    z: FloatArray,
    target_t_points: FloatArray,
    baseline: float,
    f_px: float,
    this: gtsam.CustomFactor,
    values: gtsam.Values,
    jacobians: list[FloatArray] | None,
) -> FloatArray:
    """CustomFactor callback: ``h(pose) - z`` (4,) px; fills ``H`` (4, 3)."""
    pose = values.atPose2(this.keys()[0])
    h, h_D_pose = two_point_measurement(pose, target_t_points, baseline, f_px)
    if jacobians is not None:
        jacobians[0] = h_D_pose
    return h - z


def two_point_factor(
    key: int,
    z: FloatArray,
    target_t_points: FloatArray,
    baseline: float,
    f_px: float,
    noise: gtsam.noiseModel.Base,
) -> gtsam.CustomFactor:
    """GTSAM factor on a ``Pose2`` variable for one two-point measurement (eq. 5).

    The variable is a ``Pose2`` (not a ``Vector3``): the retraction keeps the
    heading on the circle, so LM/iSAM2 never step across the +-pi seam, and the
    motion model (eq. 4) is then exactly ``BetweenFactorPose2``.

    Args:
        key: the pose key (``X(k)``).
        z: (4,) measured coordinates, px, :data:`MEASUREMENT_ORDER`.
        target_t_points: (2, 2) target points in the target frame, m.
        baseline: ``B``, m.
        f_px: ``f / p``, px.
        noise: 4-D noise model, px (quantisation 1/12 px^2 + detection noise).
    """
    z = np.asarray(z, dtype=float).reshape(4)
    points = np.asarray(target_t_points, dtype=float).reshape(2, 2)
    return gtsam.CustomFactor(
        noise, [key], partial(_two_point_error, z, points, float(baseline), float(f_px))
    )


def motion_factor(
    key_prev: int, key_next: int, v_dt: float, omega_dt: float, noise: gtsam.noiseModel.Base
) -> gtsam.BetweenFactorPose2:
    """Motion factor between consecutive states (eq. 4) as GTSAM's built-in between.

    Args:
        key_prev, key_next: pose keys.
        v_dt: distance along the heading, m; omega_dt: heading change, rad.
        noise: 3-D noise in the tangent of the previous pose (along, lateral, heading).
    """
    return gtsam.BetweenFactorPose2(key_prev, key_next, gtsam.Pose2(v_dt, 0.0, omega_dt), noise)
