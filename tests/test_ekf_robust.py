"""The EKF's row noise: the first-estimates mismatch term and the robust kernels (issue 15)."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from scipy.stats import chi2

from lampsam.backend.config import EkfConfig, SlamConfig
from lampsam.backend.ekf import EkfSlam
from lampsam.backend.ekf_update import mismatch_noise, observability_project, robust_noise
from lampsam.backend.interface import LandmarkKind
from lampsam.backend.models import Obs
from lampsam.config_loader import FieldValueError
from lampsam.datasets.odometry import Pose2OdometryModel
from lampsam.datasets.rig import OdometryModel
from lampsam.factors.geometry import wrap_angle


def _h(x: np.ndarray) -> np.ndarray:
    """``[bearing, range]`` of the landmark ``x[3:5]`` from the pose ``x[:3]``."""
    d = x[3:5] - x[:2]
    return np.array([wrap_angle(math.atan2(d[1], d[0]) - x[2]), math.hypot(d[0], d[1])])


def _num_jac(x: np.ndarray, eps: float = 1e-7) -> np.ndarray:
    """(2, 5) central differences of :func:`_h` in plain coordinates."""
    out = np.empty((2, 5))
    for j in range(5):
        dx = np.zeros(5)
        dx[j] = eps
        a, b = _h(x + dx), _h(x - dx)
        d = (a - b) / (2 * eps)
        d[0] = wrap_angle(float(a[0] - b[0])) / (2 * eps)
        out[:, j] = d
    return out


def test_robust_noise_leaves_plausible_rows_and_weights_implausible_ones() -> None:
    """Below the threshold ``R`` is unchanged for every kernel; above it Huber inflates by
    ``sqrt(d2 / threshold)`` and ``"gate"`` by the factor that puts the row's distance
    exactly on the threshold (1e-9)."""
    rng = np.random.default_rng(5)
    a = rng.normal(size=(2, 2))
    s = a @ a.T + 0.1 * np.eye(2)
    r = np.diag([0.05**2, 0.3**2])
    thr = float(chi2.ppf(0.999, 2))
    psi = s + r
    small = np.linalg.cholesky(psi) @ np.array([1.0, 1.0])  # d2 = 2
    for kernel in ("none", "huber", "gate"):
        assert robust_noise(small, s, r, thr, kernel) is r
    big = np.linalg.cholesky(psi) @ np.array([6.0, -3.0])  # d2 = 45
    d2 = float(big @ np.linalg.solve(psi, big))
    assert d2 == pytest.approx(45.0)
    np.testing.assert_allclose(robust_noise(big, s, r, thr, "huber"), r * math.sqrt(d2 / thr))
    rg = robust_noise(big, s, r, thr, "gate")
    factor = rg[0, 0] / r[0, 0]
    np.testing.assert_allclose(rg, factor * r)
    assert factor > 1.0
    assert float(big @ np.linalg.solve(s + rg, big)) == pytest.approx(thr, rel=1e-9)
    assert robust_noise(big, s, r, thr, "none") is r
    with pytest.raises(ValueError, match="cauchy"):
        robust_noise(big, s, r, thr, "cauchy")


def test_config_rejects_an_unknown_kernel_and_a_negative_mismatch() -> None:
    with pytest.raises(FieldValueError, match="robust_kernel"):
        EkfConfig(robust_kernel="cauchy")
    with pytest.raises(FieldValueError, match="fej_mismatch"):
        EkfConfig(fej_mismatch=-1.0)
    with pytest.raises(Exception, match="fej_mismach"):
        SlamConfig.from_dict({"ekf": {"fej_mismach": 1.0}})


def _stale_ekf(mismatch: float | None) -> EkfSlam:
    """An EKF with one landmark whose first estimate is 1.5 m from its state: plain first
    estimates with ``fej_mismatch = mismatch``, or the defaults when None."""
    cfg = SlamConfig()
    cfg = dataclasses.replace(cfg, ekf=dataclasses.replace(
        cfg.ekf, first_estimate_jacobians=True, sigma_start_xy=0.3, sigma_start_theta=0.05,
        fej_mismatch=mismatch or 0.0, observability_constrained=None if mismatch is None else False))
    ekf = EkfSlam(Pose2OdometryModel(), cfg, np.array([0.5, -0.2, 0.3]))
    ekf._augment(Obs(LandmarkKind.POINT2, np.array([0.4, 8.0]), np.diag([0.05**2, 0.3**2])), 7)
    ekf._slots[7].first = ekf.x[3:5] + np.array([1.2, -0.9])  # a stale linearisation point
    return ekf


def test_mismatch_noise_matches_numerical_jacobians_and_the_kalman_update() -> None:
    """One known-id sighting of a landmark whose first estimate is stale: the EKF's step
    equals the Kalman update with ``H`` at the first estimate and
    ``R + c dH P dH^T``, ``dH`` from numerical derivatives at the latest and the first
    estimates (1e-6 relative); ``c = 0`` gives the plain first-estimates update, and a
    fresh first estimate (equal to the state) adds nothing."""
    z = np.array([0.5, 7.2])
    r = np.diag([0.05**2, 0.3**2])
    steps = {}
    for c in (0.0, 2.0):
        ekf = _stale_ekf(c)
        x0, p0 = ekf.x.copy(), ekf.P.copy()
        h_first = _num_jac(np.concatenate([x0[:3], ekf._slots[7].first]))
        h_latest = _num_jac(x0)
        r_eff = r + c * (h_latest - h_first) @ p0 @ (h_latest - h_first).T
        np.testing.assert_allclose(r_eff, r + mismatch_noise(h_latest, h_first, p0, c),
                                   rtol=1e-6, atol=1e-12)
        nu = z - _h(x0)
        nu[0] = wrap_angle(float(nu[0]))
        k = p0 @ h_first.T @ np.linalg.inv(h_first @ p0 @ h_first.T + r_eff)
        ekf._update([(ekf._slots[7], Obs(LandmarkKind.POINT2, z, r))])
        np.testing.assert_allclose(ekf.x, x0 + k @ nu, rtol=1e-6, atol=1e-9)
        np.testing.assert_allclose(ekf.P, p0 - k @ h_first @ p0, rtol=1e-5, atol=1e-8)
        steps[c] = ekf.x - x0
    assert np.abs(steps[2.0] - steps[0.0]).max() > 0.02  # the term matters here
    fresh = _stale_ekf(2.0)
    fresh._slots[7].first = fresh.x[3:5].copy()
    np.testing.assert_allclose(
        fresh._row_noise(fresh._slots[7], Obs(LandmarkKind.POINT2, z, r), z - _h(fresh.x),
                         *fresh._h(fresh._slots[7], None)[1:]), r, atol=1e-15)


def test_mismatch_default_off_and_the_wheel_model_keeps_the_papers_jacobians() -> None:
    """``fej_mismatch`` is off unless set; the wheel model gets no observability
    constraint; with first estimates off the row noise is the observation's ``R``."""
    cfg = SlamConfig()
    assert EkfSlam(Pose2OdometryModel(), cfg, np.zeros(3))._mismatch == 0  # default: off
    on = dataclasses.replace(cfg, ekf=dataclasses.replace(cfg.ekf, fej_mismatch=1.0))
    assert EkfSlam(Pose2OdometryModel(), on, np.zeros(3))._mismatch == 1.0
    assert not EkfSlam(OdometryModel(), cfg, np.zeros(3))._oc
    off = dataclasses.replace(cfg, ekf=dataclasses.replace(cfg.ekf, first_estimate_jacobians=False))
    ekf = EkfSlam(Pose2OdometryModel(), off, np.zeros(3))
    ekf._augment(Obs(LandmarkKind.POINT2, np.array([0.4, 8.0]), np.diag([0.05**2, 0.3**2])), 1)
    obs = Obs(LandmarkKind.POINT2, np.array([0.4, 8.0]), np.diag([0.05**2, 0.3**2]))
    assert ekf._row_noise(ekf._slots[1], obs, np.zeros(2), *ekf._h(ekf._slots[1], None)[1:]) is obs.R


