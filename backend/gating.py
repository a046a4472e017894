"""Gating of a factor-graph backend: innovations and their covariance (paper eqs. 19-20).

Planar points use iSAM2's joint marginal of the last keyframe pose and each
candidate landmark, propagated to the current pose, so the pose-landmark
cross-covariance is kept (without it the gate is far too wide: a landmark
initialised from a pose is strongly correlated with it). Ceiling landmarks are
screened all at once in numpy with a relative gate (:meth:`Gating._screen`: the
odometry covariance since the landmark's last observing keyframe plus its
measurement-only covariance, which stands in for the cross term); corners are then
decided by that gate and the NCC, and only lamps with two or more gated candidates
pay for joint marginals (each costs several ms on a corner-dense graph).
"""

from __future__ import annotations

import math
from collections.abc import Iterable

import gtsam
import numpy as np
from gtsam.symbol_shorthand import X

from lampsam.arrays import FloatArray
from lampsam.backend.association import screen_pairs
from lampsam.backend.ceiling_graph import point_key
from lampsam.backend.gate_bracket import bracket_d2, settle_bracketed, sole_candidates
from lampsam.backend.graph_state import GraphState
from lampsam.backend.handlers import GraphLandmark
from lampsam.backend.models import Obs, for_landmark, predict, residual
from lampsam.backend.planar_gate import bearing_range_d2, range_bearing_many
from lampsam.backend.pose_cov import eq19_covariance, propagate_relative

#: Keyframes back over which the smoothers' screen uses the relative gate.
RELATIVE_GATE_KEYFRAMES = 30
#: :meth:`Gating._bound_far` settles a pair when its lower bound is this factor above
#: the new-landmark threshold: the bound's odometry is composed per keyframe, the
#: gate's per sample, which differ by up to 1e-5 relative in ``Psi`` (test run).
FAR_BOUND_MARGIN = 1.01


