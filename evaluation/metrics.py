"""Accuracy and consistency metrics for planar trajectories and landmark maps.

Trajectory statistics (APE, RPE) are computed by evo (MichaelGrupp/evo), not
rewritten here; this module converts planar poses to evo's trajectories and adds
what evo does not have: planar pose errors without alignment (the start pose is
known), NEES with chi-square bounds (Bar-Shalom, Li, Kirubarajan, *Estimation
with Applications to Tracking and Navigation*, 2001, sec. 5.4), and map error.

Poses are ``(x, y, theta)`` rows, world frame, metres and radians
(docs/conventions.md).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import TYPE_CHECKING

import numpy as np
from scipy import stats

from lampsam.angles import wrap_angle
from lampsam.arrays import FloatArray, IntArray
from lampsam.errors import LampsamError

if TYPE_CHECKING:
    from evo.core.trajectory import PoseTrajectory3D


class MetricsError(LampsamError):
    """Inputs to a metric do not fit (shapes, empty, no overlap in time)."""


def _check_poses(name: str, poses: FloatArray) -> FloatArray:
    """``poses`` as a non-empty (N, 3) float array; MetricsError naming ``name`` otherwise."""
    arr = np.asarray(poses, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise MetricsError(f"{name}: expected shape (N, 3) of x, y, theta, got {arr.shape}")
    if arr.shape[0] == 0:
        raise MetricsError(f"{name}: no poses")
    return arr


@dataclass(frozen=True)
class ErrorStats:
    """Summary of a non-negative error series (units of the series)."""

    rms: float
    max: float
    mean: float
    median: float
    n: int

    def to_dict(self) -> dict[str, float | int]:
        return asdict(self)


def error_stats(errors: FloatArray) -> ErrorStats:
    """RMS, max, mean and median of ``errors`` (N,), NaN entries ignored."""
    e = np.asarray(errors, dtype=np.float64)
    e = e[np.isfinite(e)]
    if e.size == 0:
        raise MetricsError("no finite errors to summarise")
    a = np.abs(e)
    return ErrorStats(
        rms=float(np.sqrt(np.mean(a**2))),
        max=float(a.max()),
        mean=float(a.mean()),
        median=float(np.median(a)),
        n=int(a.size),
    )


def pose_errors(estimate: FloatArray, truth: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Position and heading errors of matched poses, without any alignment.

    Args:
        estimate: (N, 3) estimated ``world_T_body`` poses.
        truth: (N, 3) true poses at the same times.

    Returns:
        ``(position_error (N,) m, heading_error (N,) rad)``; heading errors are
        signed and wrapped to (-pi, pi].
    """
    est = _check_poses("estimate", estimate)
    gt = _check_poses("truth", truth)
    if est.shape != gt.shape:
        raise MetricsError(f"estimate {est.shape} and truth {gt.shape} differ in length")
    pos = np.hypot(est[:, 0] - gt[:, 0], est[:, 1] - gt[:, 1])
    head = wrap_angle(est[:, 2] - gt[:, 2])
    return pos, head


def interpolate_poses(t_query: FloatArray, t: FloatArray, poses: FloatArray) -> FloatArray:
    """Linearly interpolate planar poses (heading along the shorter arc).

    The same as :meth:`lampsam.datasets.logrun.Trajectory.interpolate`, for arrays.

    Args:
        t_query: (M,) times, inside ``[t[0], t[-1]]`` (clamped otherwise).
        t: (N,) increasing times of ``poses``.
        poses: (N, 3).

    Returns:
        (M, 3) interpolated poses.
    """
    from lampsam.datasets.logrun import Trajectory

    p = _check_poses("poses", poses)
    return Trajectory(t=np.asarray(t, dtype=np.float64), poses=p).interpolate(t_query)


