"""Geometry, motion (eqs. 13-15) and range-bearing models: values and Jacobians."""

from __future__ import annotations

import math

import gtsam
import numpy as np
import pytest
from gtsam.utils.numerical_derivative import (
    numericalDerivative11,
    numericalDerivative21,
    numericalDerivative22,
)

from lampsam.factors.geometry import (
    FactorError,
    between,
    compose,
    coords_D_tangent,
    rot2,
    tangent_D_coords,
    wrap_angle,
    wrap_axis,
)
from lampsam.factors.motion import (
    accumulate_odometry,
    diff_drive_step,
    odometry_between,
    wheel_noise_cov,
)
from lampsam.factors.range_bearing import range_bearing

SEEDS = [0, 1, 2, 3, 4, 5]
WHEEL_BASE = 0.33


def _pose_arr(p: gtsam.Pose2) -> np.ndarray:
    return np.array([p.x(), p.y(), p.theta()])


def _random_pose(rng: np.random.Generator) -> np.ndarray:
    return np.array([*rng.uniform(-5.0, 5.0, 2), rng.uniform(-2.5, 2.5)])


# --- geometry -------------------------------------------------------------------------


def test_wrap_angle_range_and_endpoints() -> None:
    a = np.linspace(-20.0, 20.0, 4001)
    w = wrap_angle(a)
    assert np.all(w > -math.pi) and np.all(w <= math.pi)
    np.testing.assert_allclose(np.sin(w), np.sin(a), atol=1e-12)
    np.testing.assert_allclose(np.cos(w), np.cos(a), atol=1e-12)
    assert wrap_angle(math.pi) == pytest.approx(math.pi)
    assert wrap_angle(-math.pi) == pytest.approx(math.pi)
    assert wrap_angle(3 * math.pi) == pytest.approx(math.pi)


def test_wrap_axis_range_and_pi_ambiguity() -> None:
    a = np.linspace(-20.0, 20.0, 4001)
    w = wrap_axis(a)
    assert np.all(w > -math.pi / 2) and np.all(w <= math.pi / 2)
    # same line direction: 2 * angle equal modulo 2 pi
    np.testing.assert_allclose(np.sin(2 * w), np.sin(2 * a), atol=1e-12)
    np.testing.assert_allclose(wrap_axis(a + math.pi), w, atol=1e-9)
    assert wrap_axis(math.pi / 2) == pytest.approx(math.pi / 2)
    assert wrap_axis(-math.pi / 2) == pytest.approx(math.pi / 2)


@pytest.mark.parametrize("seed", SEEDS)
def test_pose_algebra_matches_gtsam(seed: int) -> None:
    rng = np.random.default_rng(seed)
    a, b = _random_pose(rng), _random_pose(rng)
    pa, pb = gtsam.Pose2(*a), gtsam.Pose2(*b)
    np.testing.assert_allclose(compose(a, b), _pose_arr(pa.compose(pb)), atol=1e-12)
    np.testing.assert_allclose(between(a, b), _pose_arr(pa.between(pb)), atol=1e-12)
    np.testing.assert_allclose(
        coords_D_tangent(a[2]) @ tangent_D_coords(a[2]), np.eye(3), atol=1e-12
    )
    np.testing.assert_allclose(rot2(a[2]), pa.rotation().matrix(), atol=1e-12)


@pytest.mark.parametrize("seed", SEEDS)
def test_coords_D_tangent_is_retract_jacobian(seed: int) -> None:
    rng = np.random.default_rng(seed)
    pose = gtsam.Pose2(*_random_pose(rng))
    num = numericalDerivative11(lambda d: _pose_arr(pose.retract(d)), np.zeros(3))
    np.testing.assert_allclose(coords_D_tangent(pose.theta()), num, atol=1e-6)


# --- motion ---------------------------------------------------------------------------


