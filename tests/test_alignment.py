"""SVD alignment (paper 2, eqs. 1-6) and RANSAC over correspondences."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from lampsam.localization.alignment import (
    AlignmentError,
    RansacConfig,
    align,
    align_planar,
    kabsch_batch,
    ransac_align,
    ransac_iterations,
)


def _scene(
    rng: np.random.Generator, n: int, planar: bool
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Body points K in front of a robot, their world images S = R K + t."""
    K = np.column_stack([rng.uniform(0.5, 4.0, n), rng.uniform(-2, 2, n), rng.uniform(0.1, 2.0, n)])
    if planar:
        yaw = rng.uniform(-np.pi, np.pi)
        R = Rotation.from_euler("z", yaw).as_matrix()
        t = np.array([rng.uniform(-5, 5), rng.uniform(-5, 5), 0.0])
    else:
        R = Rotation.random(random_state=int(rng.integers(1 << 31))).as_matrix()
        t = rng.uniform(-5, 5, 3)
    S = K @ R.T + t
    return S, K, R, t


def test_exact_recovery_without_noise(rng: np.random.Generator) -> None:
    S, K, R, t = _scene(rng, 20, planar=False)
    a = align(S, K)
    np.testing.assert_allclose(a.R, R, atol=1e-9)
    np.testing.assert_allclose(a.t, t, atol=1e-9)
    assert a.eps < 1e-9
    assert np.linalg.det(a.R) == pytest.approx(1.0, abs=1e-12)


def test_reflection_case_gives_a_proper_rotation(rng: np.random.Generator) -> None:
    # Coplanar points (z = 0): W has rank 2, so U V^T may come out with det -1.
    K = np.column_stack([rng.uniform(-1, 1, 12), rng.uniform(-1, 1, 12), np.zeros(12)])
    S = K.copy()
    # A genuine reflection of a non-planar set: det(U V^T) = -1 exactly.
    K3 = np.column_stack([rng.uniform(-1, 1, 12), rng.uniform(-1, 1, 12), rng.uniform(-1, 1, 12)])
    S3 = K3 * np.array([1.0, 1.0, -1.0])
    Sp = S3 - S3.mean(0)
    Kp = K3 - K3.mean(0)
    U, _, Vt = np.linalg.svd(Sp.T @ Kp)
    assert np.linalg.det(U @ Vt) == pytest.approx(-1.0, abs=1e-9)  # the case occurs
    R, _ = kabsch_batch(S3[None], K3[None])
    assert np.linalg.det(R[0]) == pytest.approx(1.0, abs=1e-9)
    np.testing.assert_allclose(R[0] @ R[0].T, np.eye(3), atol=1e-9)
    # For the coplanar set the reflection and the identity fit equally: a rotation comes out.
    a = align(S, K)
    np.testing.assert_allclose(a.R, np.eye(3), atol=1e-9)
    assert a.eps < 1e-9


@pytest.mark.parametrize("planar", [False, True])
def test_ransac_with_30_percent_wrong_matches(rng: np.random.Generator, planar: bool) -> None:
    n = 60
    S, K, R, t = _scene(rng, n, planar)
    S = S + rng.normal(0.0, 0.02, S.shape)  # 2 cm noise
    wrong = rng.permutation(n)[: int(0.3 * n)]
    S[wrong] = rng.uniform(-6, 6, (len(wrong), 3))  # 30 % wrong matches
    a = ransac_align(S, K, np.random.default_rng(1), RansacConfig(planar=planar))
    angle = np.linalg.norm(Rotation.from_matrix(a.R @ R.T).as_rotvec())
    assert angle < np.deg2rad(1.0)
    assert np.linalg.norm(a.t - t) < 0.05
    truth_in = np.ones(n, dtype=bool)
    truth_in[wrong] = False
    assert np.count_nonzero(a.inliers & ~truth_in) <= 1
    assert np.count_nonzero(a.inliers & truth_in) >= 0.9 * truth_in.sum()
    assert 0.01 < a.eps < 0.05  # RMS of 3-D residuals with sigma 2 cm per axis ~ 3.5 cm
    # plain least squares on the same data is ruined by the outliers
    assert np.linalg.norm(align(S, K).t - t) > 0.2


def test_planar_pose2_and_reproducibility(rng: np.random.Generator) -> None:
    S, K, R, t = _scene(rng, 30, planar=True)
    a = align_planar(S, K)
    yaw = np.arctan2(R[1, 0], R[0, 0])
    np.testing.assert_allclose(a.pose2(), [t[0], t[1], yaw], atol=1e-9)
    S[:8] += 3.0
    b1 = ransac_align(S, K, np.random.default_rng(7), RansacConfig())
    b2 = ransac_align(S, K, np.random.default_rng(7), RansacConfig())
    np.testing.assert_array_equal(b1.inliers, b2.inliers)
    np.testing.assert_allclose(b1.pose2(), [t[0], t[1], yaw], atol=1e-9)


def test_agrees_with_open3d(rng: np.random.Generator) -> None:
    o3d = pytest.importorskip("open3d")
    reg = o3d.pipelines.registration
    S, K, _, _ = _scene(rng, 40, planar=False)
    S_noisy = S + rng.normal(0, 0.01, S.shape)
    src = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(K))
    dst = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(S_noisy))
    corres = o3d.utility.Vector2iVector(
        np.column_stack([np.arange(40), np.arange(40)]).astype(np.int32)
    )
    T = reg.TransformationEstimationPointToPoint().compute_transformation(src, dst, corres)
    a = align(S_noisy, K)
    np.testing.assert_allclose(a.R, T[:3, :3], atol=1e-9)
    np.testing.assert_allclose(a.t, T[:3, 3], atol=1e-9)
    # RANSAC on clean data with wrong matches: both find the same transform
    S_bad = S_noisy.copy()
    S_bad[:10] = rng.uniform(-6, 6, (10, 3))
    dst_bad = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(S_bad))
    o3d.utility.random.seed(3)
    res = reg.registration_ransac_based_on_correspondence(
        src,
        dst_bad,
        corres,
        0.1,
        reg.TransformationEstimationPointToPoint(False),
        3,
        [],
        reg.RANSACConvergenceCriteria(2000, 0.999),
    )
    b = ransac_align(S_bad, K, np.random.default_rng(3), RansacConfig(planar=False))
    T2 = np.asarray(res.transformation)
    np.testing.assert_allclose(b.R, T2[:3, :3], atol=5e-3)
    np.testing.assert_allclose(b.t, T2[:3, 3], atol=1e-2)


def test_bad_input_raises() -> None:
    with pytest.raises(AlignmentError):
        align(np.zeros((2, 3)), np.zeros((2, 3)))
    with pytest.raises(AlignmentError):
        align(np.zeros((4, 3)), np.zeros((5, 3)))
    bad = np.ones((5, 3))
    bad[0, 0] = np.nan
    with pytest.raises(AlignmentError):
        align(bad, np.ones((5, 3)))
    rng = np.random.default_rng(0)
    with pytest.raises(AlignmentError):  # pure noise: no consensus
        ransac_align(
            rng.uniform(-5, 5, (20, 3)),
            rng.uniform(-5, 5, (20, 3)),
            rng,
            RansacConfig(inlier_threshold=0.01, min_inliers=6),
        )


def test_ransac_iterations_formula() -> None:
    assert ransac_iterations(1.0, 3, 0.999) == 1
    # 70 % inliers, 3 points: p = 0.343 -> log(0.001)/log(0.657) = 16.45 -> 17
    assert ransac_iterations(0.7, 3, 0.999) == 17
