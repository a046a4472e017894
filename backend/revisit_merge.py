"""Revisit check without ids: recent landmarks matched to the old map by constellation.

At a revisit whose drift exceeds the gate (eqs. 19-20), every tree seen again
is beyond the new-landmark threshold of its landmark and is mapped a second time;
among themselves the copies keep their shape. After each keyframe that started a
range-bearing landmark (or gave a recent one its second sighting),
:meth:`RevisitMerge._revisit_check` aligns the landmarks
made in the last :data:`RECENT_KEYFRAMES` keyframes (2+ sightings) with the
landmarks idle for :data:`IDLE_KEYFRAMES` keyframes near the current pose by one
rigid 2-D motion (:func:`lampsam.backend.constellation.align_constellation`:
every minimal pair enumerated, one-to-one inliers within ``revisit_tol``, accepted
only with ``revisit_min_inliers`` inliers and a margin of 2 over any hypothesis
pairing them differently: an unambiguous answer or none; and the drift it implies
at the current pose within :data:`REVISIT_SIGMAS` of the pose's marginal). Each inlier copy is then
tied to its old landmark (``BetweenFactorPoint2`` of zero mean, sigma
``revisit_tol / 2`` per axis: the map is not rigid to better than the tolerance)
and leaves the association (later sightings go to the old landmark); the copy's
variable stays in the graph, tied.

Frames: world, m and rad.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import gtsam
import numpy as np
from gtsam.symbol_shorthand import L

from lampsam.backend.constellation import align_constellation, best_and_rival, rank_hypotheses
from lampsam.backend.graph_state import GraphState
from lampsam.backend.handlers import GraphLandmark
from lampsam.backend.pose_cov import tangent_to_coords_cov

log = logging.getLogger(__name__)

#: Landmarks made within this many keyframes are the "recent" constellation.
RECENT_KEYFRAMES = 40
#: Landmarks not observed for this many keyframes are the "old" map.
IDLE_KEYFRAMES = 150
#: Old landmarks farther than this from the current pose estimate are left out, m
#: (a revisit's drift plus the sensing range of a planar log).
SEARCH_RADIUS = 80.0
#: The drift an alignment may claim, in sigmas of the current pose's marginal (plus
#: the tolerance; rotation: plus 0.05 rad). A revisit maps trees again only when its
#: drift is beyond the new-landmark threshold (~4.3 sigma at 0.9999), so the bound
#: must be wider than that: it keeps a chance alignment far from the prediction out.
REVISIT_SIGMAS = 8.0


@dataclass(frozen=True)
class RevisitRecord:
    """One run of the revisit check (for tracing why it tied or not).

    Attributes:
        k: keyframe; recent, old: landmark ids of the two constellations.
        n_best, runner_up: inliers of the best hypothesis and of its best rival.
        outcome: ``few`` (too few landmarks), ``weak`` (best under the inliers
            needed), ``ambiguous`` (rival within the margin), ``drift`` (beyond the
            drift bound) or ``tied``.
    """

    k: int
    recent: tuple[int, ...]
    old: tuple[int, ...]
    n_best: int
    runner_up: int
    outcome: str


class RevisitMerge(GraphState):
    """Constellation revisit check (mixin of :class:`~lampsam.backend.graph.GraphSlam`).

    Attributes:
        n_revisit_merges: copies tied to an old landmark so far.
        n_revisit_rejected: unique alignments rejected because the drift they imply
            at the current pose is beyond :data:`REVISIT_SIGMAS` of its marginal.
        revisit_ties: ``(keyframe, copy id, old id)`` of each tie.
    """

    n_revisit_merges = 0
    n_revisit_rejected = 0

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

    def _revisit_check(self, k: int, n_new: int) -> int:
        """Match recent range-bearing landmarks to old ones (module doc); the merges made.

        Runs at a keyframe that started a landmark (``n_new``) or gave a recent
        landmark its second sighting (it then joins the constellation).
        """
        cfg = self.config.association
        if not n_new and not any(
                lm.kind == "point2" and lm.last_kf == k and lm.n_obs == 2
                and k - lm.first_kf <= RECENT_KEYFRAMES for lm in self._landmarks.values()):
            return 0
        recent, old = [], []
        pose = self.current_pose()
        for lm in self._landmarks.values():
            if lm.kind != "point2" or not lm.in_graph:
                continue
            if k - lm.first_kf <= RECENT_KEYFRAMES:
                if lm.n_obs >= 2:
                    recent.append(lm)
            elif (k - lm.last_kf >= IDLE_KEYFRAMES
                  and float(np.hypot(*(lm.state[:2] - pose[:2]))) <= SEARCH_RADIUS):
                old.append(lm)
        if len(recent) < cfg.revisit_min_inliers or len(old) < cfg.revisit_min_inliers:
            self._record(k, recent, old, 0, 0, "few")
            return 0
        for lm in (*recent, *old):
            self._refresh_landmark(lm)
        src = np.array([lm.state[:2] for lm in recent])
        dst = np.array([lm.state[:2] for lm in old])
        cov = tangent_to_coords_cov(pose, self.current_cov())
        sigma_theta = math.sqrt(max(float(cov[2, 2]), 0.0))
        hyps = rank_hypotheses(src, dst, cfg.revisit_tol,
                               min(math.pi, REVISIT_SIGMAS * sigma_theta + 0.05))
        n_best, runner = best_and_rival(hyps)
        if n_best < cfg.revisit_min_inliers or n_best - runner < 2:
            self._record(k, recent, old, n_best, runner,
                         "weak" if n_best < cfg.revisit_min_inliers else "ambiguous")
            return 0
        al = align_constellation(src, dst, cfg.revisit_tol, cfg.revisit_min_inliers, 2,
                                 min(math.pi, REVISIT_SIGMAS * sigma_theta + 0.05))
        assert al is not None
        # the motion moves the current pose by the drift it claims: near the prediction
        c, s = math.cos(al.theta), math.sin(al.theta)
        moved = np.array([[c, -s], [s, c]]) @ pose[:2] + al.shift
        sigma_xy = math.sqrt(max(float(np.linalg.eigvalsh(cov[:2, :2])[-1]), 0.0))
        if float(np.hypot(*(moved - pose[:2]))) > REVISIT_SIGMAS * sigma_xy + cfg.revisit_tol:
            self.n_revisit_rejected += 1
            self._record(k, recent, old, n_best, runner, "drift")
            return 0
        self._record(k, recent, old, n_best, runner, "tied")
        noise = gtsam.noiseModel.Isotropic.Sigma(2, cfg.revisit_tol / 2.0)
        self.revisit_ties.extend((k, recent[a].id, old[b].id) for a, b in al.pairs)
        for a, b in al.pairs:
            copy, orig = recent[a], old[b]
            self._add_factor(gtsam.BetweenFactorPoint2(L(copy.id), L(orig.id),
                                                       np.zeros(2), noise))
            orig.n_obs += copy.n_obs
            orig.last_kf = k
            del self._landmarks[copy.id]
        self.n_revisit_merges += len(al.pairs)
        log.info("revisit at keyframe %d: %d recent landmarks tied to old ones (rotation "
                 "%.3f rad, shift %.1f m, rms %.2f m, runner-up %d inliers)", k, len(al.pairs),
                 al.theta, float(np.hypot(*al.shift)), al.rms, al.runner_up)
        return len(al.pairs)
