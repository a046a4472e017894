"""The paper's EKF-SLAM (paper 1, eqs. 13-25), exploiting the sparsity of its Jacobians.

State ``X = [x, y, theta, landmark_1, ..., landmark_n]`` (plain coordinates, world
frame; landmark states in :mod:`lampsam.backend.models`), covariance ``P``.

- Covariance storage: :class:`lampsam.backend.covariance.LowerCovariance`, the lower
  triangle of a growable buffer, updated in place (no n x n copies, no periodic
  re-symmetrisation).
- Prediction (eqs. 13-15): only the robot block changes. With ``F_x`` the robot
  Jacobian and ``F_u Q F_u^T`` the wheel noise, ``P_RR <- F_x P_RR F_x^T + F_u Q F_u^T``
  and ``P_MR <- P_MR F_x^T``; the landmark block ``P_MM`` is untouched. Several odometry
  increments between two frames are composed on the 3x3 block first, so a step
  costs O(n) regardless of the odometry rate. No dense ``F P F^T``.
- Gate (eqs. 19-20), vectorised over a frame: :mod:`lampsam.backend.ekf_gate`;
  association: :mod:`lampsam.backend.association`.
- Update (eqs. 21-23), one observation at a time: ``H`` has nonzero columns only
  for the robot and one landmark, so ``P H^T = P[:, R] H_R^T + P[:, L] H_L^T``
  (n x k), ``K = P H^T Psi^-1`` and ``P <- P - K (P H^T)^T``, which equals
  ``(I - K H) P`` (eq. 23); with ``Psi = C C^T`` and ``W = P H^T C^-T`` this is the
  symmetric rank-k downdate ``P <- P - W W^T`` (BLAS ``dsyrk``, in place).
- Augmentation (eqs. 24-25) with the full cross-covariance
  ``P_new,all = grad g_R P[R, :]`` and
  ``P_new,new = grad g_R P_RR grad g_R^T + grad g_Z P_new grad g_Z^T``; ceiling
  landmarks carry the 0-5 m height prior in ``P_new``.
- Removal of landmarks that stay uncertain or are seen only once (paper sec. IV):
  rows and columns deleted (the triangle compacted in place).
"""

from __future__ import annotations

import collections
import logging
import math
import time
from typing import Any

import numpy as np

from lampsam.arrays import FloatArray
from lampsam.backend.association import (
    TentativeLandmarks,
    associate,
    corner_budget,
)
from lampsam.backend.config import SlamConfig
from lampsam.backend.covariance import LowerCovariance
from lampsam.backend.ekf_gate import Screened, screen_frame
from lampsam.backend.ekf_joint import joint_point2
from lampsam.backend.ekf_landmarks import (
    PRUNE_BATCH,
    Slot,
    free_id,
    grown_state,
    max_sigma_2x2,
    note_relative_sigma,
    prune_round,
    remove_landmarks,
)
from lampsam.backend.ekf_update import (
    invariant_update,
    observability_project,
    stacked_gain,
)
from lampsam.backend.innovation_scale import innovation_scale, learn_scale
from lampsam.backend.interface import (
    Frame,
    LandmarkEstimate,
    LandmarkKind,
    SlamBackend,
    SlamResult,
    StepEstimate,
    StepHistory,
    log_pruned,
)
from lampsam.backend.landmark_merge import CoVisibility, ekf_merge_once
from lampsam.backend.models import (
    Obs,
    for_landmark,
    initialize,
    landmark_estimate,
    observations_from_frame,
    predict,
    residual,
)
from lampsam.backend.odometry import OdometryConstants, Pose2Motion, motion_model
from lampsam.backend.odometry_scale import (
    IdleOdometry,
    ScaledMotion,
    feed_scale,
    odometry_scale,
)
from lampsam.errors import EstimationError
from lampsam.factors.geometry import tangent_D_coords, wrap_angle, wrap_axis

log = logging.getLogger(__name__)


