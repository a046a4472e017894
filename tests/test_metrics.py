"""Metrics against hand-computed cases and GTSAM."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest

from lampsam.evaluation import metrics as M


def test_pose_errors_hand_case() -> None:
    est = np.array([[1.0, 2.0, 3.1], [0.0, 0.0, 0.0]])
    gt = np.array([[1.3, 2.4, -3.1], [0.0, 0.0, 0.5]])
    pos, head = M.pose_errors(est, gt)
    np.testing.assert_allclose(pos, [0.5, 0.0], atol=1e-12)  # 3-4-5 triangle
    # 3.1 - (-3.1) = 6.2 rad wraps to 6.2 - 2 pi = -0.0832
    np.testing.assert_allclose(head, [6.2 - 2 * np.pi, -0.5], atol=1e-12)
    s = M.error_stats(pos)
    assert s.rms == pytest.approx(np.sqrt(0.125)) and s.max == pytest.approx(0.5) and s.n == 2


def test_se2_log_matches_gtsam(rng: np.random.Generator) -> None:
    poses = np.column_stack([rng.uniform(-5, 5, 20), rng.uniform(-5, 5, 20), rng.uniform(-3.1, 3.1, 20)])
    poses[0] = [0.3, -0.2, 0.0]  # the small-angle branch
    poses[1] = [0.3, -0.2, 1e-12]
    ours = M.se2_log(poses)
    ref = np.array([gtsam.Pose2.Logmap(gtsam.Pose2(*p)) for p in poses])
    np.testing.assert_allclose(ours, ref, atol=1e-9)


def test_tangent_errors_match_gtsam_between(rng: np.random.Generator) -> None:
    a = np.column_stack([rng.uniform(-5, 5, 10), rng.uniform(-5, 5, 10), rng.uniform(-3, 3, 10)])
    b = a + rng.normal(0, 0.2, a.shape)
    ours = M.tangent_errors(a, b)
    ref = np.array(
        [gtsam.Pose2.Logmap(gtsam.Pose2(*p).between(gtsam.Pose2(*q))) for p, q in zip(a, b, strict=True)]
    )
    np.testing.assert_allclose(ours, ref, atol=1e-9)


def test_nees_hand_case_and_singular() -> None:
    e = np.array([[1.0, 0.0, 0.0], [0.0, 2.0, 0.1]])
    P = np.array([np.diag([4.0, 1.0, 1.0]), np.diag([1.0, 1.0, 0.0])])
    out = M.nees(e, P)
    assert out[0] == pytest.approx(0.25)
    assert np.isnan(out[1])  # singular covariance -> NaN, not an exception


def test_chi2_bounds_known_values() -> None:
    lo, hi = M.chi2_bounds(3, 1)
    assert lo == pytest.approx(0.2158, abs=1e-4) and hi == pytest.approx(9.3484, abs=1e-4)
    lo10, hi10 = M.chi2_bounds(3, 10)  # chi2(30) quantiles / 10
    assert lo10 == pytest.approx(1.6791, abs=1e-4) and hi10 == pytest.approx(4.6979, abs=1e-4)


def test_nees_summary_detects_overconfidence(rng: np.random.Generator) -> None:
    n_runs, n_steps = 10, 200
    # Consistent: errors drawn from the reported covariance.
    consistent = np.sum(rng.normal(size=(n_runs, n_steps, 3)) ** 2, axis=2)
    s = M.nees_summary(consistent, dof=3)
    assert abs(s.mean - 3.0) < 3 * np.sqrt(2 * 3 / (n_runs * n_steps)) * 3  # 3 sigma of the mean
    assert not s.overconfident and not s.underconfident and s.fraction_inside > 0.85
    assert M.nees_summary(consistent / 4.0, dof=3).underconfident
    # Covariance reported 4x too small -> NEES about 12.
    s_over = M.nees_summary(4.0 * consistent, dof=3)
    assert s_over.overconfident and s_over.fraction_above > 0.9


def test_evo_ape_rpe_constant_offset() -> None:
    t = np.arange(0.0, 50.0, 0.5)
    gt = np.column_stack([0.1 * t, np.zeros_like(t), np.zeros_like(t)])
    est = gt + [0.0, 0.1, 0.0]
    out = M.evo_ape_rpe(t, est, t, gt)
    assert out["ape_rmse_m"] == pytest.approx(0.1, abs=1e-9)
    assert out["rpe_trans_per_m"] == pytest.approx(0.0, abs=1e-9)  # an offset is no drift
    assert out["path_length_m"] == pytest.approx(0.1 * t[-1], abs=1e-9)


def test_evo_no_overlap_raises() -> None:
    t = np.arange(10.0)
    p = np.zeros((10, 3))
    with pytest.raises(M.MetricsError):
        M.evo_ape_rpe(t, p, t + 100.0, p)


def test_interpolate_poses_shorter_arc() -> None:
    t = np.array([0.0, 1.0])
    p = np.array([[0.0, 0.0, 3.0], [1.0, 2.0, -3.0]])  # crosses +-pi
    q = M.interpolate_poses(np.array([0.5]), t, p)
    np.testing.assert_allclose(q[0, :2], [0.5, 1.0])
    assert abs(abs(q[0, 2]) - np.pi) < 0.01  # through pi, not through 0


def test_map_error_by_id() -> None:
    stats, n = M.map_error(
        np.array([3, 7, -1]),
        np.array([[1.0, 1.0, 2.5], [0.0, 0.3, 2.4], [9.0, 9.0, 9.0]]),
        np.array([7, 3]),
        np.array([[0.0, 0.0, 2.5], [1.0, 1.4, 2.5]]),
    )
    assert n == 2
    assert stats.rms == pytest.approx(np.sqrt((0.4**2 + 0.3**2) / 2))


def test_autocorrelation_time_iid_and_ar1(rng: np.random.Generator) -> None:
    iid = rng.normal(size=20000)
    assert M.integrated_autocorrelation_time(iid) == pytest.approx(1.0, abs=0.1)
    # AR(1) with coefficient a has tau = (1 + a) / (1 - a) = 19 for a = 0.9
    a, x = 0.9, np.empty(50000)
    x[0] = 0.0
    e = rng.normal(size=x.size)
    for i in range(1, x.size):
        x[i] = a * x[i - 1] + e[i]
    assert M.integrated_autocorrelation_time(x) == pytest.approx(19.0, rel=0.15)


def test_correlated_nees_is_not_called_overconfident(rng: np.random.Generator) -> None:
    # One run, 600 steps of a slowly varying but consistent NEES (mean 3 over the long run):
    # a 10 % excursion of the time average must not count as significant.
    steps = 600
    slow = np.repeat(np.sum(rng.normal(size=(30, 3)) ** 2, axis=1), steps // 30)
    s = M.nees_summary(slow * 3.3 / slow.mean(), dof=3)
    assert not s.overconfident