def _unobservable(pose_xy: np.ndarray, first_xy: np.ndarray) -> np.ndarray:
    """(5, 3) a global translation (x, y) and rotation of robot and landmark."""
    return np.array([[1, 0, -pose_xy[1]], [0, 1, pose_xy[0]], [0, 0, 1],
                     [1, 0, -first_xy[1]], [0, 1, first_xy[0]]], float)


def test_observability_projection_is_the_nearest_jacobian_with_the_constraint() -> None:
    """``H* N = 0`` (1e-12); ``H*`` is nearer to ``H`` than other Jacobians with the
    constraint (random ones, Frobenius norm); a Jacobian that already satisfies it (the
    latest estimate equal to the first) is unchanged; the batched call equals the single
    ones; the result differs from the first-estimates Jacobian when the landmark has
    moved (a stale first estimate)."""
    rng = np.random.default_rng(11)
    pose = np.array([2.0, -1.0, 0.4])
    latest = np.array([9.0, 4.0])
    first = latest + np.array([3.0, -2.5])
    h = _num_jac(np.concatenate([pose, latest]))
    n = _unobservable(pose[:2], first)
    h_r, h_l = observability_project(h[:, :3], h[:, 3:], pose[:2], first)
    hs = np.hstack([h_r, h_l])
    np.testing.assert_allclose(hs @ n, 0.0, atol=1e-12)
    proj = np.eye(5) - n @ np.linalg.solve(n.T @ n, n.T)
    for _ in range(20):
        other = rng.normal(size=(2, 5)) @ proj
        other = hs + 0.1 * other
        assert np.linalg.norm(h - hs) <= np.linalg.norm(h - other) + 1e-12
    same_r, same_l = observability_project(h[:, :3], h[:, 3:], pose[:2], latest)
    np.testing.assert_allclose(np.hstack([same_r, same_l]), h, atol=1e-6)
    h_first = _num_jac(np.concatenate([pose, first]))
    assert np.abs(hs - h_first).max() > 0.01
    many_r, many_l = observability_project(np.stack([h[:, :3]] * 3), np.stack([h[:, 3:]] * 3),
                                           pose[:2], np.stack([first, latest, first]))
    np.testing.assert_allclose(many_r[0], h_r, atol=1e-12)
    np.testing.assert_allclose(many_l[2], h_l, atol=1e-12)
    np.testing.assert_allclose(many_r[1], same_r, atol=1e-12)


