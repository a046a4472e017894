"""Stereo two-point relative pose estimators (paper 3): raw, EKF, iSAM2, batch.

One small interface: every estimator is fed the frames of a
:class:`~lampsam.datasets.stereo_types.StereoRun` in time order through
``step(k, run)`` and gives a :class:`StereoStep` (pose, covariance, status); at
the end :func:`estimate` packs them into a :class:`StereoResult`.

* ``raw``: per-frame triangulation of the two points (inverse of eq. 2), closed
  form two-point alignment, then Gauss-Newton on the four coordinates (eq. 5).
* ``ekf``: the paper's EKF, eqs. 6-12, with motion eq. 4 and measurement eq. 5.
* ``isam2``: the same factors (``factors.stereo``) in iSAM2, one update per
  frame; its per-frame output is the online (filtered) estimate of the newest pose.
* ``batch``: Levenberg-Marquardt over the whole run (the smoother).

State: ``target_T_camera = (x, y, theta)``, the rig pose in the target frame
(docs/stereo.md). Covariances are over the plain coordinates ``(x, y, theta)``;
the graph estimators convert GTSAM's tangent marginals with
``coords_D_tangent = blockdiag(R(theta), 1)``.

Every output is finite: frames before the first usable measurement have status
``uninitialised`` and a zero pose with ``valid = False``; a frame whose
measurement cannot be used keeps the prediction and says why in ``status``.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass

import gtsam
import numpy as np
from gtsam.symbol_shorthand import X

from lampsam.angles import wrap_angle
from lampsam.arrays import BoolArray, FloatArray
from lampsam.datasets.stereo_types import StereoRig, StereoRun
from lampsam.errors import EstimationError
from lampsam.factors.geometry import coords_D_tangent
from lampsam.factors.stereo import (
    camera_point,
    motion_factor,
    motion_model,
    pose_vector,
    triangulate_point,
    two_point_factor,
    two_point_measurement,
)
from lampsam.observe import emit

log = logging.getLogger(__name__)

ESTIMATORS = ("raw", "ekf", "isam2", "batch")

# Per-frame status values.
OK = "ok"  #: measurement used
NOT_SEEN = "not_seen"  #: no measurement this frame (target not imaged); prediction only
UNINITIALISED = "uninitialised"  #: no usable measurement yet; pose is zeros, valid False
BAD_DISPARITY = "bad_disparity"  #: raw: zero or negative disparity of a point
COLLINEAR = "collinear"  #: raw: both points on nearly the same camera ray
BEHIND = "behind_camera"  #: a point (estimated or predicted) at depth <= min_depth
NONFINITE = "nonfinite"  #: measurement holds NaN/inf
GATED = "gated"  #: innovation failed the chi-square gate; update skipped
FAILED = "failed"  #: raw: Gauss-Newton did not converge / ill-conditioned


@dataclass(frozen=True)
class StereoEstimatorConfig:
    """Settings shared by the four estimators.

    Attributes:
        min_disparity_px: raw triangulation needs ``x_r - x_l`` above this, px (default 0.5).
        min_separation_px: raw flags ``collinear`` when the two points' mean
            coordinates ``(x_l + x_r) / 2`` (their rays from the rig centre) are
            closer than this, px: the points are nearly in line with the camera,
            cannot be told apart, and the heading rests on their depth difference (default 1).
        min_depth: a point nearer than this (estimated or predicted depth) is
            treated as behind the camera, m (default 0.05).
        gn_iterations: Gauss-Newton steps of the raw solver (default 6).
        max_condition: raw fails when ``H^T H`` is worse conditioned than this (default 1e10).
        sigma_init: prior standard deviations ``(x, y, theta)`` (m, m, rad) put on
            the first raw fix, for the EKF and both smoothers alike (default (1.0, 1.0, 0.3)).
        gate_chi2: innovation gate (4 dof; default 25, p ~ 5e-5); 0 disables it.
        isam2_relinearize_threshold: iSAM2 relinearisation threshold (default 0.01).
        isam2_extra_updates: extra ``update()`` calls per frame (each one more
            Gauss-Newton iteration with relinearisation; default 2).
        lm_max_iterations: batch LM iterations (default 100).
    """

    min_disparity_px: float = 0.5
    min_separation_px: float = 1.0
    min_depth: float = 0.05
    gn_iterations: int = 6
    max_condition: float = 1e10
    sigma_init: tuple[float, float, float] = (1.0, 1.0, 0.3)
    gate_chi2: float = 25.0
    isam2_relinearize_threshold: float = 0.01
    isam2_extra_updates: int = 2
    lm_max_iterations: int = 100


@dataclass(frozen=True)
class StereoStep:
    """One estimator step.

    Attributes:
        pose: (3,) ``(x, y, theta)`` m, rad (zeros when not valid).
        cov: (3, 3) covariance over ``(x, y, theta)``.
        status: one of the module's status strings.
        valid: an estimate exists for this frame.
    """

    pose: FloatArray
    cov: FloatArray
    status: str
    valid: bool


@dataclass(frozen=True)
class StereoResult:
    """A finished run of one estimator.

    Attributes:
        estimator: ``raw``, ``ekf``, ``isam2`` or ``batch``.
        t: (N,) frame times, s.
        poses: (N, 3) estimates ``(x, y, theta)`` (finite; zeros where not valid).
        covariances: (N, 3, 3) over ``(x, y, theta)``.
        status: (N,) status strings.
        valid: (N,) bool.
        step_time_s: (N,) wall time per frame, s (batch: total / N).
    """

    estimator: str
    t: FloatArray
    poses: FloatArray
    covariances: FloatArray
    status: tuple[str, ...]
    valid: BoolArray
    step_time_s: FloatArray

    def status_counts(self) -> dict[str, int]:
        """How many frames have each status."""
        out: dict[str, int] = {}
        for s in self.status:
            out[s] = out.get(s, 0) + 1
        return out


_INVALID_COV = np.eye(3) * 1e6


def _invalid(status: str) -> StereoStep:
    """A step without an estimate: zero pose, the placeholder covariance, ``status``."""
    return StereoStep(np.zeros(3), _INVALID_COV.copy(), status, False)


def measurement_cov(run: StereoRun) -> FloatArray:
    """(4, 4) measurement covariance, px^2: quantisation 1/12 + detection noise."""
    return np.eye(4) * run.noise.var_measurement_px2


def motion_tangent_cov(run: StereoRun, dt: float) -> FloatArray:
    """(3, 3) motion noise of one step in the tangent (along, lateral, heading)."""
    n = run.noise
    return np.diag([(n.sigma_v * dt) ** 2, (n.sigma_lateral * dt) ** 2, (n.sigma_omega * dt) ** 2])


def step_input(run: StereoRun, k: int) -> tuple[float, float, float]:
    """``(dt, v_dt, omega_dt)`` of the step ending at frame ``k`` (zeros for k = 0)."""
    if k == 0:
        return 0.0, 0.0, 0.0
    dt = float(run.t[k] - run.t[k - 1])
    return dt, float(run.v[k]) * dt, float(run.omega[k]) * dt


def measurement_status(z: FloatArray, seen: bool) -> str:
    """``ok``, ``not_seen`` or ``nonfinite`` for a raw measurement row."""
    if not seen:
        return NOT_SEEN
    if not np.all(np.isfinite(z)):
        return NONFINITE
    return OK


def predicted_depths_ok(pose: FloatArray, points: FloatArray, min_depth: float) -> bool:
    """True when both target points are at least ``min_depth`` in front of the rig."""
    return all(camera_point(pose, p)[0][0] > min_depth for p in points)


# --------------------------------------------------------------------------- raw
def triangulate_two_points(
    z: FloatArray,
    target_t_points: FloatArray,
    rig: StereoRig,
    var_px2: float,
    cfg: StereoEstimatorConfig,
) -> tuple[FloatArray, FloatArray, str]:
    """Per-frame pose from the four coordinates alone.

    Triangulates each point (inverse of eq. 2), aligns the two points with the
    target (closed form: heading from the direction between them, translation
    from their mean), then refines with Gauss-Newton on eq. 5.

    Args:
        z: (4,) ``[xl1, xr1, xl2, xr2]`` px.
        target_t_points: (2, 2) the target points in the target frame, m.
        rig: baseline and ``f/p``.
        var_px2: variance of one image coordinate, px^2 (for the covariance).
        cfg: thresholds.

    Returns:
        ``pose`` (3,), ``cov`` (3, 3) over ``(x, y, theta)`` and a status
        (``ok``, ``nonfinite``, ``bad_disparity``, ``collinear``, ``behind_camera``,
        ``failed``); pose zeros and a large covariance unless ``ok``.
    """
    bad = (np.zeros(3), _INVALID_COV.copy())
    if not np.all(np.isfinite(z)):
        return *bad, NONFINITE
    b, f_px = rig.baseline, rig.f_px
    if min(z[1] - z[0], z[3] - z[2]) <= cfg.min_disparity_px:
        return *bad, BAD_DISPARITY
    if abs((z[0] + z[1]) - (z[2] + z[3])) < 2.0 * cfg.min_separation_px:
        return *bad, COLLINEAR
    pts = np.asarray(target_t_points, dtype=float)
    c1 = triangulate_point(z[0], z[1], b, f_px)
    c2 = triangulate_point(z[2], z[3], b, f_px)
    dc, do = c2 - c1, pts[1] - pts[0]
    theta = math.atan2(do[1], do[0]) - math.atan2(dc[1], dc[0])
    c, s = math.cos(theta), math.sin(theta)
    rot = np.array([[c, -s], [s, c]])
    t = pts.mean(axis=0) - rot @ (0.5 * (c1 + c2))
    pose = gtsam.Pose2(t[0], t[1], theta)
    info = None
    for _ in range(cfg.gn_iterations):
        if not predicted_depths_ok(pose_vector(pose), pts, cfg.min_depth):
            return *bad, BEHIND
        h, h_D = two_point_measurement(pose, pts, b, f_px)
        info = h_D.T @ h_D
        if np.linalg.cond(info) > cfg.max_condition:
            return *bad, FAILED
        delta = np.linalg.solve(info, -h_D.T @ (h - z))
        pose = pose.retract(delta)
        if np.linalg.norm(delta) < 1e-10:
            break
    vec = np.array([pose.x(), pose.y(), pose.theta()])
    if info is None or not np.all(np.isfinite(vec)):
        return *bad, FAILED
    if not predicted_depths_ok(vec, pts, cfg.min_depth):
        return *bad, BEHIND
    _, h_D = two_point_measurement(vec, pts, b, f_px)
    cov_tangent = np.linalg.inv(h_D.T @ h_D) * var_px2
    jac = coords_D_tangent(vec[2])
    return vec, jac @ cov_tangent @ jac.T, OK


def raw_fix(
    run: StereoRun, k: int, cfg: StereoEstimatorConfig
) -> tuple[FloatArray, FloatArray, str]:
    """:func:`triangulate_two_points` on frame ``k`` of a run."""
    return triangulate_two_points(run.z[k], run.target_t_points, run.rig,
                                  run.noise.var_measurement_px2, cfg)


def _start_pose(run: StereoRun, k: int, cfg: StereoEstimatorConfig, status: str) -> FloatArray | None:
    """(3,) raw fix of frame ``k`` to start a recursive estimator, or None if it has none.

    Args:
        run: the run; k: frame index; cfg: solver thresholds.
        status: the measurement status of frame ``k`` (:func:`measurement_status`).
    """
    if status != OK:
        return None
    pose, _, raw_status = raw_fix(run, k, cfg)
    return pose if raw_status == OK else None


class RawEstimator:
    """Per-frame triangulation; no memory between frames."""

    def __init__(self, run: StereoRun, cfg: StereoEstimatorConfig) -> None:
        self.run, self.cfg = run, cfg

    def step(self, k: int) -> StereoStep:
        """Estimate frame ``k`` from its measurement alone."""
        status = measurement_status(self.run.z[k], bool(self.run.seen[k]))
        if status != OK:
            return _invalid(status)
        pose, cov, status = raw_fix(self.run, k, self.cfg)
        return StereoStep(pose, cov, status, status == OK)


# --------------------------------------------------------------------------- EKF
class StereoEkf:
    """The paper's EKF (eqs. 6-12) over ``(x, y, theta)``.

    Initialised at the first frame with a valid raw fix (mean = that fix,
    covariance ``diag(sigma_init^2)``), then updated with that frame's
    measurement like every later one.
    """

    def __init__(self, run: StereoRun, cfg: StereoEstimatorConfig) -> None:
        self.run, self.cfg = run, cfg
        self.x: FloatArray | None = None
        self.P: FloatArray | None = None
        self.cov_meas = measurement_cov(run)  # the paper's R, px^2

    def predict(self, dt: float, v_dt: float, omega_dt: float) -> None:
        """Eqs. 6-8: ``x = f(x)``, ``P = A P A^T + Q`` with ``Q`` from the odometry noise."""
        assert self.x is not None and self.P is not None
        jac = coords_D_tangent(self.x[2])
        cov_motion = jac @ motion_tangent_cov(self.run, dt) @ jac.T  # the paper's Q
        self.x, a, _ = motion_model(self.x, v_dt, omega_dt)
        self.P = a @ self.P @ a.T + cov_motion

    def update(self, z: FloatArray) -> str:
        """Eqs. 9-12; returns the status (the update is skipped unless ``ok``)."""
        assert self.x is not None and self.P is not None
        pts = self.run.target_t_points
        if not predicted_depths_ok(self.x, pts, self.cfg.min_depth):
            return BEHIND
        rig = self.run.rig
        h, h_D_tangent = two_point_measurement(self.x, pts, rig.baseline, rig.f_px)
        H = h_D_tangent @ coords_D_tangent(self.x[2]).T  # eq. 9, coordinates
        innov = z - h
        S = H @ self.P @ H.T + self.cov_meas
        if self.cfg.gate_chi2 > 0 and float(innov @ np.linalg.solve(S, innov)) > self.cfg.gate_chi2:
            return GATED
        K = np.linalg.solve(S, H @ self.P).T  # eq. 10 (S and P symmetric)
        x = self.x + K @ innov  # eq. 11
        x[2] = wrap_angle(x[2])
        P = self.P - K @ H @ self.P  # eq. 12
        self.x, self.P = x, 0.5 * (P + P.T)
        return OK

    def step(self, k: int) -> StereoStep:
        """Predict with the odometry of step ``k``, then update with frame ``k``."""
        z, status = self.run.z[k], measurement_status(self.run.z[k], bool(self.run.seen[k]))
        if self.x is None:
            pose = _start_pose(self.run, k, self.cfg, status)
            if pose is None:
                return _invalid(UNINITIALISED)
            self.x, self.P = pose, np.diag(np.square(self.cfg.sigma_init))
        else:
            self.predict(*step_input(self.run, k))
        if status == OK:
            status = self.update(z)
        assert self.x is not None and self.P is not None
        return StereoStep(self.x.copy(), self.P.copy(), status, True)


# --------------------------------------------------------------------------- graphs
def _noise(cov: FloatArray) -> gtsam.noiseModel.Base:
    """Gaussian noise model of a covariance matrix."""
    return gtsam.noiseModel.Gaussian.Covariance(np.asarray(cov, dtype=float))


def _coords_cov(pose: FloatArray, cov_tangent: FloatArray) -> FloatArray:
    """(3, 3) covariance in plain coordinates from one in GTSAM's right tangent at ``pose``."""
    jac = coords_D_tangent(pose[2])
    return jac @ cov_tangent @ jac.T


