"""Factor-graph backends: iSAM2 (online) and batch Levenberg-Marquardt (offline).

Both build the same graph (DESIGN sec. 4):

- keyframe poses ``X(k)`` (``Pose2``), a prior on the known start pose;
- odometry ``BetweenFactorPose2`` between consecutive keyframes, its covariance the
  wheel noise propagated through eqs. 13-15
  (:func:`lampsam.factors.motion.accumulate_odometry`, with its floor);
- measurement factors built by a per-kind landmark handler
  (:class:`Point2Handler` for planar range-bearing: GTSAM's built-in
  ``BearingRangeFactor2D``; :class:`lampsam.backend.ceiling_graph.CeilingHandler`
  for lamps and corners).

Keyframes: the first frame, then a frame after the robot has moved
``keyframe_distance`` or turned ``keyframe_angle`` since the last keyframe (the
default; 0.05 m, 0.15 rad), or every frame with observations (``every_frame``); the
smoothers do not use other frames' observations. Between
keyframes the current pose is the last keyframe estimate composed with the odometry
since then, with the covariance propagated to first order
(``Sigma = Ad(delta^-1) Sigma_k Ad(delta^-1)^T + Sigma_delta`` in the right tangent).
Each keyframe gives factors to at most ``AssociationConfig.max_corner_updates`` corners
already in the graph, those with the longest tracks first (:func:`corner_budget`):
iSAM2 puts every newly observed variable in the root clique, so the update and the
pose marginal grow with the cube of their number, and a frame carries 50-150 corners.

New variables are initialised from the current estimate plus odometry, never from a
file's dead reckoning (DESIGN sec. 6). Lamps (and planar points) enter the graph at
their first sight, initialised like the EKF's (eqs. 24-25, with the height prior, so
a single sight is never an indeterminate system). Corners use delayed
initialisation: they stay pending (gated, not in the graph) until triangulated from
at least two keyframes with enough parallax and a height above the camera
(:meth:`GraphSlam._try_triangulate`, ``Isam2Config.corner_init_*``); a corner
initialised from one ray could be pulled under the lens by the next update, where
GTSAM's projection factor throws. Corner factors carry a Huber loss by default
(``Isam2Config.corner_huber_k``): they are associated by gate + NCC without ids. A
failed iSAM2 update is not fatal: the offending factors are dropped and iSAM2 is
rebuilt (:meth:`GraphSlam._recover`, logged). Landmarks with fewer than
``min_observations`` observations are left out of the reported map, with a warning.

Association (eqs. 19-20): planar points use iSAM2's joint marginal of the last
keyframe pose and each candidate landmark, propagated to the current pose, so the
pose-landmark cross-covariance is kept (without it the gate is far too wide and
MRCLAM's gate-only run diverged). Ceiling landmarks are screened all at once in
numpy with a relative gate (:meth:`GraphSlam._screen`: the odometry covariance since
the landmark's last observing keyframe plus its measurement-only covariance, which
stands in for the cross term); corners are then decided by that gate and the NCC,
and only lamps with two or more gated candidates pay for joint marginals (each costs
several ms on a corner-dense graph). The batch backend runs the same online pass
(``init = "isam2"``) or a pure odometry pass (``init = "odometry"``: running
estimate = dead reckoning, gating then without cross-covariance: meant for known
association) and then one LM over the whole graph, with Huber noise if configured;
if LM fails (a trial step throwing), the iSAM2 estimate is kept, with a warning.
"""

from __future__ import annotations

import logging
import math
import re
import time
from dataclasses import dataclass, field
from typing import Any

import gtsam
import numpy as np
from gtsam.symbol_shorthand import L, X

from lampsam.arrays import FloatArray
from lampsam.backend.association import associate, corner_budget, screen_pairs
from lampsam.backend.ceiling import MIN_USABLE_HEIGHT
from lampsam.backend.config import SlamConfig
from lampsam.backend.ekf import WheelParams, check_wheel, landmark_estimate
from lampsam.backend.interface import (
    Frame,
    LandmarkEstimate,
    SlamBackend,
    SlamResult,
    StepEstimate,
    log_pruned,
)
from lampsam.backend.models import (
    Obs,
    for_landmark,
    initialize,
    observations_from_frame,
    predict,
    residual,
)
from lampsam.errors import EstimationError
from lampsam.factors.geometry import coords_D_tangent, wrap_angle
from lampsam.factors.gtsam_factors import bearing_range_factor, odometry_factor
from lampsam.factors.motion import accumulate_odometry

log = logging.getLogger(__name__)

#: Sights of a lamp triangulated to tighten its gate (:meth:`GraphSlam._tighten_lamp_gate`).
_LAMP_SIGHTS = 6

#: Keyframes back over which the smoothers' screen uses the relative gate.
_RELATIVE_GATE_KEYFRAMES = 30

#: Variance floor used for the per-step odometry composition (the factor's own floor
#: is added once per keyframe).
_STEP_FLOOR = 1e-14


def tangent_to_coords_cov(pose: FloatArray, cov_t: FloatArray) -> FloatArray:
    """Covariance in GTSAM's right tangent -> over plain coordinates (x, y, theta).

    Args:
        pose: (3,) the pose; cov_t: (3, 3) tangent covariance.

    Returns:
        (3, 3) ``J cov_t J^T`` with ``J = blockdiag(R(theta), 1)``.
    """
    j = coords_D_tangent(float(pose[2]))
    return j @ cov_t @ j.T


def compose_cov(delta: FloatArray, cov_a: FloatArray, cov_b: FloatArray) -> FloatArray:
    """Right-tangent covariance of ``a * b`` from those of ``a`` and ``b`` (first order).

    Args:
        delta: (3,) the pose ``b``.
        cov_a: (3, 3) covariance of ``a`` (tangent at ``a``).
        cov_b: (3, 3) covariance of ``b`` (tangent at ``b``), independent of ``a``.

    Returns:
        (3, 3) ``Ad(b^-1) cov_a Ad(b^-1)^T + cov_b``.
    """
    ad = gtsam.Pose2(*delta).inverse().AdjointMap()
    return ad @ cov_a @ ad.T + cov_b


