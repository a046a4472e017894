"""Differential-drive motion model and wheel-odometry noise (paper 1, eqs. 13-15).

Three layers, all pure numpy:

* :func:`diff_drive_step` -- one step of eq. 13 with its Jacobians (eq. 14) w.r.t.
  the **plain coordinates** ``(x, y, theta)`` of the pose and the wheel travels
  ``(d_left, d_right)``: exactly what the EKF prediction needs.
* :func:`wheel_noise_cov` -- eq. 15, the covariance of the wheel travels.
* :func:`accumulate_odometry` / :func:`odometry_between` -- the relative motion of a
  sequence of wheel increments (several images between two keyframes) expressed in
  the start pose's body frame, with its covariance propagated step by step through
  eqs. 13-15 and given in GTSAM's right tangent at the relative pose, i.e. the noise
  ``gtsam.BetweenFactorPose2`` expects. A small floor is added so the covariance
  is never singular (two wheels give a rank-2 covariance on three degrees of
  freedom, and zero motion gives zero covariance).

Wheel order everywhere in this module: ``(d_left, d_right)`` -- columns of
``next_D_wheels`` and rows/columns of :func:`wheel_noise_cov`. The paper writes
``Q = diag(k_r |ds_r|, k_l |ds_l|)`` in the opposite order; the content is the same.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence

import numpy as np

from lampsam.arrays import FloatArray
from lampsam.factors.geometry import FactorError, tangent_D_coords, wrap_angle

__all__ = [
    "DEFAULT_FLOOR_VAR",
    "accumulate_odometry",
    "diff_drive_step",
    "odometry_between",
    "wheel_noise_cov",
]

logger = logging.getLogger(__name__)

#: Default variance floor added to the tangent covariance of every odometry
#: between-factor: (m^2, m^2, rad^2) = (1 mm)^2, (1 mm)^2, (1 mrad)^2. It is about an
#: encoder tick and the sideways slip the two-wheel model cannot express; small
#: against the wheel noise of a keyframe (k = 1e-3 m over 0.4 m: sigma 2 cm) but it
#: keeps a stationary robot's factor finite (information 1e6 instead of infinity).
DEFAULT_FLOOR_VAR: FloatArray = np.array([1e-6, 1e-6, 1e-6])


def diff_drive_step(
    pose: FloatArray, d_left: float, d_right: float, wheel_base: float
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """One differential-drive step (paper 1, eq. 13) and its Jacobians (eq. 14).

    ``ds = (d_right + d_left) / 2``, ``dth = (d_right - d_left) / b``, then
    ``x += ds cos(theta + dth/2)``, ``y += ds sin(theta + dth/2)``, ``theta += dth``.

    Args:
        pose: (3,) ``world_T_body = (x, y, theta)`` before the step; m, m, rad.
        d_left: travel of the left wheel during the step, metres (signed).
        d_right: travel of the right wheel during the step, metres (signed).
        wheel_base: distance between the wheels ``b``, metres (> 0).

    Returns:
        pose_next: (3,) pose after the step, heading wrapped to ``(-pi, pi]``.
        next_D_pose: (3, 3) Jacobian w.r.t. the plain coordinates ``(x, y, theta)``
            (not GTSAM's tangent): eq. 14's ``F_x``.
        next_D_wheels: (3, 2) Jacobian w.r.t. ``(d_left, d_right)``: eq. 14's ``F_u``.
    """
    ds = 0.5 * (d_right + d_left)
    dth = (d_right - d_left) / wheel_base
    a = pose[2] + 0.5 * dth
    c, s = math.cos(a), math.sin(a)
    pose_next = np.array([pose[0] + ds * c, pose[1] + ds * s, wrap_angle(pose[2] + dth)])
    next_D_pose = np.array([[1.0, 0.0, -ds * s], [0.0, 1.0, ds * c], [0.0, 0.0, 1.0]])
    k = ds / (2.0 * wheel_base)
    next_D_wheels = np.array(
        [
            [0.5 * c + k * s, 0.5 * c - k * s],
            [0.5 * s - k * c, 0.5 * s + k * c],
            [-1.0 / wheel_base, 1.0 / wheel_base],
        ]
    )
    return pose_next, next_D_pose, next_D_wheels


def wheel_noise_cov(d_left: float, d_right: float, k_r: float, k_l: float) -> FloatArray:
    """Covariance of the wheel travels of one step (paper 1, eq. 15).

    ``var_left = k_l |d_left|``, ``var_right = k_r |d_right|``, independent.

    Args:
        d_left: left wheel travel, metres.
        d_right: right wheel travel, metres.
        k_r: right wheel noise constant, metres (variance per metre travelled).
        k_l: left wheel noise constant, metres.

    Returns:
        (2, 2) ``diag(k_l |d_left|, k_r |d_right|)`` in m^2, ordered (left, right)
        like ``next_D_wheels`` of :func:`diff_drive_step`.
    """
    return np.diag([k_l * abs(d_left), k_r * abs(d_right)])


def _as_floor(floor: float | Sequence[float] | FloatArray) -> FloatArray:
    """(3,) variance floor (m^2, m^2, rad^2) from a scalar or 3 values; FactorError unless finite and > 0."""
    arr = np.broadcast_to(np.asarray(floor, dtype=float), (3,)).copy()
    if not np.all(np.isfinite(arr)) or np.any(arr <= 0.0):
        raise FactorError(f"odometry covariance floor must be finite and > 0, got {arr}")
    return arr


def accumulate_odometry(
    d_left: FloatArray,
    d_right: FloatArray,
    wheel_base: float,
    k_r: float,
    k_l: float,
    floor: float | Sequence[float] | FloatArray = DEFAULT_FLOOR_VAR,
) -> tuple[FloatArray, FloatArray]:
    """Relative motion of a sequence of wheel increments and its covariance.

    Starting at the identity pose with zero covariance, each increment ``i`` applies
    eq. 13 and propagates ``P <- F_x P F_x^T + F_u Q_i F_u^T`` (eqs. 14-15) in plain
    coordinates. At the end the covariance is moved to GTSAM's right tangent at the
    relative pose ``delta``: ``T P T^T`` with ``T = blockdiag(R(theta_delta)^T, 1)``
    (conventions.md "Pose Jacobians"), and ``diag(floor)`` is added.

    The result is exactly what ``gtsam.BetweenFactorPose2(X(i), X(j), Pose2(*delta),
    noiseModel.Gaussian.Covariance(cov))`` needs.

    Args:
        d_left: (N,) left wheel travels, metres; N >= 0 (N = 0 gives the identity).
        d_right: (N,) right wheel travels, metres.
        wheel_base: wheel base ``b``, metres (> 0).
        k_r: right wheel noise constant (eq. 15), metres.
        k_l: left wheel noise constant (eq. 15), metres.
        floor: variances added to the diagonal of the tangent covariance, a scalar or
            (3,) in (m^2, m^2, rad^2); must be > 0. Default :data:`DEFAULT_FLOOR_VAR`.

    Returns:
        delta: (3,) ``start_T_end = (x, y, theta)`` in the start pose's body frame.
        cov: (3, 3) covariance of ``delta`` in GTSAM's right tangent at ``delta``,
            symmetric positive definite.

    Raises:
        FactorError: mismatched lengths, NaN/inf travels, ``wheel_base <= 0``,
            negative noise constants or a non-positive floor.
    """
    left = np.atleast_1d(np.asarray(d_left, dtype=float))
    right = np.atleast_1d(np.asarray(d_right, dtype=float))
    if left.ndim != 1 or left.shape != right.shape:
        raise FactorError(
            f"d_left and d_right must be 1-D of equal length, got {left.shape} and {right.shape}"
        )
    if not (np.all(np.isfinite(left)) and np.all(np.isfinite(right))):
        raise FactorError("wheel travels contain NaN or inf")
    if not (wheel_base > 0.0 and math.isfinite(wheel_base)):
        raise FactorError(f"wheel_base must be finite and > 0, got {wheel_base}")
    if not (k_r >= 0.0 and k_l >= 0.0):
        raise FactorError(f"wheel noise constants must be >= 0, got k_r={k_r}, k_l={k_l}")
    floor_var = _as_floor(floor)

    pose = np.zeros(3)
    cov = np.zeros((3, 3))
    for dl, dr in zip(left.tolist(), right.tolist(), strict=True):
        pose, f_x, f_u = diff_drive_step(pose, dl, dr, wheel_base)
        cov = f_x @ cov @ f_x.T + f_u @ wheel_noise_cov(dl, dr, k_r, k_l) @ f_u.T
    t = tangent_D_coords(pose[2])
    cov = t @ cov @ t.T
    cov = 0.5 * (cov + cov.T) + np.diag(floor_var)
    return pose, cov


def odometry_between(
    d_left: float | FloatArray,
    d_right: float | FloatArray,
    wheel_base: float,
    k_r: float,
    k_l: float,
    floor: float | Sequence[float] | FloatArray = DEFAULT_FLOOR_VAR,
) -> tuple[FloatArray, FloatArray]:
    """Relative pose and tangent covariance of one odometry step (or several).

    A scalar pair is one step of eq. 13; arrays are passed to
    :func:`accumulate_odometry`, which this wraps.

    Args:
        d_left: left wheel travel(s), metres, scalar or (N,).
        d_right: right wheel travel(s), metres, same shape as ``d_left``.
        wheel_base: wheel base, metres.
        k_r: right wheel noise constant (eq. 15), metres.
        k_l: left wheel noise constant (eq. 15), metres.
        floor: tangent variance floor, scalar or (3,) (m^2, m^2, rad^2).

    Returns:
        delta: (3,) relative pose in the start pose's body frame.
        cov: (3, 3) covariance in GTSAM's right tangent at ``delta`` (for
            ``gtsam.BetweenFactorPose2``).
    """
    return accumulate_odometry(
        np.atleast_1d(np.asarray(d_left, dtype=float)),
        np.atleast_1d(np.asarray(d_right, dtype=float)),
        wheel_base,
        k_r,
        k_l,
        floor,
    )
