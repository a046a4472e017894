"""The state a factor-graph backend keeps, and the primitives every part of it uses.

:class:`GraphState` holds the growing graph (everything, for batch LM, and the
pending part for the next iSAM2 update), the initial values, the iSAM2 instance,
the keyframe estimates and odometry, the landmarks and the per-step records. The
parts of the smoother are mixins over it, one job each:

- :class:`lampsam.backend.isam2_update.Isam2Updates`: one iSAM2 update per keyframe,
  and the rebuild after a failed one;
- :class:`lampsam.backend.gating.Gating`: innovations and gates (eqs. 19-20);
- :class:`lampsam.backend.landmarks.LandmarkLifecycle`: start, observe, triangulate,
  insert and prune landmarks;
- :class:`lampsam.backend.graph.GraphSlam`: keyframes, steps and the final result.

Poses are ``world_T_body`` ``(x, y, theta)``; pose covariances here are in GTSAM's
right tangent (:mod:`lampsam.backend.pose_cov`).
"""

from __future__ import annotations

import math

import gtsam
import numpy as np
from gtsam.symbol_shorthand import X

from lampsam.arrays import FloatArray
from lampsam.backend.ceiling import CeilingModel
from lampsam.backend.ceiling_graph import CEILING_SYMBOLS
from lampsam.backend.config import SlamConfig
from lampsam.backend.handlers import (
    GraphLandmark,
    GraphValue,
    LandmarkHandler,
    Point2Handler,
    ValueKind,
    value_of_kind,
)
from lampsam.backend.innovation_scale import innovation_scale
from lampsam.backend.interface import LandmarkKind, SlamBackend
from lampsam.backend.models import Obs
from lampsam.backend.odometry import OdometryConstants, motion_model
from lampsam.backend.odometry_scale import IdleOdometry, ScaledMotion, odometry_scale
from lampsam.backend.pose_cov import compose_cov, pose_array
from lampsam.backend.reassociate import Pass
from lampsam.errors import EstimationError


