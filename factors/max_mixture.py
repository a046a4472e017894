"""Max-mixture range-bearing factor: one sighting, several candidate landmarks, or none.

Olson & Agarwal, "Inference on networks of mixtures for robust robot mapping" (RSS 2012,
IJRR 2013): a measurement whose association is uncertain enters the graph as one factor
whose likelihood is the *max* of its components' rather than their sum, so the negative
log-likelihood stays a sum of squares and the component is re-chosen at every
linearisation. Here the components are the range-bearing model against each candidate
landmark (all with the sighting's stated noise ``R``, so their normalisers are equal and
drop out) and a "none of them" component of constant squared cost ``null_chi2`` (the
description length's price of a sighting that matches nothing, ``c_new``): the factor's
squared whitened error is

    ``min(null_chi2, min_j |W (h(x, l_j) - z)|^2)``,

``W`` the sqrt information of ``R`` (:func:`lampsam.factors.gtsam_factors.sqrt_information`),
the bearing residual wrapped to ``(-pi, pi]``. The chosen component gives the residual and
its Jacobians; the other landmarks get zero Jacobians, the null component zero everywhere
(its residual ``(sqrt(null_chi2), 0)`` is a constant).

Frames: pose ``world_T_body = (x, y, theta)`` (m, rad), landmarks world (m), ``z =
[bearing, range]`` in the body frame (rad, m), as ``BearingRangeFactor2D``.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import gtsam
import numpy as np

from lampsam.arrays import FloatArray
from lampsam.factors.geometry import FactorError, wrap_angle
from lampsam.factors.gtsam_factors import check_cov, pose_array, sqrt_information
from lampsam.factors.range_bearing import range_bearing

__all__ = ["max_mixture_choice", "max_mixture_factor", "mixture_residual"]


def mixture_residual(pose: FloatArray, landmarks: Sequence[FloatArray], z: FloatArray,
                     sqrt_info: FloatArray, null_chi2: float
                     ) -> tuple[int, FloatArray, FloatArray, FloatArray]:
    """The max-mixture's chosen component, its whitened residual and Jacobians.

    Args:
        pose: (3,) ``(x, y, theta)``; landmarks: the candidates, each (2,) world, m;
        z: (2,) measured ``[bearing, range]``; sqrt_info: (2, 2) ``W`` with
        ``W^T W = R^-1``; null_chi2: the "none of them" component's squared error.

    Returns:
        ``(j, e (2,), e_D_pose (2, 3), e_D_landmark (2, 2))``: ``j`` the chosen
        candidate's index, -1 for none (then ``e = (sqrt(null_chi2), 0)`` and both
        Jacobians zero); ``e = W (h - z)`` (bearing wrapped).
    """
    best = (-1, np.array([math.sqrt(null_chi2), 0.0]), np.zeros((2, 3)), np.zeros((2, 2)))
    best_c = float(null_chi2)
    for j, lm in enumerate(landmarks):
        try:
            h, h_p, h_l = range_bearing(pose, lm)
        except FactorError:  # the landmark on the pose: not this component
            continue
        nu = np.array([wrap_angle(float(h[0] - z[0])), float(h[1] - z[1])])
        e = sqrt_info @ nu
        c = float(e @ e)
        if c < best_c:
            best_c, best = c, (j, e, sqrt_info @ h_p, sqrt_info @ h_l)
    return best


def max_mixture_choice(pose: FloatArray, landmarks: Sequence[FloatArray], z: FloatArray,
                       cov: FloatArray, null_chi2: float) -> tuple[int, float]:
    """``(chosen candidate index or -1, its squared error)`` of :func:`mixture_residual`
    with the sighting's covariance ``cov`` (2, 2)."""
    j, e, _, _ = mixture_residual(pose, landmarks, z, sqrt_information(cov), null_chi2)
    return j, float(e @ e)


def max_mixture_factor(pose_key: int, landmark_keys: Sequence[int], z: FloatArray,
                       cov: FloatArray, null_chi2: float) -> gtsam.CustomFactor:
    """A range-bearing sighting of one of ``landmark_keys`` or of none (module doc).

    Args:
        pose_key: the sighting's pose ``X(k)`` (``Pose2``); landmark_keys: its candidates
            ``L(j)`` (``Point2``), at least one.
        z: (2,) ``[bearing, range]``, rad and m; cov: (2, 2) its noise.
        null_chi2: squared error of "none of them" (> 0), e.g. ``c_new``.

    Returns:
        ``gtsam.CustomFactor`` on ``[pose_key, *landmark_keys]`` with a unit noise model
        (the residual is whitened inside); ``2 x error`` is the chosen component's
        squared error.
    """
    if not landmark_keys:
        raise FactorError("max_mixture_factor: no candidate landmark")
    if not null_chi2 > 0.0:
        raise FactorError(f"max_mixture_factor: null_chi2 must be > 0, got {null_chi2}")
    w = sqrt_information(check_cov(cov, 2, "max-mixture sighting"))
    meas = np.asarray(z, float).copy()
    n = len(landmark_keys)

    def error(this: gtsam.CustomFactor, values: gtsam.Values, H: Any) -> FloatArray:
        ks = this.keys()
        pose = pose_array(values.atPose2(ks[0]))
        lms = [np.asarray(values.atPoint2(ks[1 + i]), float) for i in range(n)]
        j, e, e_p, e_l = mixture_residual(pose, lms, meas, w, null_chi2)
        if H is not None:
            H[0] = e_p
            for i in range(n):
                H[1 + i] = e_l if i == j else np.zeros((2, 2))
        return e

    return gtsam.CustomFactor(gtsam.noiseModel.Unit.Create(2), [pose_key, *landmark_keys],
                              error)
