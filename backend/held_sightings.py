"""Held range-bearing sightings without ids: held while ambiguous, given back once not.

With ``association.planar_unique`` a sighting whose nearest landmark has a material
rival (:func:`lampsam.backend.planar_gate.rival_ratio`: the second likeliest landmark's Gaussian likelihood is at
least ``planar_unique_ratio`` of the best's, eq. 19-20) is neither matched nor
mapped: nearest neighbour would give a tree to its neighbour, and the pose would
follow the wrong match (docs/failures.md, the long revisit). Such a sighting is
*held* with its candidates (every landmark screened within the new-landmark
threshold; at each re-gate also the landmarks started near it since, which may be
the tree it saw: :meth:`HeldSightings._started_since`). Later keyframes tighten the
pose of its keyframe and the landmarks (the next sightings of the same trees, a loop
closure), so at ages
:data:`GIVE_BACK_AGES` keyframes :meth:`HeldSightings._give_back` re-gates it:
eq. 19 at the held keyframe ``X(kk)`` with the joint marginal of ``X(kk)`` and the
candidates at iSAM2's current linearisation (one ``jointMarginalCovariance`` query)
and the candidates' current estimates. When the best is inside the gate and no
rival is material any more, the sighting (inside the tighter :data:`GIVE_BACK_PROB` gate) becomes a factor of that landmark. A
sighting not given back within :data:`HOLD_KEYFRAMES` keyframes stays out of the
graph (counted: ``n_held - n_held_given_back - n_revisit_resolved`` in the
result's ``extra``); the revisit check (:mod:`lampsam.backend.revisit_merge`) may also
resolve it by constellation.

Frames: world, m and rad; ``[bearing, range]`` observations.
"""

from __future__ import annotations

import math
from collections.abc import Mapping

import numpy as np
from gtsam.symbol_shorthand import L, X

from lampsam.backend.association import mahalanobis2
from lampsam.backend.config import chi2_quantile
from lampsam.backend.gating import Gating
from lampsam.backend.models import Obs, init_point2, predict, residual
from lampsam.backend.planar_gate import rival_material
from lampsam.backend.pose_cov import eq19_covariance

#: Ages (keyframes since the sighting) at which a held sighting is re-gated.
GIVE_BACK_AGES = frozenset({1, 2, 4, 8, 16, 32})
#: A held sighting older than this is given up (the revisit check's window too).
HOLD_KEYFRAMES = 40
#: A held sighting is given back only inside this chi-square probability's gate
#: (2 dof: d2 < 4.61), tighter than the association's (0.99: 9.21). On Victoria
#: Park's first 3,500 poses the held sightings given back at d2 6-9 were other
#: trees' (8 of 9), those at d2 <= 3.6 their own (52 of 52): a held sighting in
#: the outer gate is most often a tree not yet mapped.
GIVE_BACK_PROB = 0.9
#: A landmark started after a sighting was held, closer than this (m) to the sighting
#: placed from its keyframe's estimate, joins its candidates at the re-gate.
SINCE_RADIUS_M = 10.0