class GraphState(SlamBackend):
    """State and graph-building primitives shared by the smoother's parts.

    Args:
        odometry: the odometry model's constants (wheel or Pose2 increments;
            :func:`lampsam.backend.odometry.motion_model`).
        config: the SLAM config.
        start_pose: (3,) known start pose ``world_T_body``, m and rad.
        ceiling: the ceiling observation model (lamps/corners), or None.
        ceiling_handler: graph handler for ceiling kinds, or None.
        online: keep an iSAM2 estimate (True) or only odometry (False).
    """

    def __init__(self, odometry: OdometryConstants, config: SlamConfig, start_pose: FloatArray,
                 ceiling: CeilingModel | None = None,
                 ceiling_handler: LandmarkHandler | None = None, online: bool = True) -> None:
        self.motion = motion_model(odometry)
        self.config = config
        self.ceiling = ceiling
        self.handlers: dict[LandmarkKind, LandmarkHandler] = {LandmarkKind.POINT2: Point2Handler()}
        if ceiling_handler is not None:
            self.handlers[LandmarkKind.LAMP] = ceiling_handler
            self.handlers[LandmarkKind.CORNER] = ceiling_handler
        self.online = online
        #: the range-bearing gate's online innovation scale (``association.planar_noise_adapt``)
        self.noise_scale = innovation_scale(config.association)
        self.odo_scale = odometry_scale(config.association)  # learnt odometry noise, or None
        self.idle = IdleOdometry()  # per landmark, the odometry since its last sighting
        if self.odo_scale is not None:
            self.motion = ScaledMotion(self.motion, self.odo_scale)
        #: iSAM2's parameters (a lamp-only relinearisation threshold needs the ceiling
        #: graph's symbol characters: :data:`~lampsam.backend.ceiling_graph.CEILING_SYMBOLS`)
        self.isam2_params = config.isam2.to_gtsam(
            CEILING_SYMBOLS if ceiling_handler is not None else None)
        self.isam = gtsam.ISAM2(self.isam2_params) if online else None
        #: the fixed-lag smoother (``isam2.fixed_lag``, iSAM2 backend only); ``isam`` is
        #: then its own ISAM2 (a live reference), read as usual
        self.smoother: gtsam.IncrementalFixedLagSmoother | None = None
        if online and config.isam2.fixed_lag > 0 and self.name == "isam2":
            self.smoother = gtsam.IncrementalFixedLagSmoother(float(config.isam2.fixed_lag),
                                                              self.isam2_params)
            self.isam = self.smoother.getISAM2()
        self.graph = gtsam.NonlinearFactorGraph()  # everything, for batch LM
        self.initial = gtsam.Values()  # initial guesses of every variable
        self._new_graph = gtsam.NonlinearFactorGraph()
        self._new_values = gtsam.Values()
        cfg = config.isam2
        start = np.asarray(start_pose, float)
        prior_sigmas = np.array([cfg.sigma_start_xy, cfg.sigma_start_xy, cfg.sigma_start_theta])
        self._add_value(X(0), gtsam.Pose2(*start))
        self._add_factor(gtsam.PriorFactorPose2(X(0), gtsam.Pose2(*start),
                                                gtsam.noiseModel.Diagonal.Sigmas(prior_sigmas)))
        self._kf_pose = start.copy()  # current estimate of the last keyframe
        #: its tangent covariance (:attr:`_kf_cov`); after an iSAM2 update, the key
        #: whose marginal it is, computed when first read
        self._kf_cov_value: FloatArray = np.diag(prior_sigmas**2)
        self._kf_cov_key: int | None = None
        self._kf_poses: list[FloatArray] = [start.copy()]  # running (odometry-pass) estimates
        self._k = 0
        self._k_isam = 0  # the newest keyframe sent to iSAM2 (< _k while keyframes are deferred)
        self._delta = np.zeros(3)
        self._delta_cov = np.zeros((3, 3))
        self._wheel_since_kf: list[FloatArray] = []
        #: odometry (delta, covariance with the factor's floor) of the first step's
        #: samples since the last keyframe: the factor's own when no others follow
        self._first_rel: tuple[FloatArray, FloatArray] | None = None
        self._landmarks: dict[int, GraphLandmark] = {}
        self._next_id = 0
        self._last_t = -math.inf
        # per-step records
        self._times: list[float] = []
        self._step_kf: list[int] = []
        self._step_delta: list[FloatArray] = []
        self._step_delta_cov: list[FloatArray] = []
        self._step_times: list[float] = []
        self._keyframes: list[bool] = []
        self.update_times: list[float] = []  # iSAM2 update() per keyframe, s
        self.estimate_times: list[float] = []  # then the pose estimate + marginal, s
        self.n_pruned = 0
        self.pruned: dict[str, int] = {}  # by reason; sums to n_pruned
        self.n_recoveries = 0  # failed updates whose measurements were dropped
        #: iSAM2 rebuilt with QR after an ill-conditioned clique (nothing dropped), and
        #: whether it factors with QR from then on (:mod:`lampsam.backend.isam2_update`)
        self.n_refactorized = 0
        self.qr_factorization = False
        #: iSAM2 rebuilt from a Levenberg-Marquardt solution after its Gauss-Newton step
        #: raised the graph's error (:meth:`~lampsam.backend.isam2_update.Isam2Updates._damp_divergence`)
        self.n_damped = 0
        self._update_factor_lids: list[tuple[int, int]] = []  # (graph index, landmark)
        self._joint_cache: dict[int, tuple[FloatArray, FloatArray, FloatArray] | None] = {}
        # (lamp id, measurement size) -> (keyframe, exact eq.-19 distance there), for _reuse_far
        self._far: dict[tuple[int, int], tuple[int, float]] = {}
        self.n_far_reused = 0
        #: landmark id -> (gate keyframe, joint blocks) of its last exact joint marginal
        #: (:meth:`~lampsam.backend.gate_shortcuts.LampGateShortcuts._bound_far`)
        self._joint_at: dict[int, tuple[int, tuple[FloatArray, FloatArray, FloatArray]]] = {}
        self.n_far_bounded = 0
        #: lamp pairs settled inside / outside the gate by :meth:`~lampsam.backend.gate_shortcuts.LampGateShortcuts._bracket`
        self.n_bracket_inside = 0
        self.n_bracket_outside = 0
        self._odo: list[tuple[FloatArray, FloatArray]] = [(np.zeros(3), np.zeros((3, 3)))]
        #: range-bearing sightings without ids ``(keyframe, z, R, landmark id)``, for the
        #: batch re-association (:meth:`LandmarkLifecycle._reassociate`)
        self._planar_sightings: list[tuple[int, FloatArray, FloatArray, int]] = []
        #: (keyframe, landmark id) -> graph indices of that range-bearing sighting's
        #: factors (no ids: a contradicted association is moved by index)
        self._planar_factor_at: dict[tuple[int, int], list[int]] = {}
        self.reassociation_passes: list[Pass] = []
        self._entries_left = 1 << 30  # corners that may still enter the graph this keyframe
        self._rel_cache: tuple[int, dict[int, FloatArray]] | None = None
        self._pose_cache: dict[int, FloatArray] = {}  # iSAM2's keyframe estimates until the next update
        self._point_keys: dict[int, int] = {}  # landmark id -> position key (Gating._refresh_visible)
        self._left_poses: set[int] = set()  # keyframes the fixed-lag smoother marginalised
        self._fl_alive: set[int] = set()  # keys in the fixed-lag window
        self._fl_gone: set[int] = set()  # keys it marginalised
        self._fl_last = gtsam.Values()  # the window's estimate after the last update

    @property
    def planar_sightings(self) -> list[tuple[int, FloatArray, FloatArray, int]]:
        """Range-bearing sightings associated without ids, ``(keyframe, z, R, landmark
        id)`` (a copy; keyframe 0 is the start pose), as the EKF's ``planar_sightings``
        (by step there)."""
        return list(self._planar_sightings)

    # ------------------------------------------------------------------ graph building
    def _add_value(self, key: int, value: GraphValue) -> None:
        self._new_values.insert(key, value)
        self.initial.insert(key, value)

    def _add_factor(self, factor: gtsam.NonlinearFactor, lid: int | None = None) -> None:
        """Add to the pending update and the full graph; ``lid``: the measured landmark."""
        self._new_graph.add(factor)
        self.graph.add(factor)
        if lid is not None:
            self._update_factor_lids.append((self.graph.size() - 1, lid))

    def _add_planar_sighting(self, lm: GraphLandmark, k: int, obs: Obs) -> None:
        """A range-bearing sighting without id of keyframe ``k`` as factors of ``lm``
        (recorded with their graph indices in ``_planar_factor_at``)."""
        for f in self.handlers[lm.kind].factors(lm, k, obs, self._robust_for(lm.kind)):
            self._add_factor(f, lm.id)
            self._planar_factor_at.setdefault((k, lm.id), []).append(self.graph.size() - 1)

    def _require_ceiling(self) -> CeilingModel:
        """The ceiling model; an EstimationError for a ceiling kind without one."""
        if self.ceiling is None:
            raise EstimationError("ceiling landmarks need a CeilingModel (make_backend camera=)")
        return self.ceiling

    @property
    def robust(self) -> float | None:
        """Huber threshold for measurement factors (batch with ``huber_k`` set), else None."""
        return self.config.batch.huber_k if self.name == "batch" else None

    def _robust_for(self, kind: str) -> float | None:
        """Huber threshold for a kind's factors: corners get ``isam2.corner_huber_k``."""
        if kind == "corner" and self.config.isam2.corner_huber_k is not None:
            return self.config.isam2.corner_huber_k
        return self.robust

    # ------------------------------------------------------------------ estimates
    def _get(self, key: int, kind: ValueKind) -> GraphValue:
        """Current estimate of a variable: iSAM2's if it has it, else the initial value."""
        if self.isam is not None and self.isam.valueExists(key):
            if kind == "point2":
                return np.asarray(self.isam.calculateEstimatePoint2(key), float)
            if kind == "point3":
                return np.asarray(self.isam.calculateEstimatePoint3(key), float)
            if kind == "vector":
                return np.asarray(self.isam.calculateEstimateVector(key), float)
            if kind == "pose2":
                return self.isam.calculateEstimatePose2(key)
        return value_of_kind(self.initial, key, kind)

    def _pose_of(self, k: int) -> FloatArray:
        """Current estimate of keyframe ``k`` (read-only: cached until the next iSAM2 update)."""
        if k == self._k:
            return self._kf_pose
        if k > self._k_isam:  # deferred (not yet in iSAM2): its prediction
            return self._kf_poses[k]
        if self.isam is not None:
            pose = self._pose_cache.get(k)
            if pose is None:
                if k in self._left_poses:  # marginalised by the fixed-lag smoother
                    return self._kf_poses[k]
                pose = self._pose_cache[k] = pose_array(self.isam.calculateEstimatePose2(X(k)))
            return pose
        return self._kf_poses[k]

    @property
    def _kf_cov(self) -> FloatArray:
        """(3, 3) tangent covariance of the last keyframe.

        After an iSAM2 update it is that keyframe's marginal, computed on first read:
        iSAM2 does not change until the next update, so the value is the one an
        eager ``marginalCovariance`` after the update gives, and a run that never
        reads it (known ids, no gate, no online covariance) never pays for it.
        """
        if self._kf_cov_key is not None:
            assert self.isam is not None
            self._kf_cov_value = np.asarray(self.isam.marginalCovariance(self._kf_cov_key))
            self._kf_cov_key = None
        return self._kf_cov_value

    @_kf_cov.setter
    def _kf_cov(self, cov: FloatArray) -> None:
        self._kf_cov_value = cov
        self._kf_cov_key = None

    def current_pose(self) -> FloatArray:
        """Current pose (3,): the last keyframe's estimate composed with the odometry since."""
        if not self._wheel_since_kf:  # no odometry since the keyframe: its own estimate
            return self._kf_pose.copy()
        return pose_array(gtsam.Pose2(*self._kf_pose).compose(gtsam.Pose2(*self._delta)))

    def current_cov(self) -> FloatArray:
        """Current pose's tangent covariance (3, 3): the last keyframe's marginal
        composed with the odometry's since."""
        return compose_cov(self._delta, self._kf_cov, self._delta_cov)

    def _refresh_landmark(self, lm: GraphLandmark) -> None:
        """Update the cached estimate/covariance of an in-graph landmark from iSAM2."""
        if not lm.in_graph or self.isam is None:
            return
        lm.state = self.handlers[lm.kind].read(lm, self._get)