@pytest.mark.parametrize("seed", SEEDS)
def test_diff_drive_step_jacobians(seed: int) -> None:
    rng = np.random.default_rng(seed)
    pose = _random_pose(rng)
    wheels = rng.uniform(-0.1, 0.1, 2)

    def f(p: np.ndarray, w: np.ndarray) -> np.ndarray:
        return diff_drive_step(p, w[0], w[1], WHEEL_BASE)[0]

    _, next_D_pose, next_D_wheels = diff_drive_step(pose, wheels[0], wheels[1], WHEEL_BASE)
    np.testing.assert_allclose(next_D_pose, numericalDerivative21(f, pose, wheels), atol=1e-6)
    np.testing.assert_allclose(next_D_wheels, numericalDerivative22(f, pose, wheels), atol=1e-6)


def test_diff_drive_step_values() -> None:
    # straight ahead: both wheels 0.5 m, heading 90 deg -> +0.5 m in y
    nxt, _, _ = diff_drive_step(np.array([1.0, 2.0, math.pi / 2]), 0.5, 0.5, WHEEL_BASE)
    np.testing.assert_allclose(nxt, [1.0, 2.5, math.pi / 2], atol=1e-12)
    # turn in place: right forward, left back -> heading += 2 d / b, no translation
    nxt, _, _ = diff_drive_step(np.zeros(3), -0.1, 0.1, WHEEL_BASE)
    np.testing.assert_allclose(nxt, [0.0, 0.0, 0.2 / WHEEL_BASE], atol=1e-12)
    np.testing.assert_allclose(
        wheel_noise_cov(-0.2, 0.4, k_r=1e-3, k_l=2e-3), np.diag([4e-4, 4e-4]), atol=1e-15
    )


def test_accumulate_matches_chained_steps_and_floor() -> None:
    rng = np.random.default_rng(11)
    dl, dr = rng.uniform(0.0, 0.05, 10), rng.uniform(0.0, 0.05, 10)
    pose = np.zeros(3)
    for a, b in zip(dl, dr, strict=True):
        pose = diff_drive_step(pose, a, b, WHEEL_BASE)[0]
    delta, cov = accumulate_odometry(dl, dr, WHEEL_BASE, 1e-3, 1e-3)
    np.testing.assert_allclose(delta, pose, atol=1e-12)
    assert np.all(np.linalg.eigvalsh(cov) > 0.0)
    # zero motion: exactly the floor, never singular
    delta0, cov0 = odometry_between(0.0, 0.0, WHEEL_BASE, 1e-3, 1e-3, floor=1e-8)
    np.testing.assert_allclose(delta0, np.zeros(3), atol=1e-15)
    np.testing.assert_allclose(cov0, 1e-8 * np.eye(3), atol=1e-20)
    delta_e, cov_e = accumulate_odometry(np.zeros(0), np.zeros(0), WHEEL_BASE, 1e-3, 1e-3)
    np.testing.assert_allclose(delta_e, np.zeros(3), atol=1e-15)
    assert np.linalg.matrix_rank(cov_e) == 3


def test_accumulate_rejects_bad_input() -> None:
    with pytest.raises(FactorError, match="NaN"):
        accumulate_odometry(np.array([0.1, np.nan]), np.array([0.1, 0.1]), WHEEL_BASE, 1e-3, 1e-3)
    with pytest.raises(FactorError, match="equal length"):
        accumulate_odometry(np.zeros(2), np.zeros(3), WHEEL_BASE, 1e-3, 1e-3)
    with pytest.raises(FactorError, match="wheel_base"):
        accumulate_odometry(np.zeros(2), np.zeros(2), 0.0, 1e-3, 1e-3)
    with pytest.raises(FactorError, match="floor"):
        accumulate_odometry(np.zeros(2), np.zeros(2), WHEEL_BASE, 1e-3, 1e-3, floor=0.0)


