"""Configuration of data association (``[association]``): the gate, landmark
initialisation and pruning, and the no-ids options, shared by every backend.

A frozen dataclass with documented defaults, checked on construction like the rest of
:mod:`lampsam.backend.config` (which composes it into ``SlamConfig`` and re-exports it,
with :func:`chi2_quantile`).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field

from scipy.special import chdtri

from lampsam.config_loader import FieldValueError, check_limits, limits, plain
from lampsam.factors.ceiling import HeightPrior


@functools.lru_cache(maxsize=64)
def chi2_quantile(prob: float, dof: int) -> float:
    """The ``prob`` quantile of the chi-square distribution with ``dof`` degrees of freedom."""
    return float(chdtri(dof, 1.0 - prob))


@dataclass(frozen=True)
class AssociationConfig:
    """Data association, landmark initialisation and pruning (shared by all backends).

    Attributes:
        use_known_ids: use ``landmark_id`` when an observation carries one
            (known association); otherwise associate by the gate (default True).
        gate_prob: chi-square probability of the Mahalanobis gate, paper eq. 20
            (default 0.99); the threshold ``d`` is ``chi2.ppf(gate_prob, dof)``.
        new_prob: an observation farther than ``chi2.ppf(new_prob, dof)`` from every
            landmark starts a new one; between the two thresholds it is ambiguous
            and dropped (default 0.9999; set equal to ``gate_prob`` for the paper's
            single threshold).
        ncc_min: minimum normalised cross-correlation for a corner match among
            the gated candidates (default 0.7).
        height_min, height_max: plausible height range of ceiling landmarks above
            the camera, m (paper: 0-5 m; default 0.5-5.0, see
            :class:`lampsam.factors.ceiling.HeightPrior`): a Gaussian whose +-2 sigma
            spans the range is the initialisation prior (eqs. 24-25).
        min_observations: a landmark needs this many observations to be in the
            map (default 2). One seen fewer times is reported apart, flagged
            (``SlamResult.provisional``, ``flag = seen_once`` in ``landmarks.csv``)
            unless ``prune_once_seen``.
        joint_compatibility: without ids, planar (range-bearing) observations of a
            frame are paired by joint compatibility (:func:`lampsam.backend.association.jcbb`)
            instead of greedy nearest neighbour: in the EKF on every frame
            (:mod:`lampsam.backend.ekf_joint`), in the smoothers on every keyframe
            with an ambiguity, with the joint marginal of the pose and all candidates
            (:mod:`lampsam.backend.joint_gating`). Default False: on Victoria Park
            without ids it did not prevent divergence (docs/graph-backend.md,
            docs/failures.md).
        prune_once_seen: drop landmarks seen fewer than ``min_observations`` times
            from the output altogether (default False: keep them, flagged).
        prune_after_steps: a landmark not re-observed for this many steps after
            creation, with fewer than ``min_observations`` observations or a
            position sigma above ``prune_sigma``, is removed (default 30).
        prune_sigma: largest acceptable horizontal position sigma of a settled
            landmark, m (default 1.0).
        prune_relative: the EKF judges a landmark without a known id by its own
            uncertainty: the horizontal sigma of its position conditional on the
            pose that last saw it (from the joint covariance of pose and landmark
            at that sighting), not its absolute sigma, which also holds the robot's
            uncertainty (default True; False: the absolute sigma, the rule before
            issue #15). On a log stating odometry noise far too large the robot's
            sigma grows to metres and the absolute rule pruned most landmarks
            (docs/ekf-lamps.md). Landmarks with a known id keep the absolute rule.
        lamp_min_separation: the smoothers start no new lamp where a mapped lamp
            is predicted within this distance in normalised ceiling coordinates
            (default 0.1, about 25 cm on a 2.5 m ceiling; lamps do not overlap), see
            :meth:`lampsam.backend.gating.Gating._near_known_lamp`; 0 disables.
        max_corner_updates: per frame (keyframe), at most this many corners already
            in the map are used, longest tracks first, and at most
            ``max(2, budget - kept)`` new corners enter it
            (:func:`lampsam.backend.association.corner_budget`; default 10; None: all).
            The smoothers apply it; the EKF only with ``EkfConfig.corner_budget``.
            The simulator's truth frames carry about 100 corners each (the frontend
            up to 150). In iSAM2 every observed landmark joins the root clique: on
            the lab run's first 600 frontend frames, 25 corners re-eliminated a median
            152 variables per update (17.6 ms, loaded), 10 corners 56 (5.3 ms); with
            all corners the whole lab run took 3.5x longer than with 25 for no
            accuracy. In the EKF the update is ``O(n^2 K)`` in the state size ``n``
            and the rows ``K``. Over 10 seeds of 60 s of lab (images, odometry floor
            1e-8) the batch smoother's mean position RMS was 6.5 mm with 10 and with 25.
        gate_noise_scale: the smoothers' gate for range-bearing observations
            without ids uses ``s R`` instead of the stated measurement noise ``R``
            (:meth:`lampsam.backend.gating.Gating._screen_planar`; default 1.0). For
            logs whose stated noise is conservative (Victoria Park's 0.2 rad
            bearing sigma: the innovations of true matches have a median
            Mahalanobis distance of 0.03 against the chi-square's 1.39), the
            stated noise makes trees several metres apart compatible; the factors
            keep ``R``.
        planar_confirm_sightings: without ids, a new range-bearing landmark stays
            tentative until it has this many sightings (default 1: mapped at its
            first sight, the paper's rule, eqs. 24-25). Every backend reads it: the
            smoothers keep it gated and out of the graph, forgotten with its
            sightings if not confirmed within ``isam2.corner_pending_keyframes``
            keyframes; the EKF fuses the sightings in a tentative list
            (:class:`lampsam.backend.association.TentativeLandmarks`, forgotten after
            ``ekf.tentative_max_idle`` steps).
        planar_reject_ambiguous: without ids, a range-bearing observation with two
            or more landmarks inside the relative gate (of
            :meth:`lampsam.backend.gating.Gating._screen_planar`) is dropped instead
            of given to the nearest (default False).
        planar_unique: without ids, a range-bearing observation is matched only when
            no second landmark is within the new-landmark threshold of it (exact
            distances, eq. 19); else it is held (neither matched nor mapped) and
            re-gated at later keyframes, given back once unambiguous
            (:mod:`lampsam.backend.held_sightings`; the result's ``extra`` counts
            ``n_held`` and ``n_held_given_back``). Default False (docs/failures.md:
            worse on Victoria Park's first 3,500 poses, 0.58 against 0.44 m, and
            alone it diverges the held-out loop log, 9.4 against 0.20 m). Still off
            with the final solve (docs/noids-offline.md, "Which online settings
            should be the defaults"): with ``revisit_check`` the final answer is
            worse on the held-out loop (0.22 against 0.20 m) and, with ``cov_scale``
            16 as Victoria Park needs, the loop's run fails; for a log like Victoria
            Park set both and ``[pose2_odometry] cov_scale = 16``.
        planar_unique_prob: the rival's zone for ``planar_unique``: the chi-square
            quantile of this probability (default 0: the new-landmark threshold,
            ``new_prob``; e.g. ``gate_prob`` for a rival inside the gate only).
        planar_unique_ratio: with ``planar_unique``, a rival in that zone holds the
            sighting only when its likelihood (eq. 19, Gaussian with its own ``Psi``)
            is at least this fraction of the nearest landmark's
            (:func:`lampsam.backend.planar_gate.rival_ratio`); default 0: any rival holds it.
            Held sightings are re-gated later and given back once unambiguous
            (:mod:`lampsam.backend.held_sightings`).
        planar_relative_gate: without ids, gate range-bearing observations of
            landmarks seen in the last 30 keyframes relative to their last sighting
            (odometry covariance since then; final, no joint marginal) instead of
            with iSAM2's joint marginal (default False: it trusts the odometry
            noise, and on MRCLAM, whose odometry noise is assumed, it diverged).
            ``gate_noise_scale`` also scales the landmark's measurement-only
            covariance in this gate.
        planar_noise_adapt: without ids, gate range-bearing observations with the
            innovation covariance scaled by a factor estimated online from the
            squared distances of unambiguous matches
            (:class:`lampsam.backend.innovation_scale.InnovationScale`: ``margin x``
            their median over the chi-square's truncated median, clamped to
            ``[planar_noise_floor, 1]`` over the last ``planar_noise_window``
            matches). Never wider than the stated noise; the factors and the EKF
            update keep the stated ``R``. Default False: on logs whose stated noise
            is right the scale stays 1 (no change); where it is conservative and the
            revisits are within the gate it maps each tree once where the stated
            gate merges neighbours; on Victoria Park neither holds
            (docs/graph-backend.md).
        planar_noise_floor, planar_noise_margin, planar_noise_window: its clamp,
            safety factor and window (defaults 0.05, 2.0, 200).
        planar_merge_every: EKF without ids: every this many steps, merge the best
            unambiguous pair of duplicate planar landmarks
            (:mod:`lampsam.backend.landmark_merge`: joint-marginal distance of
            ``l_i - l_j`` below the ``gate_prob`` gate, no second partner below the
            ``new_prob`` threshold, never seen in one frame); 0 (default) never.
        planar_merge_min_obs: sightings each landmark of a pair needs (default 3).
        planar_merge_radius: only pairs closer than this are tested, m (default 30).
        revisit_check: smoothers without ids: after a keyframe that starts a
            range-bearing landmark, match the local scan (every landmark sighted in
            the last 40 keyframes) to the landmarks made before it near the
            prediction by one unambiguous rigid motion
            (:mod:`lampsam.backend.revisit_merge`) and merge each matched copy with
            its old landmark (default False: alone it diverges the held-out loop
            log, 12.2 against 0.20 m; docs/failures.md; with ``planar_unique``, still
            off after the final solve: ``planar_unique`` above).
        revisit_tol, revisit_min_inliers: its inlier distance in m (default 0.75)
            and inliers needed (default 4).
        revisit_tie_sigma: the merge's tie (``BetweenFactorPoint2``) sigma per
            axis, m (default 0.05).
        odometry_noise_adapt: without ids, multiply the odometry covariance by a
            variance factor learnt online from the innovations of unambiguous
            range-bearing matches (:mod:`lampsam.backend.odometry_scale`: maximum
            likelihood of ``nu ~ N(0, a S_x + b R)`` truncated at the gate, over the
            last ``odometry_noise_window`` matches; the factor starts at 1, the
            stated noise, and stays in ``[1, odometry_noise_max]``). Every backend
            reads it; known-id runs never gate, so they are unchanged (default False).
        odometry_noise_max, odometry_noise_window: its upper bound (default 100) and
            window (default 150 matches).
        alias_odds: smoothers without ids: a range-bearing match inside the gate is
            kept only when its likelihood (eq. 19, Gaussian with its own ``Psi``) is
            at least this many times that of "a landmark not mapped yet" at the
            map's landmark density (:mod:`lampsam.backend.alias_gate`); a sighting
            whose every gated match fails starts a landmark of its own
            (``alias_new``) or is held. 0 (default): off, the gate alone
            (docs/noids-aliasing.md).
        alias_spacing: the landmark spacing for ``alias_odds``, m (density
            ``1 / spacing^2``); 0 (default): the median nearest-neighbour distance
            of the mapped planar landmarks, re-estimated at every keyframe.
        alias_new: a sighting the alias test refused starts a landmark of its own
            (default True: a tree mapped twice is merged by the final solve, where a
            held one is lost: on cityTrees_reduced_1k holding recorded 152-218 of
            406 sightings); False: it is dropped, or held with ``planar_unique``.
    """

    use_known_ids: bool = True
    gate_prob: float = field(default=0.99, metadata=limits(gt=0.0, lt=1.0))
    new_prob: float = field(default=0.9999, metadata=limits(gt=0.0, lt=1.0))
    ncc_min: float = field(default=0.7, metadata=limits(ge=-1.0, le=1.0))
    height_min: float = field(default=0.5, metadata=limits(ge=0.0))
    height_max: float = field(default=5.0, metadata=limits(gt=0.0))
    min_observations: int = field(default=2, metadata=limits(ge=1))
    joint_compatibility: bool = False
    prune_once_seen: bool = False
    prune_after_steps: int = field(default=30, metadata=limits(ge=0))
    prune_sigma: float = field(default=1.0, metadata=limits(gt=0.0))
    prune_relative: bool = True
    lamp_min_separation: float = field(default=0.1, metadata=limits(ge=0.0))
    max_corner_updates: int | None = field(default=10, metadata=limits(ge=0))
    gate_noise_scale: float = field(default=1.0, metadata=limits(gt=0.0, le=1.0))
    planar_confirm_sightings: int = field(default=1, metadata=limits(ge=1))
    planar_reject_ambiguous: bool = False
    planar_unique: bool = False
    planar_unique_prob: float = field(default=0.0, metadata=limits(ge=0.0, lt=1.0))
    planar_unique_ratio: float = field(default=0.0, metadata=limits(ge=0.0, le=1.0))
    planar_relative_gate: bool = False
    planar_noise_adapt: bool = False
    planar_noise_floor: float = field(default=0.05, metadata=limits(gt=0.0, le=1.0))
    planar_noise_margin: float = field(default=2.0, metadata=limits(gt=0.0))
    planar_noise_window: int = field(default=200, metadata=limits(ge=1))
    planar_merge_every: int = field(default=0, metadata=limits(ge=0))
    planar_merge_min_obs: int = field(default=3, metadata=limits(ge=1))
    planar_merge_radius: float = field(default=30.0, metadata=limits(gt=0.0))
    revisit_check: bool = False
    revisit_tol: float = field(default=0.75, metadata=limits(gt=0.0))
    revisit_min_inliers: int = field(default=4, metadata=limits(ge=3))
    revisit_tie_sigma: float = field(default=0.05, metadata=limits(gt=0.0))
    odometry_noise_adapt: bool = False
    odometry_noise_max: float = field(default=100.0, metadata=limits(ge=1.0))
    odometry_noise_window: int = field(default=150, metadata=limits(ge=1))
    alias_odds: float = field(default=0.0, metadata=limits(ge=0.0))
    alias_spacing: float = field(default=0.0, metadata=limits(ge=0.0))
    alias_new: bool = True

    def __post_init__(self) -> None:
        """Check the declared ranges (:class:`FieldValueError` naming the key)."""
        check_limits(self)
        if self.height_max <= self.height_min:
            raise FieldValueError("height_max", f"must exceed height_min ({plain(self.height_min)}), "
                                  f"got {plain(self.height_max)}")

    def height_prior(self) -> HeightPrior:
        """The factors' :class:`HeightPrior` for ``[height_min, height_max]``."""
        return HeightPrior(self.height_min, self.height_max)

    def gate(self, dof: int) -> float:
        """Mahalanobis gate ``d`` of paper eq. 20 for a ``dof``-dimensional innovation."""
        return chi2_quantile(self.gate_prob, dof)

    def unique_threshold(self, dof: int) -> float:
        """Squared distance inside which a second landmark makes a sighting ambiguous
        (``planar_unique``)."""
        if self.planar_unique_prob > 0.0:
            return chi2_quantile(self.planar_unique_prob, dof)
        return self.new_threshold(dof)

    def new_threshold(self, dof: int) -> float:
        """Squared Mahalanobis distance beyond which an observation starts a new landmark."""
        return chi2_quantile(max(self.new_prob, self.gate_prob), dof)
