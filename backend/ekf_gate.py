"""The EKF's vectorised gate (paper 1, eqs. 19-20): a frame's candidates and distances.

For :class:`lampsam.backend.ekf.EkfSlam`: every ceiling landmark of a kind is projected
at once (:meth:`lampsam.backend.ceiling.CeilingModel.project_many`); for the visible
ones ``S = H P H^T`` (eq. 19 without ``R``, with the robot-landmark cross term: exact)
is built from gathered blocks of ``P``
(:func:`lampsam.backend.ekf_update.gathered_s`), and
:func:`lampsam.backend.association.screen_pairs` computes every observation x landmark
distance in numpy. Planar landmarks use the update's own Jacobians
(:func:`lampsam.backend.planar_gate.ekf_point2_jacobians`), optionally at first
estimates or observability-constrained. State ``x`` in plain coordinates (world frame,
m, rad), ``P`` a :class:`lampsam.backend.covariance.LowerCovariance`.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from lampsam.arrays import FloatArray
from lampsam.backend.association import screen_pairs
from lampsam.backend.config import AssociationConfig
from lampsam.backend.covariance import LowerCovariance
from lampsam.backend.ekf_landmarks import Slot
from lampsam.backend.ekf_update import gathered_s
from lampsam.backend.interface import LandmarkKind
from lampsam.backend.models import Obs
from lampsam.backend.planar_gate import ekf_point2_jacobians, screen_point2
from lampsam.factors.geometry import tangent_D_coords

if TYPE_CHECKING:
    from lampsam.backend.ceiling import CeilingModel

#: ``{observation index: {landmark id: (squared distance, inside the gate)}}``
Screened = dict[int, dict[int, tuple[float, bool]]]


def screen_frame(obs: list[Obs], slots: dict[int, Slot], doomed: set[int], x: FloatArray,
                 cov: LowerCovariance, ceiling: CeilingModel | None, config: AssociationConfig,
                 first_estimates: bool, constrained: bool, noise_scale: float
                 ) -> tuple[dict[str, list[int]], Screened]:
    """Candidates per kind and the vectorised gate of a frame's observations.

    Args:
        obs: the frame's observations.
        slots: the filter's landmark slots by id; ``doomed`` ids are skipped.
        x: (n,) the state; ``cov`` its covariance.
        ceiling: the ceiling model, or None for range-bearing runs (every landmark
            is then a planar candidate).
        config: the association settings (gate, thresholds).
        first_estimates, constrained: the planar Jacobians' options
            (``ekf.first_estimate_jacobians``, ``ekf.observability_constrained``).
        noise_scale: the learnt innovation scale of planar sightings.

    Returns:
        ``(candidates, screened)`` for :func:`lampsam.backend.association.associate`.
    """
    cands: dict[str, list[int]] = {}
    screened: Screened = {}
    ceiling_slots: dict[str, list[Slot]] = {}
    for lid, slot in slots.items():
        if lid in doomed:
            continue
        if ceiling is None or slot.kind == "point2":
            cands.setdefault(slot.kind, []).append(lid)
        else:
            ceiling_slots.setdefault(slot.kind, []).append(slot)
    pose = x[:3]
    planar = cands.get(LandmarkKind.POINT2, [])
    if planar and any(o.kind == LandmarkKind.POINT2 for o in obs):
        screened.update(screen_planar(obs, planar, slots, x, cov, config, first_estimates,
                                      constrained, noise_scale))
    if ceiling is None:
        return cands, screened
    t_d_c = tangent_D_coords(pose[2])
    for kind, kind_slots in ceiling_slots.items():
        offs = np.array([sl.offset for sl in kind_slots])
        idx = offs[:, None] + np.arange(3)[None, :]  # (M, 3) position columns
        m, m_d_pose, m_d_pt, vis = ceiling.project_many(pose, x[idx])
        keep = np.flatnonzero(vis)
        lids = [kind_slots[j].id for j in keep]
        cands[kind] = lids
        if not any(o.kind == kind for o in obs):
            continue
        h_r = m_d_pose[keep] @ t_d_c  # (M, 2, 3) coordinates
        h_l = m_d_pt[keep]
        s_pred = gathered_s(cov, idx[keep], h_r, h_l)
        screened.update(screen_pairs(obs, kind, lids, m[keep], s_pred, config, exact=True))
    return cands, screened


def screen_planar(obs: list[Obs], lids: list[int], slots: dict[int, Slot], x: FloatArray,
                  cov: LowerCovariance, config: AssociationConfig, first_estimates: bool,
                  constrained: bool, noise_scale: float) -> Screened:
    """Exact eq.-19/20 distances of every planar observation to the planar landmarks
    ``lids``, with the update's Jacobians
    (:func:`lampsam.backend.planar_gate.ekf_point2_jacobians`) and ``S = H P H^T`` from
    gathered blocks of ``P``; arguments as :func:`screen_frame`."""
    offs = np.array([slots[lid].offset for lid in lids])
    idx = offs[:, None] + np.arange(2)[None, :]  # (M, 2)
    firsts = None
    if first_estimates:
        firsts = np.array([sl.first[:2] if sl.first is not None else x[sl.offset : sl.offset + 2]
                           for sl in (slots[lid] for lid in lids)])
    z_hat, h_r, h_l = ekf_point2_jacobians(x[:3], x[idx], firsts, constrained)
    return screen_point2(obs, lids, z_hat, gathered_s(cov, idx, h_r, h_l), config, noise_scale)
