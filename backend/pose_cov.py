"""Pose-covariance algebra on SE(2) in GTSAM's right tangent (docs/conventions.md).

Pose covariances inside the smoothers live in the right tangent of the pose
(``x = x_hat Exp(xi)``, ``xi = (dx_body, dy_body, dtheta)``); the backends report
them over plain world coordinates ``(x, y, theta)``. These pure functions compose
odometry with its covariance to first order (Barfoot & Furgale 2014, "Associating
uncertainty with three-dimensional poses", sec. III, in SE(2)), condition the
odometry between two keyframes on both keyframes' final estimates, and carry a
keyframe's joint marginal with a landmark to the current pose (the gate's eq. 19).
"""

from __future__ import annotations

import gtsam
import numpy as np

from lampsam.arrays import FloatArray
from lampsam.factors.geometry import coords_D_tangent
from lampsam.factors.gtsam_factors import pose_array as pose_array  # the one Pose2 -> array


def tangent_to_coords_cov(pose: FloatArray, cov_t: FloatArray) -> FloatArray:
    """Covariance in GTSAM's right tangent -> over plain coordinates (x, y, theta).

    Args:
        pose: (3,) the pose ``world_T_body``.
        cov_t: (3, 3) right-tangent covariance, m^2 / rad^2.

    Returns:
        (3, 3) ``J cov_t J^T`` with ``J = blockdiag(R(theta), 1)``
        (:func:`lampsam.factors.geometry.coords_D_tangent`).
    """
    j = coords_D_tangent(float(pose[2]))
    return j @ cov_t @ j.T


def compose_cov(delta: FloatArray, cov_a: FloatArray, cov_b: FloatArray) -> FloatArray:
    """Right-tangent covariance of ``a * b`` from those of ``a`` and ``b`` (first order).

    ``a b Exp(xi) = a Exp(xi_a) b Exp(xi_b)`` gives ``xi = Ad(b^-1) xi_a + xi_b``.

    Args:
        delta: (3,) the pose ``b`` (x, y, theta).
        cov_a: (3, 3) covariance of ``a`` (tangent at ``a``).
        cov_b: (3, 3) covariance of ``b`` (tangent at ``b``), independent of ``a``.

    Returns:
        (3, 3) ``Ad(b^-1) cov_a Ad(b^-1)^T + cov_b``.
    """
    ad = gtsam.Pose2(*delta).inverse().AdjointMap()
    return ad @ cov_a @ ad.T + cov_b


def odometry_bridge(delta: FloatArray, cov_delta: FloatArray, delta_kf: FloatArray,
                    cov_kf: FloatArray, pose_k: FloatArray, pose_k1: FloatArray
                    ) -> tuple[FloatArray, FloatArray]:
    """A step between keyframes ``k`` and ``k+1``, conditioned on both final estimates.

    The odometry from keyframe ``k`` to the step, ``delta = delta_hat Exp(a)``
    (``a ~ N(0, A)``), and on to keyframe ``k+1``, ``eps = eps_hat Exp(b)``, compose to
    ``Delta ~ Delta_hat Exp(M a + b)`` with ``M = Ad(eps_hat^-1)`` and covariance
    ``Sigma = M A M^T + B``. The smoother fixes ``Delta`` to
    ``pose_k^-1 pose_k1``, i.e. the residual ``r = Log(Delta_hat^-1 Delta)``, and
    the Gaussian conditional (first order, a Brownian bridge along the odometry) is
    ``a | r ~ N(G r, A - G M A)`` with ``G = A M^T Sigma^-1``. Without it, the steps
    between keyframes would carry the whole odometry drift since keyframe ``k``.
    The covariance is right when the odometry model's noise is (measured figures:
    docs/graph-backend.md).

    Args:
        delta, cov_delta: (3,), (3, 3) odometry from keyframe ``k`` to the step and
            its right-tangent covariance.
        delta_kf, cov_kf: (3,), (3, 3) odometry from keyframe ``k`` to ``k+1`` (the
            odometry factor's) and its covariance.
        pose_k, pose_k1: (3,) final estimates of the two keyframes, world frame.

    Returns:
        ``(delta', cov')``: the conditioned odometry to the step and its covariance;
        the inputs unchanged if the system is degenerate.
    """
    d_hat = gtsam.Pose2(*delta)
    big = gtsam.Pose2(*delta_kf)
    eps = d_hat.inverse().compose(big)
    m = eps.inverse().AdjointMap()
    observed = gtsam.Pose2(*pose_k).inverse().compose(gtsam.Pose2(*pose_k1))
    r = gtsam.Pose2.Logmap(big.inverse().compose(observed))
    a_mt = cov_delta @ m.T
    try:
        gain = np.linalg.solve(np.asarray(cov_kf, float), a_mt.T).T
    except np.linalg.LinAlgError:
        return delta, cov_delta
    if not np.all(np.isfinite(gain)):
        return delta, cov_delta
    out = d_hat.compose(gtsam.Pose2.Expmap(gain @ r))
    cov = cov_delta - gain @ m @ cov_delta
    return np.array([out.x(), out.y(), out.theta()]), 0.5 * (cov + cov.T)