def test_odometry_covariance_against_monte_carlo() -> None:
    """Propagated tangent covariance vs. N = 20,000 sampled runs, each entry within 3 sigma.

    The sampling noise of a covariance entry is ``sqrt((P_ii P_jj + P_ij^2) / N)``.
    The floor is tiny so that the comparison sees the propagated part.
    """
    rng = np.random.default_rng(2026)
    n_steps, n_samples = 15, 20_000
    k_r, k_l = 2e-3, 1e-3
    dl = 0.03 + 0.01 * np.sin(np.arange(n_steps))  # a gentle curve
    dr = 0.035 + 0.01 * np.cos(np.arange(n_steps))
    floor = 1e-12
    delta, cov = accumulate_odometry(dl, dr, WHEEL_BASE, k_r, k_l, floor=floor)
    mean_pose = gtsam.Pose2(*delta)
    sig_l = np.sqrt(k_l * np.abs(dl))
    sig_r = np.sqrt(k_r * np.abs(dr))
    noisy_l = dl + rng.standard_normal((n_samples, n_steps)) * sig_l
    noisy_r = dr + rng.standard_normal((n_samples, n_steps)) * sig_r
    xi = np.empty((n_samples, 3))
    for i in range(n_samples):
        pose = np.zeros(3)
        for a, b in zip(noisy_l[i], noisy_r[i], strict=True):
            pose = diff_drive_step(pose, a, b, WHEEL_BASE)[0]
        xi[i] = mean_pose.localCoordinates(gtsam.Pose2(*pose))
    sample = np.cov(xi.T)
    tol = 3.0 * np.sqrt((np.outer(np.diag(cov), np.diag(cov)) + cov**2) / n_samples)
    assert np.all(np.abs(sample - cov) <= tol), (sample, cov, tol)
    assert np.all(np.abs(xi.mean(axis=0)) <= 3.0 * np.sqrt(np.diag(cov) / n_samples) + 1e-4)


# --- range-bearing --------------------------------------------------------------------


@pytest.mark.parametrize("seed", SEEDS)
@pytest.mark.parametrize("offset", [None, (0.2, -0.05, 0.3)])
def test_range_bearing_jacobians(seed: int, offset: tuple[float, float, float] | None) -> None:
    rng = np.random.default_rng(seed)
    pose = gtsam.Pose2(*_random_pose(rng))
    lm = rng.uniform(-5.0, 5.0, 2)
    off = None if offset is None else np.array(offset)
    z, z_D_pose, z_D_lm = range_bearing(_pose_arr(pose), lm, off)

    def h(p: gtsam.Pose2, l: np.ndarray) -> np.ndarray:
        out = range_bearing(_pose_arr(p), l, off)[0]
        out[0] = z[0] + wrap_angle(out[0] - z[0])  # no jump across +-pi
        return out

    np.testing.assert_allclose(z_D_pose, numericalDerivative21(h, pose, lm), atol=1e-6)
    np.testing.assert_allclose(z_D_lm, numericalDerivative22(h, pose, lm), atol=1e-6)


@pytest.mark.parametrize("seed", SEEDS)
def test_range_bearing_matches_gtsam(seed: int) -> None:
    rng = np.random.default_rng(seed)
    pose = gtsam.Pose2(*_random_pose(rng))
    lm = rng.uniform(-5.0, 5.0, 2)
    z = range_bearing(_pose_arr(pose), lm)[0]
    assert z[0] == pytest.approx(pose.bearing(lm).theta(), abs=1e-12)
    assert z[1] == pytest.approx(pose.range(lm), abs=1e-12)
    # sensor offset = the same as observing from the composed sensor pose
    off = np.array([0.3, 0.1, -0.4])
    sensor = pose.compose(gtsam.Pose2(*off))
    z_off = range_bearing(_pose_arr(pose), lm, off)[0]
    assert z_off[0] == pytest.approx(sensor.bearing(lm).theta(), abs=1e-12)
    assert z_off[1] == pytest.approx(sensor.range(lm), abs=1e-12)