def test_observability_constrained_update_equals_the_kalman_update() -> None:
    """One known-id sighting of a landmark with a stale first estimate (default config:
    observability-constrained Jacobians on for Pose2 range-bearing runs): the EKF's step
    and covariance equal the Kalman update with ``H*`` built here from numerical
    derivatives at the latest estimate and the explicit ``N`` (1e-6)."""
    z = np.array([0.5, 7.2])
    r = np.diag([0.05**2, 0.3**2])
    ekf = _stale_ekf(None)
    assert ekf._oc and ekf._mismatch == 0
    x0, p0 = ekf.x.copy(), ekf.P.copy()
    n = _unobservable(x0[:2], ekf._slots[7].first)
    h = _num_jac(x0) @ (np.eye(5) - n @ np.linalg.solve(n.T @ n, n.T))
    nu = z - _h(x0)
    nu[0] = wrap_angle(float(nu[0]))
    k = p0 @ h.T @ np.linalg.inv(h @ p0 @ h.T + r)
    ekf._update([(ekf._slots[7], Obs(LandmarkKind.POINT2, z, r))])
    np.testing.assert_allclose(ekf.x, x0 + k @ nu, rtol=1e-6, atol=1e-8)
    np.testing.assert_allclose(ekf.P, p0 - k @ h @ p0, rtol=1e-5, atol=1e-8)