class HeldSightings(Gating):
    """Holding ambiguous sightings and giving them back (mixin of :class:`~lampsam.backend.graph.GraphSlam`).

    Attributes:
        n_held: sightings held so far; n_held_given_back: of them given back to a
            landmark by :meth:`_give_back`.
    """

    n_held = 0
    n_held_given_back = 0

    @property
    def _held(self) -> list[tuple[int, Obs]]:
        """Range-bearing sightings held as ambiguous ``(keyframe, obs)``, newest last."""
        return self.__dict__.setdefault("_held_sightings", [])

    @property
    def _held_cands(self) -> dict[int, tuple[int, ...]]:
        """``id(obs)`` of a held sighting -> its candidate landmark ids."""
        return self.__dict__.setdefault("_held_candidates", {})

    def _hold(self, k: int, dropped: list[tuple[Obs, tuple[int, ...]]]) -> None:
        """Hold keyframe ``k``'s ambiguous sightings with their candidates; forget the
        ones older than :data:`HOLD_KEYFRAMES`."""
        held = [(kk, o) for kk, o in self._held if kk > k - HOLD_KEYFRAMES]
        held += [(k, o) for o, _ in dropped]
        self.__dict__["_held_sightings"] = held
        alive = {id(o) for _, o in held}
        cands = {i: c for i, c in self._held_cands.items() if i in alive}
        cands.update((id(o), c) for o, c in dropped)
        self.__dict__["_held_candidates"] = cands
        self.n_held += len(dropped)
        if getattr(self, "_trace_revisit", False):  # (trace_noids_online.py --held)
            self.__dict__.setdefault("_hold_log", []).extend((k, o, c) for o, c in dropped)

    def _give_back(self, k: int) -> int:
        """Re-gate the held sightings whose age is in :data:`GIVE_BACK_AGES`; each one now
        unambiguous (best inside the :data:`GIVE_BACK_PROB` gate, no material rival) becomes a factor of its
        landmark. Returns the number given back."""
        if self.isam is None:
            return 0
        cfg = self.config.association
        gate, unique_t = chi2_quantile(GIVE_BACK_PROB, 2), cfg.unique_threshold(2)
        given: set[int] = set()
        trace = getattr(self, "_trace_revisit", False)  # (trace_noids_online.py --held)
        for kk, o in self._held:
            if k - kk not in GIVE_BACK_AGES or kk > self._k_isam:
                continue
            lids = [lid for lid in (*self._held_cands.get(id(o), ()), *self._started_since(kk, o))
                    if lid in self._landmarks and self._landmarks[lid].in_graph
                    and self._landmarks[lid].kind == "point2"]
            lids = list(dict.fromkeys(lids))
            scored = self._regate(kk, o, lids)
            if not scored:
                if trace:
                    self._trace_held(k, kk, o, "no candidate" if not lids else "no marginal", [])
                continue
            best = min(scored)
            near = [(d2, ld) for d2, ld, lid in scored if d2 < unique_t
                    and (lid == best[2] or not self._same_place(best[2], lid))]
            if best[0] >= gate or rival_material(near, cfg):
                if trace:
                    self._trace_held(k, kk, o, "outside" if best[0] >= gate else "rival", scored)
                continue
            if trace:
                self._trace_held(k, kk, o, "given", scored)
            lm = self._landmarks[best[2]]
            if trace:  # (trace_noids_online.py)
                self.__dict__.setdefault("_give_back_log", []).append(
                    (k, kk, lm.id, best[0], sorted(scored)[1][0] if len(scored) > 1 else math.inf))
            self._add_planar_sighting(lm, kk, o)
            self._planar_sightings.append((kk, o.z, o.R, lm.id))
            lm.n_obs += 1
            lm.last_kf = max(lm.last_kf, kk)
            given.add(id(o))
        if given:
            self.__dict__["_held_sightings"] = [(kk, o) for kk, o in self._held
                                                if id(o) not in given]
            self.n_held_given_back += len(given)
        return len(given)

    def _started_since(self, kk: int, o: Obs) -> list[int]:
        """Range-bearing landmarks started after keyframe ``kk`` within
        :data:`SINCE_RADIUS_M` of held sighting ``o`` placed from ``kk``'s estimate: the
        tree it saw may have been mapped since it was held (its candidates are the
        landmarks screened then; one started at ``kk`` itself is another sighting's of
        that keyframe)."""
        xy = init_point2(self._pose_of(kk), o.z)[0]
        return [lm.id for lm in self._landmarks.values()
                if lm.first_kf > kk and lm.kind == "point2"
                and float(np.hypot(*(lm.state[:2] - xy))) < SINCE_RADIUS_M]

    def _trace_held(self, k: int, kk: int, o: Obs, why: str,
                    scored: list[tuple[float, float, int]]) -> None:
        """Record one give-back attempt ``(k, kk, id(obs), why, sorted d2s)`` (tracing only)."""
        self.__dict__.setdefault("_held_log", []).append(
            (k, kk, id(o), why, sorted((d2, lid) for d2, _, lid in scored)))

    def _same_place(self, a: int, b: int) -> bool:
        """Whether planar landmarks ``a`` and ``b`` stand closer than ``revisit_tol``
        (one tree mapped twice, or two file ids at one place): a rival there cannot
        pull the pose to another tree, so it does not hold a sighting."""
        pa, pb = self._landmarks[a].state[:2], self._landmarks[b].state[:2]
        return float(np.hypot(*(pa - pb))) < self.config.association.revisit_tol

    def _regate(self, kk: int, obs: Obs, lids: list[int]) -> list[tuple[float, float, int]]:
        """``(d2, log det Psi, landmark id)`` of a sighting of keyframe ``kk`` against each
        landmark in ``lids`` (eq. 19 with the joint marginal of ``X(kk)`` and all of
        them, at iSAM2's current estimate); empty when iSAM2 cannot give it."""
        if not lids or self.isam is None:
            return []
        try:
            full = np.asarray(self.isam.jointMarginalCovariance(
                [X(kk), *(L(lid) for lid in lids)]).fullMatrix())
        except (RuntimeError, IndexError):
            return []
        pose = self._pose_of(kk)
        r = obs.R * self.config.association.gate_noise_scale
        scale = self.noise_scale.scale
        out = []
        for j, lid in enumerate(lids):
            lm = self._landmarks[lid]
            self._refresh_landmark(lm)
            z_hat, h_p, h_l = predict(lm.kind, pose, lm.state, obs)
            sl = slice(3 + 2 * j, 5 + 2 * j)
            joint = (full[:3, :3], full[:3, sl], full[sl, sl])
            psi = eq19_covariance(h_p, h_l, joint, np.zeros(3), np.zeros((3, 3)), r) * scale
            nu = residual(obs, z_hat)
            sign, logdet = np.linalg.slogdet(psi)
            d2 = mahalanobis2(nu, psi) if sign > 0 else math.inf
            out.append((d2, float(logdet) if sign > 0 else 0.0, lid))
        return out


def held_candidates(screened: Mapping[int, Mapping[int, tuple[float, bool]]], i: int
                    ) -> tuple[int, ...]:
    """The landmark ids screened for observation ``i`` (those within the new-landmark
    threshold: the candidates a held sighting is re-gated against)."""
    return tuple(screened.get(i, {}))

