"""The exact gate of a factor-graph backend: eq.-19 innovations with the pose-landmark cross-covariance.

Planar points and ambiguous lamps are gated with iSAM2's joint marginal of the last
keyframe pose ``X(k)`` and the candidate landmark, propagated to the current pose
``x = x_k * delta`` (:func:`~lampsam.backend.pose_cov.eq19_covariance`), so the
pose-landmark cross-covariance is kept (without it the gate is far too wide: a
landmark initialised from a pose is strongly correlated with it). The joint
blocks are cached per keyframe (:meth:`ExactGate._joint_cov`, fetched in one
Bayes-tree query by :meth:`ExactGate._prefetch_joint`).

Also here, for the screen (:mod:`lampsam.backend.gating`) and the lamp shortcuts
(:mod:`lampsam.backend.gate_shortcuts`): the odometry since a recent keyframe, its
mean (:meth:`ExactGate._odometry_since`) and tangent covariance
(:meth:`ExactGate._relative_covs`).

Frames: world; poses ``(x, y, theta)`` in m and rad, covariances in the right
tangent of ``Pose2``; measurements as :mod:`lampsam.backend.models`.
"""

from __future__ import annotations

import math

import gtsam
import numpy as np
from gtsam.symbol_shorthand import X

from lampsam.arrays import FloatArray
from lampsam.backend.graph_state import GraphState
from lampsam.backend.handlers import GraphLandmark
from lampsam.backend.models import Obs, for_landmark, predict, residual
from lampsam.backend.pose_cov import eq19_covariance, propagate_relative

#: Keyframes back over which the smoothers' screen uses the relative gate.
RELATIVE_GATE_KEYFRAMES = 30


class ExactGate(GraphState):
    """Exact eq.-19 innovations from iSAM2's joint marginals (mixin of :class:`~lampsam.backend.graph.GraphSlam`)."""

    def _joint_cov(self, lm: GraphLandmark, k: int) -> tuple[FloatArray, FloatArray, FloatArray] | None:
        """Joint marginal blocks ``(S_kk, S_kl, S_ll)`` of keyframe ``k`` and a landmark.

        From iSAM2's ``jointMarginalCovariance``; the landmark block is over the
        EKF-form state (the handler's keys, in order). Shapes (3, 3), (3, d), (d, d)
        with ``d = len(lm.state)``; the pose in the right tangent of ``X(k)``, the
        landmark in world coordinates (m, rad). None without iSAM2.
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
            obs: the frame's observations; screened: :meth:`~lampsam.backend.gating.Gating._screen`'s pre-screen.

        Planar points are prefetched too: the planar screen leaves its pairs to the
        joint marginal with a NaN distance, and :func:`associate` asks each of them (on
        the held-out pillars log the per-landmark queries were 97 % of the online
        run's CPU; one query for all of a frame's landmarks is 70x cheaper there).

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
                # NaN: a planar pair the screen left to the joint marginal (associate asks it)
                if (not exact and (d2 < gate or math.isnan(d2)) and lid not in seen
                        and lid not in self._joint_cache
                        and lid in self._landmarks and self._landmarks[lid].in_graph):
                    seen.add(lid)
                    lids.append(lid)
        if len(lids) < 2:  # a single landmark: _joint_cov's own query is the same call
            return 0
        keys = [X(k)]
        spans: list[tuple[int, list[int]]] = []
        size = 3
        for lid in lids:
            lm = self._landmarks[lid]
            handler = self.handlers[lm.kind]
            start = size  # the blocks come in the query's order
            lm_keys = handler.keys(lm)
            keys.extend(lm_keys)
            # a Point2 has a 2-D tangent; Pose2, Point3 and the axis Pose2 are 3-D
            size += (2 if lm.kind == "point2" else 3) * len(lm_keys)
            spans.append((lid, [start + j for j in handler.state_index(lm)]))
        try:
            full = np.asarray(self.isam.jointMarginalCovariance(keys).fullMatrix())
        except (RuntimeError, IndexError):
            return 0
        if full.shape != (size, size):
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

        Args:
            gate_ctx: ``(k, pose (3,), delta (3,), delta_cov (3, 3))``: the last keyframe in
                iSAM2, the current pose (world), the odometry since ``X(k)`` and its
                covariance (:meth:`~lampsam.backend.graph.GraphSlam._gate_context`).
            lid: the landmark; obs: the observation.

        Returns:
            ``nu`` (m,) and ``Psi`` (m, m) in the measurement's units (``m`` its rows
            for this landmark), ``Psi`` scaled by the online innovation scale for
            planar points; None when the landmark is not predictable from ``pose``.
        """
        k, pose, delta, delta_cov = gate_ctx
        lm = self._landmarks[lid]
        pred = self._predicted(lm, obs, pose)
        if pred is None:
            return None
        obs, z_hat, h_p, h_l = pred
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
        inn = self._innovation(gate_ctx, lid, obs)
        pred = None if inn is None else self._predicted(self._landmarks[lid], obs, gate_ctx[1])
        if inn is None or pred is None:
            return None
        return inn[0], inn[1], pred[2]

    def _predicted(self, lm: GraphLandmark, obs: Obs, pose: FloatArray
                   ) -> tuple[Obs, FloatArray, FloatArray, FloatArray] | None:
        """``(obs', z_hat, H_p, H_l)`` of landmark ``lm`` seen from ``pose`` (3,), world.

        ``obs'`` is ``obs`` cut to the landmark's measurement
        (:func:`~lampsam.backend.models.for_landmark`: a lamp's axis row only for a lamp
        with an axis), ``z_hat`` its prediction, ``H_p`` (m, 3) its Jacobian in the
        pose's right tangent and ``H_l`` (m, d) in the landmark's coordinates; None when
        the model cannot predict it (a ceiling point behind or at the camera).
        """
        o = for_landmark(obs, len(lm.state))
        try:
            z_hat, h_p, h_l = predict(lm.kind, pose, lm.state, o, self.ceiling)
        except Exception:
            return None
        return o, z_hat, h_p, h_l

    def _relative_covs(self) -> dict[int, FloatArray]:
        """(3, 3) tangent covariance of the current keyframe relative to each recent keyframe.

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

    def _odometry_since(self, j: int) -> FloatArray:
        """(3,) ``x_j^-1 x_k`` (x, y in m, theta in rad) from the keyframes' odometry (``k`` the current keyframe)."""
        d = gtsam.Pose2()
        for step in range(j + 1, self._k + 1):
            d = d.compose(gtsam.Pose2(*self._odo[step][0]))
        return np.array([d.x(), d.y(), d.theta()])

