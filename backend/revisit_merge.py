"""Revisit check without ids: the local scan matched to the older map by constellation.

At a revisit whose drift exceeds the gate (eqs. 19-20), every tree seen again
is beyond the new-landmark threshold of its landmark and is mapped a second time;
among themselves the copies keep their shape. After each keyframe that started a
range-bearing landmark, :meth:`RevisitMerge._revisit_check` builds the *local
scan*: every landmark sighted in the last :data:`RECENT_KEYFRAMES` keyframes at the
mean of those sightings, each placed from its keyframe's current estimate (the new
landmarks and the current sightings, in the drifted frame they share). It is
aligned with the landmarks made before that window within a pose-uncertainty-sized
window around the prediction (the scan's largest range plus
:data:`REVISIT_SIGMAS` x the pose marginal's largest position sigma, at most
:data:`SEARCH_RADIUS`) by one rigid 2-D motion
(:func:`lampsam.backend.constellation.align_constellation`: every minimal pair
enumerated, one-to-one inliers within ``revisit_tol``, accepted only with
``revisit_min_inliers`` inliers and a margin of 2 over any hypothesis pairing them
differently). The answer is refused when the drift it implies at the current pose
is beyond :data:`REVISIT_SIGMAS` of the pose's marginal, when the matched old
landmarks also match the old map elsewhere (:func:`self_similarity`: a row or grid
of trees), or when an older landmark sighted in the window pairs with another one
(a wrong match, or a wrong alignment). Each inlier made in the window is merged with
its old landmark: a ``BetweenFactorPoint2`` of zero mean and sigma
``revisit_tie_sigma`` (a merge as a stiff tie: iSAM2 re-solves with it) and it
leaves the association (later sightings go to the old landmark).

Frames: world, m and rad.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import gtsam
import numpy as np
from gtsam.symbol_shorthand import L

from lampsam.arrays import FloatArray
from lampsam.backend.constellation import (
    align_constellation,
    best_and_rival,
    best_apart,
    rank_hypotheses,
)
from lampsam.backend.handlers import GraphLandmark
from lampsam.backend.held_sightings import HeldSightings
from lampsam.backend.interface import LandmarkKind
from lampsam.backend.models import Obs, init_point2
from lampsam.backend.pose_cov import tangent_to_coords_cov

log = logging.getLogger(__name__)

#: Landmarks sighted within this many keyframes are the local scan; those made
#: before them are the older map.
RECENT_KEYFRAMES = 40
#: Points of the local scan aligned at most (the newest), and old landmarks at most
#: (the nearest): the enumeration of pairs grows with the square of each.
MAX_SCAN = 16
MAX_OLD = 40
#: The pose-uncertainty part of the search window is capped at this, m.
SEARCH_RADIUS = 80.0
#: The drift an alignment may claim, in sigmas of the current pose's marginal (plus
#: the tolerance; rotation: plus 0.05 rad). A revisit maps trees again only when its
#: drift is beyond the new-landmark threshold (~4.3 sigma at 0.9999), so the bound
#: must be wider than that: it keeps a chance alignment far from the prediction out.
REVISIT_SIGMAS = 8.0


def self_similarity(dst: FloatArray, idx: list[int], tol: float, max_rotation: float) -> int:
    """Inliers of the best motion taking the matched old landmarks ``dst[idx]`` onto
    ``dst`` with most of them paired to another landmark than themselves.

    A constellation matched in a repetitive map (a row or a grid of trees) also
    matches the map shifted by one spacing: the check's answer is then unique only
    by chance (which copies happen to be in the window), so a match whose old
    landmarks match themselves elsewhere within the margin is refused.
    """
    sub = np.asarray(dst, float)[idx]
    ident = frozenset((i, b) for i, b in enumerate(idx))
    return best_apart(rank_hypotheses(sub, dst, tol, max_rotation), ident)


@dataclass(frozen=True)
class RevisitRecord:
    """One run of the revisit check (for tracing why it tied or not).

    Attributes:
        k: keyframe; recent, old: landmark ids of the two constellations.
        n_best, runner_up: inliers of the best hypothesis and of its best rival.
        outcome: ``few`` (too few landmarks), ``weak`` (best under the inliers
            needed), ``ambiguous`` (rival within the margin), ``drift`` (beyond the
            drift bound), ``self-similar``, ``uninformative`` (it contradicts a
            current association, but without its self-pairs it has fewer than
            ``revisit_min_inliers`` inliers), ``contradicts`` (not moved), ``confirmed``
            or ``tied``.
    """

    k: int
    recent: tuple[int, ...]
    old: tuple[int, ...]
    n_best: int
    runner_up: int
    outcome: str


class RevisitMerge(HeldSightings):
    """Constellation revisit check (mixin of :class:`~lampsam.backend.graph.GraphSlam`).

    Attributes:
        n_revisit_merges: copies tied to an old landmark so far.
        n_revisit_rejected: unique alignments rejected because the drift they imply
            at the current pose is beyond :data:`REVISIT_SIGMAS` of its marginal.
        revisit_ties: ``(keyframe, copy id, old id)`` of each tie.
    """

    n_revisit_merges = 0
    n_revisit_rejected = 0
    n_revisit_ambiguous = 0
    n_revisit_resolved = 0
    n_revisit_moved = 0

    @property
    def revisit_ties(self) -> list[tuple[int, int, int]]:
        """``(keyframe, copy id, old id)`` of every tie made (created on first use)."""
        return self.__dict__.setdefault("_revisit_ties", [])

    @property
    def revisit_log(self) -> list[RevisitRecord]:
        """Every run of the check, when ``_trace_revisit`` is set (else empty)."""
        return self.__dict__.setdefault("_revisit_log", [])

    def _record(self, k: int, recent: list[GraphLandmark], old: list[GraphLandmark],
                n_best: int, runner: int, outcome: str) -> None:
        if getattr(self, "_trace_revisit", False):
            self.revisit_log.append(RevisitRecord(k, tuple(lm.id for lm in recent),
                                                  tuple(lm.id for lm in old), n_best, runner,
                                                  outcome))

    def _revisit_check(self, k: int, n_new: int, dropped: list[Obs] | None = None) -> int:
        """Match the local scan to the older map (module doc); the merges made.

        Runs at a keyframe that started a range-bearing landmark (``n_new``): a
        sighting beyond every gate, the sign of a revisit with drift; or that
        held sightings as ambiguous (``dropped``; :meth:`_hold` keeps them for the scan).
        """
        cfg = self.config.association
        if not n_new and not dropped:
            return 0
        lo = k - RECENT_KEYFRAMES
        held = [(kk, o) for kk, o in self._held if kk > lo]  # (this keyframe's: _hold)
        pose = self.current_pose()
        # the local scan: each landmark sighted in the window at its sightings' mean,
        # every sighting placed from its keyframe's current estimate
        pts: dict[int, list[FloatArray]] = {}
        max_range = 0.0
        for kk, z, _, lid in reversed(self._planar_sightings):
            if kk <= lo - RECENT_KEYFRAMES:
                break  # (held sightings placed later are at most a window out of order)
            if kk <= lo or lid not in self._landmarks:
                continue
            pts.setdefault(int(lid), []).append(init_point2(self._pose_of(int(kk)), z)[0])
            max_range = max(max_range, float(z[1]))
        recent = [self._landmarks[lid] for lid in pts]
        if len(recent) + len(held) < cfg.revisit_min_inliers:
            return 0  # (no marginal asked for: a ceiling run has no range-bearing scan)
        # held sightings: one point per cluster (the same tree from several keyframes)
        clusters: list[list[tuple[int, Obs, FloatArray]]] = []
        sums = np.zeros((len(held), 2))  # running sum of each cluster's points
        for kk, o in held:
            pt = init_point2(self._pose_of(kk), o.z)[0]
            max_range = max(max_range, float(o.z[1]))
            n_cl = len(clusters)
            if n_cl:
                means = sums[:n_cl] / np.array([len(cl) for cl in clusters])[:, None]
                inside = np.flatnonzero(np.hypot(*(means - pt).T) < cfg.revisit_tol)
                if len(inside):  # the first cluster within the tolerance
                    j = int(inside[0])
                    clusters[j].append((kk, o, pt))
                    sums[j] += pt
                    continue
            clusters.append([(kk, o, pt)])
            sums[n_cl] = pt
        cov = tangent_to_coords_cov(pose, self.current_cov())
        sigma_xy = math.sqrt(max(float(np.linalg.eigvalsh(cov[:2, :2])[-1]), 0.0))
        sigma_theta = math.sqrt(max(float(cov[2, 2]), 0.0))
        radius = max_range + min(REVISIT_SIGMAS * sigma_xy, SEARCH_RADIUS) + cfg.revisit_tol
        old = []
        for lm in self._landmarks.values():
            if (lm.kind == "point2" and lm.in_graph and lm.first_kf <= lo
                    and float(np.hypot(*(lm.state[:2] - pose[:2]))) <= radius):
                self._refresh_landmark(lm)
                old.append(lm)
        old = sorted(old, key=lambda lm: float(np.hypot(*(lm.state[:2] - pose[:2]))))[:MAX_OLD]
        # the scan's newest MAX_SCAN points (the enumeration grows with their square)
        recent = sorted(recent, key=lambda lm: -lm.last_kf)[:MAX_SCAN]
        clusters = sorted(clusters, key=lambda cl: -max(kk for kk, _, _ in cl))[
            :max(MAX_SCAN - len(recent), 0)]
        n_src = len(recent) + len(clusters)
        if n_src < cfg.revisit_min_inliers or len(old) < cfg.revisit_min_inliers:
            self._record(k, recent, old, 0, 0, "few")
            return 0
        src = np.array([*(np.mean(pts[lm.id], axis=0) for lm in recent),
                        *(np.mean([q for _, _, q in cl], axis=0) for cl in clusters)])
        dst = np.array([lm.state[:2] for lm in old])
        max_rot = min(math.pi, REVISIT_SIGMAS * sigma_theta + 0.05)
        hyps = rank_hypotheses(src, dst, cfg.revisit_tol, max_rot)
        n_best, runner = best_and_rival(hyps)
        if n_best < cfg.revisit_min_inliers or n_best - runner < 2:
            self._record(k, recent, old, n_best, runner,
                         "weak" if n_best < cfg.revisit_min_inliers else "ambiguous")
            if n_best >= cfg.revisit_min_inliers:
                self.n_revisit_ambiguous += 1
            return 0
        al = align_constellation(src, dst, cfg.revisit_tol, cfg.revisit_min_inliers, 2, max_rot)
        assert al is not None
        self_rival = self_similarity(dst, [b for _, b in al.pairs], cfg.revisit_tol, max_rot)
        if 2 * self_rival > n_best:  # the old map repeats itself there: no unique answer
            self._record(k, recent, old, n_best, self_rival, "self-similar")
            self.n_revisit_ambiguous += 1
            return 0
        # the motion moves the current pose by the drift it claims: near the prediction
        c, s = math.cos(al.theta), math.sin(al.theta)
        moved = np.array([[c, -s], [s, c]]) @ pose[:2] + al.shift
        if float(np.hypot(*(moved - pose[:2]))) > REVISIT_SIGMAS * sigma_xy + cfg.revisit_tol:
            self.n_revisit_rejected += 1
            self._record(k, recent, old, n_best, runner, "drift")
            return 0
        # an older landmark sighted in the window must pair with itself (else a
        # sighting went to the wrong landmark, or the alignment is wrong: no tie)
        pairs = [(recent[a], old[b]) for a, b in al.pairs if a < len(recent)]
        wrong = [(r, o) for r, o in pairs if r.first_kf <= lo and r.id != o.id]
        # a landmark paired with itself is what "no revisit" predicts too: moving
        # sightings needs the inliers that say something new (copies, held clusters,
        # the contradicted pairs) to be enough on their own
        informative = len(al.pairs) - sum(1 for r, o in pairs if r.id == o.id)
        if wrong and informative < cfg.revisit_min_inliers:
            self._record(k, recent, old, n_best, runner, "uninformative")
            return 0
        if wrong and not (2 * len(wrong) < n_best and self._move_window_sightings(wrong, lo)):
            self._record(k, recent, old, n_best, runner, "contradicts")
            return 0
        copies = [(r, o) for r, o in pairs if r.first_kf > lo]
        resolved = [(clusters[a - len(recent)], old[b]) for a, b in al.pairs if a >= len(recent)]
        self._record(k, recent, old, n_best, runner,
                     "tied" if copies or resolved else "confirmed")
        for cl, orig in resolved:  # held sightings given to the landmark they match
            for kk, o, _ in cl:
                self._add_planar_sighting(orig, kk, o)
                self._planar_sightings.append((kk, o.z, o.R, orig.id))
                orig.n_obs += 1
            orig.last_kf = k
            self.n_revisit_resolved += len(cl)
        taken = {id(o) for cl, _ in resolved for _, o, _ in cl}
        self.__dict__["_held_sightings"] = [(kk, o) for kk, o in held if id(o) not in taken]
        noise = gtsam.noiseModel.Isotropic.Sigma(2, cfg.revisit_tie_sigma)
        self.revisit_ties.extend((k, copy.id, orig.id) for copy, orig in copies)
        for copy, orig in copies:
            self._add_factor(gtsam.BetweenFactorPoint2(L(copy.id), L(orig.id),
                                                       np.zeros(2), noise))
            orig.n_obs += copy.n_obs
            orig.last_kf = k
            del self._landmarks[copy.id]
        self.n_revisit_merges += len(copies)
        if copies:
            log.info("revisit at keyframe %d: %d landmarks merged with older ones (rotation "
                     "%.3f rad, shift %.1f m, rms %.2f m, %d inliers, runner-up %d)", k,
                     len(copies), al.theta, float(np.hypot(*al.shift)), al.rms, n_best,
                     al.runner_up)
        return len(copies) + len(resolved)

    def _move_window_sightings(self, wrong: list[tuple[GraphLandmark, GraphLandmark]],
                               lo: int) -> bool:
        """Give the window's sightings of each landmark ``r`` to ``o`` (``wrong`` pairs):
        the alignment says they were another tree's.

        Their factors are removed from iSAM2 (``ISAM2.update``'s ``removeFactorIndices``;
        a factor of the current keyframe, not yet sent, is emptied in the pending
        update, keeping iSAM2's factor indices those of the full graph) and from the
        full graph (its slot emptied), and re-added as factors of ``o``. Refused
        (False, nothing changed) with a fixed-lag smoother, when iSAM2's factors are
        not the full graph's (a rebuild dropped some), or when ``r`` would be left
        without a sighting before the window.
        """
        if self.isam is None or self.smoother is not None:
            return False
        n_isam = self.graph.size() - self._new_graph.size()
        if self.isam.getFactorsUnsafe().size() != n_isam:
            return False
        moves: list[tuple[GraphLandmark, GraphLandmark, list[tuple[int, int]]]] = []
        for r, o in wrong:
            at = [kk for kk, lid in self._planar_factor_at if lid == r.id]
            if not any(kk <= lo for kk in at):
                return False
            moves.append((r, o, [(kk, i) for kk in at if kk > lo
                                 for i in self._planar_factor_at[(kk, r.id)]]))
        remove: list[int] = []
        for r, o, idx in moves:
            for _, i in idx:
                if i < n_isam:
                    remove.append(i)
                else:
                    self._new_graph.remove(i - n_isam)
                self.graph.remove(i)
            kks = sorted({kk for kk, _ in idx})
            for kk in kks:
                del self._planar_factor_at[(kk, r.id)]
            for j, (kk, z, cov, lid) in enumerate(self._planar_sightings):
                if lid == r.id and kk > lo:
                    self._add_planar_sighting(o, kk, Obs(LandmarkKind.POINT2, z, cov))
                    self._planar_sightings[j] = (kk, z, cov, o.id)
                    r.n_obs -= 1
                    o.n_obs += 1
            o.last_kf = max(o.last_kf, kks[-1] if kks else o.last_kf)
            self.n_revisit_moved += len(kks)
        if remove:
            self.isam.update(gtsam.NonlinearFactorGraph(), gtsam.Values(), remove)
        self._joint_cache, self._joint_at, self._pose_cache = {}, {}, {}
        log.info("revisit: %d sightings of %d landmarks moved to the landmarks the "
                 "alignment pairs them with", sum(len(i) for _, _, i in moves), len(moves))
        return True
