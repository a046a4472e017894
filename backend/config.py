"""Configuration of the SLAM backends: frozen dataclasses with documented defaults.

``SlamConfig`` composes the per-part configs; the CLI (``commands/``) reads TOML and builds
them with the strict loader (:mod:`lampsam.config_loader`). Ranges are declared
on the fields (``metadata=limits(...)``) and checked on construction, so a
negative distance fails from Python as from a file. GTSAM parameter objects are
built in one method each (``to_gtsam()``). The offline parts (``[batch]``,
``[reassociation]``) live in :mod:`lampsam.backend.config_offline` and are re-exported here.
"""

from __future__ import annotations

import functools
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import NamedTuple

import gtsam
import numpy as np
from scipy.special import chdtri

from lampsam.backend.config_graph import PoseGraphConfig
from lampsam.backend.config_offline import BatchConfig, ReassociationConfig
from lampsam.config_loader import FieldValueError, check_limits, from_mapping, limits, plain
from lampsam.datasets.odometry import Pose2OdometryModel
from lampsam.factors.ceiling import HeightPrior


@functools.lru_cache(maxsize=64)
def chi2_quantile(prob: float, dof: int) -> float:
    """The ``prob`` quantile of the chi-square distribution with ``dof`` degrees of freedom."""
    return float(chdtri(dof, 1.0 - prob))


