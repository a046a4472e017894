"""Particle filter: resampling, likelihood, motion, estimate, convergence, kidnapping."""

from __future__ import annotations

import math

import numpy as np
import pytest

from lampsam.localization.grid import OccupancyGrid
from lampsam.localization.likelihood import (
    BeamModelConfig,
    LikelihoodFieldModel,
    RayCastModel,
    beam_log_likelihood,
    scan_log_likelihood,
)
from lampsam.localization.particle_filter import (
    KldConfig,
    MotionNoise,
    ParticleFilter,
    ParticleFilterConfig,
    ParticleFilterError,
    kld_sample_size,
    sample_candidate_discs,
    sample_motion,
    spread,
    systematic_resample,
    weighted_estimate,
    wrap,
)
from lampsam.localization.raycast import cast_rays

RES = 0.05


def l_room() -> OccupancyGrid:
    """An asymmetric 6 m x 4 m room at 5 cm: outer walls, a partition, two boxes."""
    lo = np.full((80, 120), -4.0)
    lo[:2, :] = lo[-2:, :] = lo[:, :2] = lo[:, -2:] = 4.0
    lo[:50, 70:72] = 4.0          # partition from the bottom wall, x = 3.5 m, up to y = 2.5 m
    lo[55:65, 20:30] = 4.0        # box at x 1.0-1.5, y 2.75-3.25
    lo[10:16, 95:110] = 4.0       # box at x 4.75-5.5, y 0.5-0.8
    return OccupancyGrid(lo, RES, np.zeros(3))


def _scan(grid: OccupancyGrid, pose: np.ndarray, angles: np.ndarray, rng: np.random.Generator,
          sigma: float = 0.02) -> np.ndarray:
    r = cast_rays(grid, pose[None, :], angles, max_range=8.0)[0]
    return r + rng.normal(0.0, sigma, r.shape)


# ---------------------------------------------------------------------- resampling
def test_systematic_resample_counts_proportional_to_weights(rng: np.random.Generator) -> None:
    w = rng.uniform(0.0, 1.0, 50) ** 3
    w /= w.sum()
    n = 1000
    trials = 400
    counts = np.zeros((trials, w.size))
    for k in range(trials):
        idx = systematic_resample(w, n, rng)
        counts[k] = np.bincount(idx, minlength=w.size)
        # Low variance: every particle gets floor(n w) or ceil(n w) copies.
        assert np.all(np.abs(counts[k] - n * w) < 1.0 + 1e-9)
    # Unbiased: mean counts match n w within 3 sigma (per-trial variance <= 1/4).
    tol = 3 * 0.5 / math.sqrt(trials)
    np.testing.assert_allclose(counts.mean(axis=0), n * w, atol=tol)


def test_systematic_resample_rejects_zero_weights(rng: np.random.Generator) -> None:
    with pytest.raises(ParticleFilterError, match="positive"):
        systematic_resample(np.zeros(4), 4, rng)


def test_kld_sample_size_formula() -> None:
    cfg = KldConfig(epsilon=0.05, z_quantile=2.326, n_min=1, n_max=10**6)
    # k = 11 bins: (10 / 0.1) (1 - 2/90 + sqrt(2/90) 2.326)^3, by hand = 100 * 1.32464^3 = 232.4
    k = 10.0
    expected = k / 0.1 * (1 - 2 / (9 * k) + math.sqrt(2 / (9 * k)) * 2.326) ** 3
    assert expected == pytest.approx(232.4, abs=0.1)
    assert kld_sample_size(11, cfg) == math.ceil(expected)
    assert kld_sample_size(1, KldConfig(n_min=300)) == 300


def test_kld_resampling_shrinks_a_concentrated_set(rng: np.random.Generator) -> None:
    grid = l_room()
    model = LikelihoodFieldModel(grid, BeamModelConfig(max_range=8.0))
    cfg = ParticleFilterConfig(kld=KldConfig(n_min=100, n_max=5000))
    pf = ParticleFilter(model, cfg, rng)
    pf.init_particles(np.column_stack([rng.normal(1.0, 0.05, 5000), rng.normal(1.0, 0.05, 5000),
                                       rng.normal(0.0, 0.02, 5000)]))
    pf.resample()
    assert 100 <= pf.n < 500   # a handful of bins need a few hundred particles
    pf.init_uniform(grid, 5000)
    pf.resample()
    assert pf.n > 2000         # particles everywhere need many