class StereoIsam2:
    """iSAM2 over ``X(k)``: prior at the first fix, eq. 4 between factors, eq. 5 factors.

    The same gate as the EKF, evaluated with the prediction from the previous
    marginal. Output per frame: the estimate and marginal of the newest pose.
    """

    def __init__(self, run: StereoRun, cfg: StereoEstimatorConfig) -> None:
        self.run, self.cfg = run, cfg
        params = gtsam.ISAM2Params()
        params.setRelinearizeThreshold(cfg.isam2_relinearize_threshold)
        params.relinearizeSkip = 1
        self.isam = gtsam.ISAM2(params)
        self.k_prev: int | None = None
        self.x_prev: FloatArray | None = None
        self.P_prev: FloatArray | None = None
        self.meas_noise = _noise(measurement_cov(run))

    def _measurement_factor(self, k: int) -> gtsam.CustomFactor:
        """The two-point measurement factor (eq. 5) of frame ``k`` on ``X(k)``."""
        rig = self.run.rig
        return two_point_factor(
            X(k), self.run.z[k], self.run.target_t_points, rig.baseline, rig.f_px, self.meas_noise
        )

    def step(self, k: int) -> StereoStep:
        """Add frame ``k`` (pose, motion factor, measurement factor) and update."""
        z, status = self.run.z[k], measurement_status(self.run.z[k], bool(self.run.seen[k]))
        graph = gtsam.NonlinearFactorGraph()
        values = gtsam.Values()
        if self.k_prev is None:
            pose = _start_pose(self.run, k, self.cfg, status)
            if pose is None:
                return _invalid(UNINITIALISED)
            p0 = gtsam.Pose2(*pose)
            graph.add(gtsam.PriorFactorPose2(X(k), p0, gtsam.noiseModel.Diagonal.Sigmas(
                np.asarray(self.cfg.sigma_init, dtype=float))))
            values.insert(X(k), p0)
            x_pred = pose
            p_pred = np.diag(np.square(self.cfg.sigma_init))
        else:
            assert self.x_prev is not None and self.P_prev is not None
            dt, v_dt, omega_dt = step_input(self.run, k)
            q_t = motion_tangent_cov(self.run, dt)
            graph.add(motion_factor(X(self.k_prev), X(k), v_dt, omega_dt, _noise(q_t)))
            x_pred, a, _ = motion_model(self.x_prev, v_dt, omega_dt)
            p_pred = a @ self.P_prev @ a.T + _coords_cov(self.x_prev, q_t)
            values.insert(X(k), gtsam.Pose2(*x_pred))
        if status == OK:
            status = self._check(z, x_pred, p_pred)
            if status == OK:
                graph.add(self._measurement_factor(k))
        self.isam.update(graph, values)
        for _ in range(self.cfg.isam2_extra_updates):
            self.isam.update()
        pose = pose_vector(self.isam.calculateEstimatePose2(X(k)))
        cov = _coords_cov(pose, self.isam.marginalCovariance(X(k)))
        self.k_prev, self.x_prev, self.P_prev = k, pose, cov
        return StereoStep(pose, cov, status, True)

    def _check(self, z: FloatArray, x_pred: FloatArray, p_pred: FloatArray) -> str:
        """Depth check and chi-square gate on the predicted measurement."""
        pts, rig = self.run.target_t_points, self.run.rig
        if not predicted_depths_ok(x_pred, pts, self.cfg.min_depth):
            return BEHIND
        if self.cfg.gate_chi2 <= 0:
            return OK
        h, h_D_t = two_point_measurement(x_pred, pts, rig.baseline, rig.f_px)
        H = h_D_t @ coords_D_tangent(x_pred[2]).T
        S = H @ p_pred @ H.T + measurement_cov(self.run)
        innov = z - h
        return GATED if float(innov @ np.linalg.solve(S, innov)) > self.cfg.gate_chi2 else OK


