"""Pose candidates: SIFT-style matching, SVD/RANSAC, rotation with the robot."""

from __future__ import annotations

import numpy as np
import pytest

from lampsam.factors.geometry import wrap_angle
from lampsam.localization.candidates import (
    CandidateCollector,
    CandidateConfig,
    CandidateError,
    PoseCandidate,
    match_descriptors,
    pf_candidates,
    propagate,
)
from lampsam.localization.particle_filter import sample_candidate_discs


def _world(rng: np.random.Generator, m: int = 1000) -> tuple[np.ndarray, np.ndarray]:
    """Spatial feature map: points on the walls of a 10 m x 10 m room, random descriptors."""
    side = rng.integers(0, 4, m)
    s = rng.uniform(0, 10, m)
    x = np.where(side == 0, 0.0, np.where(side == 1, 10.0, s))
    y = np.where(side == 2, 0.0, np.where(side == 3, 10.0, s))
    y = np.where(side < 2, s, y)
    pts = np.column_stack([x, y, rng.uniform(0.2, 1.8, m)])
    desc = rng.uniform(0, 1, (m, 128)).astype(np.float32)
    return pts, desc


def _frame(
    rng: np.random.Generator,
    pts: np.ndarray,
    desc: np.ndarray,
    pose: np.ndarray,
    n_clutter: int = 15,
) -> tuple[np.ndarray, np.ndarray]:
    """Features seen by a forward camera (57 deg FOV) at ``pose``, plus clutter (7 m range)."""
    c, s = np.cos(pose[2]), np.sin(pose[2])
    d = pts[:, :2] - pose[:2]
    bx = c * d[:, 0] + s * d[:, 1]
    by = -s * d[:, 0] + c * d[:, 1]
    vis = (bx > 0.3) & (np.abs(np.arctan2(by, bx)) < np.deg2rad(28.5)) & (np.hypot(bx, by) < 7.0)
    body = np.column_stack([bx, by, pts[:, 2]])[vis] + rng.normal(0, 0.01, (int(vis.sum()), 3))
    dsc = desc[vis] + rng.normal(0, 0.02, (int(vis.sum()), 128)).astype(np.float32)
    clutter_pts = np.column_stack(
        [
            rng.uniform(0.5, 4, n_clutter),
            rng.uniform(-1, 1, n_clutter),
            rng.uniform(0, 2, n_clutter),
        ]
    )
    clutter_desc = rng.uniform(0, 1, (n_clutter, 128)).astype(np.float32)
    return np.vstack([body, clutter_pts]), np.vstack([dsc, clutter_desc])


def test_ratio_test_keeps_true_matches(rng: np.random.Generator) -> None:
    train = rng.uniform(0, 1, (50, 128)).astype(np.float32)
    query = np.vstack(
        [train[:20] + rng.normal(0, 0.01, (20, 128)), rng.uniform(0, 1, (10, 128))]
    ).astype(np.float32)
    qi, ti = match_descriptors(query, train, 0.8)
    order = np.argsort(qi)
    np.testing.assert_array_equal(qi[order], np.arange(20))
    np.testing.assert_array_equal(ti[order], np.arange(20))
    with pytest.raises(CandidateError):
        match_descriptors(query[:, :64], train, 0.8)


def test_candidates_rotate_with_the_robot(rng: np.random.Generator) -> None:
    pts, desc = _world(rng)
    truth0 = np.array([4.0, 6.0, 0.3])
    coll = CandidateCollector(pts, desc, CandidateConfig(), np.random.default_rng(5))
    # turn in place at 30 deg/s, one frame each second, odometry frame = start pose
    for k in range(12):
        th = np.deg2rad(30.0 * k)
        truth = truth0 + np.array([0, 0, th])
        body, dsc = _frame(rng, pts, desc, truth)
        coll.add_frame(float(k), np.array([0.0, 0.0, th]), body, dsc)
    final = truth0 + np.array([0, 0, np.deg2rad(330.0)])
    assert len(coll.candidates) >= 10
    for c in coll.candidates:
        # every candidate, wherever in the turn it came from, is now a hypothesis
        # of the robot's final pose: same heading, same position
        assert np.linalg.norm(c.pose[:2] - final[:2]) < 0.05
        assert abs(wrap_angle(c.pose[2] - final[2])) < np.deg2rad(1.0)
        assert 0.10 <= c.radius <= 1.5
        assert c.radius == pytest.approx(max(0.10, 5.0 * c.eps))


def test_propagate_composes_the_odometry_increment() -> None:
    c = PoseCandidate(np.array([1.0, 2.0, np.pi / 2]), 0.3, 0.02, 10, 0.0)
    (moved,) = propagate([c], np.array([1.0, 0.0, np.pi / 2]))
    np.testing.assert_allclose(moved.pose, [1.0, 3.0, np.pi], atol=1e-12)
    np.testing.assert_allclose(c.pose, [1.0, 2.0, np.pi / 2])  # input unchanged


def test_equal_particles_per_candidate(rng: np.random.Generator) -> None:
    cands = [
        PoseCandidate(np.array([1.0, 1.0, 0.0]), 0.1, 0.02, 10, 0.0),
        PoseCandidate(np.array([5.0, 5.0, 1.0]), 1.0, 0.2, 8, 1.0),
    ]
    p = sample_candidate_discs(pf_candidates(cands), 500, 0.05, np.random.default_rng(2))
    assert p.shape == (1000, 3)
    assert np.all(np.hypot(p[:500, 0] - 1, p[:500, 1] - 1) <= 0.1 + 1e-12)
    assert np.all(np.hypot(p[500:, 0] - 5, p[500:, 1] - 5) <= 1.0 + 1e-12)
    # uniform over the disc: mean squared radius r^2 / 2 (N = 500, 3 sigma ~ 0.04 r^2)
    r2 = (p[500:, 0] - 5) ** 2 + (p[500:, 1] - 5) ** 2
    assert abs(r2.mean() - 0.5) < 0.04
    assert [r for _, r in pf_candidates(cands)] == [0.1, 1.0]


def test_no_candidate_from_unrelated_features(rng: np.random.Generator) -> None:
    pts, desc = _world(rng)
    coll = CandidateCollector(pts, desc, CandidateConfig(), np.random.default_rng(5))
    out = coll.add_frame(
        0.0,
        np.zeros(3),
        rng.uniform(0, 3, (40, 3)),
        rng.uniform(0, 1, (40, 128)).astype(np.float32),
    )
    assert out is None and coll.candidates == []