# ---------------------------------------------------------------------- likelihood
def test_beam_log_likelihood_hand_computed() -> None:
    cfg = BeamModelConfig(sigma_hit=0.2, z_hit=0.8, z_rand=0.2, max_range=5.0)
    # a = 0.8 / (sqrt(2 pi) 0.2) = 1.595769; a exp(-0.125) = 1.408265; + 0.2/5 -> log(1.448265)
    assert float(beam_log_likelihood(np.array([0.1]), cfg)[0]) == pytest.approx(0.370364, abs=2e-6)
    pure = BeamModelConfig(sigma_hit=0.2, z_hit=1.0, z_rand=0.0, max_range=5.0)
    expected = -0.5 * (0.1 / 0.2) ** 2 - math.log(math.sqrt(2 * math.pi) * 0.2)
    assert float(beam_log_likelihood(np.array([0.1]), pure)[0]) == pytest.approx(expected, abs=1e-6)
    # A scan: beams summed in log space, NaN and max-range beams skipped, times beam_weight.
    measured = np.array([1.0, np.nan, 2.0, 7.0])
    expected_r = np.array([[1.1, 3.0, 2.0, 1.0]])
    total = float(beam_log_likelihood(np.array([-0.1, 0.0]), cfg).sum())
    assert scan_log_likelihood(expected_r, measured, cfg)[0] == pytest.approx(total, abs=1e-6)
    half = BeamModelConfig(sigma_hit=0.2, z_hit=0.8, z_rand=0.2, max_range=5.0, beam_weight=0.5)
    assert scan_log_likelihood(expected_r, measured, half)[0] == pytest.approx(0.5 * total,
                                                                                abs=1e-6)


def test_models_agree_on_exact_endpoints(rng: np.random.Generator) -> None:
    grid = l_room()
    cfg = BeamModelConfig(sigma_hit=0.1, max_range=8.0)
    pose = np.array([2.0, 1.5, 0.3])
    angles = np.radians(np.arange(0.0, 360.0, 5.0))
    ranges = cast_rays(grid, pose[None], angles, 8.0)[0]
    per_beam_peak = float(beam_log_likelihood(np.array([0.0]), cfg)[0])
    lf = LikelihoodFieldModel(grid, cfg)
    march = RayCastModel(grid, cfg, "march")
    # Exact ranges: ray casting scores every beam at the peak. Endpoints land on the wall
    # cell's boundary, so the field (nearest cell, distance 0 or one cell) is within 0.05 m.
    np.testing.assert_allclose(march.log_likelihood(pose[None], ranges, angles),
                               [per_beam_peak * angles.size], rtol=1e-5)
    one_cell = float(beam_log_likelihood(np.array([RES]), cfg)[0])
    ll_lf = float(lf.log_likelihood(pose[None], ranges, angles)[0])
    assert angles.size * one_cell - 1e-3 <= ll_lf <= angles.size * per_beam_peak + 1e-3
    # Both prefer the true pose to a shifted one.
    poses = np.array([pose, pose + [0.3, 0.0, 0.0], pose + [0.0, 0.0, 0.2]])
    for model in (lf, march, RayCastModel(grid, cfg, "table", n_angles=72)):
        ll = model.log_likelihood(poses, ranges, angles)
        assert ll[0] > ll[1] and ll[0] > ll[2]


