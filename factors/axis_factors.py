"""GTSAM factors of a lamp's long axis ``A(j)`` (paper III.4: the axis angle mod pi).

Three forms of the same residual ``wrap_axis(phi - theta - alpha)`` (see
:func:`lampsam.factors.ceiling.lamp_axis_residual`): the built-in ``BetweenFactorPose2``
on ``(X, A)`` with ``A`` a ``Pose2`` whose translation carries no information (used by
the smoothers, the fastest), and ``CustomFactor`` forms on a ``Rot2`` per observation or
per frame (kept as the reference). Costs and the choice between them: the module
docstring of :mod:`lampsam.factors.gtsam_factors`.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from functools import lru_cache
from typing import Any

import gtsam
import numpy as np

from lampsam.arrays import FloatArray
from lampsam.factors.ceiling import lamp_axis_residual
from lampsam.factors.geometry import FactorError
from lampsam.factors.gtsam_factors import huber_sqrt, noise_model, pose_array, robust_wrap

__all__ = [
    "AxisObservation",
    "axis_anchor_prior",
    "lamp_axis_between_factor",
    "lamp_axis_factor",
    "lamp_axis_frame_factor",
]


@dataclass(frozen=True)
class AxisObservation:
    """One lamp-axis observation for :func:`lamp_axis_frame_factor`.

    Attributes:
        axis_key: ``A(j)`` (a ``Rot2``).
        alpha: measured axis in the ``(u, v)`` plane, radians (mod pi).
        sigma: its standard deviation, radians.
    """

    axis_key: int
    alpha: float
    sigma: float


def lamp_axis_factor(
    pose_key: int,
    axis_key: int,
    alpha: float,
    sigma: float,
    robust: float | None = None,
) -> gtsam.CustomFactor:
    """Lamp axis observation (``phi_i = phi - theta`` mod pi), one ``CustomFactor``.

    Args:
        pose_key: ``X(k)``.
        axis_key: ``A(j)``, a ``gtsam.Rot2``.
        alpha: measured axis, radians, any representative mod pi.
        sigma: its standard deviation, radians (> 0).
        robust: optional Huber threshold.

    Returns:
        ``gtsam.CustomFactor`` with a 1-D residual wrapped to ``(-pi/2, pi/2]``.
    """
    if not sigma > 0.0:
        raise FactorError(f"axis sigma must be > 0, got {sigma}")
    meas = float(alpha)

    def error(this: gtsam.CustomFactor, values: gtsam.Values, H: Any) -> FloatArray:
        pose = pose_array(values.atPose2(this.keys()[0]))
        phi = values.atRot2(this.keys()[1]).theta()
        r, r_D_pose, r_D_phi = lamp_axis_residual(pose, phi, meas)
        if H is not None:
            H[0] = r_D_pose
            H[1] = r_D_phi
        return np.array([r])

    return gtsam.CustomFactor(
        noise_model(np.array([[sigma * sigma]]), robust), [pose_key, axis_key], error
    )


def lamp_axis_frame_factor(
    pose_key: int,
    observations: Sequence[AxisObservation],
    robust: float | None = None,
) -> gtsam.CustomFactor:
    """All lamp-axis observations of one frame in one ``CustomFactor``.

    Residual ``i`` is ``wrap_axis(phi_i - theta - alpha_i) / sigma_i`` (whitened, unit
    noise model), Huber per observation if ``robust`` is set.

    Args:
        pose_key: ``X(k)``.
        observations: one :class:`AxisObservation` per lamp, distinct axis keys.
        robust: optional Huber threshold.

    Returns:
        ``gtsam.CustomFactor`` on ``[pose_key, axis keys...]`` with a (K,) residual.
    """
    obs = list(observations)
    if not obs:
        raise FactorError("lamp_axis_frame_factor needs at least one observation")
    keys = [pose_key] + [o.axis_key for o in obs]
    if len(set(keys)) != len(keys):
        raise FactorError("lamp_axis_frame_factor: axis keys must be distinct")
    alphas = [float(o.alpha) for o in obs]
    inv_sig = [1.0 / float(o.sigma) for o in obs]
    n = len(obs)

    def error(this: gtsam.CustomFactor, values: gtsam.Values, H: Any) -> FloatArray:
        ks = this.keys()
        pose = pose_array(values.atPose2(ks[0]))
        res = np.empty(n)
        d_pose = np.zeros((n, 3))
        d_phi = np.empty(n)
        for i in range(n):
            r, _, _ = lamp_axis_residual(pose, values.atRot2(ks[i + 1]).theta(), alphas[i])
            e = r * inv_sig[i]
            g = 1.0
            if robust is not None:
                e_arr, g_arr = huber_sqrt(np.array([e]), robust)
                e, g = float(e_arr[0]), float(g_arr[0, 0])
            res[i] = e
            d_pose[i, 2] = -g * inv_sig[i]
            d_phi[i] = g * inv_sig[i]
        if H is not None:
            H[0] = d_pose
            for i in range(n):
                col = np.zeros((n, 1))
                col[i, 0] = d_phi[i]
                H[i + 1] = col
        return res

    return gtsam.CustomFactor(gtsam.noiseModel.Unit.Create(n), keys, error)


@lru_cache(maxsize=1)
def _axis_anchor_noise() -> gtsam.noiseModel.Base:
    return gtsam.noiseModel.Diagonal.Precisions(np.array([1.0, 1.0, 0.0]))


def lamp_axis_between_factor(
    pose_key: int,
    axis_key: int,
    alpha: float,
    sigma: float,
    predicted: float,
    robust: float | None = None,
) -> gtsam.BetweenFactorPose2:
    """Lamp axis observation as GTSAM's built-in ``BetweenFactorPose2`` (no callback).

    The axis variable ``A(j)`` is then a ``Pose2`` whose rotation is the axis ``phi``
    and whose translation carries no information: the factor's noise model has zero
    precision on ``x, y`` and ``1/sigma^2`` on the angle, and :func:`axis_anchor_prior`
    holds the translation. With GTSAM's default ``Pose2`` chart the angle row of
    ``Local(measured, X^-1 A)`` is ``wrap_angle(phi - theta - alpha)`` and its
    Jacobians are ``-1`` on ``theta`` and ``+1`` on ``phi``, exactly those of
    :func:`lamp_axis_factor` (paper III.4, ``phi_i = phi - theta``); the ``x, y``
    rows are whitened to zero, so the two factors have the same error, gradient and
    Hessian (checked in ``tests/test_factors_gtsam.py``).

    A line's angle is known mod pi, a ``Pose2`` angle mod 2 pi: the representative
    of ``alpha`` nearest to ``predicted`` is fixed here, once. The residual stays
    right while the estimate moves by less than pi/2 from that prediction (a gated
    match is within a few sigma).

    Args:
        pose_key: ``X(k)``.
        axis_key: ``A(j)``, a ``gtsam.Pose2`` anchored by :func:`axis_anchor_prior`.
        alpha: measured axis in the image, radians (any representative mod pi).
        sigma: its standard deviation, radians (> 0).
        predicted: current prediction of ``phi - theta`` in the graph's own
            representative of ``phi``, radians.
        robust: optional Huber threshold (on the angle residual alone, since the
            other rows whiten to zero).

    Returns:
        ``gtsam.BetweenFactorPose2`` on ``(X(k), A(j))``.
    """
    if not sigma > 0.0:
        raise FactorError(f"axis sigma must be > 0, got {sigma}")
    a = float(alpha)
    a += math.pi * round((float(predicted) - a) / math.pi)
    base = gtsam.noiseModel.Diagonal.Precisions(np.array([0.0, 0.0, 1.0 / (sigma * sigma)]))
    return gtsam.BetweenFactorPose2(pose_key, axis_key, gtsam.Pose2(0.0, 0.0, a),
                                    robust_wrap(base, robust))


def axis_anchor_prior(axis_key: int, xy: FloatArray, phi: float) -> gtsam.PriorFactorPose2:
    """Fix the information-free translation of a ``Pose2`` axis variable.

    Unit precision on ``x, y`` (metres), zero on the angle, so the prior says nothing
    about the axis itself. Put its mean at the variable's initial value: the
    translation then never moves (it is decoupled from the angle in ``Pose2``'s
    chart, see :func:`lamp_axis_between_factor`).

    Args:
        axis_key: ``A(j)``.
        xy: (2,) the translation the variable was inserted with, metres.
        phi: the angle it was inserted with, radians (unused by the error).

    Returns:
        ``gtsam.PriorFactorPose2``.
    """
    return gtsam.PriorFactorPose2(axis_key, gtsam.Pose2(float(xy[0]), float(xy[1]), float(phi)),
                                  _axis_anchor_noise())
