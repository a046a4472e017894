"""Configuration of the SLAM backends: frozen dataclasses with documented defaults.

``SlamConfig`` composes the per-part configs; the CLI (``commands/``) reads TOML and builds
them with the strict loader (:mod:`lampsam.config_loader`). Ranges are declared
on the fields (``metadata=limits(...)``) and checked on construction, so a
negative distance fails from Python as from a file. GTSAM parameter objects are
built in one method each (``to_gtsam()``). The offline parts (``[batch]``,
``[reassociation]``) live in :mod:`lampsam.backend.config_offline`, ``[association]`` in
:mod:`lampsam.backend.config_association` and ``[graph]`` in :mod:`lampsam.backend.config_graph`;
all are re-exported here.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import NamedTuple

import gtsam
import numpy as np

from lampsam.backend.config_association import AssociationConfig as AssociationConfig
from lampsam.backend.config_association import chi2_quantile as chi2_quantile
from lampsam.backend.config_graph import PoseGraphConfig
from lampsam.backend.config_offline import BatchConfig, ReassociationConfig
from lampsam.config_loader import FieldValueError, check_limits, from_mapping, limits
from lampsam.datasets.odometry import Pose2OdometryModel


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
            same as every variable's (default None).
        relinearize_skip: relinearise every this many updates (default 10, GTSAM's;
            1 made the lab run's updates 2-3x slower).
        cache_linearized_factors: GTSAM's ``cacheLinearizedFactors`` (keep each
            factor's linearisation between relinearisations; default True, GTSAM's).
        find_unused_factor_slots: GTSAM's ``findUnusedFactorSlots`` (default False).
        extra_updates: extra ``update()`` calls per keyframe (default 0).
        sigma_start_xy, sigma_start_theta: prior on the known start pose (m, rad; default 1e-3).
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
            (:meth:`~lampsam.backend.gate_shortcuts.LampGateShortcuts._reuse_far`; default 5: on the lab
            path 0.78x the online CPU and keyframe p95 57 -> 43 ms, 10-seed accuracy
            unchanged, docs/speed.md; 0: always exact).
        far_lamp_factor: see ``far_lamp_recheck`` (default 2.0).
        far_lamp_bound: settle a lamp without a joint marginal when a lower bound of
            its exact gate distance, from its last joint marginal carried by the
            odometry, is beyond the new-landmark threshold
            (:meth:`~lampsam.backend.gate_shortcuts.LampGateShortcuts._bound_far`; the same decisions as
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
            behind (default 1: off, one update per keyframe). While frames wait in its queue
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
        features: ceiling feature types to use, a subset of ``("lamps", "corners")`` (default both).
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
