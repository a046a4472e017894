"""Lamp-gate shortcuts: settle a lamp pair without iSAM2's joint marginal when the decision is known.

The exact gate (:mod:`lampsam.backend.gate_exact`) walks the Bayes tree to a
revisited lamp's old clique (50-100 ms on the lab path, docs/speed.md). Three
shortcuts settle the pairs whose association decision does not depend on the exact
distance, in the order :meth:`~lampsam.backend.gating.Gating._screen` applies them:

- :meth:`LampGateShortcuts._bound_far`: a lower bound of the distance from the lamp's
  last joint marginal, carried through the odometry since, is beyond the
  new-landmark threshold;
- :meth:`LampGateShortcuts._reuse_far`: the lamp's recent exact distance was far
  beyond it;
- :meth:`LampGateShortcuts._bracket`: a bracket of the exact distance
  (:mod:`lampsam.backend.gate_bracket`) fixes the decision.

``screened`` maps an observation index to ``{landmark id: (d2, exact)}`` (the
``screened`` of :func:`~lampsam.backend.association.associate`); a settled pair
becomes ``(d2, True)``. Counters: ``n_far_bounded``, ``n_far_reused``,
``n_bracket_inside``, ``n_bracket_outside``.
"""

from __future__ import annotations

import numpy as np

from lampsam.arrays import FloatArray
from lampsam.backend.gate_bracket import bracket_d2, settle_bracketed, sole_candidates
from lampsam.backend.gate_exact import ExactGate
from lampsam.backend.models import Obs, residual
from lampsam.backend.pose_cov import eq19_covariance

#: :meth:`LampGateShortcuts._bound_far` settles a pair when its lower bound is this factor above
#: the new-landmark threshold: the bound's odometry is composed per keyframe, the
#: gate's per sample, which differ by up to 1e-5 relative in ``Psi`` (test run).
FAR_BOUND_MARGIN = 1.01


class LampGateShortcuts(ExactGate):
    """Shortcuts of the lamp gate (mixin of :class:`~lampsam.backend.graph.GraphSlam`)."""

    def _bound_far(self, obs: list[Obs], pose: FloatArray,
                   screened: dict[int, dict[int, tuple[float, bool]]]
                   ) -> dict[int, dict[int, tuple[float, bool]]]:
        """Settle a lamp pair without a joint marginal when a lower bound of its eq.-19 distance is beyond the new-landmark threshold.

        The lamp's last exact joint marginal, of ``(X(j), lamp)`` at an earlier gate
        (:attr:`_joint_at`, within :data:`~lampsam.backend.gate_exact.RELATIVE_GATE_KEYFRAMES`), is carried to the
        current pose through the odometry since ``X(j)`` alone
        (:func:`~lampsam.backend.pose_cov.eq19_covariance`). That is the joint marginal of a graph with fewer
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

        ``rel`` is :meth:`~lampsam.backend.gate_exact.ExactGate._relative_covs`; ``chain`` caches :meth:`~lampsam.backend.gate_exact.ExactGate._odometry_since`.
        None when the record is too old for ``rel``, the landmark's state changed size
        (an axis seen since) or the prediction fails.
        """
        j, joint = rec
        lm = self._landmarks[lid]
        if j not in rel or joint[2].shape[0] != len(lm.state):
            return None
        if j not in chain:
            chain[j] = self._odometry_since(j)
        pred = self._predicted(lm, obs, pose)
        if pred is None:
            return None
        o_lm, z_hat, h_p, h_l = pred
        nu = residual(o_lm, z_hat)
        psi = eq19_covariance(h_p, h_l, joint, chain[j], rel[j], o_lm.R)
        return float(nu @ np.linalg.solve(psi, nu)), psi

    def _reuse_far(self, obs: list[Obs], screened: dict[int, dict[int, tuple[float, bool]]]
                   ) -> dict[int, dict[int, tuple[float, bool]]]:
        """Skip the joint marginal of a lamp whose recent exact distance was far beyond the gate.

        A lamp whose exact eq.-19 distance (:meth:`~lampsam.backend.gate_exact.ExactGate._innovation`, same measurement size)
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
            pred = self._predicted(lm, obs[i], pose)
            if pred is None:
                continue
            o, z_hat, h_p, h_l = pred
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

