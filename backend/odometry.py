"""Odometry as the backends see it: a motion model over a step's odometry samples.

Every backend (EKF, iSAM2, batch) is fed, per step, the odometry samples since the
previous step as a (K, m) array and asks a :class:`MotionModel` for what it needs:

- :class:`WheelMotion`: differential-drive wheel travel ``(d_left, d_right)``, m = 2
  (paper 1, eqs. 13-15; :mod:`lampsam.factors.motion`), the ceiling robot's;
- :class:`Pose2Motion`: relative Pose2 increments with their own covariance, m = 12
  (``[dx, dy, dtheta, cov row-major]``; :mod:`lampsam.factors.pose2_odometry`), what
  ``nav_msgs/Odometry`` and GTSAM/iSAM/g2o files give; samples without covariance
  and the floor that keeps a robot at rest non-singular come from
  :class:`lampsam.datasets.odometry.Pose2OdometryModel`.

:func:`motion_model` picks the model from the constants a run carries.
"""

from __future__ import annotations

import math
from typing import Protocol, TypeAlias

import numpy as np

from lampsam.arrays import FloatArray
from lampsam.datasets.odometry import POSE2_SAMPLE_WIDTH, Pose2OdometryModel
from lampsam.errors import EstimationError
from lampsam.factors.geometry import wrap_angle
from lampsam.factors.motion import accumulate_odometry, diff_drive_step, wheel_noise_cov
from lampsam.factors.pose2_odometry import accumulate_pose2, pose2_step


class WheelParams(Protocol):
    """The wheel model's constants (``lampsam.datasets.logrun.OdometryModel`` is one).

    Attributes:
        wheel_base: distance between the wheels, m.
        k_r, k_l: wheel noise variances per metre of travel, m (eq. 15:
            ``var(d) = k |d|``).
    """

    @property
    def wheel_base(self) -> float: ...  # noqa: D102

    @property
    def k_r(self) -> float: ...  # noqa: D102

    @property
    def k_l(self) -> float: ...  # noqa: D102


class MotionModel(Protocol):
    """What a backend needs of the odometry over one step's samples."""

    #: columns of a sample row
    width: int

    def check(self, t: float, samples: FloatArray) -> FloatArray:
        """(K, width) float samples, or EstimationError (NaN / inf increments)."""

    def relative(self, samples: FloatArray, floor_var: float | FloatArray
                 ) -> tuple[FloatArray, FloatArray]:
        """``(delta (3,), cov (3, 3))``: the samples' composed motion in the body frame
        of the first sample's start, and its right-tangent covariance plus
        ``diag(floor_var)`` (a ``BetweenFactorPose2``'s measurement and noise)."""

    def ekf_predict(self, pose: FloatArray, samples: FloatArray
                    ) -> tuple[FloatArray, FloatArray, FloatArray]:
        """``(pose', F (3, 3), Q (3, 3))`` over the samples in plain coordinates:
        ``P_RR <- F P_RR F^T + Q`` (eqs. 13-15 composed)."""


def check_wheel(t: float, wheel: FloatArray) -> FloatArray:
    """Validate a step's wheel travels.

    Args:
        t: step time, s (for the message).
        wheel: (K, 2) ``(d_left, d_right)`` travels, m.

    Returns:
        The travels as a float (K, 2) array.

    Raises:
        EstimationError: wrong shape or NaN / inf.
    """
    arr = np.asarray(wheel, dtype=float).reshape(-1, 2)
    if not np.all(np.isfinite(arr)):
        raise EstimationError(f"t={t:.3f} s: odometry increment is NaN or inf")
    return arr


class WheelMotion:
    """Differential-drive wheel travel (paper 1, eqs. 13-15).

    Args:
        params: wheel base and noise constants.
    """

    width = 2

    def __init__(self, params: WheelParams) -> None:
        self.params = params

    def check(self, t: float, samples: FloatArray) -> FloatArray:
        """(K, 2) ``(d_left, d_right)``, m; see :func:`check_wheel`."""
        return check_wheel(t, samples)

    def relative(self, samples: FloatArray, floor_var: float | FloatArray
                 ) -> tuple[FloatArray, FloatArray]:
        """:func:`lampsam.factors.motion.accumulate_odometry` of the travels."""
        p = self.params
        return accumulate_odometry(samples[:, 0], samples[:, 1], p.wheel_base, p.k_r, p.k_l,
                                   floor_var)

    def ekf_predict(self, pose: FloatArray, samples: FloatArray
                    ) -> tuple[FloatArray, FloatArray, FloatArray]:
        """Eq. 13 per sample; ``F`` the product of eq. 14's ``F_x``, ``Q`` eq. 15 propagated."""
        b, k_r, k_l = self.params.wheel_base, self.params.k_r, self.params.k_l
        pose = np.asarray(pose, float).copy()
        f_tot = np.eye(3)
        q_acc = np.zeros((3, 3))
        for d_left, d_right in samples:
            pose, f_x, f_u = diff_drive_step(pose, float(d_left), float(d_right), b)
            q_acc = f_x @ q_acc @ f_x.T + f_u @ wheel_noise_cov(d_left, d_right, k_r, k_l) @ f_u.T
            f_tot = f_x @ f_tot
        return pose, f_tot, q_acc


