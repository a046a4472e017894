"""GTSAM factors of inverse-depth ceiling corners ``C(j) = (alpha_x, alpha_y, rho)``.

A corner is anchored at the pose of its first sight ``X(a)``; its projection into a
later pose is :func:`lampsam.factors.ceiling.project_inverse_depth`. Per observation or
one ``CustomFactor`` per frame (faster inside a GTSAM optimizer), and the first sight with
the height prior as one built-in ``PriorFactorVector``. Costs against the ``Point3``
alternative: the module docstring of :mod:`lampsam.factors.gtsam_factors`.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import gtsam
import numpy as np

from lampsam.arrays import FloatArray
from lampsam.factors.ceiling import HeightPrior, project_inverse_depth, project_inverse_depth_batch
from lampsam.factors.geometry import FactorError
from lampsam.factors.gtsam_factors import check_cov, noise_model, pose_array, sqrt_information

__all__ = [
    "InverseDepthObservation",
    "inverse_depth_factor",
    "inverse_depth_first_sight_prior",
    "inverse_depth_frame_factor",
]


@dataclass(frozen=True)
class InverseDepthObservation:
    """One inverse-depth corner observation for :func:`inverse_depth_frame_factor`.

    Attributes:
        anchor_key: ``X(a)`` of the corner's first sight (not the observing pose).
        corner_key: ``C(j)`` holding ``(alpha_x, alpha_y, rho)``.
        m: (2,) measured normalised coordinates.
        cov_m: (2, 2) their covariance.
    """

    anchor_key: int
    corner_key: int
    m: FloatArray
    cov_m: FloatArray


def _huber_sqrt_rows(e: FloatArray, k: float) -> tuple[FloatArray, FloatArray]:
    """:func:`huber_sqrt` applied to each row of ``e`` (K, d); returns (K, d), (K, d, d)."""
    n_rows, d = e.shape
    norms = np.linalg.norm(e, axis=1)
    r = e.copy()
    r_D_e = np.broadcast_to(np.eye(d), (n_rows, d, d)).copy()
    big = norms > k
    if np.any(big):
        nb = norms[big]
        eb = e[big]
        gb = np.sqrt(2.0 * k * nb - k * k)
        sb = gb / nb
        ds_dn = (k / gb - sb) / nb
        r[big] = sb[:, None] * eb
        r_D_e[big] = sb[:, None, None] * np.eye(d) + (ds_dn / nb)[:, None, None] * np.einsum(
            "ki,kj->kij", eb, eb
        )
    return r, r_D_e


def inverse_depth_factor(
    pose_key: int,
    anchor_key: int,
    corner_key: int,
    m: FloatArray,
    cov_m: FloatArray,
    body_t_camera: FloatArray,
    robust: float | None = None,
) -> gtsam.CustomFactor:
    """Inverse-depth corner seen from a pose other than its anchor (``CustomFactor``).

    Model :func:`lampsam.factors.ceiling.project_inverse_depth`; residual = predicted
    - measured. The first sight is :func:`inverse_depth_first_sight_prior`, not this.

    Args:
        pose_key: observing pose ``X(k)``.
        anchor_key: anchor pose ``X(a)``, ``a != k``.
        corner_key: ``C(j)``, a (3,) vector ``(alpha_x, alpha_y, rho)``.
        m: (2,) measured normalised coordinates.
        cov_m: (2, 2) their covariance.
        body_t_camera: (3,) camera offset, metres.
        robust: optional Huber threshold.

    Returns:
        ``gtsam.CustomFactor`` on ``[pose_key, anchor_key, corner_key]``.
    """
    if pose_key == anchor_key:
        raise FactorError("inverse_depth_factor: the anchor sight is a prior, not a factor")
    cov_m = check_cov(cov_m, 2, "inverse depth")
    meas = np.asarray(m, dtype=float).copy()
    off = np.asarray(body_t_camera, dtype=float).copy()

    def error(this: gtsam.CustomFactor, values: gtsam.Values, H: Any) -> FloatArray:
        ks = this.keys()
        pred, j_pose, j_anchor, j_idp = project_inverse_depth(
            pose_array(values.atPose2(ks[0])), pose_array(values.atPose2(ks[1])), values.atVector(ks[2]), off
        )
        if H is not None:
            H[0], H[1], H[2] = j_pose, j_anchor, j_idp
        return pred - meas

    return gtsam.CustomFactor(noise_model(cov_m, robust), [pose_key, anchor_key, corner_key], error)


def inverse_depth_frame_factor(
    pose_key: int,
    observations: Sequence[InverseDepthObservation],
    body_t_camera: FloatArray,
    robust: float | None = None,
) -> gtsam.CustomFactor:
    """All inverse-depth corner observations of one frame in one ``CustomFactor``.

    Residuals are whitened per observation (unit noise model); Huber per observation
    when ``robust`` is set (:func:`huber_sqrt`). Anchors shared by several corners
    appear once among the keys and their Jacobian blocks are stacked.

    Args:
        pose_key: observing pose ``X(k)``.
        observations: :class:`InverseDepthObservation` s, distinct corners, anchors
            different from ``pose_key``.
        body_t_camera: (3,) camera offset, metres.
        robust: optional Huber threshold.

    Returns:
        ``gtsam.CustomFactor`` with a (2K,) residual.
    """
    obs = list(observations)
    if not obs:
        raise FactorError("inverse_depth_frame_factor needs at least one observation")
    anchor_keys: list[int] = []
    anchor_slot: dict[int, int] = {}
    corner_keys: list[int] = []
    for o in obs:
        if o.anchor_key == pose_key:
            raise FactorError("inverse_depth_frame_factor: anchor sight must be a prior")
        if o.anchor_key not in anchor_slot:
            anchor_slot[o.anchor_key] = len(anchor_keys)
            anchor_keys.append(o.anchor_key)
        corner_keys.append(o.corner_key)
    keys = [pose_key, *anchor_keys, *corner_keys]
    if len(set(keys)) != len(keys):
        raise FactorError("inverse_depth_frame_factor: corner keys must be distinct")
    n = len(obs)
    n_anchor = len(anchor_keys)
    which_anchor = np.array([anchor_slot[o.anchor_key] for o in obs])
    anchor_masks = [which_anchor == u for u in range(n_anchor)]
    whiten = np.stack([sqrt_information(check_cov(o.cov_m, 2, "inverse depth")) for o in obs])
    meas = np.stack([np.asarray(o.m, dtype=float) for o in obs])
    off = np.asarray(body_t_camera, dtype=float).copy()
    rows = np.arange(n)

    def error(this: gtsam.CustomFactor, values: gtsam.Values, H: Any) -> FloatArray:
        ks = this.keys()
        pose = pose_array(values.atPose2(ks[0]))
        anchors = np.stack([pose_array(values.atPose2(ks[1 + u])) for u in range(n_anchor)])[which_anchor]
        idps = np.stack([values.atVector(ks[1 + n_anchor + i]) for i in range(n)])
        pred, j_pose, j_anchor, j_idp = project_inverse_depth_batch(pose, anchors, idps, off)
        e = np.einsum("kij,kj->ki", whiten, pred - meas)
        g = whiten
        if robust is not None:
            e, r_D_e = _huber_sqrt_rows(e, robust)
            g = r_D_e @ whiten
        if H is not None:
            H[0] = (g @ j_pose).reshape(2 * n, 3)
            g_anchor = g @ j_anchor
            for u in range(n_anchor):
                block = np.zeros((n, 2, 3))
                block[anchor_masks[u]] = g_anchor[anchor_masks[u]]
                H[1 + u] = block.reshape(2 * n, 3)
            g_idp = g @ j_idp
            for i in range(n):
                block = np.zeros((n, 2, 3))
                block[rows[i]] = g_idp[i]
                H[1 + n_anchor + i] = block.reshape(2 * n, 3)
        return e.reshape(2 * n)

    return gtsam.CustomFactor(gtsam.noiseModel.Unit.Create(2 * n), keys, error)


def inverse_depth_first_sight_prior(
    corner_key: int,
    m: FloatArray,
    cov_m: FloatArray,
    prior: HeightPrior | None = None,
    robust: float | None = None,
) -> gtsam.PriorFactorVector:
    """First sight of an inverse-depth corner plus the height prior, one built-in factor.

    Seen from its anchor the corner projects to ``alpha`` whatever the anchor pose
    (:func:`lampsam.factors.ceiling.project_inverse_depth`), so the first observation
    is the prior ``alpha ~ N(m, cov_m)``; with the height range as ``rho ~ N(rho_mean,
    rho_sigma^2)`` (:class:`HeightPrior`) it is one ``PriorFactorVector`` with a
    block-diagonal covariance.

    Args:
        corner_key: ``C(j)``.
        m: (2,) normalised coordinates at the anchor.
        cov_m: (2, 2) their covariance.
        prior: height range, default :class:`HeightPrior` ().
        robust: optional Huber threshold on the whitened 3-vector (the ``rho`` part
            is within 2 sigma by construction, so in practice it acts on ``alpha``).

    Returns:
        ``gtsam.PriorFactorVector`` on the (3,) inverse-depth vector.
    """
    prior = prior or HeightPrior()
    cov_m = check_cov(cov_m, 2, "inverse depth prior")
    cov = np.zeros((3, 3))
    cov[:2, :2] = cov_m
    cov[2, 2] = prior.rho_sigma**2
    mean = np.array([float(m[0]), float(m[1]), prior.rho_mean])
    return gtsam.PriorFactorVector(corner_key, mean, noise_model(cov, robust))