def se2_log(poses: FloatArray) -> FloatArray:
    """Logarithm map of SE(2), vectorised: GTSAM's ``Pose2.Logmap`` ordering.

    Args:
        poses: (N, 3) poses ``(x, y, theta)``.

    Returns:
        (N, 3) tangent vectors ``(v_x, v_y, omega)`` such that
        ``Pose2.Expmap(xi) == pose``.
    """
    p = np.atleast_2d(np.asarray(poses, dtype=np.float64))
    w = wrap_angle(p[:, 2])
    half = 0.5 * w
    small = np.abs(w) < 1e-9
    # V^{-1} = (w/2) [[cot(w/2), 1], [-1, cot(w/2)]] for Pose2 (GTSAM Pose2::Logmap).
    cot = np.where(small, 0.0, np.cos(half) / np.where(small, 1.0, np.sin(half)))
    a = np.where(small, 1.0 - w**2 / 12.0, half * cot)
    vx = a * p[:, 0] + half * p[:, 1]
    vy = -half * p[:, 0] + a * p[:, 1]
    return np.column_stack([vx, vy, w])


def between(a: FloatArray, b: FloatArray) -> FloatArray:
    """Relative poses ``a^{-1} b`` for matched rows of (N, 3) arrays."""
    a = np.atleast_2d(a)
    b = np.atleast_2d(b)
    c, s = np.cos(a[:, 2]), np.sin(a[:, 2])
    dx, dy = b[:, 0] - a[:, 0], b[:, 1] - a[:, 1]
    return np.column_stack([c * dx + s * dy, -s * dx + c * dy, wrap_angle(b[:, 2] - a[:, 2])])


def tangent_errors(estimate: FloatArray, truth: FloatArray) -> FloatArray:
    """Errors in the estimate's right-perturbation tangent: ``Log(est^{-1} truth)``.

    This is the frame of GTSAM marginal covariances (``truth = est.retract(xi)``).

    Returns:
        (N, 3) tangent errors ``(v_x, v_y, omega)``.
    """
    return se2_log(between(_check_poses("estimate", estimate), _check_poses("truth", truth)))


def coordinate_errors(estimate: FloatArray, truth: FloatArray) -> FloatArray:
    """Errors in plain coordinates ``(x, y, theta)``: the frame of an EKF covariance.

    Returns:
        (N, 3) ``truth - estimate`` with the heading wrapped.
    """
    est = _check_poses("estimate", estimate)
    gt = _check_poses("truth", truth)
    d = gt - est
    d[:, 2] = wrap_angle(d[:, 2])
    return d


def nees(errors: FloatArray, covariances: FloatArray) -> FloatArray:
    """Normalised estimation error squared ``e^T P^{-1} e`` per step.

    Args:
        errors: (N, D) errors, in the same frame as ``covariances``.
        covariances: (N, D, D) the estimator's reported covariances.

    Returns:
        (N,) NEES; NaN where a covariance is not positive definite.
    """
    e = np.asarray(errors, dtype=np.float64)
    P = np.asarray(covariances, dtype=np.float64)
    if P.shape != (*e.shape, e.shape[1]):
        raise MetricsError(f"errors {e.shape} and covariances {P.shape} do not match")
    out = np.full(e.shape[0], np.nan)
    try:
        L = np.linalg.cholesky(P)
        z = np.linalg.solve(L, e[..., None])[..., 0]
        return np.sum(z**2, axis=1)
    except np.linalg.LinAlgError:
        for i in range(e.shape[0]):
            try:
                Li = np.linalg.cholesky(P[i])
            except np.linalg.LinAlgError:
                continue
            zi = np.linalg.solve(Li, e[i])
            out[i] = float(zi @ zi)
        return out


def chi2_bounds(dof: int, n_runs: int = 1, probability: float = 0.95) -> tuple[float, float]:
    """Two-sided bounds of the run-averaged NEES under consistency.

    With ``n_runs`` independent runs, ``n_runs * mean NEES ~ chi2(dof * n_runs)``,
    so the bounds are ``chi2.ppf((1 -+ p) / 2, dof * n_runs) / n_runs``.

    Returns:
        ``(lower, upper)``; e.g. ``(0.216, 9.348)`` for dof 3, one run, p 0.95.
    """
    if dof < 1 or n_runs < 1 or not 0.0 < probability < 1.0:
        raise MetricsError(f"bad chi-square bound arguments: dof={dof}, runs={n_runs}, p={probability}")
    k = dof * n_runs
    lo = stats.chi2.ppf((1.0 - probability) / 2.0, k) / n_runs
    hi = stats.chi2.ppf((1.0 + probability) / 2.0, k) / n_runs
    return float(lo), float(hi)


