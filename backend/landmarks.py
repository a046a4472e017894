"""Landmark lifecycle in a factor-graph backend: start, observe, triangulate, insert, prune.

New variables are initialised from the current estimate plus odometry, never from a
file's dead reckoning (DESIGN sec. 6). Lamps (and planar points) enter the graph at
their first sight, initialised like the EKF's (eqs. 24-25, with the height prior, so
a single sight is never an indeterminate system). Corners use delayed
initialisation: they stay pending (gated, not in the graph) until triangulated from
at least two keyframes with enough parallax and a height above the camera
(:meth:`LandmarkLifecycle._try_triangulate`, ``Isam2Config.corner_init_*``); a
corner initialised from one ray could be pulled under the lens by the next update,
where GTSAM's projection factor throws. Landmarks with fewer than
``min_observations`` observations are left out of the reported map, with a warning.
"""

from __future__ import annotations

import collections
import logging
import math

import gtsam
import numpy as np
from gtsam.symbol_shorthand import L, X

from lampsam.arrays import FloatArray
from lampsam.backend.ceiling import MIN_USABLE_HEIGHT
from lampsam.backend.graph_state import GraphState
from lampsam.backend.handlers import GraphLandmark, GraphValue
from lampsam.backend.interface import LandmarkKind, log_pruned
from lampsam.backend.models import Obs, try_initialize
from lampsam.backend.reassociate import Sightings, refine
from lampsam.errors import EstimationError

log = logging.getLogger(__name__)

#: Sights of a lamp triangulated to tighten its gate (:meth:`LandmarkLifecycle._tighten_lamp_gate`).
LAMP_SIGHTS = 6


