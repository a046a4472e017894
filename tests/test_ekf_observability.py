"""The observability-constrained EKF's measurement Jacobians (OC-EKF, issue 15)."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from lampsam.backend.config import SlamConfig
from lampsam.backend.ekf import EkfSlam
from lampsam.backend.ekf_update import observability_project
from lampsam.backend.interface import LandmarkKind
from lampsam.backend.models import Obs
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


def _stale_ekf(oc: bool | None = None) -> EkfSlam:
    """A Pose2 range-bearing EKF (defaults but ``ekf.observability_constrained = oc``) with
    one landmark whose first estimate is 1.5 m from its state."""
    cfg = SlamConfig()
    cfg = dataclasses.replace(cfg, ekf=dataclasses.replace(
        cfg.ekf, sigma_start_xy=0.3, sigma_start_theta=0.05, observability_constrained=oc))
    ekf = EkfSlam(Pose2OdometryModel(), cfg, np.array([0.5, -0.2, 0.3]))
    ekf._augment(Obs(LandmarkKind.POINT2, np.array([0.4, 8.0]), np.diag([0.05**2, 0.3**2])), 7)
    ekf._slots[7].first = ekf.x[3:5] + np.array([1.2, -0.9])  # a stale linearisation point
    return ekf


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
    """One known-id sighting of a landmark with a stale first estimate: with the default
    (observability-constrained Jacobians on for Pose2 range-bearing runs) the EKF's step
    and covariance equal the Kalman update with ``H*`` built here from numerical
    derivatives at the latest estimate and the explicit ``N`` (1e-6); with
    ``observability_constrained = false``, with ``H`` at the first estimate."""
    z = np.array([0.5, 7.2])
    r = np.diag([0.05**2, 0.3**2])
    steps = {}
    for oc in (None, False):
        ekf = _stale_ekf(oc)
        assert ekf._oc is (oc is None) and ekf._fej
        x0, p0 = ekf.x.copy(), ekf.P.copy()
        if oc is None:
            n = _unobservable(x0[:2], ekf._slots[7].first)
            h = _num_jac(x0) @ (np.eye(5) - n @ np.linalg.solve(n.T @ n, n.T))
        else:  # plain first estimates: H at the first estimate
            h = _num_jac(np.concatenate([x0[:3], ekf._slots[7].first]))
        nu = z - _h(x0)
        nu[0] = wrap_angle(float(nu[0]))
        k = p0 @ h.T @ np.linalg.inv(h @ p0 @ h.T + r)
        ekf._update([(ekf._slots[7], Obs(LandmarkKind.POINT2, z, r))])
        np.testing.assert_allclose(ekf.x, x0 + k @ nu, rtol=1e-6, atol=1e-8)
        np.testing.assert_allclose(ekf.P, p0 - k @ h @ p0, rtol=1e-5, atol=1e-8)
        steps[oc] = ekf.x - x0
    assert np.abs(steps[None] - steps[False]).max() > 0.01  # the projection matters here


def test_observability_constraint_is_automatic_on_pose2_range_bearing_runs_only() -> None:
    """Auto: on with Pose2 odometry and no ceiling; off for the wheel model (the paper's
    EKF), with ``first_estimate_jacobians = false`` and with the right-invariant EKF."""
    cfg = SlamConfig()
    assert EkfSlam(Pose2OdometryModel(), cfg, np.zeros(3))._oc
    assert not EkfSlam(OdometryModel(), cfg, np.zeros(3))._oc
    for key in ("first_estimate_jacobians", "right_invariant"):
        value = key == "right_invariant"
        other = dataclasses.replace(cfg, ekf=dataclasses.replace(cfg.ekf, **{key: value}))
        assert not EkfSlam(Pose2OdometryModel(), other, np.zeros(3))._oc
    with pytest.raises(Exception, match="observability_constrainde"):
        SlamConfig.from_dict({"ekf": {"observability_constrainde": True}})