# ---------------------------------------------------------------------- motion, estimate
def test_sample_motion_noise_free_and_monte_carlo(rng: np.random.Generator) -> None:
    zero = MotionNoise(0, 0, 0, 0, 0, 0)
    p = np.array([[1.0, 2.0, math.pi / 2]])
    prev, now = np.array([0.0, 0.0, 0.0]), np.array([1.0, 0.0, 0.5])
    # Body-frame increment (1, 0, 0.5) applied at heading 90 deg: (1, 3, 90 + 28.6 deg).
    np.testing.assert_allclose(sample_motion(p, prev, now, zero, rng),
                               [[1.0, 3.0, math.pi / 2 + 0.5]], atol=1e-12)
    # The reverse motion: body-frame increment R(-0.5) (-1, 0) = (-cos 0.5, sin 0.5), -0.5 rad,
    # applied at heading 90 deg: (1 - sin 0.5, 2 - cos 0.5).
    back = sample_motion(p, now, prev, zero, rng)
    np.testing.assert_allclose(back, [[1.0 - math.sin(0.5), 2.0 - math.cos(0.5),
                                       math.pi / 2 - 0.5]], atol=1e-12)
    noise = MotionNoise(a_trans_trans=0.1, sigma_trans_min=0.0, a_trans_rot=0.0, a_rot_trans=0.0,
                        a_rot_rot=0.0, sigma_rot_min=0.0)
    n = 20000
    out = sample_motion(np.zeros((n, 3)), prev, np.array([2.0, 0.0, 0.0]), noise, rng)
    # Translation noise only: x ~ N(2, 0.2^2); 3 sigma bounds with N = 20000.
    assert out[:, 0].mean() == pytest.approx(2.0, abs=3 * 0.2 / math.sqrt(n))
    assert out[:, 0].std() == pytest.approx(0.2, rel=3 / math.sqrt(2 * n))
    np.testing.assert_allclose(out[:, 1:], 0.0, atol=1e-12)


def test_weighted_estimate_circular_mean_and_covariance(rng: np.random.Generator) -> None:
    n = 40000
    th = wrap(math.pi + rng.normal(0.0, 0.1, n))   # straddles the +-pi cut
    xy = rng.multivariate_normal([1.0, -2.0], [[0.04, 0.01], [0.01, 0.09]], n)
    parts = np.column_stack([xy, th])
    mean, cov = weighted_estimate(parts, np.zeros(n))
    assert abs(wrap(mean[2] - math.pi)) < 3 * 0.1 / math.sqrt(n)
    np.testing.assert_allclose(mean[:2], [1.0, -2.0], atol=3 * 0.3 / math.sqrt(n))
    np.testing.assert_allclose(cov[:2, :2], [[0.04, 0.01], [0.01, 0.09]], atol=0.003)
    assert cov[2, 2] == pytest.approx(0.01, rel=0.05)
    sxy, sth = spread(parts, np.zeros(n))
    assert sth == pytest.approx(0.1, rel=0.05)
    assert sxy == pytest.approx(math.sqrt(np.linalg.eigvalsh([[0.04, 0.01], [0.01, 0.09]])[-1]),
                                rel=0.05)
    # Weights: a particle with (almost) all the weight is the estimate.
    lw = np.full(n, -50.0)
    lw[7] = 0.0
    np.testing.assert_allclose(weighted_estimate(parts, lw)[0], parts[7], atol=1e-9)


def test_candidate_initialisation_same_count_per_disc(rng: np.random.Generator) -> None:
    cands = [(np.array([1.0, 1.0, 0.0]), 0.2), (np.array([4.0, 3.0, 3.0]), 0.5)]
    p = sample_candidate_discs(cands, 250, 0.05, rng)
    assert p.shape == (500, 3)
    for k, (pose, r) in enumerate(cands):
        part = p[k * 250:(k + 1) * 250]
        assert np.all(np.hypot(part[:, 0] - pose[0], part[:, 1] - pose[1]) <= r)
        assert np.all(np.abs(wrap(part[:, 2] - pose[2])) < 5 * 0.05)
    with pytest.raises(ParticleFilterError, match="no candidates"):
        sample_candidate_discs([], 10, 0.1, rng)


# ---------------------------------------------------------------------- end to end
def _drive(pf: ParticleFilter, grid: OccupancyGrid, path: np.ndarray, angles: np.ndarray,
           rng: np.random.Generator, odom_noise: float = 0.01) -> list[float]:
    """Run the filter along a true path; odometry = truth + small drift; returns evidence."""
    evidence = []
    odom = path[0].copy()
    for k in range(len(path)):
        if k > 0:
            step = path[k] - path[k - 1]
            new_odom = odom + step + rng.normal(0.0, odom_noise, 3) * [1, 1, 0.5]
            pf.predict(odom, new_odom)
            odom = new_odom
        pf.update(_scan(grid, path[k], angles, rng), angles)
        evidence.append(pf.evidence_per_beam)
        pf.resample_if_needed()
    return evidence