@dataclass(frozen=True)
class NeesSummary:
    """Consistency summary of NEES series from one or more runs."""

    mean: float  # time average of the run-averaged NEES (ideal: dof)
    lower: float  # 95 % bound of the run-averaged NEES at one step
    upper: float
    fraction_inside: float  # fraction of steps whose run-averaged NEES is inside the bounds
    fraction_above: float  # fraction above the upper bound (overconfidence)
    mean_lower: float  # 95 % bounds for ``mean`` itself, with the effective number of
    mean_upper: float  # independent steps N / tau (tau: integrated autocorrelation time)
    dof: int
    n_runs: int

    @property
    def overconfident(self) -> bool:
        """True when the time-averaged NEES exceeds its own 95 % upper bound."""
        return self.mean > self.mean_upper

    @property
    def underconfident(self) -> bool:
        """True when the time-averaged NEES is below its own 95 % lower bound."""
        return self.mean < self.mean_lower

    def to_dict(self) -> dict[str, float | int | bool]:
        d: dict[str, float | int | bool] = dict(asdict(self))
        d["overconfident"] = self.overconfident
        d["underconfident"] = self.underconfident
        return d


def integrated_autocorrelation_time(x: FloatArray) -> float:
    """Integrated autocorrelation time ``tau = 1 + 2 sum_k rho_k`` of a series.

    The sum stops at the first non-positive autocorrelation (initial positive
    sequence, Geyer 1992). A series of N correlated samples carries about
    ``N / tau`` independent samples' worth of information about its mean.

    Args:
        x: (N,) series, finite.

    Returns:
        ``tau >= 1`` (1 for an independent series).
    """
    v = np.asarray(x, dtype=np.float64)
    v = v[np.isfinite(v)]
    n = v.size
    if n < 4 or np.var(v) == 0.0:
        return 1.0
    d = v - v.mean()
    nfft = 1 << (2 * n - 1).bit_length()
    f = np.fft.rfft(d, nfft)
    acf = np.fft.irfft(f * np.conj(f), nfft)[:n]
    acf /= acf[0]
    tau = 1.0
    for k in range(1, n):
        if acf[k] <= 0.0:
            break
        tau += 2.0 * acf[k]
    return float(max(tau, 1.0))


def nees_summary(nees_runs: FloatArray, dof: int = 3, probability: float = 0.95) -> NeesSummary:
    """Summarise NEES of M runs x N steps (NaN steps ignored).

    Args:
        nees_runs: (M, N) or (N,) NEES values, one row per run, aligned in step.
        dof: dimension of the error (3 for x, y, theta).
        probability: two-sided probability of the bounds.
    """
    arr = np.atleast_2d(np.asarray(nees_runs, dtype=np.float64))
    m = arr.shape[0]
    avg = np.nanmean(arr, axis=0)
    avg = avg[np.isfinite(avg)]
    if avg.size == 0:
        raise MetricsError("no finite NEES values")
    lo, hi = chi2_bounds(dof, m, probability)
    # The time average's bounds count independent samples: consecutive steps of one run
    # are strongly correlated, so N steps are worth N / tau of them.
    tau = integrated_autocorrelation_time(avg)
    n_eff = max(1, int(round(avg.size / tau)))
    mean_lo, mean_hi = chi2_bounds(dof, m * n_eff, probability)
    return NeesSummary(
        mean=float(avg.mean()),
        lower=lo,
        upper=hi,
        fraction_inside=float(np.mean((avg >= lo) & (avg <= hi))),
        fraction_above=float(np.mean(avg > hi)),
        mean_lower=mean_lo,
        mean_upper=mean_hi,
        dof=dof,
        n_runs=m,
    )


def to_evo(t: FloatArray, poses: FloatArray) -> PoseTrajectory3D:
    """Planar poses to an ``evo.core.trajectory.PoseTrajectory3D`` (z = 0, yaw quaternion).

    evo is imported lazily, inside the function.

    Args:
        t: (N,) timestamps, s.
        poses: (N, 3) ``(x, y, theta)`` in the world frame, metres and radians.

    Returns:
        The trajectory; orientation is the yaw quaternion ``(cos(theta/2), 0, 0, sin(theta/2))``.
    """
    from evo.core.trajectory import PoseTrajectory3D

    p = _check_poses("poses", poses)
    xyz = np.column_stack([p[:, 0], p[:, 1], np.zeros(len(p))])
    half = 0.5 * p[:, 2]
    wxyz = np.column_stack([np.cos(half), np.zeros(len(p)), np.zeros(len(p)), np.sin(half)])
    return PoseTrajectory3D(positions_xyz=xyz, orientations_quat_wxyz=wxyz, timestamps=np.asarray(t, float))


