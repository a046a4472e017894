"""Vectorised gate of range-bearing observations against every planar landmark (eqs. 19-20).

Without ids, each ``[bearing, range]`` observation of a frame is compared with every
mapped planar landmark; one Python call per pair (``EkfSlam._innovation``) made the
EKF's association cost grow with the map times the observations. Here all landmarks
are predicted at once and every observation x landmark squared Mahalanobis distance
comes from one numpy expression (the 2x2 inverse in closed form, the bearing
innovation wrapped to (-pi, pi]).
"""

from __future__ import annotations

import numpy as np

from lampsam.arrays import FloatArray
from lampsam.backend.config import AssociationConfig
from lampsam.backend.models import Obs


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
    d = lm - np.asarray(pose[:2], float)
    z = np.empty((len(lm), 2))
    z[:, 0] = np.arctan2(d[:, 1], d[:, 0]) - float(pose[2])
    z[:, 0] = (z[:, 0] + np.pi) % (2 * np.pi) - np.pi
    z[:, 1] = np.hypot(d[:, 0], d[:, 1])
    dl = d if lin is None else np.asarray(lin, float).reshape(-1, 2) - np.asarray(pose[:2], float)
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


def screen_point2(observations: list[Obs], lids: list[int], z_hat: FloatArray, s: FloatArray,
                  config: AssociationConfig) -> dict[int, dict[int, tuple[float, bool]]]:
    """Every planar observation without an id against M predicted landmarks.

    Args:
        observations: the frame's observations (other kinds and those with an id
            that known association will use are skipped).
        lids: (M,) landmark ids.
        z_hat: (M, 2) predicted ``[bearing, range]``; s: (M, 2, 2) ``H P H^T`` (eq. 19
            without ``R``, with the robot-landmark cross term).
        config: association thresholds.

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
    psi = r[:, None, :, :] + np.asarray(s, float)[None, :, :, :]
    nu = z[:, None, :] - np.asarray(z_hat, float)[None, :, :]
    nu[..., 0] = (nu[..., 0] + np.pi) % (2 * np.pi) - np.pi
    a, b, d = psi[..., 0, 0], 0.5 * (psi[..., 0, 1] + psi[..., 1, 0]), psi[..., 1, 1]
    det = a * d - b * b
    with np.errstate(divide="ignore", invalid="ignore"):
        d2 = (d * nu[..., 0] ** 2 - 2.0 * b * nu[..., 0] * nu[..., 1] + a * nu[..., 1] ** 2) / det
    d2 = np.where((det > 0) & (a > 0) & np.isfinite(d2), d2, np.inf)
    thr = config.new_threshold(2)
    for row, i in enumerate(idx):
        keep = np.flatnonzero(d2[row] < thr)
        out[i] = {lids[j]: (float(d2[row, j]), True) for j in keep}
    return out