def odometry_bridge(delta: FloatArray, cov_delta: FloatArray, delta_kf: FloatArray,
                    cov_kf: FloatArray, pose_k: FloatArray, pose_k1: FloatArray
                    ) -> tuple[FloatArray, FloatArray]:
    """A step between keyframes ``k`` and ``k+1``, conditioned on both final estimates.

    The odometry from keyframe ``k`` to the step, ``delta = delta_hat Exp(a)``
    (``a ~ N(0, A)``), and on to keyframe ``k+1``, ``eps = eps_hat Exp(b)``, compose to
    ``Delta ~ Delta_hat Exp(M a + b)`` with ``M = Ad(eps_hat^-1)`` and covariance
    ``Sigma = M A M^T + B``. The smoother fixes ``Delta`` to
    ``pose_k^-1 pose_k1``, i.e. the residual ``r = Log(Delta_hat^-1 Delta)``, and
    the Gaussian conditional (first order, a Brownian bridge along the odometry) is
    ``a | r ~ N(G r, A - G M A)`` with ``G = A M^T Sigma^-1``. Without it, the steps
    between keyframes would carry the whole odometry drift since keyframe ``k``: with
    keyframes every 0.1 m on 10 seeds of 60 s of lab, the heading RMS over all steps
    was 0.18 deg, with the bridge 0.12 deg (0.04 deg with a keyframe at every frame).

    The covariance assumes the wheel model is right. On lab it is (keyframes every
    0.05 m: batch NEES 3.00, inside the band; the unconditioned ``A`` gave 2.25,
    conservative). On MRCLAM, whose odometry is commanded ``(v, w)`` turned into wheel
    travel with an assumed noise, the steps between keyframes come out overconfident
    (iSAM2 NEES 14.2 against 4.6 with the unconditioned ``A``, same means).

    Args:
        delta, cov_delta: (3,), (3, 3) odometry from keyframe ``k`` to the step and
            its right-tangent covariance.
        delta_kf, cov_kf: (3,), (3, 3) odometry from keyframe ``k`` to ``k+1`` (the
            odometry factor's) and its covariance.
        pose_k, pose_k1: (3,) final estimates of the two keyframes.

    Returns:
        ``(delta', cov')``: the conditioned odometry to the step and its covariance;
        the inputs unchanged if the system is degenerate.
    """
    d_hat = gtsam.Pose2(*delta)
    big = gtsam.Pose2(*delta_kf)
    eps = d_hat.inverse().compose(big)
    m = eps.inverse().AdjointMap()
    observed = gtsam.Pose2(*pose_k).inverse().compose(gtsam.Pose2(*pose_k1))
    r = gtsam.Pose2.Logmap(big.inverse().compose(observed))
    a_mt = cov_delta @ m.T
    try:
        gain = np.linalg.solve(np.asarray(cov_kf, float), a_mt.T).T
    except np.linalg.LinAlgError:
        return delta, cov_delta
    if not np.all(np.isfinite(gain)):
        return delta, cov_delta
    out = d_hat.compose(gtsam.Pose2.Expmap(gain @ r))
    cov = cov_delta - gain @ m @ cov_delta
    return np.array([out.x(), out.y(), out.theta()]), 0.5 * (cov + cov.T)


@dataclass
class _Landmark:
    """A landmark known to a graph backend."""

    id: int
    kind: str
    in_graph: bool
    n_obs: int
    state: FloatArray  # EKF-form estimate (refreshed from iSAM2 when gating)
    cov: FloatArray  # first-sight covariance (eq. 25 marginal), used without iSAM2
    pending: list[tuple[int, Obs]] = field(default_factory=list)  # (keyframe, obs) to add
    patch: Any = None
    oriented: bool = False
    last_kf: int = 0  # last keyframe that observed it
    cov_rel: Any = None  # (3, 3) position covariance relative to that keyframe's pose
    sights: list[tuple[int, Obs]] = field(default_factory=list)  # first sights of a lamp


class Point2Handler:
    """Planar range-bearing landmarks in the graph: ``Point2`` + ``BearingRangeFactor2D``."""

    kind = "point2"

    def insert(self, lm: _Landmark, values: gtsam.Values) -> None:
        """Insert the landmark's variable(s) with its current estimate."""
        values.insert(L(lm.id), np.asarray(lm.state[:2], float))

    def priors(self, lm: _Landmark, graph: Any, pose_of: Any, config: SlamConfig) -> None:
        """No prior is needed for a planar landmark seen twice."""

    def factors(self, lm: _Landmark, k: int, obs: Obs, robust: float | None
                ) -> list[gtsam.NonlinearFactor]:
        """``BearingRangeFactor2D(X(k), L(id))`` (built-in C++, via the factors adapter)."""
        return [bearing_range_factor(X(k), L(lm.id), float(obs.z[0]), float(obs.z[1]), obs.R,
                                     robust=robust)]

    def read(self, lm: _Landmark, get: Any) -> FloatArray:
        """EKF-form state from an estimate source (``get(key, "point2")``)."""
        return np.asarray(get(L(lm.id), "point2"), float)

    def marginal(self, lm: _Landmark, marginal_of: Any) -> FloatArray:
        """Covariance of the EKF-form state from a marginal source."""
        return np.asarray(marginal_of(L(lm.id)))

    def state_index(self, lm: _Landmark) -> list[int]:
        """Rows of the EKF-form state in the tangent of :meth:`keys` (all of them)."""
        return [0, 1]

    def keys(self, lm: _Landmark) -> list[int]:
        """Graph keys of the landmark."""
        return [L(lm.id)]


