"""Merging duplicate planar landmarks (backend/landmark_merge.py) and the odometry cov_scale."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.stats import chi2

from lampsam.backend.covariance import LowerCovariance
from lampsam.backend.landmark_merge import (
    CoVisibility,
    ekf_merge_once,
    equality_update,
    lower_diff_cov,
    merge_pairs,
)
from lampsam.datasets.odometry import Pose2OdometryModel

GATE = float(chi2.ppf(0.99, 2))
AMBIGUITY = float(chi2.ppf(0.9999, 2))


def _state(rng: np.random.Generator, landmarks: list[tuple[float, float]]
           ) -> tuple[np.ndarray, np.ndarray]:
    """A pose and planar landmarks with a random SPD covariance (pose-landmark
    correlations included), each landmark about 0.5 m sigma."""
    n = 3 + 2 * len(landmarks)
    x = np.concatenate([[0.0, 0.0, 0.1], np.ravel(landmarks)])
    a = rng.normal(scale=0.15, size=(n, n))
    p = a @ a.T + np.diag([0.01, 0.01, 1e-3] + [0.25] * (n - 3))
    return x, p


def _candidates(x: np.ndarray, cov: LowerCovariance, m: int
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    ids = np.arange(m)
    offsets = 3 + 2 * ids
    return ids, offsets, x[offsets[:, None] + np.arange(2)]


def test_duplicate_is_merged_and_update_matches_dense_kalman() -> None:
    rng = np.random.default_rng(3)
    # landmark 1 is a copy of landmark 0 (0.6 m off); landmark 2 is another tree
    x, p = _state(rng, [(10.0, 0.0), (10.5, 0.3), (25.0, 4.0)])
    cov = LowerCovariance(p)
    ids, offsets, xy = _candidates(x, cov, 3)
    pairs = merge_pairs(ids, xy, np.array([5, 40, 7]), lower_diff_cov(cov, offsets),
                        CoVisibility().together, GATE, AMBIGUITY, radius=30.0)
    assert [(q.keep, q.drop) for q in pairs] == [(0, 1)]  # the older one is kept
    h = np.zeros((2, len(x)))
    h[:, 3:5] = np.eye(2)
    h[:, 5:7] = -np.eye(2)
    d = x[3:5] - x[5:7]
    assert pairs[0].d2 == pytest.approx(float(d @ np.linalg.solve(h @ p @ h.T, d)), rel=1e-9)
    # the pseudo-measurement l0 - l1 = 0, against the dense Kalman update (eqs. 21-23)
    var = 1e-6
    s = h @ p @ h.T + var * np.eye(2)
    k = p @ h.T @ np.linalg.inv(s)
    x_ref = x + k @ (0.0 - h @ x)
    p_ref = p - k @ h @ p
    x_new = x.copy()
    equality_update(x_new, cov, 3, 5, var)
    np.testing.assert_allclose(x_new, x_ref, atol=1e-9)
    np.testing.assert_allclose(cov.dense(), p_ref, atol=1e-9)
    assert np.linalg.norm(x_new[3:5] - x_new[5:7]) < 1e-3  # one tree now


def test_near_pair_seen_together_is_not_merged() -> None:
    rng = np.random.default_rng(4)
    x, p = _state(rng, [(10.0, 0.0), (10.5, 0.3)])
    cov = LowerCovariance(p)
    covis = CoVisibility()
    covis.add_frame([0, 1])  # both seen in one frame: two trees
    ids, offsets, xy = _candidates(x, cov, 2)
    assert merge_pairs(ids, xy, np.array([5, 40]), lower_diff_cov(cov, offsets),
                       covis.together, GATE, AMBIGUITY, radius=30.0) == []
    x_before = x.copy()
    assert ekf_merge_once(x, cov, ids, offsets, np.array([5, 40]), covis, GATE, AMBIGUITY,
                          30.0) is None
    np.testing.assert_array_equal(x, x_before)


def test_ambiguous_duplicate_is_not_merged() -> None:
    rng = np.random.default_rng(5)
    # landmark 1 is within the gate of both 0 and 2: which tree it copies is unclear
    x, p = _state(rng, [(10.0, 0.0), (10.6, 0.0), (11.2, 0.0)])
    cov = LowerCovariance(p)
    ids, offsets, xy = _candidates(x, cov, 3)
    covis = CoVisibility()
    covis.add_frame([0, 2])
    pairs = merge_pairs(ids, xy, np.array([1, 9, 2]), lower_diff_cov(cov, offsets),
                        covis.together, GATE, AMBIGUITY, radius=30.0)
    assert pairs == []


def test_merge_moves_exclusions_to_the_kept_landmark() -> None:
    covis = CoVisibility()
    covis.add_frame([1, 7])
    covis.merge(keep=0, drop=1)
    assert covis.together(0, 7) and covis.together(7, 0)
    assert not covis.together(7, 1) and 1 not in covis.seen_with


def test_pose2_cov_scale_scales_only_a_sample_s_own_covariance() -> None:
    base = Pose2OdometryModel()
    scaled = Pose2OdometryModel(cov_scale=16.0)
    delta = np.array([1.0, 0.0, 0.1])
    own = np.diag([1e-2, 4e-2, 1e-3])
    floor = np.diag([base.var_floor_xy, base.var_floor_xy, base.var_floor_theta])
    np.testing.assert_allclose(scaled.sample_cov(delta, own), 16.0 * own + floor)
    missing = np.full((3, 3), np.nan)  # the model's default noise is not scaled
    np.testing.assert_allclose(scaled.sample_cov(delta, missing), base.sample_cov(delta, missing))
    with pytest.raises(ValueError, match="cov_scale"):
        Pose2OdometryModel(cov_scale=0.0)
