"""Online odometry noise scale (backend/odometry_scale.py): estimator, idle odometry, wrapper."""

from __future__ import annotations

import numpy as np
import pytest

from lampsam.backend.odometry import Pose2Motion
from lampsam.backend.odometry_scale import IdleOdometry, OdometryNoiseScale, ScaledMotion
from lampsam.datasets.odometry import Pose2OdometryModel

GATE = 9.21  # chi-square(2) 99 %


def _gated_samples(rng: np.random.Generator, a: float, b: float, n: int
                   ) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """Innovations ``nu ~ N(0, a A + b B)`` kept only inside the gate of ``A + B``."""
    out = []
    while len(out) < n:
        u = rng.normal(size=(2, 2))
        big = np.exp(rng.uniform(-3.0, 1.0)) * (u @ u.T) / 2
        v = rng.normal(size=(2, 2))
        rest = v @ v.T / 2 + 0.05 * np.eye(2)
        nu = np.linalg.cholesky(a * big + b * rest) @ rng.normal(size=2)
        if nu @ np.linalg.solve(big + rest, nu) < GATE:
            out.append((nu, big, rest))
    return out


@pytest.mark.parametrize(("a", "b"), [(1.0, 1.0), (4.0, 1.0), (16.0, 0.1), (4.0, 0.02)])
def test_estimator_recovers_a_known_scale(a: float, b: float) -> None:
    """300 gated Monte Carlo matches: the odometry factor within 1.6x of the truth (the
    grid steps 1.19x; the gate truncates the sample), and never below 1 (the prior)."""
    est = OdometryNoiseScale(GATE, window=300, min_count=300, every=300)
    for nu, big, rest in _gated_samples(np.random.default_rng(int(a * 100 + b * 10)), a, b, 300):
        est.add(nu, big, rest)
    assert max(a, 1.0) / 1.6 <= est.scale <= max(a, 1.0) * 1.6
    assert b / 2.5 <= est.b_hat <= b * 2.5


def test_estimator_waits_and_clamps() -> None:
    """No estimate before ``min_count`` matches; never above ``max_scale``."""
    est = OdometryNoiseScale(GATE, window=100, min_count=50, every=10, max_scale=8.0)
    samples = _gated_samples(np.random.default_rng(7), 64.0, 1.0, 100)
    for nu, big, rest in samples[:49]:
        est.add(nu, big, rest)
    assert est.scale == 1.0 and not est.history
    for nu, big, rest in samples[49:]:
        est.add(nu, big, rest)
    assert est.scale == 8.0


def test_idle_odometry_composes_and_restarts() -> None:
    """``C <- F C F^T + Q`` per step from zero at the landmark's sighting; a sighting resets."""
    idle = IdleOdometry()
    idle.seen(3)
    f = np.array([[1.0, 0.0, -0.5], [0.0, 1.0, 1.0], [0.0, 0.0, 1.0]])
    q = np.diag([0.01, 0.02, 0.001])
    idle.propagate(f, q)
    idle.propagate(f, q)
    c = idle.cov(3)
    assert c is not None
    np.testing.assert_allclose(c, f @ q @ f.T + q, atol=1e-15)
    idle.seen(9)  # a new landmark starts from zero; the old one keeps its C
    assert idle.cov(9) is not None and np.all(idle.cov(9) == 0.0)
    np.testing.assert_allclose(idle.cov(3), f @ q @ f.T + q, atol=1e-15)
    idle.seen(3)
    assert np.all(idle.cov(3) == 0.0)
    assert idle.cov(4) is None


def test_scaled_motion_scales_every_covariance() -> None:
    """The wrapper's factor and EKF covariances are ``scale`` times the model's; the
    increments and Jacobians are the model's."""
    inner = Pose2Motion(Pose2OdometryModel())
    est = OdometryNoiseScale(GATE)
    est.scale = 16.0
    idle = IdleOdometry()
    idle.seen(0)
    wrapped = ScaledMotion(inner, est, idle)
    row = np.r_[0.5, 0.02, 0.01, np.diag([1e-4, 9e-4, 1e-5]).ravel()]
    samples = wrapped.check(0.0, row)
    d0, c0 = inner.relative(samples, 1e-9)
    d1, c1 = wrapped.relative(samples, 1e-9)
    np.testing.assert_allclose(d1, d0)
    np.testing.assert_allclose(c1, 16.0 * c0)
    pose = np.array([1.0, 2.0, 0.3])
    p0, f0, q0 = inner.ekf_predict(pose, samples)
    p1, f1, q1 = wrapped.ekf_predict(pose, samples)
    np.testing.assert_allclose(p1, p0)
    np.testing.assert_allclose(f1, f0)
    np.testing.assert_allclose(q1, 16.0 * q0)
    np.testing.assert_allclose(idle.cov(0), q1)
