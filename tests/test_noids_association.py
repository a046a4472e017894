"""Association without ids: the online innovation scale, the new-landmark rule under it,
the constellation match of re-found landmarks and the EKF's merge update."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.stats import chi2

from lampsam.backend.association import (
    Assignment,
    InnovationScale,
    associate,
    innovation_scale,
    learn_scale,
)
from lampsam.backend.config import AssociationConfig
from lampsam.backend.constellation import equality_gain, match_constellation
from lampsam.backend.covariance import LowerCovariance
from lampsam.backend.models import Obs
from lampsam.backend.planar_gate import screen_point2


def _gated_d2(rng: np.random.Generator, s: float, n: int, gate: float) -> np.ndarray:
    """Squared distances of innovations drawn with ``s`` times a random stated
    covariance, measured against the stated one, keeping those inside ``gate``."""
    out: list[float] = []
    while len(out) < n:
        a = rng.normal(size=(2, 2))
        psi = a @ a.T + 0.1 * np.eye(2)  # the stated innovation covariance
        nu = rng.multivariate_normal(np.zeros(2), s * psi)
        d2 = float(nu @ np.linalg.solve(psi, nu))
        if d2 < gate:
            out.append(d2)
    return np.array(out)


@pytest.mark.parametrize("s", [0.08, 0.3, 0.7])
def test_innovation_scale_recovers_a_known_scale(s: float) -> None:
    """Monte Carlo (seeded): innovations whose true covariance is ``s`` times the
    stated one, gated at the 99 % chi-square(2) quantile as the backends see them;
    with margin 1 the estimate over a 400-match window is within 12 % of ``s`` (the
    median's relative standard error over 400 samples is about 6 %)."""
    rng = np.random.default_rng(7)
    gate = float(chi2.ppf(0.99, 2))
    est = InnovationScale(2, 0.99, window=400, min_count=20, floor=0.01, margin=1.0)
    for d2 in _gated_d2(rng, s, 400, gate):
        est.add(float(d2))
    assert est.scale == pytest.approx(s, rel=0.12)


def test_innovation_scale_clamps_and_waits() -> None:
    """The scale stays 1 until ``min_count`` matches, never goes below the floor (true
    scale 0.005 against floor 0.05) and never above 1 (true scale 3, truncated at
    the gate); the margin multiplies the estimate."""
    rng = np.random.default_rng(11)
    gate = float(chi2.ppf(0.99, 2))
    est = InnovationScale(2, 0.99, window=200, min_count=20, floor=0.05, margin=1.0)
    small = _gated_d2(rng, 0.005, 200, gate)
    for d2 in small[:19]:
        est.add(float(d2))
    assert est.scale == 1.0
    for d2 in small[19:]:
        est.add(float(d2))
    assert est.scale == 0.05
    big = InnovationScale(2, 0.99, window=200, min_count=20, floor=0.05, margin=1.0)
    for d2 in _gated_d2(rng, 3.0, 200, gate):
        big.add(float(d2))
    assert big.scale == 1.0
    m1 = InnovationScale(2, 0.99, window=300, min_count=20, floor=0.01, margin=1.0)
    m2 = InnovationScale(2, 0.99, window=300, min_count=20, floor=0.01, margin=2.0)
    for d2 in _gated_d2(rng, 0.1, 300, gate):
        m1.add(float(d2))
        m2.add(float(d2))
    assert m2.scale == pytest.approx(2.0 * m1.scale, rel=1e-12)
    with pytest.raises(ValueError, match="floor"):
        InnovationScale(floor=0.0)


def test_scaled_gate_new_landmark_rule() -> None:
    """A new tree 6 m from a mapped one, seen at 15 m with the stated 0.2 rad bearing
    sigma (innovation covariance S + R from a 0.5 m landmark sigma): at the stated
    noise it lands inside the 99 % gate (d2 < 9.21) and is taken for the mapped tree.
    With the scale learnt from matches whose real scatter is 0.1 of the stated
    covariance, its distance is ``d2 / s`` > the new-landmark threshold: it starts a
    landmark. The mapped tree's own re-sighting (d2 0.1) still matches."""
    cfg = AssociationConfig(use_known_ids=False, planar_noise_adapt=True,
                            planar_noise_floor=0.05, planar_noise_margin=1.0)
    r = np.diag([0.2**2, 0.63**2])
    z_hat = np.array([[0.0, 15.0]])  # mapped tree at bearing 0, 15 m
    s_pred = np.array([np.diag([(0.5 / 15.0) ** 2, 0.5**2])])
    new_tree = Obs("point2", np.array([6.0 / 15.0, 15.0]), r)  # 6 m to the side
    same_tree = Obs("point2", np.array([0.01, 15.1]), r)
    psi = s_pred[0] + r
    d2_new = float((new_tree.z - z_hat[0]) @ np.linalg.solve(psi, new_tree.z - z_hat[0]))
    assert 0.2 * cfg.new_threshold(2) < d2_new < cfg.gate(2)

    def nothing(lid: int, o: Obs) -> None:
        return None

    stated = innovation_scale(cfg).recent
    scr = screen_point2([new_tree], [5], z_hat, s_pred, cfg, stated.scale)
    a = associate([new_tree], {"point2": [5]}, nothing, cfg, lambda i: True, None, scr)
    assert a[0].status == "matched" and a[0].landmark_id == 5  # the stated gate: wrong match
    rng = np.random.default_rng(3)
    for d2 in _gated_d2(rng, 0.1, 50, cfg.gate(2)):
        stated.add(float(d2))
    assert stated.scale == pytest.approx(0.1, rel=0.35)
    scr = screen_point2([new_tree, same_tree], [5], z_hat, s_pred, cfg, stated.scale)
    a = associate([new_tree, same_tree], {"point2": [5]}, nothing, cfg, lambda i: True,
                  None, scr)
    assert a[0].status == "new" and a[0].landmark_id is None
    assert a[1].status == "matched" and a[1].landmark_id == 5


def test_learn_scale_takes_only_unambiguous_matches() -> None:
    """Only a match whose observation has a single landmark below the new-landmark
    threshold feeds the estimator, unscaled (the screen holds ``d2 / s``)."""
    cfg = AssociationConfig(use_known_ids=False, planar_noise_adapt=True)
    est = innovation_scale(cfg).recent
    est.scale = 0.5
    r = np.eye(2)
    obs = [Obs("point2", np.zeros(2), r), Obs("point2", np.zeros(2), r)]
    screened = {0: {1: (0.4, True)}, 1: {1: (0.2, True), 2: (3.0, True)}}
    assignments = [Assignment(0, 1, "matched", 0.4), Assignment(1, 1, "matched", 0.2)]
    scales = innovation_scale(cfg)
    scales.recent = est
    learn_scale(scales, obs, assignments, screened)
    assert list(est._d2) == [pytest.approx(0.2)]
    off = innovation_scale(AssociationConfig(use_known_ids=False))
    learn_scale(off, obs, assignments, screened)
    assert off.recent.n_seen == 0 and off.scale == 1.0


def _trees(rng: np.random.Generator, n: int, spacing: float) -> np.ndarray:
    """``n`` random points in a square, at least ``spacing`` apart (dart throwing)."""
    pts: list[np.ndarray] = []
    while len(pts) < n:
        p = rng.uniform(0.0, 80.0, 2)
        if all(np.hypot(*(p - q)) >= spacing for q in pts):
            pts.append(p)
    return np.array(pts)


def test_constellation_finds_the_copies_under_drift() -> None:
    """60 trees at least 4 m apart; six of them re-mapped after a drift of 0.15 rad
    and (6, -4) m with 0.3 m scatter, plus two genuinely new trees: the match pairs
    the six copies with their originals and recovers the drift (rotation within
    0.05 rad)."""
    rng = np.random.default_rng(5)
    old = _trees(rng, 60, 4.0)
    pick = np.array([3, 8, 15, 22, 40, 51])
    ang, t = 0.15, np.array([6.0, -4.0])
    rot = np.array([[math.cos(ang), -math.sin(ang)], [math.sin(ang), math.cos(ang)]])
    # copies: old = R new + t  =>  new = R^T (old - t)
    copies = (old[pick] - t) @ rot + rng.normal(0.0, 0.3, (6, 2))
    extra = np.array([[200.0, 200.0], [-50.0, 10.0]])
    new = np.vstack([copies, extra])
    m = match_constellation(new, old, radius=25.0, tol=1.5, min_inliers=4, max_angle=0.3)
    assert m is not None
    assert m.pairs == [(i, int(pick[i])) for i in range(6)]
    assert m.rotation == pytest.approx(ang, abs=0.05)
    assert m.rms < 1.0


def test_constellation_refuses_ambiguous_and_sparse_cases() -> None:
    """On a regular 5 m grid every shift by one cell fits as well as the true one:
    no match (the margin). Three copies are fewer than ``min_inliers`` 4: no match."""
    g = np.array([[5.0 * i, 5.0 * j] for i in range(8) for j in range(8)])
    new = g[[9, 10, 11, 17, 18, 19]] + np.array([0.2, -0.1])
    assert match_constellation(new, g, radius=12.0, tol=1.0, min_inliers=4) is None
    rng = np.random.default_rng(2)
    old = _trees(rng, 40, 4.0)
    assert match_constellation(old[:3] + 0.5, old, radius=10.0, tol=1.0, min_inliers=4) is None


def test_equality_gain_fuses_two_estimates_of_one_tree() -> None:
    """Robot (3) + two independent landmark estimates a, b: the merge constraint
    ``a - b = 0`` gives both the information-weighted mean and its covariance
    ``(Pa^-1 + Pb^-1)^-1`` (to the constraint's 1e-8 m^2), and moves a robot
    correlated with b by the gain on that correlation."""
    pa = np.array([[1.0, 0.2], [0.2, 0.5]])
    pb = np.array([[0.3, 0.0], [0.0, 2.0]])
    p = np.zeros((7, 7))
    p[:3, :3] = np.diag([0.5, 0.5, 0.01])
    p[3:5, 3:5] = pa
    p[5:7, 5:7] = pb
    p[0, 5] = p[5, 0] = 0.2  # robot x correlated with b's x
    x = np.array([0.0, 0.0, 0.0, 10.0, 5.0, 12.0, 4.0])
    cov = LowerCovariance(p, 8)
    w, dx = equality_gain(cov, x, [(3, 5)], 1e-8)
    x1 = x + dx
    cov.downdate(w)
    p1 = cov.dense()
    ia, ib = np.linalg.inv(pa), np.linalg.inv(pb)
    fused_cov = np.linalg.inv(ia + ib)
    fused = fused_cov @ (ia @ x[3:5] + ib @ x[5:7])
    np.testing.assert_allclose(x1[3:5], fused, atol=1e-5)
    np.testing.assert_allclose(x1[5:7], fused, atol=1e-5)
    np.testing.assert_allclose(p1[3:5, 3:5], fused_cov, atol=1e-6)
    # the robot x moves by cov(x_r, a - b) Psi^-1 (b - a) = -0.2 * [Psi^-1 (b - a)]_0
    psi = pa + pb + 1e-8 * np.eye(2)
    expect = np.array([-0.2, 0.0]) @ np.linalg.solve(psi, x[5:7] - x[3:5])
    assert x1[0] == pytest.approx(expect, abs=1e-9)


def test_idle_scales_keep_revisits_apart() -> None:
    """With ``planar_noise_idle_split`` 30, a match of a landmark idle 50 steps feeds
    the 'old' estimator only, and each landmark's gate uses its own bucket's scale."""
    cfg = AssociationConfig(use_known_ids=False, planar_noise_adapt=True,
                            planar_noise_idle_split=30)
    scales = innovation_scale(cfg)
    scales.recent.scale = 0.1
    obs = [Obs("point2", np.zeros(2), np.eye(2))]
    learn_scale(scales, obs, [Assignment(0, 4, "matched", 2.0)], {0: {4: (2.0, True)}},
                lambda lid: 50)
    assert scales.old.n_seen == 1 and scales.recent.n_seen == 0
    assert list(scales.old._d2) == [pytest.approx(2.0)]  # old scale 1: unscaled as is
    np.testing.assert_allclose(scales.scales(np.array([0, 30, 31, 500])), [0.1, 0.1, 1.0, 1.0])
