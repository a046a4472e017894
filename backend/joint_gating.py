"""Joint compatibility for the smoothers' range-bearing observations without ids.

The individual gate (:mod:`lampsam.backend.gating`, eqs. 19-20 with iSAM2's joint
marginal of the last keyframe and one landmark) lets each sighting pick its nearest
landmark alone. Where a keyframe is ambiguous (a sighting with two or more
landmarks inside its gate, or one landmark inside the gates of two sightings),
:meth:`JointGating._joint_planar` re-pairs its sightings by JCBB (Neira & Tardos
2001; :func:`lampsam.backend.association.jcbb`): the stacked innovation of a
hypothesis and its covariance ``H P H^T + R`` over all its rows, with ``P`` the
joint marginal of the current pose and every candidate landmark at iSAM2's current
linearisation (one ``jointMarginalCovariance`` query), so the shared pose error is
counted once, not once per sighting.

Frames: world; the pose block in the right tangent of ``Pose2``, landmarks ``(x, y)``.
"""

from __future__ import annotations

import math

import gtsam
import numpy as np
from gtsam.symbol_shorthand import L, X

from lampsam.arrays import FloatArray
from lampsam.backend.alias_gate import refuses
from lampsam.backend.association import Assignment, mahalanobis2, reassign_jointly
from lampsam.backend.gating import Gating
from lampsam.backend.models import Obs, predict, residual