class GraphSlam(SlamBackend):
    """Shared machinery of the iSAM2 and batch backends (see module docstring).

    Args:
        wheel: wheel base and noise constants (eq. 15).
        config: the SLAM config.
        start_pose: (3,) known start pose.
        ceiling: :class:`lampsam.backend.ceiling.CeilingModel` (lamps/corners) or None.
        ceiling_handler: graph handler for ceiling kinds, or None.
        online: keep an iSAM2 estimate (True) or only odometry (False).
    """

    name = "graph"

    def __init__(self, wheel: WheelParams, config: SlamConfig, start_pose: FloatArray,
                 ceiling: Any = None, ceiling_handler: Any = None, online: bool = True) -> None:
        self.wheel = wheel
        self.config = config
        self.ceiling = ceiling
        self.handlers: dict[str, Any] = {"point2": Point2Handler()}
        if ceiling_handler is not None:
            self.handlers["lamp"] = ceiling_handler
            self.handlers["corner"] = ceiling_handler
        self.online = online
        self.isam = gtsam.ISAM2(config.isam2.to_gtsam()) if online else None
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
        self._kf_cov = np.diag(prior_sigmas**2)  # its tangent covariance
        self._kf_poses: list[FloatArray] = [start.copy()]  # running (odometry-pass) estimates
        self._k = 0
        self._delta = np.zeros(3)
        self._delta_cov = np.zeros((3, 3))
        self._wheel_since_kf: list[FloatArray] = []
        self._landmarks: dict[int, _Landmark] = {}
        self._next_id = 0
        self._last_t = -math.inf
        # per-step records
        self._times: list[float] = []
        self._step_kf: list[int] = []
        self._step_delta: list[FloatArray] = []
        self._step_delta_cov: list[FloatArray] = []
        self._step_online_pose: list[FloatArray] = []
        self._step_online_cov: list[FloatArray] = []
        self._step_times: list[float] = []
        self._keyframes: list[bool] = []
        self.update_times: list[float] = []  # iSAM2 update() per keyframe, s
        self.estimate_times: list[float] = []  # then the pose estimate + marginal, s
        self.n_pruned = 0
        self.pruned: dict[str, int] = {}  # by reason; sums to n_pruned
        self.n_recoveries = 0
        self._update_factor_lids: list[tuple[int, int]] = []  # (graph index, landmark)
        self._joint_cache: dict[int, tuple[FloatArray, FloatArray, FloatArray] | None] = {}
        self._odo: list[tuple[FloatArray, FloatArray]] = [(np.zeros(3), np.zeros((3, 3)))]
        self._entries_left = 1 << 30  # corners that may still enter the graph this keyframe
        self._rel_cache: tuple[int, dict[int, FloatArray]] | None = None
        self._flush()

    # ------------------------------------------------------------------ graph building
    def _add_value(self, key: int, value: Any) -> None:
        self._new_values.insert(key, value)
        self.initial.insert(key, value)

    def _add_factor(self, factor: gtsam.NonlinearFactor, lid: int | None = None) -> None:
        """Add to the pending update and the full graph; ``lid``: the measured landmark."""
        self._new_graph.add(factor)
        self.graph.add(factor)
        if lid is not None:
            self._update_factor_lids.append((self.graph.size() - 1, lid))

    @property
    def robust(self) -> float | None:
        """Huber threshold for measurement factors (batch with ``huber_k`` set), else None."""
        return self.config.batch.huber_k if self.name == "batch" else None

    def _robust_for(self, kind: str) -> float | None:
        """Huber threshold for a kind's factors: corners get ``isam2.corner_huber_k``."""
        if kind == "corner" and self.config.isam2.corner_huber_k is not None:
            return self.config.isam2.corner_huber_k
        return self.robust

    def _flush(self) -> None:
        """Send the new factors and values to iSAM2 (one update)."""
        if self.isam is None:
            self._new_graph = gtsam.NonlinearFactorGraph()
            self._new_values = gtsam.Values()
            return
        t0 = time.perf_counter()
        try:
            self.isam.update(self._new_graph, self._new_values)
            for _ in range(self.config.isam2.extra_updates):
                self.isam.update()
        except RuntimeError as exc:
            self._recover(exc)
        t1 = time.perf_counter()
        self._new_graph = gtsam.NonlinearFactorGraph()
        self._new_values = gtsam.Values()
        self._update_factor_lids = []
        self._kf_pose = _pose_array(self.isam.calculateEstimatePose2(X(self._k)))
        if self.config.isam2.pose_cov_every_step:
            self._kf_cov = np.asarray(self.isam.marginalCovariance(X(self._k)))
        self.update_times.append(t1 - t0)
        self.estimate_times.append(time.perf_counter() - t1)

    def _recover(self, exc: RuntimeError) -> None:
        """Rebuild iSAM2 after a failed update, without the offending measurements.

        A failed ``update()`` (e.g. GTSAM's CheiralityException: a relinearised
        landmark below the camera) leaves iSAM2 in an unknown state. The landmark
        named in the message (else every landmark measured in this update) loses
        the factors added in this update; one that entered the graph in this update
        is removed altogether, and so is any ceiling landmark whose estimate is
        now below the camera (no usable linearisation point). A fresh iSAM2 is then
        built from the whole remaining graph, started from the last estimate (each
        removed landmark's factors go too). Logged as a warning.

        Raises:
            EstimationError: the rebuilt graph fails too.
        """
        named = {int(m.group(1)) for m in re.finditer(r"\bl(\d+)\b", str(exc))}
        new_lids = {lid for _, lid in self._update_factor_lids}
        bad = (named & set(self._landmarks)) or new_lids
        drop_idx = {i for i, lid in self._update_factor_lids if lid in bad}
        entered = {lid for lid in bad if self._new_values.exists(L(lid))}
        try:
            old = self.isam.calculateEstimate() if self.isam is not None else gtsam.Values()
        except RuntimeError:
            old = gtsam.Values()
        if self.ceiling is not None:  # landmarks the failed step put under the lens
            z_min = float(self.ceiling.body_t_camera[2]) + MIN_USABLE_HEIGHT
            for lid, lm in self._landmarks.items():
                if lm.in_graph and lm.kind in ("lamp", "corner") and old.exists(L(lid)):
                    if float(old.atPoint3(L(lid))[2]) < z_min:
                        entered.add(lid)
        log.warning("iSAM2 update failed at keyframe %d (%s: %s): dropping this update's "
                    "factors of %d landmarks (%d removed) and rebuilding iSAM2",
                    self._k, type(exc).__name__, str(exc).strip()[:120], len(bad), len(entered))
        removed_keys = set()
        for lid in entered:
            lm = self._landmarks.pop(lid)
            removed_keys.update(self.handlers[lm.kind].keys(lm))
            self.n_pruned += 1
            self.pruned["failed_update"] = self.pruned.get("failed_update", 0) + 1
        graph = gtsam.NonlinearFactorGraph()
        for i in range(self.graph.size()):
            f = self.graph.at(i)
            if f is None or i in drop_idx or any(key in removed_keys for key in f.keys()):
                continue
            graph.add(f)
        values = gtsam.Values()
        for key in self.initial.keys():
            if key in removed_keys:
                continue
            src = old if old.exists(key) else self.initial
            values.insert(key, _value_at(src, key))
        initial = gtsam.Values()
        for key in self.initial.keys():
            if key not in removed_keys:
                initial.insert(key, _value_at(self.initial, key))
        self.graph = graph
        self.initial = initial
        self.isam = gtsam.ISAM2(self.config.isam2.to_gtsam())
        try:
            self.isam.update(graph, values)
        except RuntimeError as exc2:
            raise EstimationError(f"iSAM2 rebuild failed at keyframe {self._k}: "
                                  f"{type(exc2).__name__} {exc2}") from exc2
        self._joint_cache = {}
        self.n_recoveries += 1

    # ------------------------------------------------------------------ estimates
    def _get(self, key: int, kind: str) -> Any:
        if self.isam is not None and self.isam.valueExists(key):
            if kind == "point2":
                return self.isam.calculateEstimatePoint2(key)
            if kind == "point3":
                return self.isam.calculateEstimatePoint3(key)
            if kind == "vector":
                return self.isam.calculateEstimateVector(key)
            if kind == "pose2":
                return self.isam.calculateEstimatePose2(key)
        return _value_of_kind(self.initial, key, kind)

    def _pose_of(self, k: int) -> FloatArray:
        """Current estimate of keyframe ``k``."""
        if k == self._k:
            return self._kf_pose
        if self.isam is not None:
            return _pose_array(self.isam.calculateEstimatePose2(X(k)))
        return self._kf_poses[k]

    def current(self) -> tuple[FloatArray, FloatArray]:
        """Current pose (3,) and its tangent covariance (3, 3)."""
        pose = gtsam.Pose2(*self._kf_pose).compose(gtsam.Pose2(*self._delta))
        cov = compose_cov(self._delta, self._kf_cov, self._delta_cov)
        return _pose_array(pose), cov

    def _refresh_landmark(self, lm: _Landmark) -> None:
        """Update the cached estimate/covariance of an in-graph landmark from iSAM2."""
        if not lm.in_graph or self.isam is None:
            return
        lm.state = self.handlers[lm.kind].read(lm, self._get)

    # ------------------------------------------------------------------ association
    def _joint_cov(self, lm: _Landmark, k: int) -> tuple[FloatArray, FloatArray, FloatArray] | None:
        """Joint marginal blocks ``(S_kk, S_kl, S_ll)`` of keyframe ``k`` and a landmark.

        From iSAM2's ``jointMarginalCovariance``; the landmark block is over the
        EKF-form state (the handler's keys, in order). None without iSAM2.
        """
        if self.isam is None or not lm.in_graph:
            return None
        if lm.id in self._joint_cache:
            return self._joint_cache[lm.id]
        keys = [X(k), *self.handlers[lm.kind].keys(lm)]
        try:
            full = np.asarray(self.isam.jointMarginalCovariance(keys).fullMatrix())
        except RuntimeError:
            self._joint_cache[lm.id] = None
            return None
        # graph tangent -> EKF-form state (e.g. only the angle of a Pose2 axis)
        idx = np.r_[0:3, 3 + np.asarray(self.handlers[lm.kind].state_index(lm), int)]
        full = full[np.ix_(idx, idx)]
        out = full[:3, :3], full[:3, 3:], full[3:, 3:]
        self._joint_cache[lm.id] = out
        return out

    def _innovation(self, gate_ctx: tuple[int, FloatArray, FloatArray, FloatArray], lid: int,
                    obs: Obs) -> tuple[FloatArray, FloatArray] | None:
        """``(nu, Psi)`` (eq. 19) with the pose-landmark cross-covariance.

        The current pose is ``x = x_k * delta`` (``k`` the last keyframe in iSAM2), so
        in the right tangent ``dx = Ad(delta^-1) dx_k + d_delta``: its covariance and
        cross-covariance with a landmark follow from the joint marginal of
        ``(X(k), landmark)``. Without the cross term the gate is far too wide: a
        landmark initialised from the pose is strongly correlated with it.
        """
        k, pose, delta, delta_cov = gate_ctx
        lm = self._landmarks[lid]
        obs = for_landmark(obs, len(lm.state))
        try:
            z_hat, h_p, h_l = predict(lm.kind, pose, lm.state, obs, self.ceiling)
        except Exception:
            return None
        joint = self._joint_cov(lm, k)
        if joint is None:  # no joint marginal: independent pose and landmark
            _, pose_cov = self.current()
            psi = h_p @ pose_cov @ h_p.T + h_l @ lm.cov @ h_l.T + obs.R
            return residual(obs, z_hat), psi
        s_kk, s_kl, s_ll = joint
        ad = gtsam.Pose2(*delta).inverse().AdjointMap()
        s_xx = ad @ s_kk @ ad.T + delta_cov
        s_xl = ad @ s_kl
        cross = h_p @ s_xl @ h_l.T
        psi = h_p @ s_xx @ h_p.T + cross + cross.T + h_l @ s_ll @ h_l.T + obs.R
        return residual(obs, z_hat), psi

    def _screen(self, obs: list[Obs], pose: FloatArray, pose_cov: FloatArray
                ) -> tuple[dict[str, list[int]], dict[int, dict[int, tuple[float, bool]]]]:
        """Candidates per kind and a cheap vectorised gate for ceiling observations.

        Ceiling landmarks are projected all at once
        (:meth:`~lampsam.backend.ceiling.CeilingModel.project_many`) from their
        cached states; the visible ones that are in the graph are refreshed from
        iSAM2. The screen uses ``S = H_p Sigma_x H_p^T + H_l Sigma_l H_l^T`` (pose
        and landmark marginals, no cross term: wider than eq. 19's true
        covariance, since a landmark is positively correlated with the pose that
        placed it), with ``Sigma_x`` the current pose marginal and ``Sigma_l`` the
        landmark's initialisation covariance (eq. 25 or the triangulation; an
        upper bound of its marginal, and free, where iSAM2's landmark marginals cost
        several ms each). Only ambiguous observations then cost joint marginals
        (:meth:`_mark_ambiguous`, :meth:`_joint_cov`, cached per keyframe). Planar
        landmarks go the per-pair way (joint marginal per pair, as before).

        Returns:
            ``(candidates, screened)`` for :func:`associate`.
        """
        cands: dict[str, list[int]] = {}
        screened: dict[int, dict[int, tuple[float, bool]]] = {}
        by_kind: dict[str, list[_Landmark]] = {}
        for lid, lm in self._landmarks.items():
            if self.ceiling is None or lm.kind == "point2":
                cands.setdefault(lm.kind, []).append(lid)
            else:
                by_kind.setdefault(lm.kind, []).append(lm)
        for kind, lms in by_kind.items():
            pts = np.array([lm.state[:3] for lm in lms])
            vis = self.ceiling.in_view_many(pose, pts)
            visible = [lms[j] for j in np.flatnonzero(vis)]
            for lm in visible:
                self._refresh_landmark(lm)
            if not visible:
                cands[kind] = []
                continue
            pts = np.array([lm.state[:3] for lm in visible])
            m, h_p, h_l, vis = self.ceiling.project_many(pose, pts)
            keep = np.flatnonzero(vis)
            lids = [visible[j].id for j in keep]
            cands[kind] = lids
            if not keep.size or not any(o.kind == kind for o in obs):
                continue
            rel = self._relative_covs()
            cov_l = np.empty((len(keep), 3, 3))
            cov_x = np.empty((len(keep), 3, 3))
            for n, j in enumerate(keep):
                lm = visible[j]
                if lm.cov_rel is not None and lm.last_kf in rel:
                    cov_l[n] = lm.cov_rel
                    cov_x[n] = rel[lm.last_kf]
                else:
                    cov_l[n] = lm.cov[:3, :3]
                    cov_x[n] = pose_cov
            hp, hl = h_p[keep], h_l[keep]
            s_pred = (hp @ cov_x @ np.transpose(hp, (0, 2, 1))
                      + hl @ cov_l @ np.transpose(hl, (0, 2, 1)))
            sc = screen_pairs(obs, kind, lids, m[keep], s_pred, self.config.association,
                              exact=True)
            screened.update(self._mark_ambiguous(obs, sc))
        return cands, screened

    def _relative_covs(self) -> dict[int, FloatArray]:
        """Tangent covariance of the current keyframe relative to each recent keyframe.

        Composes the odometry factors' covariances (eqs. 13-15, with their floor)
        backwards from the current keyframe ``k`` over the last
        :data:`_RELATIVE_GATE_KEYFRAMES` keyframes: ``{j: cov(x_j^-1 x_k)}``. Cached
        for the keyframe (the screen asks once per landmark kind).
        """
        k = self._k
        if self._rel_cache is not None and self._rel_cache[0] == k:
            return self._rel_cache[1]
        out: dict[int, FloatArray] = {k: np.zeros((3, 3))}
        delta = np.zeros(3)
        cov = np.zeros((3, 3))
        for j in range(k - 1, max(k - _RELATIVE_GATE_KEYFRAMES, 0) - 1, -1):
            d_j, c_j = self._odo[j + 1]
            cov = compose_cov(delta, c_j, cov)
            delta = _pose_array(gtsam.Pose2(*d_j).compose(gtsam.Pose2(*delta)))
            out[j] = cov
        self._rel_cache = (k, out)
        return out

    def _mark_ambiguous(self, obs: list[Obs], screened: dict[int, dict[int, tuple[float, bool]]]
                        ) -> dict[int, dict[int, tuple[float, bool]]]:
        """Keep the cheap distance where it decides alone; ask for the joint marginal otherwise.

        Corners: the NCC picks the winner among the gated candidates (paper), so the
        cheap (wider) gate is final; a wrong match that it lets through is bounded by
        the Huber loss on corner factors (``isam2.corner_huber_k``). Lamps: an
        observation with at most one landmark inside the cheap gate is decided by
        it (the true eq.-19 covariance could only reject the match); with two or
        more, the exact distances (iSAM2 joint marginal with the pose-landmark cross
        term, :meth:`_joint_cov`) pick the winner. iSAM2's joint marginals cost
        several ms each on a graph dense with corners (17 ms on the lab run), so
        this keeps them to the few ambiguous lamp observations.
        """
        cfg = self.config.association
        out: dict[int, dict[int, tuple[float, bool]]] = {}
        for i, pairs in screened.items():
            o = obs[i]
            gate = cfg.gate(len(o.z))
            inside = [lid for lid, (d2, _) in pairs.items() if d2 < gate]
            if o.kind == "corner" or len(inside) <= 1:
                out[i] = {lid: (d2, len(o.z) == 2) for lid, (d2, _) in pairs.items()}
            else:
                out[i] = {lid: (d2, False) for lid, (d2, _) in pairs.items()}
        return out

    def _near_known_lamp(self, pose: FloatArray, obs: Obs, lamp_ids: Any) -> bool:
        """Whether a mapped lamp is predicted within ``lamp_min_separation`` of ``obs``.

        Two lamps cannot overlap in the image, so such an observation is of that
        lamp even when its gate rejects it. A lamp's centroid can be off by a few
        tenths of a pixel near the image edge (lens distortion across a large blob),
        several times its nominal sigma; while iSAM2 waits to relinearise a young
        lamp, its exact gate then rejected such sights and the smoothers mapped one
        strip lamp two to four times, every later sight of it becoming ambiguous
        (and costing joint marginals). The observation is dropped instead.
        """
        sep = self.config.association.lamp_min_separation
        ids = [lid for lid in lamp_ids if lid in self._landmarks]
        if self.ceiling is None or not ids or sep <= 0.0:
            return False
        pts = np.array([self._landmarks[lid].state[:3] for lid in ids])
        m, _, _, vis = self.ceiling.project_many(pose, pts)
        d = np.hypot(m[:, 0] - obs.z[0], m[:, 1] - obs.z[1])
        return bool(np.any(vis & (d < sep)))

    def _new_id(self) -> int:
        while self._next_id in self._landmarks:
            self._next_id += 1
        lid = self._next_id
        self._next_id += 1
        return lid

    # ------------------------------------------------------------------ keyframe
    def _is_keyframe(self) -> bool:
        cfg = self.config.isam2
        if cfg.every_frame or self._k == 0:
            # The first frame is always a keyframe: seen from the known start pose it
            # anchors the map's heading. Skipping it (the robot has not moved yet)
            # leaves the map's heading to one frame of odometry, ~0.3 deg on lab,
            # which nothing later can observe (60 s of lab, 10 seeds: 18.4 mm
            # against 6.3 mm with thresholds of 1e-4 that skipped only that frame).
            return True
        return bool(math.hypot(self._delta[0], self._delta[1]) >= cfg.keyframe_distance
                    or abs(self._delta[2]) >= cfg.keyframe_angle)

    def _make_keyframe(self, obs: list[Obs]) -> tuple[int, int]:
        """Add a keyframe with its odometry factor and the frame's observations."""
        pose, pose_cov = self.current()
        gate_ctx = (self._k, pose, self._delta.copy(), self._delta_cov.copy())
        wheel = np.concatenate(self._wheel_since_kf) if self._wheel_since_kf else np.zeros((0, 2))
        w = self.wheel
        delta, cov = accumulate_odometry(wheel[:, 0], wheel[:, 1], w.wheel_base, w.k_r, w.k_l,
                                         self.config.isam2.odometry_floor_var)
        k = self._k + 1
        self._add_value(X(k), gtsam.Pose2(*pose))
        self._add_factor(odometry_factor(X(k - 1), X(k), delta, cov))
        self._k = k
        self._kf_poses.append(pose.copy())
        self._odo.append((np.asarray(delta, float), np.asarray(cov, float)))
        n_matched = n_new = 0
        self._joint_cache = {}
        if obs:
            gating = not self.config.association.use_known_ids or any(
                o.landmark_id is None for o in obs)
            cands, screened = self._screen(obs, pose, pose_cov) if gating else ({}, {})
            patches = {lid: self._landmarks[lid].patch for lid in cands.get("corner", ())}
            assignments = associate(
                obs, cands, lambda lid, o: self._innovation(gate_ctx, lid, o),
                self.config.association, lambda i: i in self._landmarks, patches, screened)
            matches: list[tuple[_Landmark, Obs]] = []
            for a in assignments:
                o = obs[a.obs_index]
                if a.status == "matched" and a.landmark_id in self._landmarks:
                    lm = self._landmarks[a.landmark_id]
                    if lm.kind != o.kind:
                        continue
                    matches.append((lm, o))
                elif a.status == "new":
                    if o.kind == "lamp" and a.landmark_id is None and self._near_known_lamp(
                            pose, o, cands.get("lamp", ())):
                        continue
                    n_new += self._start_landmark(pose, pose_cov, k, o, a.landmark_id)
            matches, self._entries_left = corner_budget(
                matches, self.config.association.max_corner_updates)
            for lm, o in matches:
                self._observe(lm, k, o)
                n_matched += 1
        if k % 10 == 0:
            self._forget_pending(k)
        # The keyframe's own estimate: the prediction until iSAM2 updates it.
        self._kf_pose = pose
        self._kf_cov = pose_cov
        self._delta = np.zeros(3)
        self._delta_cov = np.zeros((3, 3))
        self._wheel_since_kf = []
        for handler in {id(h): h for h in self.handlers.values()}.values():
            if hasattr(handler, "flush"):
                for f in handler.flush(self.robust, self._pose_of):
                    self._add_factor(f)
        self._flush()
        return n_matched, n_new

    def _start_landmark(self, pose: FloatArray, pose_cov: FloatArray, k: int, obs: Obs,
                        lid: int | None) -> int:
        try:
            state, g_pose, g_z, cov_z = initialize(pose, obs, self.config.association,
                                                   self.ceiling)
        except Exception as exc:
            log.debug("cannot initialise a landmark: %s", exc)
            return 0
        cov_meas = g_z @ cov_z @ g_z.T
        cov = g_pose @ pose_cov @ g_pose.T + cov_meas
        if lid is None:
            lid = self._new_id()
        else:
            self._next_id = max(self._next_id, lid + 1)
        oriented = obs.kind == "lamp" and obs.has_axis
        lm = _Landmark(lid, obs.kind, False, 1, state, cov, [(k, obs)], obs.patch, oriented, k,
                       cov_meas[:3, :3])
        self._landmarks[lid] = lm
        if lm.kind == "lamp":
            lm.sights.append((k, obs))
        if lm.kind != "corner" or self.ceiling is None:
            self._enter_graph(lm)
        return 1

    def _try_triangulate(self, lm: _Landmark) -> bool:
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
        chi2 = 0.0
        for pose, m, c in zip(poses, ms, covs, strict=True):
            try:
                m_hat, _, _ = self.ceiling.predict(pose, point, with_axis=False)
            except Exception:
                return False
            r = m - m_hat
            chi2 += float(r @ np.linalg.solve(c, r))
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
        point, cov = self.ceiling.triangulate(poses, ms, covs)
        return poses, ms, covs, point, cov, float(point[2] - self.ceiling.body_t_camera[2])

    def _placed_cov(self, cov_rel: FloatArray) -> FloatArray:
        """A triangulated point's covariance (3, 3) plus the current keyframe's x, y variance."""
        return cov_rel + np.diag([*np.diag(self._kf_cov)[:2], 0.0])

    def _forget_pending(self, k: int) -> None:
        """Forget pending corners not seen for ``corner_pending_keyframes`` keyframes."""
        horizon = self.config.isam2.corner_pending_keyframes
        stale = [lid for lid, lm in self._landmarks.items()
                 if not lm.in_graph and lm.kind == "corner" and k - lm.last_kf > horizon]
        for lid in stale:
            del self._landmarks[lid]
        self.n_pruned += len(stale)
        if stale:
            self.pruned["pending_stale"] = self.pruned.get("pending_stale", 0) + len(stale)

    def _observe(self, lm: _Landmark, k: int, obs: Obs) -> None:
        lm.n_obs += 1
        lm.last_kf = k
        if lm.in_graph:
            for f in self.handlers[lm.kind].factors(lm, k, obs, self._robust_for(lm.kind)):
                self._add_factor(f, lm.id)
            if lm.kind == "lamp" and self.ceiling is not None:
                self._tighten_lamp_gate(lm, k, obs)
            return
        lm.pending.append((k, obs))
        if lm.kind == "corner" and self.ceiling is not None:
            if self._entries_left > 0 and self._try_triangulate(lm):
                self._enter_graph(lm)
                self._entries_left -= 1
        elif lm.n_obs >= self.config.association.min_observations:
            self._enter_graph(lm)

    def _tighten_lamp_gate(self, lm: _Landmark, k: int, obs: Obs) -> None:
        """Replace a lamp's first-sight gating covariance by a triangulated one.

        A lamp enters the graph at its first sight with eq. 25's covariance (long
        along the viewing ray, from the height prior), which keeps its screen wide
        and sends it to the costly joint marginals. Its first
        :data:`_LAMP_SIGHTS` sights are triangulated like a corner's
        (:meth:`~lampsam.backend.ceiling.CeilingModel.triangulate`); once the
        height is determined to ``corner_init_max_rel_sigma``, the triangulation
        covariance becomes the lamp's relative gating covariance.
        """
        if len(lm.sights) >= _LAMP_SIGHTS:
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
            lm.cov = self._placed_cov(cov)

    def _enter_graph(self, lm: _Landmark) -> None:
        """Insert a landmark's variables, priors and its buffered factors."""
        handler = self.handlers.get(lm.kind)
        if handler is None:
            raise EstimationError(f"no graph handler for landmark kind {lm.kind!r}")
        handler.insert(lm, self._new_values_and_initial())
        handler.priors(lm, _Adder(self), self._pose_of, self.config)
        for k, o in lm.pending:
            for f in handler.factors(lm, k, o, self._robust_for(lm.kind)):
                self._add_factor(f, lm.id)
        lm.pending = []
        lm.in_graph = True

    def _new_values_and_initial(self) -> Any:
        return _ValuesPair(self)

    # ------------------------------------------------------------------ pruning
    def _prune_once_seen(self) -> list[int]:
        """Landmarks with fewer than ``min_observations`` observations (left out of the map).

        Their variables stay in the graph (a range-bearing sight, or a ceiling sight
        with the height prior, determines them), but they are not reported.
        """
        cfg = self.config.association
        drop = [lid for lid, lm in self._landmarks.items() if lm.n_obs < cfg.min_observations]
        self.n_pruned += len(drop)
        if drop:
            self.pruned["seen_too_few"] = self.pruned.get("seen_too_few", 0) + len(drop)
        log_pruned(self.n_pruned, self.pruned, cfg.min_observations)
        return drop

    # ------------------------------------------------------------------ interface
    def step(self, t: float, wheel: FloatArray, frame: Frame | None) -> StepEstimate:
        """See :meth:`SlamBackend.step`. Raises EstimationError on NaN odometry or time reversal."""
        t0 = time.perf_counter()
        if t < self._last_t:
            raise EstimationError(f"t={t:.3f} s: time goes backwards (previous {self._last_t:.3f})")
        self._last_t = t
        wheel = check_wheel(t, wheel)
        if len(wheel):
            w = self.wheel
            d, c = accumulate_odometry(wheel[:, 0], wheel[:, 1], w.wheel_base, w.k_r, w.k_l,
                                       _STEP_FLOOR)
            self._delta_cov = compose_cov(d, self._delta_cov, c)
            self._delta = _pose_array(gtsam.Pose2(*self._delta).compose(gtsam.Pose2(*d)))
            self._wheel_since_kf.append(wheel)
        n_matched = n_new = 0
        is_kf = False
        if frame is not None:
            obs = observations_from_frame(frame, self.config.features, self.config.noise)
            if obs and self._is_keyframe():
                n_matched, n_new = self._make_keyframe(obs)
                is_kf = True
        pose, cov = self.current()
        dt = time.perf_counter() - t0
        self._times.append(t)
        self._step_kf.append(self._k)
        self._step_delta.append(self._delta.copy())
        self._step_delta_cov.append(self._delta_cov.copy())
        self._step_online_pose.append(pose)
        self._step_online_cov.append(cov)
        self._step_times.append(dt)
        self._keyframes.append(is_kf)
        return StepEstimate(t, pose, tangent_to_coords_cov(pose, cov), is_kf, n_matched, n_new, dt)

    def _final_values(self) -> tuple[gtsam.Values, Any]:
        """Final estimate and a marginal-covariance function (subclasses)."""
        raise NotImplementedError

    def finish(self, status: str = "ok") -> SlamResult:
        """Final estimate; every step's pose = its keyframe's final estimate + odometry."""
        pruned = set(self._prune_once_seen())
        t0 = time.perf_counter()
        try:
            values, marginal = self._final_values()
        except (RuntimeError, EstimationError) as exc:  # a broken graph: keep the online poses
            log.error("final optimisation failed (%s): keeping the online estimates", exc)
            values, marginal = self.initial, None
            status = status if status.startswith("failed") else f"failed: {exc}"
        final_time = time.perf_counter() - t0
        n_kf = self._k + 1
        kf_pose = np.array([_pose_array(values.atPose2(X(k))) if values.exists(X(k))
                            else self._kf_poses[k] for k in range(n_kf)])
        kf_cov = np.full((n_kf, 3, 3), np.nan)
        if marginal is not None and self.config.isam2.final_covariances:
            for k in range(n_kf):
                try:
                    kf_cov[k] = marginal(X(k))
                except (RuntimeError, IndexError):
                    continue
        n = len(self._times)
        poses = np.zeros((n, 3))
        covs = np.zeros((n, 3, 3))
        for i in range(n):
            k = self._step_kf[i]
            delta, cov_delta = self._step_delta[i], self._step_delta_cov[i]
            if k + 1 < n_kf:  # between two keyframes: condition the odometry on both
                delta, cov_delta = odometry_bridge(delta, cov_delta, *self._odo[k + 1],
                                                   kf_pose[k], kf_pose[k + 1])
            p = _pose_array(gtsam.Pose2(*kf_pose[k]).compose(gtsam.Pose2(*delta)))
            c = compose_cov(delta, kf_cov[k], cov_delta)
            poses[i] = p
            covs[i] = tangent_to_coords_cov(p, c)

        lms: list[LandmarkEstimate] = []
        for lm in self._landmarks.values():
            if not lm.in_graph or lm.id in pruned:
                continue
            handler = self.handlers[lm.kind]
            if not all(values.exists(key) for key in handler.keys(lm)):
                continue
            state = handler.read(lm, lambda key, kind: _value_of_kind(values, key, kind))
            cov = np.full((len(state), len(state)), np.nan)
            if marginal is not None:
                try:
                    cov = handler.marginal(lm, marginal)
                except (RuntimeError, IndexError):
                    pass
            lms.append(landmark_estimate(lm.id, lm.kind, state, cov, lm.n_obs, self.ceiling))
        return SlamResult(
            backend=self.name,
            times=np.asarray(self._times, float),
            poses=poses,
            pose_covs=covs,
            landmarks=lms,
            step_times_s=np.asarray(self._step_times, float),
            keyframes=np.asarray(self._keyframes, bool),
            status=status,
            final_time_s=final_time,
            n_pruned=self.n_pruned,
            pruned=dict(self.pruned),
            extra={"update_median_ms": float(np.median(self.update_times) * 1e3)
                   if self.update_times else float("nan"),
                   "update_p95_ms": float(np.percentile(self.update_times, 95) * 1e3)
                   if self.update_times else float("nan"),
                   "estimate_median_ms": float(np.median(self.estimate_times) * 1e3)
                   if self.estimate_times else float("nan")},
        )


