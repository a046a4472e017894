"""Joint compatibility (JCBB) for the EKF's planar observations without ids (eqs. 19-20).

The EKF's individual gate pairs each ``[bearing, range]`` sighting with the landmarks
inside its chi-square gate; :func:`joint_point2` re-pairs a frame's sightings so that
the chosen pairs are compatible *together* (Neira & Tardos 2001,
:func:`lampsam.backend.association.jcbb`). Only the robot block and the candidate
landmarks' blocks of ``P`` are read.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping

import numpy as np

from lampsam.arrays import FloatArray
from lampsam.backend.association import Assignment, mahalanobis2, reassign_jointly
from lampsam.backend.config import AssociationConfig
from lampsam.backend.covariance import LowerCovariance
from lampsam.backend.interface import LandmarkKind
from lampsam.backend.models import Obs, residual

#: ``(landmark id, observation) -> (nu, Psi)`` of eq. 19, or None when not predictable.
InnovationFn = Callable[[int, Obs], "tuple[FloatArray, FloatArray] | None"]
#: ``(landmark id, observation) -> (z_hat, H_robot (k, 3) coordinates, H_landmark (k, d))``;
#: may raise when the landmark is not predictable.
PredictFn = Callable[[int, Obs], "tuple[FloatArray, FloatArray, FloatArray]"]


def joint_point2(obs: list[Obs], assignments: list[Assignment],
                 screened: Mapping[int, Mapping[int, tuple[float, bool]]],
                 config: AssociationConfig, planar: Mapping[int, tuple[int, int]],
                 innovation: InnovationFn, predict: PredictFn, cov: LowerCovariance,
                 scale: float = 1.0) -> list[Assignment]:
    """Re-pair a frame's planar observations without ids by joint compatibility (JCBB).

    Candidates are the landmarks individually inside the gate (eqs. 19-20); the
    joint innovation covariance of a hypothesis is ``H P H^T + R`` over all its
    rows (the shared robot block correlates them). An observation JCBB leaves
    unpaired keeps a greedy ``"new"`` (beyond the new-landmark threshold of every
    landmark) and is otherwise dropped, so one tree is not mapped twice.

    Args:
        obs: the frame's observations.
        assignments: the individual gate's assignments.
        screened: obs index -> {landmark id: (d2, ok)} of the vectorised screen;
            observations not in it are gated here with ``innovation``.
        config: the association thresholds (gate probability).
        planar: landmark id -> (state offset, dim) of every live planar landmark.
        innovation: eq. 19 of one pair; predict: ``h`` and its Jacobians of one pair.
        cov: the EKF covariance ``P``.
        scale: the innovation covariance scale (``innovation_scale.InnovationScale``).

    Returns:
        The assignments with the planar ones re-paired (``"matched"``), kept
        (``"new"``) or ``"dropped"``.
    """
    idx = [a.obs_index for a in assignments
           if obs[a.obs_index].kind == LandmarkKind.POINT2 and obs[a.obs_index].landmark_id is None]
    if not idx:
        return assignments
    gate = config.gate(2)
    cands: dict[int, list[int]] = {}
    for i in idx:
        if i in screened:
            cands[i] = [lid for lid, (d2, _) in screened[i].items() if d2 < gate]
            continue
        cands[i] = []
        for lid in planar:
            pred = innovation(lid, obs[i])
            if pred is not None and mahalanobis2(*pred) < gate:
                cands[i].append(lid)
    if not any(cands.values()):
        return assignments
    # Only the robot and candidate blocks of P enter H P H^T: gather those (an
    # O(m^2) read) instead of a dense copy of the whole n x n covariance.
    local: dict[int, int] = {}  # landmark id -> its first column in the gathered block
    cols = [0, 1, 2]
    for lid in sorted({lid for c in cands.values() for lid in c}):
        off, dim = planar[lid]
        local[lid] = len(cols)
        cols.extend(range(off, off + dim))
    col_idx = np.asarray(cols)
    P = cov.take(col_idx[:, None], col_idx[None, :])
    n = len(cols)

    def joint(hyp: list[tuple[int, int]]) -> tuple[FloatArray, FloatArray] | None:
        k = 2 * len(hyp)
        h = np.zeros((k, n))
        nu = np.empty(k)
        r = np.zeros((k, k))
        for row, (i, lid) in enumerate(hyp):
            try:
                z_hat, h_r, h_l = predict(lid, obs[i])
            except Exception:
                return None
            h[2 * row : 2 * row + 2, :3] = h_r
            h[2 * row : 2 * row + 2, local[lid] : local[lid] + planar[lid][1]] = h_l
            nu[2 * row : 2 * row + 2] = residual(obs[i], z_hat)
            r[2 * row : 2 * row + 2, 2 * row : 2 * row + 2] = obs[i].R
        return nu, (h @ P @ h.T + r) * scale

    return reassign_jointly(assignments, cands, joint, config)
