"""The EKF's map: landmarks added (paper 1, eqs. 24-25), merged and pruned.

- Augmentation (eqs. 24-25) with the full cross-covariance
  ``P_new,all = grad g_R P[R, :]`` and
  ``P_new,new = grad g_R P_RR grad g_R^T + grad g_Z P_new grad g_Z^T``; ceiling
  landmarks carry the 0-5 m height prior in ``P_new``.
- Removal of landmarks that stay uncertain or are seen only once (paper sec. IV):
  rows and columns deleted (the triangle compacted in place).
- Duplicate planar landmarks fused (:func:`lampsam.backend.landmark_merge.ekf_merge_once`).

Frames and units as :mod:`lampsam.backend.ekf_state`.
"""

from __future__ import annotations

import logging

import numpy as np

from lampsam.backend.ekf_landmarks import (
    PRUNE_BATCH,
    Slot,
    free_id,
    grown_state,
    max_sigma_2x2,
    prune_round,
    remove_landmarks,
)
from lampsam.backend.ekf_state import EkfState
from lampsam.backend.interface import LandmarkKind
from lampsam.backend.landmark_merge import ekf_merge_once
from lampsam.backend.models import Obs, initialize, try_initialize
from lampsam.factors.geometry import tangent_D_coords

log = logging.getLogger(__name__)


class EkfMap(EkfState):
    """Augmentation, merging and pruning of :class:`~lampsam.backend.ekf.EkfSlam` (a mixin)."""

    # ------------------------------------------------------------------ eqs. 24-25
    def _augment(self, obs: Obs, lid: int | None) -> int | None:
        """Add a landmark from one observation with the full cross-covariance (eqs. 24-25)."""
        pose = self._x[:3].copy()
        started = try_initialize(pose, obs, self.config.association, self.ceiling)
        if started is None:
            return None
        state, g_pose, g_z, cov_z = started
        g_r = g_pose @ tangent_D_coords(pose[2])  # right tangent -> coordinates
        d = len(state)
        self._x = grown_state(self._x, self._n, d)
        n = self._n
        p_r = self._cov.columns(0, 3)  # (n, 3) P[:, R]
        self._cov.append(g_r @ p_r.T, g_r @ p_r[:3] @ g_r.T + g_z @ cov_z @ g_z.T)
        self._x[n : n + d] = state
        if lid is None:
            lid = free_id(self._slots, self._next_id)
        self._next_id = max(self._next_id, lid + 1)
        # A planar landmark's first-sight measurement-only sigma scales the prune
        # threshold (a sparse outdoor map's landmarks are metres uncertain by nature);
        # ceiling landmarks keep the fixed ``prune_sigma``.
        sigma_meas = (max_sigma_2x2((g_z @ cov_z @ g_z.T)[:2, :2])
                      if obs.kind == LandmarkKind.POINT2 else 0.0)
        self._slots[lid] = Slot(lid, obs.kind, n, d, 1, self._step, self._step, obs.patch,
                                 sigma_meas, state.copy() if self._fej else None)
        if self._prune_known or obs.landmark_id is None:
            self._prune_queue.append(lid)
        self._n = n + d
        return lid

    def _confirmed(self, obs: Obs) -> bool:
        """Whether an unassociated planar sighting may start a landmark now.

        With ``association.planar_confirm_sightings > 1`` the sighting's world position (eq. 24) and
        covariance ``G_R P_RR G_R^T + G_z R G_z^T`` (eq. 25's new block) go to the
        tentative list (:class:`lampsam.backend.association.TentativeLandmarks`).
        """
        if self.tentative.confirm <= 1 and self.tentative.min_separation <= 0:
            return True
        pose = self._x[:3].copy()
        state, g_pose, g_z, cov_z = initialize(pose, obs, self.config.association, self.ceiling)
        g_r = g_pose @ tangent_D_coords(pose[2])
        cov = g_r @ self._cov.block(0, 3, 0, 3) @ g_r.T + g_z @ cov_z @ g_z.T
        mapped = None
        if self.tentative.min_separation > 0:
            offs = [s.offset for s in self._slots.values()
                    if s.kind == LandmarkKind.POINT2 and s.id not in self._doomed]
            mapped = (self._x[np.asarray(offs)[:, None] + np.arange(2)[None, :]]
                      if offs else np.zeros((0, 2)))
        return self.tentative.offer(state[:2], cov[:2, :2], self._step, mapped)

    def _merge_duplicates(self) -> None:
        """Every ``planar_merge_every`` steps, fuse one duplicate planar landmark pair
        (:func:`lampsam.backend.landmark_merge.ekf_merge_once`) and drop the newer."""
        cfg = self.config.association
        if cfg.use_known_ids or self._step % cfg.planar_merge_every:
            return
        cand = [s for s in self._slots.values() if s.kind == LandmarkKind.POINT2
                and s.n_obs >= cfg.planar_merge_min_obs and s.id not in self._doomed]
        if len(cand) < 2:
            return
        pair = ekf_merge_once(self.x, self._cov, np.array([s.id for s in cand]),
                              np.array([s.offset for s in cand]),
                              np.array([s.created for s in cand]), self.covis, cfg.gate(2),
                              cfg.new_threshold(2), cfg.planar_merge_radius)
        if pair is None:
            return
        keep, drop = self._slots[pair.keep], self._slots[pair.drop]
        keep.n_obs += drop.n_obs
        keep.last_seen = max(keep.last_seen, drop.last_seen)
        self._remove([pair.drop], pruned=False)
        self.n_merged += 1

    # ------------------------------------------------------------------ pruning
    def _remove(self, lids: list[int], pruned: bool = True) -> None:
        """Cut landmarks ``lids`` out of ``x`` and ``P``; ``pruned``: count them in
        ``n_pruned`` (a merged duplicate is not a pruned landmark)."""
        if not lids:
            return
        self._n = remove_landmarks(self._x, self._n, self._cov, self._slots, lids)
        if pruned:
            self.n_pruned += len(lids)

    def _prune(self) -> None:
        """Remove landmarks seen once long ago, or still uncertain after a while.

        A few landmarks per step are checked
        (:func:`lampsam.backend.ekf_landmarks.prune_round`); doomed landmarks stop being
        candidates at once and are cut out of ``x`` and ``P`` (an O(n^2) in-place
        compaction) in batches of :data:`~lampsam.backend.ekf_landmarks.PRUNE_BATCH` or
        every ``PRUNE_BATCH`` steps.
        """
        cfg = self.config.association
        for lid, drop in prune_round(self._prune_queue, self._slots, self._doomed, self._step,
                                     cfg, lambda s: self._cov.block(s.offset, s.offset + 2,
                                                                    s.offset, s.offset + 2)):
            if drop == "seen_too_few" and not cfg.prune_once_seen:
                self._provisional.append(self._estimate(self._slots[lid]))
            self.pruned[drop] = self.pruned.get(drop, 0) + 1
        if self._doomed and (len(self._doomed) >= PRUNE_BATCH
                             or self._step % PRUNE_BATCH == 0):
            log.debug("pruning %d landmarks", len(self._doomed))
            self._remove(sorted(self._doomed))
            self._doomed.clear()