def batch_smoother(run: StereoRun, cfg: StereoEstimatorConfig) -> list[StereoStep]:
    """Levenberg-Marquardt over the whole run (the smoother).

    Starts at the first frame with a valid raw fix (same prior as the EKF),
    initialised by chaining the odometry from it. Measurements whose depth check
    fails at the initial guess are left out (``behind_camera``); after the first
    solve, measurements with a whitened residual above ``gate_chi2`` are removed
    (``gated``) and LM runs once more.

    Returns:
        One :class:`StereoStep` per frame (marginals from ``gtsam.Marginals``).
    """
    n = len(run)
    steps: list[StereoStep] = [_invalid(UNINITIALISED) for _ in range(n)]
    k0, pose0 = None, None
    for k in range(n):
        if measurement_status(run.z[k], bool(run.seen[k])) == OK:
            pose, _, st = raw_fix(run, k, cfg)
            if st == OK:
                k0, pose0 = k, pose
                break
    if k0 is None or pose0 is None:
        return steps
    graph = gtsam.NonlinearFactorGraph()
    values = gtsam.Values()
    graph.add(gtsam.PriorFactorPose2(X(k0), gtsam.Pose2(*pose0), gtsam.noiseModel.Diagonal.Sigmas(
        np.asarray(cfg.sigma_init, dtype=float))))
    x = pose0
    values.insert(X(k0), gtsam.Pose2(*x))
    status = ["" for _ in range(n)]
    meas_noise = _noise(measurement_cov(run))
    meas_index: dict[int, int] = {}
    for k in range(k0, n):
        if k > k0:
            dt, v_dt, omega_dt = step_input(run, k)
            graph.add(motion_factor(X(k - 1), X(k), v_dt, omega_dt,
                                    _noise(motion_tangent_cov(run, dt))))
            x, _, _ = motion_model(x, v_dt, omega_dt)
            values.insert(X(k), gtsam.Pose2(*x))
        st = measurement_status(run.z[k], bool(run.seen[k]))
        if st == OK and not predicted_depths_ok(x, run.target_t_points, cfg.min_depth):
            st = BEHIND
        if st == OK:
            meas_index[k] = graph.size()
            graph.add(two_point_factor(X(k), run.z[k], run.target_t_points, run.rig.baseline,
                                       run.rig.f_px, meas_noise))
        status[k] = st
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(cfg.lm_max_iterations)
    result = gtsam.LevenbergMarquardtOptimizer(graph, values, params).optimize()
    if cfg.gate_chi2 > 0:
        gated = [k for k, i in meas_index.items()
                 if 2.0 * graph.at(i).error(result) > cfg.gate_chi2]
        if gated:
            for k in gated:
                graph.remove(meas_index[k])
                status[k] = GATED
            log.info("batch: %d measurements gated, re-solving", len(gated))
            result = gtsam.LevenbergMarquardtOptimizer(graph, result, params).optimize()
    try:
        marginals = gtsam.Marginals(graph, result)
    except RuntimeError as exc:
        raise EstimationError(f"batch smoother: marginals failed: {exc}") from exc
    for k in range(k0, n):
        pose = pose_vector(result.atPose2(X(k)))
        steps[k] = StereoStep(pose, _coords_cov(pose, marginals.marginalCovariance(X(k))),
                              status[k], True)
    return steps