class Gating(GraphState):
    """Innovations and gates (mixin of :class:`~lampsam.backend.graph.GraphSlam`)."""

    def _joint_cov(self, lm: GraphLandmark, k: int) -> tuple[FloatArray, FloatArray, FloatArray] | None:
        """Joint marginal blocks ``(S_kk, S_kl, S_ll)`` of keyframe ``k`` and a landmark.

        From iSAM2's ``jointMarginalCovariance``; the landmark block is over the
        EKF-form state (the handler's keys, in order). None without iSAM2.
        """
        if self.isam is None or not lm.in_graph:
            return None
        if lm.id in self._joint_cache:
            return self._joint_cache[lm.id]
        keys = [X(k), *self.handlers[lm.kind].keys(lm)]
        try:
            full = np.asarray(self.isam.jointMarginalCovariance(keys).fullMatrix())
        except (RuntimeError, IndexError):  # IndexError: not in iSAM2 yet (a deferred update)
            self._joint_cache[lm.id] = None
            return None
        # graph tangent -> EKF-form state (e.g. only the angle of a Pose2 axis)
        idx = np.r_[0:3, 3 + np.asarray(self.handlers[lm.kind].state_index(lm), int)]
        full = full[np.ix_(idx, idx)]
        out = full[:3, :3], full[:3, 3:], full[3:, 3:]
        self._joint_cache[lm.id] = out
        self._joint_at[lm.id] = (k, out)
        return out

    def _prefetch_joint(self, k: int, obs: list[Obs],
                        screened: dict[int, dict[int, tuple[float, bool]]]) -> int:
        """Joint marginals of every lamp the gate will ask about, in one Bayes-tree query.

        :func:`~lampsam.backend.association.associate` asks :meth:`_innovation` for the
        exact eq.-19 distance of each screened pair that is inside the gate but not
        final (a lamp with an axis, or an ambiguous one). Each such landmark needs the
        joint marginal of ``(X(k), landmark)``; one ``jointMarginalCovariance`` over
        ``X(k)`` and all of them gives the same blocks (a marginal of a Gaussian is a
        sub-block of any larger joint marginal) for one pass over the Bayes tree's
        path to the root instead of one pass per landmark. Fills the per-keyframe
        cache of :meth:`_joint_cov`; on a GTSAM error it leaves the cache alone (the
        per-landmark calls then run as before).

        Args:
            k: the last keyframe in iSAM2 (the gate's pose variable).
            obs: the frame's observations; screened: :meth:`_screen`'s pre-screen.

        Returns:
            The number of landmarks whose blocks were cached.
        """
        if self.isam is None:
            return 0
        cfg = self.config.association
        lids: list[int] = []
        seen: set[int] = set()
        for i, pairs in screened.items():
            gate = cfg.gate(len(obs[i].z))
            for lid, (d2, exact) in pairs.items():
                if (not exact and d2 < gate and lid not in seen and lid not in self._joint_cache
                        and lid in self._landmarks and self._landmarks[lid].in_graph):
                    seen.add(lid)
                    lids.append(lid)
        if len(lids) < 2:  # a single landmark: _joint_cov's own query is the same call
            return 0
        keys = [X(k)]
        spans: list[tuple[int, list[int]]] = []
        for lid in lids:
            lm = self._landmarks[lid]
            handler = self.handlers[lm.kind]
            start = 3 * len(keys)  # Pose2, Point3 and the axis Pose2 are all 3-D tangents
            keys.extend(handler.keys(lm))
            spans.append((lid, [start + j for j in handler.state_index(lm)]))
        try:
            full = np.asarray(self.isam.jointMarginalCovariance(keys).fullMatrix())
        except (RuntimeError, IndexError):
            return 0
        if full.shape != (3 * len(keys), 3 * len(keys)):
            return 0
        s_kk = full[:3, :3]
        for lid, idx in spans:
            blocks = (s_kk, full[np.ix_(np.r_[0:3], idx)], full[np.ix_(idx, idx)])
            self._joint_cache[lid] = blocks
            self._joint_at[lid] = (k, blocks)
        return len(spans)

    def _innovation(self, gate_ctx: tuple[int, FloatArray, FloatArray, FloatArray], lid: int,
                    obs: Obs) -> tuple[FloatArray, FloatArray] | None:
        """``(nu, Psi)`` (eq. 19) with the pose-landmark cross-covariance.

        The current pose is ``x = x_k * delta`` (``k`` the last keyframe in iSAM2), so
        in the right tangent ``dx = Ad(delta^-1) dx_k + d_delta``: its covariance and
        cross-covariance with a landmark follow from the joint marginal of
        ``(X(k), landmark)``. Without the cross term the gate is far too wide: a
        landmark initialised from the pose is strongly correlated with it.
        """
        k, pose, delta, delta_cov = gate_ctx
        lm = self._landmarks[lid]
        obs = for_landmark(obs, len(lm.state))
        try:
            z_hat, h_p, h_l = predict(lm.kind, pose, lm.state, obs, self.ceiling)
        except Exception:
            return None
        planar = obs.kind == "point2"
        r = obs.R * self.config.association.gate_noise_scale if planar else obs.R
        s_online = self.noise_scale.scale if planar else 1.0
        joint = self._joint_cov(lm, k)
        if joint is None:  # no joint marginal: independent pose and landmark
            pose_cov = self.current_cov()
            psi = h_p @ pose_cov @ h_p.T + h_l @ lm.cov @ h_l.T + r
            return residual(obs, z_hat), psi * s_online
        psi = eq19_covariance(h_p, h_l, joint, delta, delta_cov, r)
        nu = residual(obs, z_hat)
        if not planar:  # for _reuse_far: this keyframe's exact distance of the lamp
            self._far[(lid, len(nu))] = (self._k, float(nu @ np.linalg.solve(psi * s_online, nu)))
        return nu, psi * s_online

    def _innovation_h(self, gate_ctx: tuple[int, FloatArray, FloatArray, FloatArray], lid: int,
                      obs: Obs) -> tuple[FloatArray, FloatArray, FloatArray] | None:
        """``(nu, Psi, H_p)``: :meth:`_innovation` with the pose Jacobian (right tangent)."""
        pred = self._innovation(gate_ctx, lid, obs)
        if pred is None:
            return None
        lm = self._landmarks[lid]
        _, h_p, _ = predict(lm.kind, gate_ctx[1], lm.state, for_landmark(obs, len(lm.state)),
                            self.ceiling)
        return pred[0], pred[1], h_p

    def _screen(self, obs: list[Obs], pose: FloatArray, pose_cov: FloatArray
                ) -> tuple[dict[str, list[int]], dict[int, dict[int, tuple[float, bool]]]]:
        """Candidates per kind and a cheap vectorised gate for ceiling observations.

        Ceiling landmarks are projected all at once
        (:meth:`~lampsam.backend.ceiling.CeilingModel.project_many`) from their
        cached states; the visible ones that are in the graph are refreshed from
        iSAM2. The screen uses ``S = H_p Sigma_x H_p^T + H_l Sigma_l H_l^T`` (pose
        and landmark marginals, no cross term: wider than eq. 19's true
        covariance, since a landmark is positively correlated with the pose that
        placed it), with ``Sigma_x`` the current pose marginal and ``Sigma_l`` the
        landmark's initialisation covariance (eq. 25 or the triangulation; an
        upper bound of its marginal, and free, where iSAM2's landmark marginals cost
        several ms each). Only ambiguous observations then cost joint marginals
        (:meth:`_mark_ambiguous`, :meth:`_joint_cov`, cached per keyframe). Planar
        landmarks go the per-pair way (joint marginal per pair, as before).

        Returns:
            ``(candidates, screened)`` for :func:`associate`.
        """
        cands: dict[str, list[int]] = {}
        screened: dict[int, dict[int, tuple[float, bool]]] = {}
        by_kind: dict[str, list[GraphLandmark]] = {}
        planar: list[GraphLandmark] = []
        for lid, lm in self._landmarks.items():
            if lm.kind == "point2":
                planar.append(lm)
            elif self.ceiling is None:
                cands.setdefault(lm.kind, []).append(lid)
            else:
                by_kind.setdefault(lm.kind, []).append(lm)
        if planar:
            cands["point2"] = [lm.id for lm in planar]
            if any(o.kind == "point2" and o.landmark_id is None for o in obs) or (
                    not self.config.association.use_known_ids):
                screened.update(self._screen_planar(obs, pose, pose_cov, planar))
        obs_kinds = {o.kind for o in obs}
        for kind, lms in by_kind.items():
            pts = np.array([lm.state[:3] for lm in lms])
            ceiling = self._require_ceiling()
            vis = ceiling.in_view_many(pose, pts)
            visible = [lms[j] for j in np.flatnonzero(vis)]
            self._refresh_visible(visible)
            if not visible:
                cands[kind] = []
                continue
            pts = np.array([lm.state[:3] for lm in visible])
            m, h_p, h_l, vis = ceiling.project_many(pose, pts)
            keep = np.flatnonzero(vis)
            lids = [visible[j].id for j in keep]
            cands[kind] = lids
            if not keep.size or kind not in obs_kinds:
                continue
            rel = self._relative_covs()
            sel = [visible[j] for j in keep]
            # relative to the last sighting iSAM2 has (a later one, in keyframes whose
            # update is deferred, did not move the landmark: GraphSlam.step(update=False))
            last = [min(lm.last_kf, self._k_isam) for lm in sel]
            recent = [lm.cov_rel is not None and j in rel for lm, j in zip(sel, last, strict=True)]
            cov_l = np.array([lm.cov_rel if r else lm.cov[:3, :3]
                              for lm, r in zip(sel, recent, strict=True)], float)
            cov_x = np.array([rel[j] if r else pose_cov
                              for j, r in zip(last, recent, strict=True)], float)
            hp, hl = h_p[keep], h_l[keep]
            s_pred = (hp @ cov_x @ np.transpose(hp, (0, 2, 1))
                      + hl @ cov_l @ np.transpose(hl, (0, 2, 1)))
            sc = screen_pairs(obs, kind, lids, m[keep], s_pred, self.config.association,
                              exact=True)
            screened.update(self._bracket(obs, pose, pose_cov, self._reuse_far(obs, self._bound_far(
                obs, pose, self._mark_ambiguous(obs, sc)))))
        return cands, screened

    def _refresh_visible(self, visible: list[GraphLandmark]) -> None:
        """Refresh the cached states of the visible in-graph landmarks from iSAM2.

        The same values as :meth:`~lampsam.backend.graph_state.GraphState._refresh_landmark`;
        a point (every corner, a lamp without an axis) is read with one
        ``calculateEstimatePoint3`` call instead of going through its handler (a
        keyframe refreshes ~200 of them), its key kept per landmark id (a landmark's
        kind, hence its key, never changes).
        """
        isam = self.isam
        if isam is None:
            return
        read = isam.calculateEstimatePoint3
        keys = self._point_keys
        for lm in visible:
            if not lm.in_graph:
                continue
            if len(lm.state) == 3:
                key = keys.get(lm.id)
                if key is None:
                    key = keys[lm.id] = point_key(lm.kind, lm.id)
                try:
                    lm.state = np.asarray(read(key), float)
                    continue
                except (RuntimeError, IndexError):  # not in iSAM2 (yet): the handler's way
                    pass
            self._refresh_landmark(lm)

    def _screen_planar(self, obs: list[Obs], pose: FloatArray, pose_cov: FloatArray,
                       lms: list[GraphLandmark]) -> dict[int, dict[int, tuple[float, bool]]]:
        """Range-bearing observations against every planar landmark at once (no ids).

        The in-graph landmarks' cached states are first refreshed from iSAM2 (the
        innovation and the joint marginal at one linearisation). Every landmark is
        then screened with the pose and landmark marginals and no cross term, doubled (``2 diag(P_xx, P_ll)`` bounds the joint covariance from
        above, so a pair beyond the new-landmark threshold here is beyond it in eq. 19
        too); the pairs left are decided by the joint marginal (:meth:`_innovation`),
        exactly as without the screen. With ``association.planar_relative_gate``, a
        landmark last observed within :data:`RELATIVE_GATE_KEYFRAMES` keyframes is
        instead gated relative to that keyframe: ``Psi = H_p C H_p^T + s (H_l Sigma_rel H_l^T
        + R)`` with ``C`` the odometry covariance since then
        (:meth:`_relative_covs`), ``Sigma_rel`` its position covariance relative to
        the observing pose (measurement-only, eq. 25's ``G_z R G_z^T``) and ``s``
        ``association.gate_noise_scale``. The common uncertainty of the two poses
        cancels in a relative measurement, so this distance is final (the cross
        term of eq. 19 stands in for it). It trusts the odometry model: on MRCLAM,
        whose odometry noise is assumed and overconfident, it rejected true matches
        (docs/graph-backend.md).

        Returns:
            For :func:`associate`'s ``screened``: obs index -> {landmark id: (d2, exact)}.
        """
        idx = [i for i, o in enumerate(obs) if o.kind == "point2"]
        if not idx:
            return {}
        scale = self.config.association.gate_noise_scale
        rel = self._relative_covs()
        relative = self.config.association.planar_relative_gate
        # iSAM2's current estimates: the joint marginal below is at the current
        # linearisation, so the innovation must be too (a first-sight state against a
        # marginal shrunk by later sightings inflated d2 past the new-landmark
        # threshold: docs/failures.md, no ids online)
        for lm in lms:
            self._refresh_landmark(lm)
        pts = np.array([lm.state[:2] for lm in lms], float)
        z_hat, h_p, h_l = range_bearing_many(pose, pts)
        recent = np.array([relative and lm.last_kf in rel and lm.cov_rel is not None
                           for lm in lms])
        cov_x = np.empty((len(lms), 3, 3))
        cov_l = np.empty((len(lms), 2, 2))
        for j, lm in enumerate(lms):
            if recent[j]:
                cov_x[j] = rel[lm.last_kf]
                cov_l[j] = scale * np.asarray(lm.cov_rel)[:2, :2]
            else:
                cov_x[j] = 2.0 * pose_cov
                cov_l[j] = 2.0 * lm.cov[:2, :2]
        s_pred = (h_p @ cov_x @ np.transpose(h_p, (0, 2, 1))
                  + h_l @ cov_l @ np.transpose(h_l, (0, 2, 1)))
        z = np.array([obs[i].z[:2] for i in idx], float)
        r = np.array([obs[i].R[:2, :2] for i in idx], float) * scale
        d2 = bearing_range_d2(z, r, z_hat, s_pred) / self.noise_scale.scale
        cfg = self.config.association
        new_t, gate = cfg.new_threshold(2), cfg.gate(2)
        out: dict[int, dict[int, tuple[float, bool]]] = {}
        for row, i in enumerate(idx):
            keep = np.flatnonzero(d2[row] < new_t)
            if cfg.planar_reject_ambiguous and np.count_nonzero(
                    (d2[row, keep] < gate) & recent[keep]) >= 2:  # final distances only
                # ambiguous: no match, no new landmark (associate drops it)
                out[i] = {lms[j].id: (max(float(d2[row, j]), gate), False) for j in keep}
                continue
            # a screened (not final) pair goes to associate as unknown: it asks the
            # joint marginal, as without the screen
            out[i] = {lms[j].id: ((float(d2[row, j]), True) if recent[j] else (math.nan, False))
                      for j in keep}
        return out

    def _relative_covs(self) -> dict[int, FloatArray]:
        """Tangent covariance of the current keyframe relative to each recent keyframe.

        ``{j: cov(x_j^-1 x_k)}`` for the current keyframe ``k`` and the last
        :data:`RELATIVE_GATE_KEYFRAMES` keyframes before it, from the odometry
        factors' covariances (eqs. 13-15, with their floor). Kept incrementally: a new
        keyframe with odometry ``d_k`` (covariance ``C_k``) maps every entry through
        :func:`~lampsam.backend.pose_cov.compose_cov`,
        ``Sigma_j <- Ad(d_k^-1) Sigma_j Ad(d_k^-1)^T + C_k``, all at once
        (:func:`propagate_relative`), instead of recomposing the whole window.
        """
        k = self._k
        if self._rel_cache is not None and self._rel_cache[0] == k:
            return self._rel_cache[1]
        lo = max(k - RELATIVE_GATE_KEYFRAMES, 0)
        if self._rel_cache is None or not lo <= self._rel_cache[0] < k:
            k_c, js, covs = lo, [lo], np.zeros((1, 3, 3))
        else:
            k_c, old = self._rel_cache
            js = [j for j in old if j >= lo]
            covs = np.array([old[j] for j in js])
        for step in range(k_c + 1, k + 1):
            d, c = self._odo[step]
            covs = np.concatenate([propagate_relative(d, c, covs), np.zeros((1, 3, 3))])
            js.append(step)
        keep = [n for n, j in enumerate(js) if j >= lo]
        out = {js[n]: covs[n] for n in keep}
        self._rel_cache = (k, out)
        return out

    def _mark_ambiguous(self, obs: list[Obs], screened: dict[int, dict[int, tuple[float, bool]]]
                        ) -> dict[int, dict[int, tuple[float, bool]]]:
        """Keep the cheap distance where it decides alone; ask for the joint marginal otherwise.

        Corners: the NCC picks the winner among the gated candidates (paper), so the
        cheap (wider) gate is final; a wrong match that it lets through is bounded by
        the Huber loss on corner factors (``isam2.corner_huber_k``). Lamps: an
        observation with at most one landmark inside the cheap gate is decided by
        it (the true eq.-19 covariance could only reject the match); with two or
        more, the exact distances (iSAM2 joint marginal with the pose-landmark cross
        term, :meth:`_joint_cov`) pick the winner. iSAM2's joint marginals cost
        several ms each on a graph dense with corners (17 ms on the lab run), so
        this keeps them to the few ambiguous lamp observations. A lamp seen with its
        axis always takes the exact gate (the screen has no axis row); deciding it by
        a cheap three-row screen instead let biased sights in (docs/speed.md).

        ``screened`` must come from :func:`~lampsam.backend.association.screen_pairs`
        with ``exact=True`` (a pair's flag is then already "2-D row", the unambiguous
        case); only the ambiguous lamps' entries are replaced (in place, no copy of
        the ~50 corner rows per keyframe).
        """
        cfg = self.config.association
        for i, pairs in screened.items():
            o = obs[i]
            if o.kind == "corner" or len(pairs) <= 1:
                continue  # the screen's own flag, exact for 2-D rows (screen_pairs, exact=True)
            gate = cfg.gate(len(o.z))
            if sum(d2 < gate for d2, _ in pairs.values()) > 1:
                screened[i] = {lid: (d2, False) for lid, (d2, _) in pairs.items()}
        return screened

    def _bound_far(self, obs: list[Obs], pose: FloatArray,
                   screened: dict[int, dict[int, tuple[float, bool]]]
                   ) -> dict[int, dict[int, tuple[float, bool]]]:
        """Settle a lamp pair without a joint marginal when a lower bound of its eq.-19 distance is beyond the new-landmark threshold.

        The lamp's last exact joint marginal, of ``(X(j), lamp)`` at an earlier gate
        (:attr:`_joint_at`, within :data:`RELATIVE_GATE_KEYFRAMES`), is carried to the
        current pose through the odometry since ``X(j)`` alone
        (:func:`propagate_joint`). That is the joint marginal of a graph with fewer
        factors than iSAM2's now: every factor added since (this path's observations,
        other loop closures) only adds information, so at the same linearisation the
        propagated covariance bounds the exact one from above, ``Psi`` likewise, and
        the distance ``nu^T Psi^-1 nu`` it gives bounds the exact one from below. A
        pair whose bound is above ``association.new_threshold`` can neither match nor
        keep the observation from starting a landmark whatever the exact distance:
        :func:`~lampsam.backend.association.associate` decides it the same without
        asking iSAM2 (the exact query walks the Bayes tree to a revisited lamp's
        old clique: 50-100 ms on the lab path, docs/speed.md). Only pairs the
        association would ask about (lamps, not final, inside the screen's gate).
        The records are forgotten whenever iSAM2 relinearises
        (:meth:`~lampsam.backend.isam2_update.Isam2Updates._relinearized`): new
        Jacobians can widen a marginal (up to 4 % in ``Psi`` on a test run), so the
        bound holds between relinearisations only.
        """
        cfg = self.config
        if not cfg.isam2.far_lamp_bound or not self._joint_at or self.ceiling is None:
            return screened
        rel: dict[int, FloatArray] | None = None
        chain: dict[int, FloatArray] = {}
        for i, pairs in screened.items():
            o = obs[i]
            if o.kind != "lamp":
                continue
            gate, new_t = cfg.association.gate(len(o.z)), cfg.association.new_threshold(len(o.z))
            for lid, (d2, exact) in pairs.items():
                rec = self._joint_at.get(lid)
                if exact or not d2 < gate or rec is None:
                    continue
                if rel is None:
                    rel = self._relative_covs()
                bound = self._far_bound(rec, lid, o, pose, rel, chain)
                if bound is not None and bound[0] > FAR_BOUND_MARGIN * new_t:
                    pairs[lid] = (bound[0], True)
                    self.n_far_bounded += 1
        return screened

    def _far_bound(self, rec: tuple[int, tuple[FloatArray, FloatArray, FloatArray]], lid: int,
                   obs: Obs, pose: FloatArray, rel: dict[int, FloatArray],
                   chain: dict[int, FloatArray]) -> tuple[float, FloatArray] | None:
        """``(d2, Psi)`` of :meth:`_bound_far` from the joint record ``rec`` of landmark ``lid``.

        ``rel`` is :meth:`_relative_covs`; ``chain`` caches :meth:`_odometry_since`.
        None when the record is too old for ``rel``, the landmark's state changed size
        (an axis seen since) or the prediction fails.
        """
        j, joint = rec
        lm = self._landmarks[lid]
        if j not in rel or joint[2].shape[0] != len(lm.state):
            return None
        if j not in chain:
            chain[j] = self._odometry_since(j)
        o_lm = for_landmark(obs, len(lm.state))
        try:
            z_hat, h_p, h_l = predict(lm.kind, pose, lm.state, o_lm, self.ceiling)
        except Exception:
            return None
        nu = residual(o_lm, z_hat)
        psi = eq19_covariance(h_p, h_l, joint, chain[j], rel[j], o_lm.R)
        return float(nu @ np.linalg.solve(psi, nu)), psi

    def _odometry_since(self, j: int) -> FloatArray:
        """``x_j^-1 x_k`` (x, y, theta) from the keyframes' odometry (``k`` the current keyframe)."""
        d = gtsam.Pose2()
        for step in range(j + 1, self._k + 1):
            d = d.compose(gtsam.Pose2(*self._odo[step][0]))
        return np.array([d.x(), d.y(), d.theta()])

    def _reuse_far(self, obs: list[Obs], screened: dict[int, dict[int, tuple[float, bool]]]
                   ) -> dict[int, dict[int, tuple[float, bool]]]:
        """Skip the joint marginal of a lamp whose recent exact distance was far beyond the gate.

        A lamp whose exact eq.-19 distance (:meth:`_innovation`, same measurement size)
        was above ``isam2.far_lamp_factor`` times the new-landmark threshold at most
        ``isam2.far_lamp_recheck`` keyframes ago keeps that distance as final for this
        keyframe (it can neither match nor keep the observation from being new), so
        iSAM2 is not asked again; it is asked once the record is older. On the lab
        path one old lamp that the exact gate rejects at every keyframe of the revisit
        (distance 48-89 against a threshold of ~16) cost 50-60 ms a keyframe: the walk
        from the root to its clique, deep in the Bayes tree (docs/speed.md). The
        distance of the skipped keyframes is not the exact one; how many decisions
        that changes is measured in docs/speed.md.
        """
        cfg = self.config
        recheck = cfg.isam2.far_lamp_recheck
        if recheck <= 0 or not self._far:
            return screened
        for i, pairs in screened.items():
            o = obs[i]
            if o.kind != "lamp":
                continue
            far = cfg.isam2.far_lamp_factor * cfg.association.new_threshold(len(o.z))
            for lid, (_, exact) in pairs.items():
                rec = self._far.get((lid, len(o.z)))
                if (not exact and rec is not None and self._k - rec[0] <= recheck
                        and rec[1] > far):
                    pairs[lid] = (rec[1], True)
                    self.n_far_reused += 1
        return screened

    def _bracket(self, obs: list[Obs], pose: FloatArray, pose_cov: FloatArray,
                 screened: dict[int, dict[int, tuple[float, bool]]]
                 ) -> dict[int, dict[int, tuple[float, bool]]]:
        """Settle lamp pairs by a bracket of their exact distance (:mod:`~lampsam.backend.gate_bracket`).

        For each lamp pair the association would ask iSAM2 about (not final, inside
        the screen's gate), the exact eq.-20 distance is bracketed from the current
        pose marginal ``pose_cov`` (exact), the lamp's block of its last joint marginal
        (:attr:`_joint_at`, an upper bound of its marginal while iSAM2 has not
        relinearised) and ``R``; :func:`~lampsam.backend.gate_bracket.settle_bracketed`
        keeps the pairs whose decision the bracket fixes, which then cost no joint
        marginal. The far-lamp record the exact gate would write (:meth:`_reuse_far`)
        is written with the bracket's end. Off with ``[isam2] bracket_gate = false``
        or while keyframes wait for an update (``pose_cov`` is then a prediction).
        """
        cfg = self.config
        if (not cfg.isam2.bracket_gate or self.isam is None or self.ceiling is None
                or self._k_isam != self._k - 1):
            return screened
        ac = cfg.association
        rows = {i: pairs for i, pairs in screened.items() if obs[i].kind == "lamp"}
        gate = {i: ac.gate(len(obs[i].z)) for i in rows}
        asked = [(i, lid) for i, pairs in rows.items() for lid, (d2, exact) in pairs.items()
                 if not exact and d2 < gate[i] and lid in self._landmarks
                 and self._landmarks[lid].in_graph]
        if not asked:
            return screened
        sole = sole_candidates(
            {i: {lid: d2 for lid, (d2, _) in pairs.items()} for i, pairs in rows.items()}, gate)
        # (nu, A, B or None, R) per pair that a bracket could settle (a sole candidate, or
        # one with a lamp-marginal bound), grouped by size and whether B is known
        groups: dict[tuple[int, bool], list[tuple[tuple[int, int], FloatArray, FloatArray,
                                                  FloatArray | None, FloatArray]]] = {}
        for i, lid in asked:
            lm = self._landmarks[lid]
            rec = self._joint_at.get(lid)
            if rec is not None and rec[1][2].shape[0] != len(lm.state):
                rec = None
            if rec is None and (i, lid) not in sole:
                continue
            o = for_landmark(obs[i], len(lm.state))
            try:
                z_hat, h_p, h_l = predict(lm.kind, pose, lm.state, o, self.ceiling)
            except Exception:
                continue
            b = None if rec is None else h_l @ rec[1][2] @ h_l.T
            groups.setdefault((len(z_hat), b is not None), []).append(
                ((i, lid), residual(o, z_hat), h_p @ pose_cov @ h_p.T, b, o.R))
        bracket: dict[tuple[int, int], tuple[float, float]] = {}
        dof: dict[tuple[int, int], int] = {}
        for (dim, known), group in groups.items():
            nu, r = np.array([g[1] for g in group]), np.array([g[4] for g in group])
            # sole candidates that R alone puts inside need no bounds over t
            r_only = np.array([g[0] in sole for g in group]) & (
                np.einsum("ni,ni->n", nu, np.linalg.solve(r, nu[..., None])[..., 0])
                < np.array([gate[g[0][0]] for g in group]))
            lo, hi = bracket_d2(nu, np.array([g[2] for g in group]),
                                np.array([g[3] for g in group]) if known else None, r, r_only)
            for g, lo_j, hi_j in zip(group, lo, hi, strict=True):
                bracket[g[0]] = (float(lo_j), float(hi_j))
                dof[g[0]] = dim
        recheck = cfg.isam2.far_lamp_recheck > 0
        settled = settle_bracketed(
            sole, bracket, gate, {i: ac.new_threshold(len(obs[i].z)) for i in rows},
            {i: cfg.isam2.far_lamp_factor * ac.new_threshold(len(obs[i].z)) for i in rows}
            if recheck else None)
        for (i, lid), (d2, side) in settled.items():
            screened[i][lid] = (d2, True)
            self._far[(lid, dof[(i, lid)])] = (self._k, d2)  # as the exact gate records it
            if side == "inside":
                self.n_bracket_inside += 1
            else:
                self.n_bracket_outside += 1
        return screened

    def _near_known_lamp(self, pose: FloatArray, obs: Obs, lamp_ids: Iterable[int]) -> bool:
        """Whether a mapped lamp is predicted within ``lamp_min_separation`` of ``obs``.

        Two lamps cannot overlap in the image, so such an observation is of that
        lamp even when its gate rejects it (a centroid biased by lens distortion near
        the image edge, while iSAM2 waits to relinearise a young lamp); it is
        dropped rather than mapped as a new lamp (docs/graph-backend.md).
        """
        sep = self.config.association.lamp_min_separation
        ids = [lid for lid in lamp_ids if lid in self._landmarks]
        if self.ceiling is None or not ids or sep <= 0.0:
            return False
        pts = np.array([self._landmarks[lid].state[:3] for lid in ids])
        m, _, _, vis = self.ceiling.project_many(pose, pts)
        d = np.hypot(m[:, 0] - obs.z[0], m[:, 1] - obs.z[1])
        return bool(np.any(vis & (d < sep)))