def evo_ape_rpe(
    t_est: FloatArray,
    est: FloatArray,
    t_ref: FloatArray,
    ref: FloatArray,
    max_time_diff: float = 0.02,
    rpe_delta_m: float = 1.0,
) -> dict[str, float]:
    """APE (translation, no alignment) and RPE per metre with evo.

    Args:
        t_est, est: (N,), (N, 3) estimated trajectory.
        t_ref, ref: (K,), (K, 3) reference (ground truth).
        max_time_diff: association tolerance, s.
        rpe_delta_m: RPE segment length, m.

    Returns:
        ``ape_rmse_m``, ``ape_max_m``, ``rpe_trans_rmse_m`` (per ``rpe_delta_m``),
        ``rpe_rot_rmse_deg``, ``rpe_trans_per_m`` (= rpe_trans_rmse / delta), ``path_length_m``.
    """
    from evo.core import metrics, sync
    from evo.core.trajectory import PoseTrajectory3D

    a = to_evo(t_ref, ref)
    b = to_evo(t_est, est)
    try:
        a, b = sync.associate_trajectories(a, b, max_diff=max_time_diff)
    except sync.SyncException as exc:
        raise MetricsError(f"trajectories do not overlap in time: {exc}") from exc
    assert isinstance(a, PoseTrajectory3D) and isinstance(b, PoseTrajectory3D)
    ape = metrics.APE(metrics.PoseRelation.translation_part)
    ape.process_data((a, b))
    out = {
        "ape_rmse_m": float(ape.get_statistic(metrics.StatisticsType.rmse)),
        "ape_max_m": float(ape.get_statistic(metrics.StatisticsType.max)),
        "path_length_m": float(a.path_length),
    }
    if a.path_length > 2.0 * rpe_delta_m:
        kw = {"delta": rpe_delta_m, "delta_unit": metrics.Unit.meters, "all_pairs": False}
        rpe_t = metrics.RPE(metrics.PoseRelation.translation_part, **kw)
        rpe_t.process_data((a, b))
        rpe_r = metrics.RPE(metrics.PoseRelation.rotation_angle_deg, **kw)
        rpe_r.process_data((a, b))
        rt = float(rpe_t.get_statistic(metrics.StatisticsType.rmse))
        out["rpe_trans_rmse_m"] = rt
        out["rpe_trans_per_m"] = rt / rpe_delta_m
        out["rpe_rot_rmse_deg"] = float(rpe_r.get_statistic(metrics.StatisticsType.rmse))
    else:
        out["rpe_trans_rmse_m"] = out["rpe_trans_per_m"] = out["rpe_rot_rmse_deg"] = float("nan")
    return out


def map_error(
    est_ids: IntArray,
    est_xyz: FloatArray,
    true_ids: IntArray,
    true_xyz: FloatArray,
    dims: int = 2,
) -> tuple[ErrorStats, int]:
    """Landmark position error after association with the truth by id.

    Args:
        est_ids: (L,) ids of estimated landmarks that carry a true id (others: -1).
        est_xyz: (L, 3) estimated positions, world frame, m.
        true_ids: (T,) true landmark ids.
        true_xyz: (T, 3) true positions.
        dims: 2 for the floor-plane error, 3 to include height.

    Returns:
        ``(stats of per-landmark error, number associated)``.
    """
    lookup = {int(i): k for k, i in enumerate(np.asarray(true_ids))}
    errs = []
    for i, p in zip(np.asarray(est_ids), np.asarray(est_xyz, dtype=np.float64), strict=True):
        k = lookup.get(int(i))
        if k is None:
            continue
        errs.append(float(np.linalg.norm(p[:dims] - np.asarray(true_xyz, dtype=np.float64)[k, :dims])))
    if not errs:
        raise MetricsError("no estimated landmark could be associated with the truth")
    return error_stats(np.asarray(errs)), len(errs)
