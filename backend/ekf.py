"""The paper's EKF-SLAM (paper 1, eqs. 13-25), exploiting the sparsity of its Jacobians.

State ``X = [x, y, theta, landmark_1, ..., landmark_n]`` (plain coordinates, world
frame; landmark states in :mod:`lampsam.backend.models`), covariance ``P``. The
backend is composed of:

- :mod:`lampsam.backend.ekf_state`: the state, its covariance storage, the
  prediction (eqs. 13-15) and the innovations (eq. 19);
- gate (eqs. 19-20), vectorised over a frame: :mod:`lampsam.backend.ekf_gate`;
  association: :mod:`lampsam.backend.association`;
- :mod:`lampsam.backend.ekf_map`: augmentation (eqs. 24-25), merging and pruning;
- this module: the update and the step.

Update (eqs. 21-23), the observations of a frame stacked: ``H`` has nonzero columns
only for the robot and one landmark per row, so ``P H^T = P[:, R] H_R^T + P[:, L]
H_L^T`` (n x k), ``K = P H^T Psi^-1`` and ``P <- P - K (P H^T)^T``, which equals
``(I - K H) P`` (eq. 23); with ``Psi = C C^T`` and ``W = P H^T C^-T`` this is the
symmetric rank-k downdate ``P <- P - W W^T`` (BLAS ``dsyrk``, in place).
"""

from __future__ import annotations

import logging
import time

import numpy as np

from lampsam.arrays import FloatArray
from lampsam.backend.association import associate, corner_budget
from lampsam.backend.ekf_joint import joint_point2
from lampsam.backend.ekf_landmarks import Slot, note_relative_sigma
from lampsam.backend.ekf_map import EkfMap
from lampsam.backend.ekf_update import invariant_update, stacked_gain
from lampsam.backend.innovation_scale import learn_scale
from lampsam.backend.interface import (
    Frame,
    LandmarkEstimate,
    LandmarkKind,
    SlamResult,
    StepEstimate,
    check_step_time,
    log_pruned,
)
from lampsam.backend.models import Obs, for_landmark, observations_from_frame, residual
from lampsam.backend.odometry_scale import feed_scale
from lampsam.factors.geometry import wrap_angle, wrap_axis

log = logging.getLogger(__name__)


class EkfSlam(EkfMap):
    """EKF-SLAM of paper 1 behind the :class:`~lampsam.backend.interface.SlamBackend` interface.

    Constructed as :class:`~lampsam.backend.ekf_state.EkfState` (its arguments).
    """

    name = "ekf"

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

    # ------------------------------------------------------------------ interface
    def step(self, t: float, wheel: FloatArray, frame: Frame | None) -> StepEstimate:
        """See :meth:`SlamBackend.step`. Raises EstimationError on NaN odometry or time reversal."""
        t0 = time.perf_counter()
        self._last_t = check_step_time(t, self._last_t)
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