class Isam2Slam(GraphSlam):
    """Online iSAM2 backend: one ``update()`` per keyframe."""

    name = "isam2"

    def __init__(self, wheel: WheelParams, config: SlamConfig, start_pose: FloatArray,
                 ceiling: Any = None, ceiling_handler: Any = None) -> None:
        super().__init__(wheel, config, start_pose, ceiling, ceiling_handler, online=True)

    def _final_values(self) -> tuple[gtsam.Values, Any]:
        assert self.isam is not None
        return self.isam.calculateEstimate(), self.isam.marginalCovariance


class BatchSlam(GraphSlam):
    """Offline batch LM over the whole run (optionally started from iSAM2's estimate)."""

    name = "batch"

    def __init__(self, wheel: WheelParams, config: SlamConfig, start_pose: FloatArray,
                 ceiling: Any = None, ceiling_handler: Any = None) -> None:
        if config.batch.init not in ("isam2", "odometry"):
            raise EstimationError(f"batch.init must be 'isam2' or 'odometry', got {config.batch.init!r}")
        super().__init__(wheel, config, start_pose, ceiling, ceiling_handler,
                         online=config.batch.init == "isam2")

    def _final_values(self) -> tuple[gtsam.Values, Any]:
        start = self.isam.calculateEstimate() if self.isam is not None else self.initial
        try:
            opt = gtsam.LevenbergMarquardtOptimizer(self.graph, start, self.config.batch.to_gtsam())
            result = opt.optimize()
        except RuntimeError as exc:
            if self.isam is None:
                raise EstimationError(f"batch LM failed: {exc}") from exc
            # e.g. a trial step put a landmark below the camera: keep the online smoother's
            log.warning("batch LM failed (%s: %s): keeping the iSAM2 estimate",
                        type(exc).__name__, str(exc).strip()[:120])
            return start, self.isam.marginalCovariance
        log.info("batch LM: error %.4g -> %.4g in %d iterations",
                 self.graph.error(start), self.graph.error(result), opt.iterations())
        try:
            marginals = gtsam.Marginals(self.graph, result)
            return result, marginals.marginalCovariance
        except RuntimeError as exc:
            log.warning("batch marginals unavailable: %s", exc)
            return result, None


