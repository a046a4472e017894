"""Odometry as relative ``Pose2`` increments with their own covariance.

What ``nav_msgs/Odometry`` (twist or differenced poses), GTSAM/iSAM/g2o files and most
robots give: each sample is ``delta_i = prev_T_body`` in the previous sample's body
frame, with a (3, 3) covariance in GTSAM's right tangent at ``delta_i``
(``delta_true = delta_i Exp(xi)``, ``xi ~ N(0, C_i)``; docs/conventions.md). Beside the
wheel model (:mod:`lampsam.factors.motion`, paper 1 eqs. 13-15) it needs no robot
geometry, and it can carry sideways noise that two wheels cannot express.

Pure numpy:

* :func:`pose2_step` -- ``pose <- pose * delta`` with the plain-coordinate Jacobians
  the EKF needs (w.r.t. the pose's coordinates and the increment's right tangent);
* :func:`se2_adjoint` -- ``Ad(T)`` of a planar pose (GTSAM's ``Pose2.AdjointMap``);
* :func:`accumulate_pose2` -- the composed increment of several samples and its
  right-tangent covariance (``BetweenFactorPose2``'s noise);
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from lampsam.arrays import FloatArray
from lampsam.factors.geometry import FactorError, coords_D_tangent, wrap_angle


def pose2_step(pose: FloatArray, delta: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
    """``world_T_next = world_T_body * delta`` and its Jacobians.

    ``x' = x + c dx - s dy``, ``y' = y + s dx + c dy``, ``theta' = theta + dtheta``
    (``c, s`` of ``theta``).

    Args:
        pose: (3,) ``world_T_body = (x, y, theta)``, m and rad.
        delta: (3,) ``body_T_next = (dx, dy, dtheta)``, m and rad.

    Returns:
        next: (3,) the composed pose, theta wrapped.
        next_D_pose: (3, 3) w.r.t. the pose's plain coordinates.
        next_D_delta: (3, 3) w.r.t. the right tangent of ``delta``:
            ``blockdiag(R(theta'), 1)``.
    """
    x, y, th = float(pose[0]), float(pose[1]), float(pose[2])
    dx, dy, dth = float(delta[0]), float(delta[1]), float(delta[2])
    c, s = math.cos(th), math.sin(th)
    nxt = np.array([x + c * dx - s * dy, y + s * dx + c * dy, wrap_angle(th + dth)])
    next_D_pose = np.array([[1.0, 0.0, -s * dx - c * dy],
                            [0.0, 1.0, c * dx - s * dy],
                            [0.0, 0.0, 1.0]])
    return nxt, next_D_pose, coords_D_tangent(th + dth)


def se2_adjoint(pose: FloatArray) -> FloatArray:
    """(3, 3) adjoint ``Ad(T)`` of ``T = (x, y, theta)`` on the right tangent ``(vx, vy, w)``.

    ``T Exp(xi) = Exp(Ad(T) xi) T``; ``[[R, (y, -x)^T], [0, 0, 1]]`` (GTSAM's
    ``Pose2.AdjointMap``).
    """
    c, s = math.cos(float(pose[2])), math.sin(float(pose[2]))
    return np.array([[c, -s, float(pose[1])], [s, c, -float(pose[0])], [0.0, 0.0, 1.0]])


def _inverse(pose: FloatArray) -> FloatArray:
    c, s = math.cos(float(pose[2])), math.sin(float(pose[2]))
    x, y = float(pose[0]), float(pose[1])
    return np.array([-c * x - s * y, s * x - c * y, -float(pose[2])])


def accumulate_pose2(deltas: FloatArray, covs: FloatArray,
                     floor: float | Sequence[float] | FloatArray = 0.0
                     ) -> tuple[FloatArray, FloatArray]:
    """Composed increment of several samples and its right-tangent covariance.

    With ``D_i = D_{i-1} delta_i`` and independent sample noise,
    ``Sigma_i = Ad(delta_i^-1) Sigma_{i-1} Ad(delta_i^-1)^T + C_i`` (first order); then
    ``diag(floor)`` is added.

    Args:
        deltas: (N, 3) increments ``(dx, dy, dtheta)``, each in the previous
            sample's body frame, m and rad (N = 0 gives the identity).
        covs: (N, 3, 3) their right-tangent covariances, m^2 / rad^2.
        floor: scalar or (3,) variances added once at the end (>= 0).

    Returns:
        delta: (3,) ``start_T_end``; cov: (3, 3) its right-tangent covariance.

    Raises:
        FactorError: mismatched shapes, NaN/inf, or a negative floor.
    """
    d = np.asarray(deltas, dtype=float).reshape(-1, 3)
    c = np.asarray(covs, dtype=float).reshape(-1, 3, 3)
    if len(d) != len(c):
        raise FactorError(f"{len(d)} increments but {len(c)} covariances")
    if not (np.all(np.isfinite(d)) and np.all(np.isfinite(c))):
        raise FactorError("odometry increments or covariances contain NaN or inf")
    fl = np.broadcast_to(np.asarray(floor, dtype=float), (3,))
    if np.any(fl < 0) or not np.all(np.isfinite(fl)):
        raise FactorError(f"odometry covariance floor must be finite and >= 0, got {fl}")
    if len(d) == 1:  # one sample (a keyframe per pose): the loop below gives exactly this
        total, _, _ = pose2_step(np.zeros(3), d[0])
        return total, 0.5 * (c[0] + c[0].T) + np.diag(fl)
    total = np.zeros(3)
    cov = np.zeros((3, 3))
    for di, ci in zip(d, c, strict=True):
        ad = se2_adjoint(_inverse(di))
        cov = ad @ cov @ ad.T + ci
        total, _, _ = pose2_step(total, di)
    return total, 0.5 * (cov + cov.T) + np.diag(fl)


