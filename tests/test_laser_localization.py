"""Laser global localization from no prior (localization/laser.py, evaluation/laser_trials.py)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from lampsam.evaluation.laser_trials import OdometryNoise, holdout_split, simulated_odometry
from lampsam.factors.geometry import between, wrap_angle
from lampsam.localization.grid import OccupancyGrid
from lampsam.localization.laser import LaserLocalizerConfig, localize_scans
from lampsam.localization.likelihood import LikelihoodFieldModel
from lampsam.localization.raycast import cast_rays

RES = 0.05


def _room() -> OccupancyGrid:
    """A 10 m x 8 m walled room with asymmetric boxes (log-odds +-4)."""
    g = OccupancyGrid.empty(0.0, 0.0, 10.0, 8.0, RES)
    lo = np.full((g.height, g.width), -4.0)
    lo[:2, :] = lo[-2:, :] = lo[:, :2] = lo[:, -2:] = 4.0
    for x0, y0, x1, y1 in [(1.0, 1.0, 2.5, 1.6), (6.0, 5.0, 6.6, 8.0), (4.0, 3.0, 4.4, 3.6),
                           (8.0, 0.0, 10.0, 1.5)]:  # fmt: skip
        lo[int(y0 / RES) : int(y1 / RES), int(x0 / RES) : int(x1 / RES)] = 4.0
    g.log_odds = lo
    return g


def test_localize_scans_finds_the_pose_from_no_prior() -> None:
    grid = _room()
    rng = np.random.default_rng(4)
    angles = np.deg2rad(np.arange(-90.0, 90.0, 2.0))
    # four poses 0.2 m apart along a straight drive
    truth = np.array([[2.0 + 0.2 * k, 4.5, 0.3] for k in range(4)])
    truth[:, :2] += np.column_stack([np.zeros(4), 0.2 * np.arange(4) * np.tan(0.3)])
    ranges = cast_rays(grid, truth, angles, 12.0) + rng.normal(0, 0.02, (4, len(angles)))
    odom = simulated_odometry(truth, rng, OdometryNoise())
    cfg = replace(LaserLocalizerConfig(particles=20_000),
                  beam=replace(LaserLocalizerConfig().beam, max_range=12.0))  # fmt: skip
    model = LikelihoodFieldModel(grid, cfg.beam)
    est = localize_scans(model, grid, ranges, angles, odom, cfg, rng)
    assert np.hypot(*(est.pose[:2] - truth[-1, :2])) < 0.15
    assert abs(wrap_angle(float(est.pose[2] - truth[-1, 2]))) < np.deg2rad(3.0)
    assert est.covariance.shape == (3, 3)
    assert est.status == "localized" and est.margin >= 8.0 and est.score >= 0.45


def test_a_symmetric_room_is_never_localized() -> None:
    """An empty rectangle looks the same from a pose and its half-turn twin: no answer is staked."""
    g = OccupancyGrid.empty(0.0, 0.0, 10.0, 8.0, RES)
    lo = np.full((g.height, g.width), -4.0)
    lo[:2, :] = lo[-2:, :] = lo[:, :2] = lo[:, -2:] = 4.0
    g.log_odds = lo
    rng = np.random.default_rng(5)
    angles = np.deg2rad(np.arange(-90.0, 90.0, 2.0))
    truth = np.array([[3.0 + 0.2 * k, 3.0, 0.0] for k in range(6)])
    ranges = cast_rays(g, truth, angles, 12.0) + rng.normal(0, 0.02, (6, len(angles)))
    odom = simulated_odometry(truth, rng, OdometryNoise())
    cfg = replace(LaserLocalizerConfig(particles=20_000),
                  beam=replace(LaserLocalizerConfig().beam, max_range=12.0))  # fmt: skip
    est = localize_scans(LikelihoodFieldModel(g, cfg.beam), g, ranges, angles, odom, cfg, rng,
                         min_scans=3)  # fmt: skip
    assert est.status != "localized"
    assert est.scans_used == 6  # it kept taking scans while ambiguous


def test_simulated_odometry_keeps_the_increments_within_the_noise() -> None:
    rng = np.random.default_rng(0)
    truth = np.column_stack([np.linspace(0, 5, 51), np.sin(np.linspace(0, 3, 51)),
                             np.linspace(0, 1.5, 51)])  # fmt: skip
    odom = simulated_odometry(truth, rng, OdometryNoise(0.05, 0.05, 0.02))
    np.testing.assert_allclose(odom[0], 0.0)
    steps = np.array([between(truth[k], truth[k + 1]) for k in range(50)])
    got = np.array([between(odom[k], odom[k + 1]) for k in range(50)])
    d = np.hypot(steps[:, 0], steps[:, 1])
    # every increment within 5 sigma of its noise (0.05 m per m + 1 mm)
    assert np.all(np.abs(got[:, 0] - steps[:, 0]) < 5 * (0.05 * d + 1e-3))
    assert not np.allclose(got, steps, atol=1e-4)  # the noise is there


def test_holdout_split_never_shares_a_scan() -> None:
    m, t = holdout_split(11)
    assert set(m) & set(t) == set() and len(m) + len(t) == 11
    assert np.all(m % 2 == 0) and np.all(t % 2 == 1)