def eq19_covariance(h_p: FloatArray, h_l: FloatArray,
                    joint: tuple[FloatArray, FloatArray, FloatArray], delta: FloatArray,
                    delta_cov: FloatArray, r: FloatArray) -> FloatArray:
    """Innovation covariance ``Psi`` of eq. 19 from a keyframe's joint marginal with a landmark.

    The current pose is ``x = x_j * delta``; in the right tangent
    ``dx = Ad(delta^-1) dx_j + d_delta``, so with the joint blocks
    ``(S_jj, S_jl, S_ll)`` of ``(X(j), landmark)``:
    ``S_xx = Ad S_jj Ad^T + C``, ``S_xl = Ad S_jl`` and
    ``Psi = H_p S_xx H_p^T + H_p S_xl H_l^T + (.)^T + H_l S_ll H_l^T + R``.

    Args:
        h_p: (m, 3) and h_l: (m, d) measurement Jacobians (pose right tangent, landmark state).
        joint: ``(S_jj (3, 3), S_jl (3, d), S_ll (d, d))``.
        delta: (3,) ``x_j^-1 x``; delta_cov: (3, 3) its covariance (odometry).
        r: (m, m) measurement noise.

    Returns:
        (m, m) ``Psi``.
    """
    s_kk, s_kl, s_ll = joint
    ad = gtsam.Pose2(*delta).inverse().AdjointMap()
    s_xx = ad @ s_kk @ ad.T + delta_cov
    s_xl = ad @ s_kl
    cross = h_p @ s_xl @ h_l.T
    return h_p @ s_xx @ h_p.T + cross + cross.T + h_l @ s_ll @ h_l.T + r


def propagate_relative(delta: FloatArray, cov_delta: FloatArray, covs: FloatArray) -> FloatArray:
    """Relative covariances one keyframe on: ``Ad(d^-1) Sigma_j Ad(d^-1)^T + C`` for every ``j``.

    :func:`~lampsam.backend.pose_cov.compose_cov` of ``x_j^-1 x_(k-1)`` with the
    odometry ``d = x_(k-1)^-1 x_k``, vectorised over the window.

    Args:
        delta: (3,) odometry ``d`` (x, y, theta), m and rad.
        cov_delta: (3, 3) its right-tangent covariance ``C``.
        covs: (n, 3, 3) right-tangent covariances of ``x_j^-1 x_(k-1)``.

    Returns:
        (n, 3, 3) covariances of ``x_j^-1 x_k``.
    """
    ad = gtsam.Pose2(*delta).inverse().AdjointMap()
    return np.einsum("ab,nbc,dc->nad", ad, covs, ad) + cov_delta