class Pose2Motion:
    """Relative Pose2 increments with covariance (see module docstring).

    Args:
        model: default noise of samples without covariance, and the per-sample floor.
    """

    width = POSE2_SAMPLE_WIDTH

    def __init__(self, model: Pose2OdometryModel) -> None:
        self.model = model
        #: (3, 3) the per-sample covariance floor as :meth:`Pose2OdometryModel.sample_cov` adds it
        self.sample_floor = np.diag([model.var_floor_xy, model.var_floor_xy,
                                      model.var_floor_theta])

    def check(self, t: float, samples: FloatArray) -> FloatArray:
        """(K, 12) rows; the increments must be finite (covariances may be NaN: default)."""
        arr = np.asarray(samples, dtype=float).reshape(-1, POSE2_SAMPLE_WIDTH)
        if not np.all(np.isfinite(arr[:, :3])):
            raise EstimationError(f"t={t:.3f} s: odometry increment is NaN or inf")
        return arr

    def _covs(self, samples: FloatArray) -> FloatArray:
        return np.array([self.model.sample_cov(s[:3], s[3:].reshape(3, 3)) for s in samples]
                        ).reshape(-1, 3, 3)

    def relative(self, samples: FloatArray, floor_var: float | FloatArray
                 ) -> tuple[FloatArray, FloatArray]:
        """:func:`lampsam.factors.pose2_odometry.accumulate_pose2` of the samples.

        One sample with a scalar floor (a step per pose: the dense-log case) takes a
        short path with the same arithmetic: the increment itself (theta wrapped)
        and ``sym(sample_cov) + floor I``.
        """
        if len(samples) == 1 and isinstance(floor_var, float):
            row = samples[0]
            dx, dy, dth = row[:3].tolist()
            c = row[3:].reshape(3, 3)
            if (math.isfinite(dx) and math.isfinite(dy) and math.isfinite(dth)
                    and math.isfinite(floor_var) and floor_var >= 0.0 and np.isfinite(c).all()):
                cov = c + self.sample_floor  # Pose2OdometryModel.sample_cov of a given cov
                sym = 0.5 * (cov + cov.T)
                sym[0, 0] += floor_var
                sym[1, 1] += floor_var
                sym[2, 2] += floor_var
                return np.array([0.0 + dx, 0.0 + dy, wrap_angle(0.0 + dth)]), sym
        return accumulate_pose2(samples[:, :3], self._covs(samples), floor_var)

    def ekf_predict(self, pose: FloatArray, samples: FloatArray
                    ) -> tuple[FloatArray, FloatArray, FloatArray]:
        """``pose <- pose * delta`` per sample; ``Q`` each sample's covariance mapped by
        ``next_D_delta`` (:func:`~lampsam.factors.pose2_odometry.pose2_step`)."""
        pose = np.asarray(pose, float).copy()
        f_tot = np.eye(3)
        q_acc = np.zeros((3, 3))
        for s, c in zip(samples, self._covs(samples), strict=True):
            pose, f_x, f_d = pose2_step(pose, s[:3])
            q_acc = f_x @ q_acc @ f_x.T + f_d @ c @ f_d.T
            f_tot = f_x @ f_tot
        return pose, f_tot, q_acc


#: What a backend accepts as its odometry model.
OdometryConstants: TypeAlias = "WheelParams | Pose2OdometryModel | MotionModel"


def motion_model(odometry: OdometryConstants) -> MotionModel:
    """The motion model for a run's odometry constants.

    Args:
        odometry: wheel constants (:class:`WheelParams`), a
            :class:`~lampsam.datasets.odometry.Pose2OdometryModel`, or a ready model.
    """
    if isinstance(odometry, (WheelMotion, Pose2Motion)):
        return odometry
    if isinstance(odometry, Pose2OdometryModel):
        return Pose2Motion(odometry)
    return WheelMotion(odometry)  # type: ignore[arg-type]