@dataclass(frozen=True)
class MeasurementNoiseConfig:
    """Measurement noise not carried by the observations themselves.

    Attributes:
        sigma_range: range noise of planar range-bearing observations, m
            (default 0.15: MRCLAM's measured spread is 0.14 m).
        sigma_bearing: bearing noise, rad (default 0.05: MRCLAM 0.046 rad).
        var_axis_min: floor on a lamp axis variance, rad^2 (default 1e-4).
    """

    sigma_range: float = field(default=0.15, metadata=limits(gt=0.0))
    sigma_bearing: float = field(default=0.05, metadata=limits(gt=0.0))
    var_axis_min: float = field(default=1e-4, metadata=limits(ge=0.0))

    def __post_init__(self) -> None:
        """Check the declared ranges (:class:`FieldValueError` naming the key)."""
        check_limits(self)


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
            quantile of this probability (0, default: the new-landmark threshold,
            ``new_prob``; e.g. ``gate_prob`` for a rival inside the gate only).
        planar_unique_ratio: with ``planar_unique``, a rival in that zone holds the
            sighting only when its likelihood (eq. 19, Gaussian with its own ``Psi``)
            is at least this fraction of the nearest landmark's
            (:func:`lampsam.backend.planar_gate.rival_ratio`); 0: any rival holds it.
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
            (:class:`lampsam.backend.association.InnovationScale`: ``margin x``
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
            reads it; known-id runs never gate, so they are unchanged.
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


@dataclass(frozen=True)
class EkfConfig:
    """The paper's EKF-SLAM.

    Attributes:
        sigma_start_xy: standard deviation of the known start position, m (default 1e-3).
        sigma_start_theta: of the start heading, rad (default 1e-3).
        var_floor: additive floor on the pose process covariance per step,
            m^2 and rad^2 (default 1e-10, only to keep P positive definite at rest).
        corner_budget: apply ``association.max_corner_updates`` in the EKF too
            (default False: the paper's EKF updates with every matched corner and
            maps every new one). Over 10 seeds of 60 s of lab (frontend images) the
            EKF's mean position RMS was 17.3 mm with every corner and 12.4 mm with
            the 10-corner budget; ``lampsam compare``
            reports the paper's EKF unless this is set.
        update_iterations: Gauss-Newton iterations of the measurement update
            (default 1: the paper's EKF, eqs. 21-23, linearised once at the
            prediction). Above 1, the iterated EKF (Bell & Cathey 1993): ``h`` and
            ``H`` are re-evaluated at the updated state until the step changes by less
            than ``update_tol``; ``P`` is corrected once, with the last ``H``.
        first_estimate_jacobians: the first-estimates Jacobian EKF (Huang, Mourikis
            & Roumeliotis, IJRR 29(5) 2010) instead of the paper's Jacobians at the
            latest estimate. True / False force it; None (default) turns it on for
            range-bearing runs with Pose2 odometry (landmark-graph logs such as
            Victoria Park, where the paper does not speak) and off for wheel
            odometry (the ceiling and MRCLAM: the paper's EKF).
            Measurement Jacobians use each landmark's first estimate (at its
            initialisation) and the predicted pose; the prediction Jacobian's heading
            column uses the pose predicted at the previous step, ``p_{k+1|k} -
            p_{k|k-1}``, not the updated one. Linearising at changing points gives
            the filter heading information the data do not hold (an overconfident,
            drifting heading on long outdoor loops); first estimates keep the
            unobservable directions unobservable. Innovations still use the latest
            estimate.
        update_tol: convergence threshold of the iterated update on the largest
            change of any state entry between iterations, m or rad (default 1e-4).
        young_lamp_iterations: iterations of the update for the observations of
            young lamps (default 5; 1: the paper's single linearisation everywhere).
            A lamp starts as a long ellipse along its viewing ray (the height prior
            of eqs. 24-25) and ``(u, v)`` goes with the inverse of its height: the
            single linearisation at the prior's mean overshoots along the ray, leaves
            the lamp sure of a wrong height, the next sightings fail the gate and
            start a copy of the lamp (docs/ekf-lamps.md). Those observations are
            applied after the frame's others, as an iterated update.
        young_lamp_rel_sigma: a lamp is young while its height's standard deviation
            is above this fraction of its height above the camera (default 0.02).
        right_invariant: the right-invariant EKF (Barrau & Bonnabel, "An EKF-SLAM
            algorithm with consistency properties", 2015) for planar range-bearing
            runs: Jacobians at the latest estimates (as the paper's), but each update
            is applied as ``exp(xi) x`` on ``SE_{1+K}(2)`` (the whole map and pose
            rotated by the heading correction) and ``P`` is carried over to the
            updated state's coordinates, so the global rotation stays unobservable
            without first estimates (``first_estimate_jacobians`` is then ignored).
            True / False force it; None (default): off. An error with a ceiling model.
        prune_known_ids: remove landmarks that carry a known id (from the log) by
            the paper's rules (seen fewer than ``association.min_observations``
            times, or still uncertain, ``association.prune_after_steps`` after
            creation). True / False force it; None (default) keeps the paper's rule
            except where first-estimate Jacobians are automatically on (range-bearing
            runs with Pose2 odometry: landmark-graph logs), where such landmarks stay in
            the state: a later sighting of the same id is a loop closure, not a new
            landmark. Landmarks still seen fewer than ``min_observations`` times at
            the end are reported as provisional as before.
        tentative_max_idle: steps after which an unconfirmed tentative landmark is
            forgotten (default 100).
        new_min_separation: a confirmed tentative landmark within this distance of a
            mapped planar landmark is discarded as a copy, m (default 0: off).
        observability_constrained: the observability-constrained EKF (OC-EKF, Huang,
            Mourikis & Roumeliotis, IJRR 29(5) 2010) for planar landmarks: measurement
            Jacobians at the latest estimate, projected to the nearest ones that keep
            a global translation and rotation unobservable
            (:func:`lampsam.backend.ekf_update.observability_project`), with the
            first-estimates prediction (so ``first_estimate_jacobians`` is implied).
            Where a landmark's estimate has moved metres from its first estimate the
            first-estimates ``H`` points the update the wrong way; the projected one
            does not. True / False force it; None (default) turns it on where first
            estimates are automatic (range-bearing runs with Pose2 odometry) and
            not turned off (``first_estimate_jacobians = false`` keeps the paper's
            Jacobians). Ignored with ``right_invariant``.
    """

    sigma_start_xy: float = field(default=1e-3, metadata=limits(gt=0.0))
    sigma_start_theta: float = field(default=1e-3, metadata=limits(gt=0.0))
    var_floor: float = field(default=1e-10, metadata=limits(ge=0.0))
    corner_budget: bool = False
    update_iterations: int = field(default=1, metadata=limits(ge=1))
    update_tol: float = field(default=1e-4, metadata=limits(gt=0.0))
    young_lamp_iterations: int = field(default=5, metadata=limits(ge=1))
    young_lamp_rel_sigma: float = field(default=0.02, metadata=limits(ge=0.0))
    first_estimate_jacobians: bool | None = None
    right_invariant: bool | None = None
    prune_known_ids: bool | None = None
    tentative_max_idle: int = field(default=100, metadata=limits(ge=0))
    new_min_separation: float = field(default=0.0, metadata=limits(ge=0.0))
    observability_constrained: bool | None = None

    def __post_init__(self) -> None:
        """Check the declared ranges (:class:`FieldValueError` naming the key)."""
        check_limits(self)


class IsamSymbol(NamedTuple):
    """A graph variable character's tangent dimension and whether it is a lamp's (:meth:`Isam2Config.to_gtsam`)."""

    dim: int
    lamp: bool


@dataclass(frozen=True)
class Isam2Config:
    """Online smoothing with iSAM2.

    Attributes:
        keyframe_distance: make a keyframe after this much travel, m (default 0.05).
        keyframe_angle: or after this much rotation, rad (default 0.15).
        every_frame: make every frame with observations a keyframe (default False:
            the first frame, then the distance/angle policy above). Frames between
            keyframes are used for gating the odometry-propagated pose only; their
            observations are dropped, and in the final trajectory their poses are the
            odometry conditioned on both neighbouring keyframes
            (:func:`lampsam.backend.pose_cov.odometry_bridge`). Over 10 seeds of 60 s of
            lab (frontend images), iSAM2's mean position / heading RMS: every frame
            6.3 mm / 0.043 deg; 0.05 m 5.6 mm / 0.089 deg; 0.1 m 5.4 mm / 0.124 deg
            (heading between keyframes is the wheels' alone: 0.13-0.21 deg at 0.1 m,
            against 0.04-0.06 deg at the keyframes). On the whole lab path (2,601
            frames) ``update()`` took a median / p95 of 4.0 / 15.5 ms at 0.05 m
            (1,218 keyframes), 3.5 / 9.5 ms at 0.1 m and 7.5 / 43 ms with every frame.
            (Before the first frame was always a keyframe, the policy cost 3x in
            accuracy: see :func:`lampsam.backend.keyframes.is_keyframe`.)
        relinearize_threshold: iSAM2 relinearisation threshold (default 0.1, GTSAM's):
            a variable whose pending correction has a component above it (m, rad) is
            relinearised at the next relinearisation step (``inf``: never).
        lamp_relinearize_threshold: the threshold for lamps' variables (position and
            axis) where the graph's lamps have their own symbol characters (the ceiling
            graph: :data:`~lampsam.backend.ceiling_graph.CEILING_SYMBOLS`); None: the
            same as every variable's.
        relinearize_skip: relinearise every this many updates (default 10, GTSAM's;
            1 made the lab run's updates 2-3x slower).
        cache_linearized_factors: GTSAM's ``cacheLinearizedFactors`` (keep each
            factor's linearisation between relinearisations; default True, GTSAM's).
        find_unused_factor_slots: GTSAM's ``findUnusedFactorSlots`` (default False).
        extra_updates: extra ``update()`` calls per keyframe (default 0).
        sigma_start_xy, sigma_start_theta: prior on the known start pose (m, rad).
        pose_cov_every_step: every step's estimate carries its pose covariance (the
            last keyframe's marginal composed with the odometry since; default True).
            With the corner budget below the marginal costs, together with the pose
            estimate, a median 4.3 ms per keyframe on the whole lab path (truth
            frames, against 9.0 ms for ``update()``). When False the steps' covariances
            are NaN (not computed) and the marginal is computed only when the gate or
            a new landmark's covariance reads it (a keyframe with known ids only that
            starts no landmark never does).
        final_covariances: compute every keyframe's final marginal covariance in
            ``finish()`` (default True; NaN covariances when False, for speed).
        odometry_floor_var: variance added to each diagonal entry of every odometry
            factor's tangent covariance, m^2 / rad^2 (default 1e-9 = (0.03 mm)^2 and
            (0.03 mrad)^2 per keyframe). It was 1e-6, which at 15 keyframes a second is
            several times the lab's wheel noise itself: the smoothers then trusted
            odometry far less than the EKF did (10 seeds of 30 s of lab, frontend
            images, batch: 8.2 mm mean position error with 1e-6, 7.9 mm with 1e-8). Over
            10 seeds of 60 s of lab, 1e-8 left the batch smoother's NEES at 2.55, under
            the 95 % band of the time average [2.63, 3.39] (6.5 mm); 1e-9 gives 3.26,
            inside [2.56, 3.47] (7.0 mm). On MRCLAM (300 s) 1e-9 gives iSAM2 and batch
            0.158 m with known ids, NEES 3.47. 1e-10 (the EKF's ``var_floor``) made
            MRCLAM's iSAM2 fail with indeterminate systems: its wheel model gives a
            robot at rest no odometry noise at all.
        corner_huber_k: Huber threshold in sigmas on corner projection factors in
            both smoothers (default 1.345, the usual 95 %-efficiency value): corners
            are associated by gate + NCC without known ids, and one wrong match must
            not pull the graph; None for plain Gaussian factors.
        corner_init_min_sights: a corner enters the graph only once it is
            triangulated from this many keyframes (default 4; delayed initialisation).
            Its sights must also agree with the triangulated point (chi-square with
            2n - 3 degrees of freedom), which with 2 sights (1 degree) let wrong NCC
            matches in: over 10 seeds of 30 s of lab, 2 sights gave heading errors up
            to 2.1 deg at the ends of runs, 4 sights at most 0.5 deg.
        corner_init_max_rel_sigma: ... and the triangulated height above the camera
            has a standard deviation at most this fraction of the height (default 0.15:
            enough parallax); until then the corner is pending (gated, not in the graph).
        corner_pending_keyframes: a pending corner not seen for this many keyframes
            is forgotten (default 30).
        far_lamp_recheck: a lamp whose exact gate distance was above
            ``far_lamp_factor`` times the new-landmark threshold within this many
            keyframes keeps that distance instead of a new joint marginal
            (:meth:`~lampsam.backend.gating.Gating._reuse_far`; default 5: on the lab
            path 0.78x the online CPU and keyframe p95 57 -> 43 ms, 10-seed accuracy
            unchanged, docs/speed.md; 0: always exact).
        far_lamp_factor: see ``far_lamp_recheck`` (default 2.0).
        far_lamp_bound: settle a lamp without a joint marginal when a lower bound of
            its exact gate distance, from its last joint marginal carried by the
            odometry, is beyond the new-landmark threshold
            (:meth:`~lampsam.backend.gating.Gating._bound_far`; the same decisions as
            the exact gate; default False).
        bracket_gate: settle a lamp pair without a joint marginal when a bracket of
            its exact gate distance from the current pose marginal, the lamp's last
            marginal and ``R`` (no cross term) fixes the decision: surely inside the
            gate with no competitor, or beyond the new-landmark threshold
            (:mod:`~lampsam.backend.gate_bracket`; the same decisions as the exact
            gate; default True; false: every such pair asks iSAM2).
        fixed_lag: the online iSAM2 backend smooths over the last this many keyframes
            only (GTSAM's ``IncrementalFixedLagSmoother``; lamps never leave the
            window; :mod:`lampsam.backend.fixed_lag`); 0 (default): full iSAM2. For
            bounded cost on endless runs; the final trajectory is then the online
            one (docs/speed.md, "Fixed lag").
    """

    keyframe_distance: float = field(default=0.05, metadata=limits(ge=0.0))
    keyframe_angle: float = field(default=0.15, metadata=limits(ge=0.0))
    every_frame: bool = False
    relinearize_threshold: float = field(default=0.1, metadata=limits(ge=0.0, finite=False))
    lamp_relinearize_threshold: float | None = field(default=None,
                                                     metadata=limits(gt=0.0, finite=False))
    relinearize_skip: int = field(default=10, metadata=limits(ge=1))
    cache_linearized_factors: bool = True
    find_unused_factor_slots: bool = False
    extra_updates: int = field(default=0, metadata=limits(ge=0))
    sigma_start_xy: float = field(default=1e-3, metadata=limits(gt=0.0))
    sigma_start_theta: float = field(default=1e-3, metadata=limits(gt=0.0))
    pose_cov_every_step: bool = True
    odometry_floor_var: float = field(default=1e-9, metadata=limits(ge=0.0))
    final_covariances: bool = True
    corner_huber_k: float | None = field(default=1.345, metadata=limits(gt=0.0))
    corner_init_min_sights: int = field(default=4, metadata=limits(ge=2))
    corner_init_max_rel_sigma: float = field(default=0.15, metadata=limits(gt=0.0))
    corner_pending_keyframes: int = field(default=30, metadata=limits(ge=1))
    far_lamp_recheck: int = field(default=5, metadata=limits(ge=0))
    far_lamp_factor: float = field(default=2.0, metadata=limits(ge=1.0))
    far_lamp_bound: bool = False
    bracket_gate: bool = True
    fixed_lag: int = field(default=0, metadata=limits(ge=0))

    def __post_init__(self) -> None:
        """Check the declared ranges (:class:`FieldValueError` naming the key)."""
        check_limits(self)

    def to_gtsam(self, symbols: Mapping[str, IsamSymbol] | None = None) -> gtsam.ISAM2Params:
        """The ``gtsam.ISAM2Params`` for this config.

        Args:
            symbols: every variable character of the graph -> its :class:`IsamSymbol`.
                With it and a ``lamp_relinearize_threshold`` that differs from
                ``relinearize_threshold``, the threshold is GTSAM's per-character map
                (``ISAM2ThresholdMap``: one vector of the variable's dimension per
                character, compared component-wise; every character in the graph must
                be in it); otherwise the one scalar (the largest component).
        """
        params = gtsam.ISAM2Params()
        lamp = self.lamp_relinearize_threshold
        if symbols is not None and lamp is not None and lamp != self.relinearize_threshold:
            thresholds = gtsam.ISAM2ThresholdMap()
            for ch, sym in symbols.items():
                thresholds.insert((ch, np.full(sym.dim, lamp if sym.lamp else self.relinearize_threshold)))
            params.setRelinearizeThreshold(thresholds)
        else:
            params.setRelinearizeThreshold(self.relinearize_threshold)
        params.relinearizeSkip = self.relinearize_skip
        params.cacheLinearizedFactors = self.cache_linearized_factors
        params.findUnusedFactorSlots = self.find_unused_factor_slots
        return params


@dataclass(frozen=True)
class OnlineConfig:
    """``lampsam slam --online decoupled`` (TOML table ``[online]``; :mod:`lampsam.backend.tracking`).

    Attributes:
        catch_up: iSAM2 keyframes per update at most when the mapping worker is
            behind (1: off, one update per keyframe). While frames wait in its queue
            the worker associates each new keyframe against the prediction (the
            newest estimate plus odometry) and defers its update, up to this many
            keyframes, then runs one update for all of them
            (:meth:`~lampsam.backend.graph.GraphSlam.step` with ``update=False``).
    """

    catch_up: int = field(default=1, metadata=limits(ge=1))

    def __post_init__(self) -> None:
        """Check the declared ranges (:class:`FieldValueError` naming the key)."""
        check_limits(self)


@dataclass(frozen=True)
class SlamConfig:
    """Everything :func:`lampsam.backend.slam.run_slam` needs.

    Attributes:
        features: ceiling feature types to use, a subset of ``("lamps", "corners")``.
        association, noise, ekf, isam2, batch, reassociation: the parts above. ``noise`` is also
            the default noise of a range-bearing observation that carries no
            covariance of its own (``sigma_range``, ``sigma_bearing``).
        pose2_odometry: noise of Pose2-increment odometry samples without a
            covariance and the per-sample floor
            (:class:`~lampsam.datasets.odometry.Pose2OdometryModel`; TOML table
            ``[pose2_odometry]``); a run's ``rig.yaml`` section of the same name
            overrides it. Wheel odometry takes its constants from ``rig.yaml``.
        online: the decoupled online run's mapping worker (``[online]``).
        graph: loop closures of graph text logs (``[graph]``,
            :class:`~lampsam.backend.config_graph.PoseGraphConfig`).
    """

    features: tuple[str, ...] = ("lamps", "corners")
    association: AssociationConfig = field(default_factory=AssociationConfig)
    noise: MeasurementNoiseConfig = field(default_factory=MeasurementNoiseConfig)
    ekf: EkfConfig = field(default_factory=EkfConfig)
    isam2: Isam2Config = field(default_factory=Isam2Config)
    batch: BatchConfig = field(default_factory=BatchConfig)
    reassociation: ReassociationConfig = field(default_factory=ReassociationConfig)
    pose2_odometry: Pose2OdometryModel = field(default_factory=Pose2OdometryModel)
    online: OnlineConfig = field(default_factory=OnlineConfig)
    graph: PoseGraphConfig = field(default_factory=PoseGraphConfig)

    def __post_init__(self) -> None:
        """Check the feature names (:class:`FieldValueError` naming the key)."""
        unknown = [f for f in self.features if f not in ("lamps", "corners")]
        if unknown:
            raise FieldValueError("features", f"unknown feature {unknown[0]!r} (lamps, corners)")

    @classmethod
    def from_dict(cls, data: Mapping[str, object], source: str | Path | None = None) -> SlamConfig:
        """Build from nested tables (``[association]``, ``[ekf]``, ...; a TOML file's).

        The strict loader :func:`lampsam.config_loader.from_mapping` does the work.

        Raises:
            ConfigError: an unknown table or key, a wrong type or a value out of
                range, naming the dotted key and ``source``.
        """
        return from_mapping(cls, data, source=source)
