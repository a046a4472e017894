"""Vectorised range-bearing prediction and gate against every planar landmark (eqs. 19-20).

Without ids, each ``[bearing, range]`` observation of a frame is compared with every
mapped planar landmark; one Python call per pair (``EkfSlam._innovation``) made the
EKF's association cost grow with the map times the observations. Here all landmarks
are predicted at once and every observation x landmark squared Mahalanobis distance
comes from one numpy expression (the 2x2 inverse in closed form, the bearing
innovation wrapped to (-pi, pi]). One distance, :func:`bearing_range_d2`, serves the
EKF (:func:`screen_point2`, Jacobians in plain coordinates, optionally at first
estimates: :func:`predict_point2_many`) and the smoothers' gate (Jacobians w.r.t.
the right tangent: :func:`range_bearing_many`).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from lampsam.arrays import FloatArray
from lampsam.backend.config import AssociationConfig
from lampsam.backend.ekf_update import observability_project
from lampsam.backend.models import Obs
from lampsam.factors.geometry import mahalanobis2_2x2


def predict_point2(pose: FloatArray, landmarks: FloatArray) -> FloatArray:
    """``[bearing, range]`` (M, 2) of M planar landmarks (M, 2, world, m) seen from
    ``pose`` (3,): ``bearing = atan2(dy, dx) - theta`` wrapped to [-pi, pi), ``range = |d|``."""
    lm = np.asarray(landmarks, float).reshape(-1, 2)
    d = lm - np.asarray(pose[:2], float)
    z = np.empty((len(lm), 2))
    z[:, 0] = np.arctan2(d[:, 1], d[:, 0]) - float(pose[2])
    z[:, 0] = (z[:, 0] + np.pi) % (2 * np.pi) - np.pi
    z[:, 1] = np.hypot(d[:, 0], d[:, 1])
    return z


def predict_point2_many(pose: FloatArray, landmarks: FloatArray, lin: FloatArray | None = None
                        ) -> tuple[FloatArray, FloatArray, FloatArray]:
    """``[bearing, range]`` of M planar landmarks and the Jacobians in plain coordinates.

    ``bearing = atan2(dy, dx) - theta``, ``range = |d|`` with ``d = l - t``;
    ``d bearing / d(x, y, theta) = (dy / r^2, -dx / r^2, -1)``,
    ``d range / d(x, y, theta) = (-dx / r, -dy / r, 0)``, and the landmark Jacobian is
    minus the first two columns (the same model as
    :func:`lampsam.factors.range_bearing.range_bearing`, whose Jacobians are w.r.t.
    the right tangent).

    Args:
        pose: (3,) ``world_T_body``, m and rad.
        landmarks: (M, 2) world positions, m (the prediction's point).
        lin: (M, 2) positions at which to take the Jacobians (first estimates), or
            None: ``landmarks``.

    Returns:
        ``(z_hat (M, 2), h_pose (M, 2, 3), h_landmark (M, 2, 2))``; a landmark at the
        robot (range 0) gets infinite Jacobians (never gated in).
    """
    lm = np.asarray(landmarks, float).reshape(-1, 2)
    z = predict_point2(pose, lm)
    base = lm if lin is None else np.asarray(lin, float).reshape(-1, 2)
    dl = base - np.asarray(pose[:2], float)
    q = np.sum(dl * dl, axis=1)
    r = np.sqrt(q)
    with np.errstate(divide="ignore", invalid="ignore"):
        h_l = np.empty((len(lm), 2, 2))
        h_l[:, 0, 0] = -dl[:, 1] / q
        h_l[:, 0, 1] = dl[:, 0] / q
        h_l[:, 1, 0] = dl[:, 0] / r
        h_l[:, 1, 1] = dl[:, 1] / r
    h_r = np.zeros((len(lm), 2, 3))
    h_r[:, :, :2] = -h_l
    h_r[:, 0, 2] = -1.0
    return z, h_r, h_l


def ekf_point2_jacobians(pose: FloatArray, landmarks: FloatArray, firsts: FloatArray | None,
                         constrained: bool) -> tuple[FloatArray, FloatArray, FloatArray]:
    """The EKF's ``[bearing, range]`` predictions and update Jacobians of M planar landmarks.

    As ``EkfSlam._h`` for each landmark: Jacobians at the latest estimate (``firsts`` None:
    the paper's), at the first estimates (``constrained`` False), or at the latest estimate
    projected to keep the global pose unobservable (``constrained`` True, the OC-EKF:
    :func:`lampsam.backend.ekf_update.observability_project`).

    Args:
        pose: (3,) the predicted pose; landmarks: (M, 2) latest estimates, m.
        firsts: (M, 2) first estimates, m, or None.
        constrained: the observability-constrained Jacobians.

    Returns:
        ``(z_hat (M, 2), h_pose (M, 2, 3), h_landmark (M, 2, 2))``, plain coordinates.
    """
    z_hat, h_r, h_l = predict_point2_many(pose, landmarks, None if constrained else firsts)
    if constrained and firsts is not None:
        h_r, h_l = observability_project(h_r, h_l, pose[:2], firsts)
    return z_hat, h_r, h_l


def range_bearing_many(pose: FloatArray, pts: FloatArray
                       ) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Predicted ``[bearing, range]`` of M planar landmarks and their Jacobians, at once.

    The vectorised form of :func:`lampsam.factors.range_bearing.range_bearing`
    (no sensor offset).

    Args:
        pose: (3,) ``world_T_body``, m and rad.
        pts: (M, 2) landmarks, world frame, m.

    Returns:
        ``(z_hat (M, 2), z_D_pose (M, 2, 3) right tangent, z_D_landmark (M, 2, 2))``;
        a landmark at the sensor gets range 1e-9 m (its distances are meaningless,
        never a match).
    """
    c, s = math.cos(pose[2]), math.sin(pose[2])
    dx, dy = pts[:, 0] - pose[0], pts[:, 1] - pose[1]
    px, py = c * dx + s * dy, -s * dx + c * dy
    r2 = np.maximum(px * px + py * py, 1e-18)
    r = np.sqrt(r2)
    m = len(pts)
    p_D_pose = np.zeros((m, 2, 3))
    p_D_pose[:, 0, 0] = p_D_pose[:, 1, 1] = -1.0
    p_D_pose[:, 0, 2], p_D_pose[:, 1, 2] = py, -px
    p_D_l = np.array([[c, s], [-s, c]])
    z_D_p = np.empty((m, 2, 2))
    z_D_p[:, 0, 0], z_D_p[:, 0, 1] = -py / r2, px / r2
    z_D_p[:, 1, 0], z_D_p[:, 1, 1] = px / r, py / r
    z_hat = np.stack([np.arctan2(py, px), r], axis=1)
    return z_hat, z_D_p @ p_D_pose, z_D_p @ p_D_l


def bearing_range_d2(z: FloatArray, r: FloatArray, z_hat: FloatArray, s: FloatArray
                     ) -> FloatArray:
    """Squared Mahalanobis distances of N ``[bearing, range]`` observations to M predictions.

    ``d2[i, j] = nu^T (S_j + R_i)^-1 nu`` with ``nu = z_i - z_hat_j``, the bearing
    wrapped to (-pi, pi] (eq. 20).

    Args:
        z: (N, 2) observations; r: (N, 2, 2) their noise.
        z_hat: (M, 2) predictions; s: (M, 2, 2) prediction covariances ``H P H^T``.

    Returns:
        (N, M) distances; ``inf`` where ``S + R`` is not positive definite or the
        distance is not finite.
    """
    psi = r[:, None] + s[None]
    nu = z[:, None, :] - z_hat[None, :, :]
    nu[..., 0] = (nu[..., 0] + math.pi) % (2.0 * math.pi) - math.pi
    a, b, d = psi[..., 0, 0], 0.5 * (psi[..., 0, 1] + psi[..., 1, 0]), psi[..., 1, 1]
    d2, pd = mahalanobis2_2x2(nu[..., 0], nu[..., 1], a, b, d)
    return np.where(pd & np.isfinite(d2), d2, np.inf)


def screen_point2(observations: list[Obs], lids: list[int], z_hat: FloatArray, s: FloatArray,
                  config: AssociationConfig, scale: float = 1.0
                  ) -> dict[int, dict[int, tuple[float, bool]]]:
    """Every planar observation without an id against M predicted landmarks.

    Args:
        observations: the frame's observations (other kinds and those with an id
            that known association will use are skipped).
        lids: (M,) landmark ids.
        z_hat: (M, 2) predicted ``[bearing, range]``; s: (M, 2, 2) ``H P H^T`` (eq. 19
            without ``R``, with the robot-landmark cross term).
        config: association thresholds.
        scale: innovation covariance scale
            (:class:`lampsam.backend.innovation_scale.InnovationScale`): the distances are
            ``d2 / scale``.

    Returns:
        For :func:`lampsam.backend.association.associate`'s ``screened``: obs index ->
        {landmark id: (d2, True)} for the pairs below the new-landmark threshold.
    """
    idx = [i for i, o in enumerate(observations) if o.kind == "point2"
           and not (config.use_known_ids and o.landmark_id is not None)]
    out: dict[int, dict[int, tuple[float, bool]]] = {i: {} for i in idx}
    if not idx or not lids:
        return out
    z = np.array([observations[i].z for i in idx], float)
    r = np.array([observations[i].R for i in idx], float)
    d2 = bearing_range_d2(z, r, np.asarray(z_hat, float), np.asarray(s, float)) / scale
    thr = config.new_threshold(2)
    for row, i in enumerate(idx):
        keep = np.flatnonzero(d2[row] < thr)
        out[i] = {lids[j]: (float(d2[row, j]), True) for j in keep}
    return out


def rival_ratio(cands: Sequence[tuple[float, float]]) -> float:
    """Likelihood of the second likeliest landmark over the likeliest's (eq. 19-20).

    For an innovation ``nu ~ N(0, Psi_j)`` under "the sighting is landmark ``j``" the
    likelihood is ``|2 pi Psi_j|^(-1/2) exp(-d2_j / 2)`` with
    ``d2_j = nu^T Psi_j^-1 nu``; with equal priors over the candidates the ratio of
    two is the ratio of their posterior probabilities.

    Args:
        cands: ``(d2, log det Psi)`` of each candidate (log det 0 when unknown:
            then the ratio is ``exp(-(d2_2 - d2_1) / 2)``).

    Returns:
        The ratio in [0, 1]; 0 with fewer than two candidates.
    """
    if len(cands) < 2:
        return 0.0
    ll = sorted((-0.5 * (d2 + logdet) for d2, logdet in cands), reverse=True)
    return math.exp(ll[1] - ll[0])


def rival_material(cands: Sequence[tuple[float, float]], config: AssociationConfig) -> bool:
    """Whether a sighting with these candidates (``(d2, log det Psi)`` each, all within
    :meth:`AssociationConfig.unique_threshold`) is held (``planar_unique``): two or more
    of them when ``planar_unique_ratio`` is 0, else a rival at least that likely
    (:func:`rival_ratio`; a NaN log det, unknown, counts every candidate's as 0)."""
    if any(math.isnan(ld) for _, ld in cands):
        cands = [(d2, 0.0) for d2, _ in cands]
    if config.planar_unique_ratio <= 0.0:
        return len(cands) >= 2
    return rival_ratio(cands) >= config.planar_unique_ratio