class EkfSlam(SlamBackend):
    """EKF-SLAM of paper 1 behind the :class:`SlamBackend` interface.

    Args:
        odometry: the odometry model's constants (wheel, eq. 15, or Pose2
            increments; :func:`lampsam.backend.odometry.motion_model`).
        config: the SLAM config (association, noise, EKF part).
        start_pose: (3,) known start pose ``world_T_body``.
        ceiling: the ceiling observation model (for lamps/corners), or None for
            range-bearing runs.
    """

    name = "ekf"

    def __init__(self, odometry: OdometryConstants, config: SlamConfig, start_pose: FloatArray,
                 ceiling: Any = None) -> None:
        self.motion = motion_model(odometry)
        self.config = config
        self.ceiling = ceiling
        cap = 64
        self._x = np.zeros(cap)
        self._n = 3
        self._x[:3] = np.asarray(start_pose, float)
        cfg = config.ekf
        self._cov = LowerCovariance(np.diag([cfg.sigma_start_xy**2, cfg.sigma_start_xy**2,
                                             cfg.sigma_start_theta**2]), cap)
        self._slots: dict[int, Slot] = {}
        self._prune_queue: collections.deque[int] = collections.deque()
        self._doomed: set[int] = set()
        self._next_id = 0
        self._step = 0
        self._last_t = -math.inf
        self._history = StepHistory()
        self.n_pruned = 0
        self.pruned: dict[str, int] = {}  # by reason; sums to n_pruned
        self._provisional: list[LandmarkEstimate] = []
        fej = config.ekf.first_estimate_jacobians
        # None (auto): first estimates for range-bearing runs on Pose2 odometry (the
        # landmark-graph logs), the paper's Jacobians for the wheel model (ceiling
        # runs, MRCLAM).
        auto = ceiling is None and isinstance(self.motion, Pose2Motion)
        self._fej = auto if fej is None else fej
        inv = config.ekf.right_invariant
        if inv and ceiling is not None:
            raise EstimationError("ekf.right_invariant applies to planar range-bearing runs only")
        self._invariant = bool(inv) if inv is not None else False
        oc = config.ekf.observability_constrained
        self._oc = bool(auto and self._fej) if oc is None else oc
        if self._oc:
            self._fej = True  # the first-estimates prediction and first estimates for N
        if self._invariant:
            self._fej = self._oc = False  # the invariant error keeps the rotation unobservable
        # None (auto): landmarks with a known id are kept on the same runs.
        prune_known = config.ekf.prune_known_ids
        self._prune_known = not auto if prune_known is None else prune_known
        self._pred_xy = self._x[:2].copy()  # p_{k|k-1}: the last predicted position
        self.tentative = TentativeLandmarks(config.association.planar_confirm_sightings,
                                            config.association.gate(2),
                                            cfg.tentative_max_idle, cfg.new_min_separation)
        self.noise_scale = innovation_scale(config.association)
        self.odo_scale = odometry_scale(config.association)  # learnt odometry noise, or None
        self.idle = IdleOdometry()
        if self.odo_scale is not None:
            self.motion = ScaledMotion(self.motion, self.odo_scale, self.idle)
        self.covis = CoVisibility()  # landmarks seen together (never merged)
        self.n_merged = 0
        #: range-bearing sightings without ids ``(step, z, R, landmark id)``, for a batch
        #: re-association of the run (:mod:`lampsam.backend.reassociate`)
        self.planar_sightings: list[tuple[int, FloatArray, FloatArray, int]] = []

    # ------------------------------------------------------------------ state
    @property
    def x(self) -> FloatArray:
        """(n,) the current state vector (a view)."""
        return self._x[: self._n]

    @property
    def P(self) -> FloatArray:
        """(n, n) the current covariance (a full copy: O(n^2), for checks)."""
        return self._cov.dense()

    # ------------------------------------------------------------------ eqs. 13-15
    def predict(self, wheel: FloatArray) -> None:
        """Prediction with several odometry samples (eqs. 13-15 for wheel travel).

        Args:
            wheel: (K, m) odometry samples of the motion model (wheel: (K, 2)
                ``(d_left, d_right)`` per sample, m).
        """
        if len(wheel) == 0:
            self._pred_xy = self._x[:2].copy()
            return
        pose, f_tot, q_acc = self.motion.ekf_predict(self._x[:3], wheel)
        if self._fej:
            # Both motion models' F has heading column J (p' - p) (J: +90 deg rotation);
            # first estimates take p = p_{k|k-1} instead of the updated p_{k|k}.
            shift = self._x[:2] - self._pred_xy
            f_tot = f_tot.copy()
            f_tot[0, 2] -= shift[1]
            f_tot[1, 2] += shift[0]
        self._pred_xy = pose[:2].copy()
        self._cov.transform_leading(f_tot, q_acc + self.config.ekf.var_floor * np.eye(3))
        self._x[:3] = pose

    # ------------------------------------------------------------------ prediction helpers
    def _h(self, slot: Slot, obs: Obs | None) -> tuple[FloatArray, FloatArray, FloatArray]:
        """Predicted measurement and coordinate Jacobians (robot, landmark).

        With ``ekf.first_estimate_jacobians`` the Jacobians are taken at the landmark's
        first estimate (the prediction ``z_hat`` at the current one); with
        ``ekf.observability_constrained`` a planar landmark's are the latest ones
        projected (:func:`lampsam.backend.ekf_update.observability_project`).
        """
        pose = self._x[:3]
        state = self._x[slot.offset : slot.offset + slot.dim]
        z_hat, z_D_pose, z_D_l = predict(slot.kind, pose, state, obs, self.ceiling)
        if self._oc and slot.first is not None and slot.kind == LandmarkKind.POINT2:
            h_r, h_l = observability_project(z_D_pose @ tangent_D_coords(pose[2]), z_D_l,
                                             pose[:2], slot.first[:2])
            return z_hat, h_r, h_l
        if self._fej and slot.first is not None:
            _, z_D_pose, z_D_l = predict(slot.kind, pose, slot.first, obs, self.ceiling)
        return z_hat, z_D_pose @ tangent_D_coords(pose[2]), z_D_l

    def _innovation(self, lid: int, obs: Obs) -> tuple[FloatArray, FloatArray] | None:
        """``(nu, Psi)`` of eq. 19 for landmark ``lid`` and ``obs``."""
        slot = self._slots[lid]
        obs = for_landmark(obs, slot.dim)
        try:
            z_hat, h_r, h_l = self._h(slot, obs)
        except Exception:  # landmark behind / at the camera: not predictable here
            return None
        o, d = slot.offset, slot.dim
        cov = self._cov
        p_rr, p_rl = cov.block(0, 3, 0, 3), cov.block(0, 3, o, o + d)
        p_ll = cov.block(o, o + d, o, o + d)
        cross = h_r @ p_rl @ h_l.T
        psi = h_r @ p_rr @ h_r.T + cross + cross.T + h_l @ p_ll @ h_l.T + obs.R
        return residual(obs, z_hat), psi

    def _innovation_h(self, lid: int, obs: Obs) -> tuple[FloatArray, FloatArray, FloatArray] | None:
        """``(nu, Psi, H_r)``: :meth:`_innovation` with the robot Jacobian (2, 3)."""
        pred = self._innovation(lid, obs)
        if pred is None:
            return None
        return pred[0], pred[1], self._h(self._slots[lid], for_landmark(obs, self._slots[lid].dim))[1]

    def _screen(self, obs: list[Obs]) -> tuple[dict[str, list[int]], Screened]:
        """Candidates per kind and the vectorised gate of the frame's observations
        (:func:`lampsam.backend.ekf_gate.screen_frame`), for :func:`associate`."""
        return screen_frame(obs, self._slots, self._doomed, self._x, self._cov, self.ceiling,
                            self.config.association, self._fej, self._oc, self.noise_scale.scale)

    # ------------------------------------------------------------------ eqs. 21-23
    def _update(self, pairs: list[tuple[Slot, Obs]]) -> int:
        """EKF update (eqs. 21-23) with all associated observations of a frame.

        The observations of young lamps (:meth:`_young_lamp`) are applied after the
        others, as a second update with ``ekf.young_lamp_iterations`` iterations
        (sequential updates equal one stacked update for a linear model; the paper
        applies its ``K_i`` one observation at a time).

        Args:
            pairs: (landmark slot, observation) pairs.

        Returns:
            Number of observations used.
        """
        pairs = [(slot, for_landmark(obs, slot.dim)) for slot, obs in pairs]
        cfg = self.config.ekf
        young = ([p for p in pairs if self._young_lamp(p[0])]
                 if cfg.young_lamp_iterations > cfg.update_iterations else [])
        if not young:
            return self._update_rows(pairs, cfg.update_iterations)
        ids = {id(p) for p in young}
        rest = [p for p in pairs if id(p) not in ids]
        used = self._update_rows(rest, cfg.update_iterations) if rest else 0
        return used + self._update_rows(young, cfg.young_lamp_iterations)

    def _young_lamp(self, slot: Slot) -> bool:
        """Whether lamp ``slot``'s height is still uncertain: its standard deviation
        above ``ekf.young_lamp_rel_sigma`` times its height above the camera.

        A lamp starts (eqs. 24-25) as a long ellipse along the viewing ray (the 0-5 m
        height prior); the next frames see it from a few centimetres further on, so
        its predicted ``(u, v)`` is far from linear in the state over that ellipse
        (``u`` goes with ``1/h``). Linearised once at the prior's mean height, the
        update overshoots along the ray and leaves the lamp confident at the wrong
        height (docs/ekf-lamps.md); the iterated update (Bell & Cathey 1993) does not.
        """
        if slot.kind != LandmarkKind.LAMP or self.ceiling is None:
            return False
        o = slot.offset + 2
        height = float(self._x[o]) - float(self.ceiling.body_t_camera[2])
        var_h = float(self._cov.block(o, o + 1, o, o + 1)[0, 0])
        return var_h > (self.config.ekf.young_lamp_rel_sigma * max(height, 1e-6)) ** 2

    def _update_rows(self, pairs: list[tuple[Slot, Obs]], iterations: int) -> int:
        """One stacked update (eqs. 19-23) of ``pairs``, iterated ``iterations`` times.

        Stacking the observations into one update equals the paper's sequential
        ``K_i`` updates for a linear model; it needs one ``n x n`` rank-K correction
        instead of K (:meth:`_linearise`). With ``iterations > 1`` the state is
        re-linearised at each iterate (iterated EKF) until the step changes by less
        than ``ekf.update_tol``; ``P`` is corrected once, with the last ``W``.

        Returns:
            Number of observations used.
        """
        n = self._n
        cov = self._cov
        x0 = self._x[:n].copy()
        dx_prev: FloatArray | None = None
        for it in range(iterations):
            lin = self._linearise(pairs, x0 if it > 0 else None)
            if lin is None:
                if it == 0:
                    return 0
                break  # keep the previous iterate
            rows, w, step = lin
            self._x[:n] = x0 + step
            self._wrap_angles(rows)
            if dx_prev is not None and float(np.max(np.abs(step - dx_prev))) < self.config.ekf.update_tol:
                break
            dx_prev = step
        cov.downdate(w)  # eq. 23: (I - K H) P = P - K (P H^T)^T = P - W W^T
        if self._invariant:  # the update applied as exp(xi) x (``ekf.right_invariant``)
            invariant_update(self._x, x0, self._cov,
                             [0] + [s.offset for s in self._slots.values() if s.dim == 2])
        for slot, *_ in rows:
            slot.n_obs += 1
            slot.last_seen = self._step
        return len(rows)

    def _wrap_angles(self, rows: list[tuple[Slot, Obs, FloatArray, FloatArray, FloatArray]]) -> None:
        """Wrap the heading and the updated lamps' axis angles (after eq. 22)."""
        self._x[2] = wrap_angle(float(self._x[2]))
        for slot, *_ in rows:
            if slot.kind == "lamp" and slot.dim == 4:
                o = slot.offset + 3
                self._x[o] = wrap_axis(float(self._x[o]))

    def _linearise(self, pairs: list[tuple[Slot, Obs]], x0: FloatArray | None
                   ) -> tuple[list[tuple[Slot, Obs, FloatArray, FloatArray, FloatArray]],
                              FloatArray, FloatArray] | None:
        """One linearisation of the stacked update (eqs. 19-22) at the current state.

        The gain is :func:`lampsam.backend.ekf_update.stacked_gain`.

        Args:
            pairs: (landmark slot, observation) pairs.
            x0: the prediction, when the current state is an iterate of the iterated
                EKF: the innovation is then ``z - h(x_i) + H (x_i - x0)`` (Bell &
                Cathey 1993) and the returned step is from ``x0``; None: ``x_i = x0``.

        Returns:
            ``(rows used, W (n, K), state step (n,))``, or None when no row is
            predictable or ``Psi`` is not positive definite.
        """
        n = self._n
        rows: list[tuple[Slot, Obs, FloatArray, FloatArray, FloatArray]] = []
        for slot, obs in pairs:
            try:
                z_hat, h_r, h_l = self._h(slot, obs)
            except Exception as exc:  # behind the camera: skip this observation
                log.debug("landmark %d not predictable: %s", slot.id, exc)
                continue
            rows.append((slot, obs, residual(obs, z_hat), h_r, h_l))
        if not rows:
            return None
        if x0 is not None:
            dev = self._x[:n] - x0
            dev[2] = wrap_angle(float(dev[2]))
            for slot, obs, res, h_r, h_l in rows:
                o, d = slot.offset, slot.dim
                dl = dev[o : o + d].copy()
                if slot.kind == "lamp" and d == 4:
                    dl[3] = wrap_axis(float(dl[3]))
                res += h_r @ dev[:3] + h_l @ dl
                if obs.kind == "point2":
                    res[0] = wrap_angle(float(res[0]))
        out = stacked_gain(self._cov, [(sl.offset, sl.dim, res, h_r, h_l, o.R)
                                       for sl, o, res, h_r, h_l in rows])
        return None if out is None else (rows, *out)

    # ------------------------------------------------------------------ eqs. 24-25
    def _augment(self, obs: Obs, lid: int | None) -> int | None:
        """Add a landmark from one observation with the full cross-covariance (eqs. 24-25)."""
        pose = self._x[:3].copy()
        try:
            state, g_pose, g_z, cov_z = initialize(pose, obs, self.config.association,
                                                   self.ceiling)
        except Exception as exc:
            log.debug("cannot initialise a landmark: %s", exc)
            return None
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

    # ------------------------------------------------------------------ interface
    def step(self, t: float, wheel: FloatArray, frame: Frame | None) -> StepEstimate:
        """See :meth:`SlamBackend.step`. Raises EstimationError on NaN odometry or time reversal."""
        t0 = time.perf_counter()
        if t < self._last_t:
            raise EstimationError(f"t={t:.3f} s: time goes backwards (previous {self._last_t:.3f})")
        self._last_t = t
        self.predict(self.motion.check(t, wheel))
        n_matched = n_new = 0
        if frame is not None:
            obs = observations_from_frame(frame, self.config.features, self.config.noise)
            if obs:
                gating = not self.config.association.use_known_ids or any(
                    o.landmark_id is None for o in obs)
                cands, screened = self._screen(obs) if gating else ({}, {})
                patches = {lid: self._slots[lid].patch for lid in cands.get("corner", ())}
                assignments = associate(obs, cands, self._innovation,
                                        self.config.association, lambda i: i in self._slots,
                                        patches, screened)
                if self.config.association.joint_compatibility:
                    planar = {lid: (sl.offset, sl.dim) for lid, sl in self._slots.items()
                              if sl.kind == LandmarkKind.POINT2 and lid not in self._doomed}
                    assignments = joint_point2(
                        obs, assignments, screened, self.config.association, planar,
                        self._innovation, lambda lid, o: self._h(self._slots[lid], o),
                        self._cov, self.noise_scale.scale)
                learn_scale(self.noise_scale, obs, assignments, screened)
                if self.odo_scale is not None:
                    feed_scale(self.odo_scale, self.idle, obs, assignments, screened,
                               self._innovation_h)
                pairs = [(self._slots[a.landmark_id], obs[a.obs_index]) for a in assignments
                         if a.status == "matched" and a.landmark_id in self._slots
                         and self._slots[a.landmark_id].kind == obs[a.obs_index].kind]
                budget = (self.config.association.max_corner_updates
                          if self.config.ekf.corner_budget else None)
                pairs, entries = corner_budget(pairs, budget)
                n_matched = self._update(pairs)
                for a in assignments:
                    if a.status != "new":
                        continue
                    if obs[a.obs_index].kind == "corner":
                        if entries <= 0:
                            continue
                        entries -= 1
                    if (a.landmark_id is None and obs[a.obs_index].kind == LandmarkKind.POINT2
                            and not self._confirmed(obs[a.obs_index])):
                        continue
                    lid = self._augment(obs[a.obs_index], a.landmark_id)
                    n_new += lid is not None
                    if lid is not None:
                        pairs.append((self._slots[lid], obs[a.obs_index]))
                if self.config.association.prune_relative:  # what the pruning judges
                    note_relative_sigma(self._cov, pairs, self._slots)
                if self.config.association.planar_merge_every:
                    self.covis.add_frame(s.id for s, _ in pairs)
                self.planar_sightings.extend((self._step, o.z, o.R, sl.id) for sl, o in pairs
                                             if sl.kind == LandmarkKind.POINT2
                                             and o.landmark_id is None)
        if self.config.association.planar_merge_every:
            self._merge_duplicates()
        if self.tentative.items:
            self.tentative.expire(self._step)
        self._prune()
        self._step += 1
        dt = time.perf_counter() - t0
        pose = self._x[:3].copy()
        cov = self._cov.block(0, 3, 0, 3)
        self._history.add(t, pose, cov, dt, n_matched + n_new > 0)
        return StepEstimate(t, pose, cov, n_matched + n_new > 0, n_matched, n_new, dt)

    def _estimate(self, s: Slot) -> LandmarkEstimate:
        """The current estimate of one landmark in the state."""
        st = self._x[s.offset : s.offset + s.dim].copy()
        cov = self._cov.block(s.offset, s.offset + s.dim, s.offset, s.offset + s.dim)
        return landmark_estimate(s.id, s.kind, st, cov, s.n_obs, self.ceiling)

    def landmarks(self) -> list[LandmarkEstimate]:
        """The current map (landmarks with at least ``min_observations`` observations)."""
        return [self._estimate(s) for s in self._slots.values()
                if s.n_obs >= self.config.association.min_observations]

    def finish(self, status: str = "ok") -> SlamResult:
        """See :meth:`SlamBackend.finish`; landmarks seen fewer than ``min_observations``
        times are reported apart, flagged (``SlamResult.provisional``), unless
        ``association.prune_once_seen``."""
        cfg = self.config.association
        once = [lid for lid, s in self._slots.items()
                if s.n_obs < cfg.min_observations and lid not in self._doomed]
        if once:
            self.pruned["seen_too_few"] = self.pruned.get("seen_too_few", 0) + len(once)
            if not cfg.prune_once_seen:
                self._provisional.extend(self._estimate(self._slots[lid]) for lid in once)
        self._remove(sorted(set(once) | self._doomed))
        self._doomed.clear()
        log_pruned(self.n_pruned, self.pruned, cfg.min_observations, not cfg.prune_once_seen)
        return self._history.result(self.name, self.landmarks(), status,
                                    provisional=list(self._provisional),
                                    n_pruned=self.n_pruned, pruned=dict(self.pruned))