class LandmarkLifecycle(GraphState):
    """Landmarks entering and leaving the graph (mixin of :class:`~lampsam.backend.graph.GraphSlam`)."""

    def _new_id(self) -> int:
        while self._next_id in self._landmarks:
            self._next_id += 1
        lid = self._next_id
        self._next_id += 1
        return lid

    def _start_landmark(self, pose: FloatArray, pose_cov: FloatArray, k: int, obs: Obs,
                        lid: int | None) -> int:
        started = try_initialize(pose, obs, self.config.association, self.ceiling)
        if started is None:
            return 0
        state, g_pose, g_z, cov_z = started
        cov_meas = g_z @ cov_z @ g_z.T
        cov = g_pose @ pose_cov @ g_pose.T + cov_meas
        lid_given = lid
        if lid is None:
            lid = self._new_id()
        else:
            self._next_id = max(self._next_id, lid + 1)
        oriented = obs.kind == "lamp" and obs.has_axis
        lm = GraphLandmark(lid, LandmarkKind(obs.kind), False, 1, state, cov, [(k, obs)], obs.patch, oriented, k,
                       cov_meas[:3, :3], first_kf=k)
        self._landmarks[lid] = lm
        if lm.kind == "point2" and lid_given is None:
            self._planar_sightings.append((k, obs.z, obs.R, lid))
        if lm.kind == "lamp":
            lm.sights.append((k, obs))
        tentative = (lm.kind == "point2" and lid_given is None
                     and self.config.association.planar_confirm_sightings > 1)
        if tentative:
            lm.pending.append((k, obs))
        elif lm.kind != "corner" or self.ceiling is None:
            self._enter_graph(lm)
        return 1

    def _try_triangulate(self, lm: GraphLandmark) -> bool:
        """Delayed initialisation of a pending corner (see :class:`Isam2Config`).

        Triangulates from the pending sights' keyframe estimates
        (:meth:`~lampsam.backend.ceiling.CeilingModel.triangulate`); accepted when
        at least ``corner_init_min_sights`` distinct keyframes see it, the height
        above the camera is at least :data:`~lampsam.backend.ceiling.MIN_USABLE_HEIGHT`
        and at most ``2 * height_max``, and its sigma is at most
        ``corner_init_max_rel_sigma`` of the height. Sights inconsistent with the
        point (reprojection chi-square beyond the new-landmark threshold) drop the
        newest sight (a wrong association). On success the state and the gating
        covariance are set from the triangulation.

        Returns:
            True when the corner may enter the graph.
        """
        cfg = self.config.isam2
        ks = {k for k, _ in lm.pending}
        if len(ks) < cfg.corner_init_min_sights:
            return False
        poses, ms, covs, point, cov, h = self._triangulate_sights(lm.pending)
        if h < MIN_USABLE_HEIGHT or h > 2.0 * self.config.association.height_max:
            return False
        chi2 = self._require_ceiling().reprojection_chi2(poses, point, ms, covs)
        dof = 2 * len(poses) - 3
        if chi2 > self.config.association.new_threshold(max(dof, 1)):
            lm.pending.pop()  # the newest sight does not fit: likely a wrong match
            lm.n_obs -= 1
            return False
        if math.sqrt(max(cov[2, 2], 0.0)) > cfg.corner_init_max_rel_sigma * h:
            return False
        lm.state = point
        lm.cov = self._placed_cov(cov)
        lm.cov_rel = cov
        return True

    def _triangulate_sights(self, sights: list[tuple[int, Obs]]
                            ) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray,
                                       FloatArray, float]:
        """Triangulate a ceiling point from ``(keyframe, observation)`` sights.

        Returns:
            ``(poses (n, 3), ms (n, 2), covs (n, 2, 2), point (3,), cov (3, 3),
            height above the camera in m)``; the poses are the keyframes' current
            estimates.
        """
        poses = np.array([self._kf_poses[k] if k == self._k else self._pose_of(k)
                          for k, _ in sights])
        ms = np.array([o.z[:2] for _, o in sights])
        covs = np.array([o.R[:2, :2] for _, o in sights])
        ceiling = self._require_ceiling()
        point, cov = ceiling.triangulate(poses, ms, covs)
        return poses, ms, covs, point, cov, float(point[2] - ceiling.body_t_camera[2])

    def _placed_cov(self, cov_rel: FloatArray) -> FloatArray:
        """A triangulated point's covariance (3, 3) plus the current keyframe's x, y variance."""
        return cov_rel + np.diag([*np.diag(self._kf_cov)[:2], 0.0])

    def _forget_pending(self, k: int) -> None:
        """Forget pending corners not seen for ``corner_pending_keyframes`` keyframes."""
        horizon = self.config.isam2.corner_pending_keyframes
        stale = [lid for lid, lm in self._landmarks.items()
                 if not lm.in_graph and lm.kind in ("corner", "point2")
                 and k - lm.last_kf > horizon]
        for lid in stale:
            del self._landmarks[lid]
        self.n_pruned += len(stale)
        if stale:
            self.pruned["pending_stale"] = self.pruned.get("pending_stale", 0) + len(stale)

    def _observe(self, lm: GraphLandmark, k: int, obs: Obs) -> None:
        if lm.kind == "point2" and obs.landmark_id is None:
            self._planar_sightings.append((k, obs.z, obs.R, lm.id))
        lm.n_obs += 1
        lm.last_kf = k
        if lm.in_graph:
            if lm.kind == "point2" and obs.landmark_id is None:
                self._add_planar_sighting(lm, k, obs)
            else:
                for f in self.handlers[lm.kind].factors(lm, k, obs, self._robust_for(lm.kind)):
                    self._add_factor(f, lm.id)
            if lm.kind == "lamp" and self.ceiling is not None:
                self._tighten_lamp_gate(lm, k, obs)
            return
        lm.pending.append((k, obs))
        if lm.kind == "point2":
            if lm.n_obs >= self.config.association.planar_confirm_sightings:
                self._enter_graph(lm)
            return
        if lm.kind == "corner" and self.ceiling is not None:
            if self._entries_left > 0 and self._try_triangulate(lm):
                self._enter_graph(lm)
                self._entries_left -= 1
        elif lm.n_obs >= self.config.association.min_observations:
            self._enter_graph(lm)

    def _tighten_lamp_gate(self, lm: GraphLandmark, k: int, obs: Obs) -> None:
        """Replace a lamp's first-sight gating covariance by a triangulated one.

        A lamp enters the graph at its first sight with eq. 25's covariance (long
        along the viewing ray, from the height prior), which keeps its screen wide
        and sends it to the costly joint marginals. Its first
        :data:`LAMP_SIGHTS` sights are triangulated like a corner's
        (:meth:`~lampsam.backend.ceiling.CeilingModel.triangulate`); once the
        height is determined to ``corner_init_max_rel_sigma``, the triangulation
        covariance becomes the lamp's relative gating covariance.
        """
        if len(lm.sights) >= LAMP_SIGHTS:
            return
        lm.sights.append((k, obs))
        if len({kk for kk, _ in lm.sights}) < 2:
            return
        _, _, _, _, cov, h = self._triangulate_sights(lm.sights)
        if h >= MIN_USABLE_HEIGHT and math.sqrt(max(cov[2, 2], 0.0)) <= (
                self.config.isam2.corner_init_max_rel_sigma * h):
            lm.cov_rel = cov
            # The screen's fallback for a lamp not seen for many keyframes: as for a
            # triangulated corner, not the first sight's covariance, which spans most
            # of the height range and let lamps metres apart all pass the cheap gate
            # (each such sight then cost joint marginals).
            # Only the position block: an oriented lamp keeps its axis variance, so
            # lm.cov stays (d, d) for the gate without a joint marginal (eq. 19).
            placed = np.zeros_like(lm.cov)
            placed[:3, :3] = self._placed_cov(cov)
            placed[3:, 3:] = lm.cov[3:, 3:]
            lm.cov = placed

    def _enter_graph(self, lm: GraphLandmark) -> None:
        """Insert a landmark's variables, priors and its buffered factors."""
        handler = self.handlers.get(lm.kind)
        if handler is None:
            raise EstimationError(f"no graph handler for landmark kind {lm.kind!r}")
        handler.insert(lm, _ValuesPair(self))
        handler.priors(lm, _Adder(self), self._pose_of, self.config)
        for k, o in lm.pending:
            for f in handler.factors(lm, k, o, self._robust_for(lm.kind)):
                self._add_factor(f, lm.id)
        lm.pending = []
        lm.in_graph = True

    def _reassociate(self, start: gtsam.Values) -> gtsam.Values | None:
        """Batch re-association without ids (:func:`lampsam.backend.reassociate.refine`).

        Applies to a run whose landmarks are all range-bearing points associated
        without ids, with ``reassociation.passes > 0``: the sightings are re-associated
        against the optimised map from ``start`` (iSAM2's estimate), ``self.graph``
        becomes the graph of the final association (its first factor, the start
        prior, and the keyframe odometry kept), landmarks left without sightings are
        dropped and the others' sighting counts updated.

        Returns:
            The optimised values of the revised graph, or None when it does not apply.
        """
        cfg = self.config
        if (cfg.reassociation.passes <= 0 or not self._planar_sightings
                or any(lm.kind != "point2" for lm in self._landmarks.values())):
            return None
        live = {lid for lid, lm in self._landmarks.items() if lm.in_graph}
        rec = [r for r in self._planar_sightings if r[3] in live]
        if not rec or len(rec) != len(self._planar_sightings):
            return None  # pending (unconfirmed) sightings: keep the online association
        s = Sightings(np.array([r[0] for r in rec]), np.array([r[1][:2] for r in rec], float),
                      np.array([r[2][:2, :2] for r in rec], float),
                      np.array([r[3] for r in rec]))
        n_kf = self._k + 1
        poses = np.array([[start.atPose2(X(k)).x(), start.atPose2(X(k)).y(),
                           start.atPose2(X(k)).theta()] for k in range(n_kf)])
        lms = {lid: np.asarray(start.atPoint2(L(lid)), float) for lid in sorted(live)}
        graph, values, passes = refine(self.graph.at(0), self._odo, s, poses, lms,
                                       cfg.association.gate(2), cfg.association.new_threshold(2),
                                       cfg.reassociation)
        for n, p in enumerate(passes, 1):
            log.info("re-association pass %d: %s", n, p)
        self.reassociation_passes = passes
        counts = collections.Counter(s.lid.tolist())
        for lid in list(self._landmarks):
            if lid not in counts:
                del self._landmarks[lid]
            else:
                self._landmarks[lid].n_obs = counts[lid]
        self.graph = graph
        self._planar_sightings = [(int(k), z, r, int(lid)) for k, z, r, lid in
                                  zip(s.k, s.z, s.r, s.lid, strict=True)]
        return values

    def _prune_once_seen(self) -> list[int]:
        """Landmarks with fewer than ``min_observations`` observations (not in the map).

        Their variables stay in the graph (a range-bearing sight, or a ceiling sight
        with the height prior, determines them); they are reported apart, flagged
        (:attr:`~lampsam.backend.interface.SlamResult.provisional`), unless
        ``association.prune_once_seen``.
        """
        cfg = self.config.association
        drop = [lid for lid, lm in self._landmarks.items() if lm.n_obs < cfg.min_observations]
        self.n_pruned += len(drop)
        if drop:
            self.pruned["seen_too_few"] = self.pruned.get("seen_too_few", 0) + len(drop)
        log_pruned(self.n_pruned, self.pruned, cfg.min_observations, not cfg.prune_once_seen)
        return drop


class _ValuesPair:
    """Insert into both the pending-update Values and the all-initial Values."""

    def __init__(self, owner: GraphState) -> None:
        self.owner = owner

    def insert(self, key: int, value: GraphValue) -> None:
        self.owner._add_value(key, value)


class _Adder:
    """``add(factor)`` into both the pending-update graph and the full graph."""

    def __init__(self, owner: GraphState) -> None:
        self.owner = owner

    def add(self, factor: gtsam.NonlinearFactor) -> None:
        self.owner._add_factor(factor)