# --------------------------------------------------------------------------- driver
def estimate(
    run: StereoRun, estimator: str, cfg: StereoEstimatorConfig | None = None
) -> StereoResult:
    """Run one estimator over a whole run.

    Args:
        run: the stereo run (simulated or converted).
        estimator: ``raw``, ``ekf``, ``isam2`` or ``batch``.
        cfg: settings (defaults when None).

    Returns:
        The finished :class:`StereoResult` (finite everywhere).

    Raises:
        EstimationError: unknown estimator name.
    """
    cfg = cfg or StereoEstimatorConfig()
    n = len(run)
    times = np.zeros(n)
    if estimator == "batch":
        t0 = time.perf_counter()
        steps = batch_smoother(run, cfg)
        times[:] = (time.perf_counter() - t0) / max(n, 1)
        for k, s in enumerate(steps):  # a smoother's result exists only at the end
            emit("stereo.step", k=k, t=float(run.t[k]), estimator=estimator, step=s,
                 time_s=times[k])
    elif estimator in ("raw", "ekf", "isam2"):
        est: RawEstimator | StereoEkf | StereoIsam2
        if estimator == "raw":
            est = RawEstimator(run, cfg)
        elif estimator == "ekf":
            est = StereoEkf(run, cfg)
        else:
            est = StereoIsam2(run, cfg)
        steps = []
        for k in range(n):
            t0 = time.perf_counter()
            steps.append(est.step(k))
            times[k] = time.perf_counter() - t0
            emit("stereo.step", k=k, t=float(run.t[k]), estimator=estimator, step=steps[-1],
                 time_s=times[k])
    else:
        raise EstimationError(f"unknown estimator {estimator!r}; choose one of {ESTIMATORS}")
    poses = np.array([s.pose for s in steps]).reshape(n, 3)
    covs = np.array([s.cov for s in steps]).reshape(n, 3, 3)
    if not (np.all(np.isfinite(poses)) and np.all(np.isfinite(covs))):
        raise EstimationError(f"{estimator}: non-finite estimate (a bug: please report)")
    return StereoResult(
        estimator, np.asarray(run.t, dtype=float).copy(), poses, covs,
        tuple(s.status for s in steps), np.array([s.valid for s in steps]), times,
    )