def _path(start: np.ndarray, n: int, step: float) -> np.ndarray:
    return np.array([start + [step * k * math.cos(start[2]), step * k * math.sin(start[2]), 0.0]
                     for k in range(n)])


def test_global_localization_converges_and_detects_kidnapping(rng: np.random.Generator) -> None:
    # 20,000 particles over the free space, KLD-adaptive: a few hundred once converged.
    # (Measured over 21 seeds: 21 converged to the truth; with a fixed 5,000, 16.)
    grid = l_room()
    cfg = BeamModelConfig(sigma_hit=0.2, max_range=8.0, beam_weight=0.3)
    model = LikelihoodFieldModel(grid, cfg)
    pf = ParticleFilter(model, ParticleFilterConfig(kld=KldConfig(n_min=300, n_max=20000)), rng)
    pf.init_uniform(grid, 20000)
    angles = np.radians(np.arange(0.0, 360.0, 6.0))
    truth = _path(np.array([0.8, 1.0, 0.2]), 12, 0.15)
    _drive(pf, grid, truth, angles, rng)
    mean, cov = pf.estimate()
    assert pf.converged() and pf.n <= 1000
    assert np.hypot(*(mean[:2] - truth[-1, :2])) < 0.10
    assert abs(wrap(mean[2] - truth[-1, 2])) < math.radians(5)
    assert np.all(np.linalg.eigvalsh(cov) >= -1e-12) and cov[0, 0] < 0.15 ** 2
    assert not pf.likelihood_collapsed()
    # Kidnap: the robot is carried to the other side of the partition; odometry says nothing.
    kidnapped = _path(np.array([5.0, 3.0, -2.5]), 4, 0.0)
    collapsed = []
    for pose in kidnapped:
        pf.predict(np.zeros(3), np.zeros(3))
        pf.update(_scan(grid, pose, angles, rng), angles)
        collapsed.append(pf.likelihood_collapsed())
        pf.resample_if_needed()
    assert collapsed[0] and collapsed[1]
    # Recovery: start over with particles everywhere.
    pf.init_uniform(grid, 20000)
    recovery = _path(kidnapped[-1], 14, 0.1)
    _drive(pf, grid, recovery, angles, rng)
    mean, _ = pf.estimate()
    assert pf.converged()
    assert np.hypot(*(mean[:2] - recovery[-1, :2])) < 0.10
    assert abs(wrap(mean[2] - recovery[-1, 2])) < math.radians(5)


def test_partial_scan_from_candidates_converges(rng: np.random.Generator) -> None:
    # A 180-degree scan with gaps (NaN), particles from two candidates, one of them right.
    grid = l_room()
    model = RayCastModel(grid, BeamModelConfig(sigma_hit=0.1, max_range=8.0, beam_weight=0.5))
    pf = ParticleFilter(model, ParticleFilterConfig(), rng)
    truth = np.array([2.5, 3.0, -1.0])
    pf.init_candidates([(truth + [0.15, -0.1, 0.05], 0.3), (np.array([5.0, 1.5, 2.0]), 0.3)],
                       per_candidate=150)
    angles = np.radians(np.arange(-90.0, 90.0, 4.0))
    path = _path(truth, 6, 0.1)
    evidence = []
    odom_prev = path[0]
    for k, pose in enumerate(path):
        if k:
            pf.predict(odom_prev, pose)
            odom_prev = pose
        z = _scan(grid, pose, angles, rng)
        z[::3] = np.nan
        pf.update(z, angles)
        evidence.append(pf.evidence_per_beam)
        pf.resample_if_needed()
    mean, _ = pf.estimate()
    assert np.hypot(*(mean[:2] - path[-1, :2])) < 0.10
    assert abs(wrap(mean[2] - path[-1, 2])) < math.radians(5)
