"""Gating of a factor-graph backend: the screen of a keyframe's observations (paper eqs. 19-20).

Ceiling landmarks are screened all at once in numpy with a relative gate
(:meth:`Gating._screen`: the odometry covariance since the landmark's last observing
keyframe plus its measurement-only covariance, which stands in for the cross term);
corners are then decided by that gate and the NCC, and only lamps with two or more
gated candidates pay for joint marginals (each costs several ms on a corner-dense
graph), unless a shortcut settles them (:mod:`lampsam.backend.gate_shortcuts`).
Planar points are screened with doubled marginals, or the relative gate, and the
pairs left go to the exact gate (:mod:`lampsam.backend.gate_exact`: iSAM2's joint
marginal of the last keyframe pose and the landmark, propagated to the current
pose).

``screened`` maps an observation index to ``{landmark id: (d2, exact)}``, the
``screened`` of :func:`~lampsam.backend.association.associate`.
"""

from __future__ import annotations

import math
from collections.abc import Iterable

import numpy as np

from lampsam.arrays import FloatArray
from lampsam.backend.association import screen_pairs
from lampsam.backend.ceiling_graph import point_key
from lampsam.backend.gate_shortcuts import LampGateShortcuts
from lampsam.backend.handlers import GraphLandmark
from lampsam.backend.models import Obs
from lampsam.backend.planar_gate import bearing_range_d2, range_bearing_many


class Gating(LampGateShortcuts):
    """Screen and gates (mixin of :class:`~lampsam.backend.graph.GraphSlam`).

    The exact gate's methods (:class:`~lampsam.backend.gate_exact.ExactGate`) and the
    lamp shortcuts (:class:`~lampsam.backend.gate_shortcuts.LampGateShortcuts`) are
    inherited, so callers keep using ``Gating``.
    """

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
        (:meth:`_mark_ambiguous`, :meth:`~lampsam.backend.gate_exact.ExactGate._joint_cov`, cached per keyframe). Planar
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
        too); the pairs left are decided by the joint marginal (:meth:`~lampsam.backend.gate_exact.ExactGate._innovation`),
        exactly as without the screen. With ``association.planar_relative_gate``, a
        landmark last observed within :data:`~lampsam.backend.gate_exact.RELATIVE_GATE_KEYFRAMES` keyframes is
        instead gated relative to that keyframe: ``Psi = H_p C H_p^T + s (H_l Sigma_rel H_l^T
        + R)`` with ``C`` the odometry covariance since then
        (:meth:`~lampsam.backend.gate_exact.ExactGate._relative_covs`), ``Sigma_rel`` its position covariance relative to
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

    def _mark_ambiguous(self, obs: list[Obs], screened: dict[int, dict[int, tuple[float, bool]]]
                        ) -> dict[int, dict[int, tuple[float, bool]]]:
        """Keep the cheap distance where it decides alone; ask for the joint marginal otherwise.

        Corners: the NCC picks the winner among the gated candidates (paper), so the
        cheap (wider) gate is final; a wrong match that it lets through is bounded by
        the Huber loss on corner factors (``isam2.corner_huber_k``). Lamps: an
        observation with at most one landmark inside the cheap gate is decided by
        it (the true eq.-19 covariance could only reject the match); with two or
        more, the exact distances (iSAM2 joint marginal with the pose-landmark cross
        term, :meth:`~lampsam.backend.gate_exact.ExactGate._joint_cov`) pick the winner. iSAM2's joint marginals cost
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