class _ValuesPair:
    """Insert into both the pending-update Values and the all-initial Values."""

    def __init__(self, owner: GraphSlam) -> None:
        self.owner = owner

    def insert(self, key: int, value: Any) -> None:
        self.owner._add_value(key, value)


class _Adder:
    """``add(factor)`` into both the pending-update graph and the full graph."""

    def __init__(self, owner: GraphSlam) -> None:
        self.owner = owner

    def add(self, factor: gtsam.NonlinearFactor) -> None:
        self.owner._add_factor(factor)


def _value_of_kind(values: gtsam.Values, key: int, kind: str) -> Any:
    """The value of ``key`` read as ``kind`` (``"point2"``, ``"point3"``, ``"vector"``, ``"pose2"``)."""
    getters = {"point2": values.atPoint2, "point3": values.atPoint3,
               "vector": values.atVector, "pose2": values.atPose2}
    if kind not in getters:
        raise EstimationError(f"unknown graph value kind {kind!r}")
    return getters[kind](key)


def _value_at(values: gtsam.Values, key: int) -> Any:
    """The value of ``key`` in its own type (Pose2, Point2/3 or Vector)."""
    sym = gtsam.Symbol(key)
    ch = chr(sym.chr())
    if ch in ("x", "a"):
        return values.atPose2(key)
    for getter in (values.atPoint3, values.atPoint2, values.atVector):
        try:
            return getter(key)
        except RuntimeError:
            continue
    raise EstimationError(f"cannot read graph value {gtsam.DefaultKeyFormatter(key)}")


def _pose_array(p: gtsam.Pose2) -> FloatArray:
    return np.array([p.x(), p.y(), wrap_angle(p.theta())])