def current_pose_block(s_kk: FloatArray, s_kl: FloatArray, delta: FloatArray,
                       delta_cov: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Covariance of the current pose ``x = x_k * delta`` and its cross-covariance with landmarks.

    ``S_xx = Ad S_kk Ad^T + C`` and ``S_xl = Ad S_kl`` with ``Ad = Ad(delta^-1)``
    (right tangent, as :func:`lampsam.backend.pose_cov.eq19_covariance`).

    Args:
        s_kk: (3, 3) marginal of keyframe ``k``; s_kl: (3, m) its cross-covariance
            with the landmark block.
        delta: (3,) odometry since ``k``; delta_cov: (3, 3) its covariance.

    Returns:
        ``(S_xx (3, 3), S_xl (3, m))``.
    """
    ad = gtsam.Pose2(*delta).inverse().AdjointMap()
    return ad @ s_kk @ ad.T + delta_cov, ad @ s_kl


class JointGating(Gating):
    """JCBB on ambiguous keyframes (mixin of :class:`~lampsam.backend.graph.GraphSlam`).

    Attributes:
        n_jcbb: keyframes re-paired by JCBB; n_jcbb_changed: decisions it changed.
    """

    n_jcbb = 0
    n_jcbb_changed = 0

    def _joint_planar(self, gate_ctx: tuple[int, FloatArray, FloatArray, FloatArray],
                      obs: list[Obs], assignments: list[Assignment],
                      screened: dict[int, dict[int, tuple[float, bool]]],
                      density: float = 0.0) -> list[Assignment]:
        """Re-pair an ambiguous keyframe's range-bearing sightings by JCBB (module doc).

        Args:
            gate_ctx: ``(k, pose, delta, delta_cov)`` of the gate (last keyframe in
                iSAM2, current pose, odometry since ``k`` and its covariance).
            obs: the frame's observations; assignments: :func:`associate`'s.
            screened: the planar screen (:meth:`Gating._screen_planar`).
            density: the alias test's landmark density, as given to :func:`associate`
                (0: off); a pair it refused is no JCBB candidate.

        Returns:
            The assignments, re-paired where the keyframe is ambiguous.
        """
        gate = self.config.association.gate(2)
        odds = self.config.association.alias_odds
        cands: dict[int, list[int]] = {}
        for i, o in enumerate(obs):
            if o.kind != "point2" or o.landmark_id is not None or i not in screened:
                continue
            inside: list[tuple[float, int]] = []
            for lid, (d2, exact) in screened[i].items():
                pred = None
                if not exact or density > 0.0:
                    pred = self._innovation(gate_ctx, lid, o)  # cached joint marginal
                if not exact:
                    d2 = math.inf if pred is None else mahalanobis2(*pred)
                if d2 < gate and density > 0.0 and refuses(  # a pair associate() refused
                        d2, None if pred is None else pred[1], float(o.z[1]), density, odds):
                    continue
                if d2 < gate:
                    inside.append((d2, lid))
            cands[i] = [lid for _, lid in sorted(inside)]
        lids = sorted({lid for c in cands.values() for lid in c})
        n_uses = sum(len(c) for c in cands.values())
        if not lids or (n_uses == len(lids) and all(len(c) <= 1 for c in cands.values())):
            return assignments  # nothing ambiguous: the individual gate's answer stands
        p = self._joint_block(gate_ctx, lids)
        if p is None:
            return assignments
        col = {lid: 3 + 2 * n for n, lid in enumerate(lids)}
        pose = gate_ctx[1]
        r_scale = self.config.association.gate_noise_scale
        s_online = self.noise_scale.scale

        def joint(hyp: list[tuple[int, int]]) -> tuple[FloatArray, FloatArray] | None:
            m = 2 * len(hyp)
            h = np.zeros((m, p.shape[0]))
            nu = np.empty(m)
            r = np.zeros((m, m))
            for row, (i, lid) in enumerate(hyp):
                z_hat, h_p, h_l = predict("point2", pose, self._landmarks[lid].state[:2], obs[i])
                rows = slice(2 * row, 2 * row + 2)
                h[rows, :3] = h_p
                h[rows, col[lid]:col[lid] + 2] = h_l
                nu[rows] = residual(obs[i], z_hat)
                r[rows, rows] = obs[i].R[:2, :2] * r_scale
            return nu, (h @ p @ h.T + r) * s_online

        self.n_jcbb += 1
        out = reassign_jointly(assignments, cands, joint, self.config.association)
        self.n_jcbb_changed += sum(a.landmark_id != b.landmark_id or a.status != b.status
                                   for a, b in zip(assignments, out, strict=True))
        return out

    def _joint_block(self, gate_ctx: tuple[int, FloatArray, FloatArray, FloatArray],
                     lids: list[int]) -> FloatArray | None:
        """(3 + 2m, 3 + 2m) covariance of the current pose and landmarks ``lids``.

        In-graph landmarks from one ``jointMarginalCovariance`` of ``X(k)`` and
        them; a landmark not yet in the graph (tentative) with its first-sight
        covariance, uncorrelated. None without iSAM2 or when GTSAM refuses.
        """
        if self.isam is None:
            return None
        k, _, delta, delta_cov = gate_ctx
        in_graph = [lid for lid in lids if self._landmarks[lid].in_graph]
        try:
            full = np.asarray(self.isam.jointMarginalCovariance(
                [X(k), *[L(lid) for lid in in_graph]]).fullMatrix())
        except RuntimeError:
            return None
        pos = {lid: 3 + 2 * n for n, lid in enumerate(in_graph)}
        n = 3 + 2 * len(lids)
        p = np.zeros((n, n))
        idx = [np.arange(3)]
        for lid in lids:
            idx.append(np.arange(pos[lid], pos[lid] + 2) if lid in pos else np.full(2, -1))
        src = np.concatenate(idx)
        ok = src >= 0
        p[np.ix_(ok, ok)] = full[np.ix_(src[ok], src[ok])]
        for j, lid in enumerate(lids):
            if lid not in pos:
                c = 3 + 2 * j
                p[c:c + 2, c:c + 2] = self._landmarks[lid].cov[:2, :2]
        s_xx, s_xl = current_pose_block(p[:3, :3], p[:3, 3:], delta, delta_cov)
        p[:3, :3] = s_xx
        p[:3, 3:] = s_xl
        p[3:, :3] = s_xl.T
        return p
