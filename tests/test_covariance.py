"""The in-place lower-triangle covariance and the EKF built on it, against dense formulas.

Every check compares with the textbook dense expression (``P - P H^T S^-1 H P``,
``T P T^T + Q``, index deletion) on random symmetric positive definite states, to
1e-9 absolute on unit-scale matrices.
"""

from __future__ import annotations

import numpy as np
import pytest

from lampsam.backend.config import SlamConfig
from lampsam.backend.covariance import LowerCovariance, syrk_lower_inplace
from lampsam.backend.ekf import EkfSlam
from lampsam.backend.models import Obs
from lampsam.datasets.logrun import Rig
from lampsam.factors.geometry import wrap_angle
from lampsam.factors.motion import diff_drive_step, wheel_noise_cov

TOL = 1e-9


def _spd(rng: np.random.Generator, n: int) -> np.ndarray:
    a = rng.normal(size=(n, n)) / np.sqrt(n)
    return a @ a.T + 0.1 * np.eye(n)


def _stored(n: int, rng: np.random.Generator, capacity: int) -> tuple[LowerCovariance, np.ndarray]:
    p = _spd(rng, n)
    cov = LowerCovariance(p, capacity)
    # garbage in the unused upper triangle must never be read
    cov._buf[np.triu_indices(n, 1)] = rng.normal(size=n * (n - 1) // 2) * 1e6
    return cov, p


@pytest.mark.parametrize("n, k", [(1, 1), (7, 3), (50, 12), (131, 1)])
def test_downdate_equals_dense_rank_k(n: int, k: int) -> None:
    """``dsyrk`` on the stored triangle (leading dimension > n) equals ``P - W W^T``."""
    rng = np.random.default_rng(n * 100 + k)
    cov, p = _stored(n, rng, capacity=n + 17)
    w = rng.normal(size=(n, k)) * 0.1
    outside = cov._buf[n:].copy()
    cov.downdate(w)
    np.testing.assert_allclose(cov.dense(), p - w @ w.T, atol=TOL, rtol=0)
    np.testing.assert_array_equal(cov._buf[n:], outside)  # rows beyond n untouched


def test_syrk_rejects_bad_buffers() -> None:
    """A non-contiguous buffer or a wrongly shaped factor is a ValueError, not a silent copy."""
    buf = np.zeros((10, 10))
    with pytest.raises(ValueError, match="C-contiguous"):
        syrk_lower_inplace(buf[:, :8], 8, np.ones((8, 2)))
    with pytest.raises(ValueError, match="expected"):
        syrk_lower_inplace(buf, 8, np.ones((7, 2)))


def test_reads_match_dense() -> None:
    """``block`` (below, above, across the diagonal), ``columns`` and ``take``."""
    rng = np.random.default_rng(1)
    n = 23
    cov, p = _stored(n, rng, capacity=40)
    for r0, r1, c0, c1 in [(10, 14, 0, 3), (0, 3, 10, 14), (5, 9, 5, 9), (4, 12, 8, 20),
                           (0, n, 0, n), (22, 23, 0, 23)]:
        np.testing.assert_array_equal(cov.block(r0, r1, c0, c1), p[r0:r1, c0:c1])
    for o, d in [(0, 3), (5, 2), (20, 3)]:
        np.testing.assert_array_equal(cov.columns(o, d), p[:, o : o + d])
    ik = np.array([[3, 4, 5], [17, 18, 19]])
    np.testing.assert_array_equal(cov.take(ik[:, :, None], ik[:, None, :]),
                                  p[ik[:, :, None], ik[:, None, :]])
    with pytest.raises(IndexError):
        cov.block(0, n + 1, 0, 1)


def test_transform_leading_equals_dense() -> None:
    """Robot-only motion: ``T P T^T + Q`` with ``T = diag(F, I)``; ``P_MM`` unchanged."""
    rng = np.random.default_rng(2)
    n = 30
    cov, p = _stored(n, rng, capacity=32)
    f = np.eye(3) + 0.3 * rng.normal(size=(3, 3))
    q = _spd(rng, 3) * 0.01
    t = np.eye(n)
    t[:3, :3] = f
    ref = t @ p @ t.T
    ref[:3, :3] += q
    cov.transform_leading(f, q)
    np.testing.assert_allclose(cov.dense(), ref, atol=TOL, rtol=0)


def test_append_grow_and_delete_equal_dense() -> None:
    """Appending past the capacity and deleting scattered states match the dense edits."""
    rng = np.random.default_rng(3)
    cov, p = _stored(6, rng, capacity=8)
    for d in (2, 3, 2, 3, 2):  # grows 8 -> 12 -> 18 -> ...
        big = _spd(rng, p.shape[0] + d)
        cross, new = big[-d:, :-d], big[-d:, -d:]
        cov.append(cross, new)
        p = np.block([[p, cross.T], [cross, new]])
    assert cov.n == p.shape[0] == 18 and cov.capacity >= 18
    np.testing.assert_array_equal(cov.dense(), p)
    keep = np.ones(cov.n, bool)
    keep[[3, 4, 9, 10, 11, 17]] = False
    cov.delete(keep)
    np.testing.assert_array_equal(cov.dense(), p[np.ix_(keep, keep)])
    cov.delete(np.ones(cov.n, bool))  # nothing removed: unchanged
    np.testing.assert_array_equal(cov.dense(), p[np.ix_(keep, keep)])


def _ekf_with_random_state(rng: np.random.Generator, n_lm: int) -> EkfSlam:
    """An EKF with ``n_lm`` planar landmarks around the robot and a random SPD covariance."""
    be = EkfSlam(Rig().odometry, SlamConfig(), np.array([0.3, -0.2, 0.4]))
    for j in range(n_lm):
        z = np.array([rng.uniform(-1.2, 1.2), rng.uniform(1.0, 4.0)])
        obs = Obs("point2", z, np.diag([0.01**2, 0.03**2]), landmark_id=j)
        assert be._augment(obs, j) == j
    n = be._n
    be._cov = LowerCovariance(_spd(rng, n) * 0.05, n + 5)
    return be


def test_ekf_update_equals_dense_kalman_formula() -> None:
    """Stacked update (eqs. 21-23) = ``x + K nu`` and ``P - K S K^T`` with the dense ``H``."""
    rng = np.random.default_rng(4)
    be = _ekf_with_random_state(rng, 40)
    n = be._n
    x0, p0 = be.x.copy(), be.P
    seen = [3, 11, 12, 30, 39]
    pairs = []
    for j in seen:
        z = np.array([rng.uniform(-1.0, 1.0), rng.uniform(1.0, 4.0)])
        pairs.append((be._slots[j], Obs("point2", z, np.diag([0.02**2, 0.05**2]), landmark_id=j)))
    h = np.zeros((2 * len(seen), n))
    nu = np.zeros(2 * len(seen))
    r = np.zeros((2 * len(seen), 2 * len(seen)))
    for i, (slot, obs) in enumerate(pairs):
        z_hat, h_r, h_l = be._h(slot, obs)
        h[2 * i : 2 * i + 2, :3] = h_r
        h[2 * i : 2 * i + 2, slot.offset : slot.offset + 2] = h_l
        nu[2 * i : 2 * i + 2] = obs.z - z_hat
        nu[2 * i] = wrap_angle(float(nu[2 * i]))
        r[2 * i : 2 * i + 2, 2 * i : 2 * i + 2] = obs.R
    s = h @ p0 @ h.T + r
    k = p0 @ h.T @ np.linalg.inv(s)
    x_ref = x0 + k @ nu
    x_ref[2] = wrap_angle(float(x_ref[2]))
    p_ref = p0 - k @ s @ k.T
    assert be._update(pairs) == len(seen)
    np.testing.assert_allclose(be.x, x_ref, atol=TOL, rtol=0)
    np.testing.assert_allclose(be.P, p_ref, atol=TOL, rtol=0)


def test_ekf_prediction_equals_dense_jacobian_product() -> None:
    """Several odometry samples: ``F P F^T + sum F_u Q F_u^T`` on the full state."""
    rng = np.random.default_rng(5)
    be = _ekf_with_random_state(rng, 25)
    n = be._n
    p0, pose = be.P, be.x[:3].copy()
    wheel = np.array([[0.010, 0.012], [0.011, 0.009], [0.0, 0.001]])
    odo = be.motion.params  # the wheel model's constants
    t = np.eye(n)
    q = np.zeros((n, n))
    for dl, dr in wheel:
        pose, f_x, f_u = diff_drive_step(pose, float(dl), float(dr), odo.wheel_base)
        step = np.eye(n)
        step[:3, :3] = f_x
        t = step @ t
        q = step @ q @ step.T
        q[:3, :3] += f_u @ wheel_noise_cov(dl, dr, odo.k_r, odo.k_l) @ f_u.T
    ref = t @ p0 @ t.T + q
    ref[:3, :3] += be.config.ekf.var_floor * np.eye(3)
    be.predict(wheel)
    np.testing.assert_allclose(be.P, ref, atol=TOL, rtol=0)
    np.testing.assert_allclose(be.x[:3], pose, atol=TOL, rtol=0)
