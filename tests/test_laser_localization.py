"""Laser global localization from no prior (localization/laser.py, evaluation/laser_trials.py)."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from lampsam.evaluation.laser_trials import OdometryNoise, holdout_split, simulated_odometry
from lampsam.factors.geometry import between, wrap_angle
from lampsam.localization.grid import OccupancyGrid
from lampsam.localization.laser import LaserLocalizerConfig, localize_scans
from lampsam.localization.likelihood import LikelihoodFieldModel
from lampsam.localization.raycast import cast_rays

RES = 0.05


def _empty_room() -> OccupancyGrid:
    """A 10 m x 8 m room with 10 cm walls and nothing inside (log-odds +-4): symmetric."""
    g = OccupancyGrid.empty(0.0, 0.0, 10.0, 8.0, RES)
    lo = np.full((g.height, g.width), -4.0)
    lo[:2, :] = lo[-2:, :] = lo[:, :2] = lo[:, -2:] = 4.0
    g.log_odds = lo
    return g


def _room() -> OccupancyGrid:
    """The walled room of :func:`_empty_room` with asymmetric boxes (log-odds +-4)."""
    g = _empty_room()
    lo = g.log_odds
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
    g = _empty_room()
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


def _room_log(tmp_path: Path) -> Path:
    """A CARMEN log of a loop in :func:`_room` (0.15 m per scan, seeded range noise) and
    its map (``tmp_path / "map"``, built by ``lampsam build-map``); returns the log."""
    from lampsam.cli import main
    from lampsam.datasets.carmen import carmen_beam_angles

    grid = _room()
    angles = carmen_beam_angles(180)
    rng = np.random.default_rng(8)
    # a loop around the room's middle, 0.15 m per scan
    s = np.arange(0.0, 14.0, 0.15)
    poses = np.column_stack([5.0 + 2.2 * np.cos(s / 2.2), 4.5 + 1.5 * np.sin(s / 2.2),
                             s / 2.2 + np.pi / 2])  # fmt: skip
    ranges = np.minimum(cast_rays(grid, poses, angles, 81.0) + rng.normal(0, 0.01, (len(s), 180)),
                        81.83)  # fmt: skip
    lines = []
    for k, (p, r) in enumerate(zip(poses, ranges, strict=True)):
        ts = 100.0 + 0.5 * k
        lines.append(f"FLASER 180 {' '.join(f'{v:.3f}' for v in r)} {p[0]:.4f} {p[1]:.4f} "
                     f"{p[2]:.4f} {p[0]:.4f} {p[1]:.4f} {p[2]:.4f} {ts:.3f} host {ts:.3f}")  # fmt: skip
    log_path = tmp_path / "room.log"
    log_path.write_text("\n".join(lines) + "\n")
    assert main(["build-map", str(log_path), "--out", str(tmp_path / "map")]) == 0
    return log_path


def test_cli_localize_carmen_log_trials(tmp_path: Path) -> None:
    """`lampsam localize LOG --map MAP --scans odd --trials N`: scored trials, strict summary."""
    import json

    from lampsam.cli import main

    log_path = _room_log(tmp_path)
    out = tmp_path / "loc"
    rc = main(["localize", str(log_path), "--map", str(tmp_path / "map"), "--scans", "odd",
               "--trials", "3", "--out", str(out)])  # fmt: skip
    doc = json.loads((out / "result.json").read_text(), parse_constant=lambda c: 1 / 0)
    summary = doc["summary"]
    assert summary["trials"] == 3 and summary["wrong_accepted"] == 0 and rc == 0
    assert summary["correct"] == summary["localized"] >= 2
    assert all(t["scans"][0] % 2 == 1 for t in doc["trials"])  # odd scans only
    assert doc["status"] == "ok"


def test_cli_localize_carmen_log_keeps_finished_trials_when_stopped(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A stop (SIGTERM / SIGINT raise KeyboardInterrupt in ``localize``) during the third
    of four trials: exit code 3, ``result.json`` written with the two finished trials and
    status ``interrupted`` (before: nothing written)."""
    import json

    from lampsam.cli import main
    from lampsam.evaluation import laser_trials as lt

    log_path = _room_log(tmp_path)
    calls: list[int] = []
    real = lt.run_trial

    def stopped_on_third(*a, **k):  # type: ignore[no-untyped-def]
        calls.append(1)
        if len(calls) == 3:
            raise KeyboardInterrupt("stopped by SIGTERM")
        return real(*a, **k)

    monkeypatch.setattr(lt, "run_trial", stopped_on_third)
    out = tmp_path / "loc"
    rc = main(["localize", str(log_path), "--map", str(tmp_path / "map"), "--scans", "odd",
               "--trials", "4", "--out", str(out)])  # fmt: skip
    doc = json.loads((out / "result.json").read_text(), parse_constant=lambda c: 1 / 0)
    assert rc == 3 and doc["status"] == "interrupted"
    assert doc["summary"]["trials"] == len(doc["trials"]) == 2


def test_research_adds_modes_and_keeps_a_converged_cluster() -> None:
    """The re-search while not accepted adds candidates as modes and keeps the filter's cluster.

    In an empty rectangle the search finds the pose and its half-turn twin; the
    filter has converged on the pose. The twin joins with ``research_share`` of
    the weight; the cluster keeps the rest and, the twin fitting the scan as
    well, after the next update too (before, the filter was re-seeded with
    equal particles in every candidate's disc: half the weight on the twin).
    """
    from lampsam.localization.laser import LaserAcceptConfig, _research, search_pyramid
    from lampsam.localization.particle_filter import ParticleFilter

    grid = _empty_room()
    rng = np.random.default_rng(9)
    angles = np.deg2rad(np.arange(-90.0, 90.0, 2.0))
    truth = np.array([[3.0 + 0.2 * k, 3.0, 0.0] for k in range(4)])
    ranges = cast_rays(grid, truth, angles, 12.0) + rng.normal(0, 0.02, (4, len(angles)))
    odom = simulated_odometry(truth, rng, OdometryNoise())
    cfg = replace(LaserLocalizerConfig(), beam=replace(LaserLocalizerConfig().beam, max_range=12.0))
    model = LikelihoodFieldModel(grid, cfg.beam)
    pf = ParticleFilter(model, cfg.pf, rng)
    pf.init_candidates([(truth[-1], 0.05)], 500, 0.01)  # converged at the last scan
    modes = _research(model, search_pyramid(model, cfg), pf, ranges, angles, odom, cfg,
                      LaserAcceptConfig(), np.zeros((0, 3)))  # fmt: skip
    twin = np.array([10.0 - truth[-1, 0], 8.0 - truth[-1, 1]])
    assert pf.n > 500 and np.any(np.hypot(*(pf.particles[500:, :2] - twin).T) < 0.3)
    w = np.exp(pf.log_weights)
    assert w.sum() == pytest.approx(1.0, abs=1e-9)
    assert w[:500].sum() == pytest.approx(1.0 - cfg.research_share, abs=1e-9)  # the cluster's weight
    assert len(modes) >= 2  # the twin is also a competing hypothesis of the acceptance test
    pf.update(ranges[-1], angles)
    near = np.hypot(*(pf.particles[:, :2] - truth[-1, :2]).T) < 0.2
    assert np.exp(pf.log_weights)[near].sum() > 0.6


def test_add_particles_rejects_a_bad_share() -> None:
    from lampsam.localization.particle_filter import ParticleFilter, ParticleFilterError

    grid = _room()
    pf = ParticleFilter(LikelihoodFieldModel(grid, LaserLocalizerConfig().beam), LaserLocalizerConfig().pf,
                        np.random.default_rng(1))  # fmt: skip
    pf.init_particles(np.array([[2.0, 2.0, 0.0]]))
    with pytest.raises(ParticleFilterError, match="share"):
        pf.add_particles(np.array([[3.0, 3.0, 0.0]]), 1.0)
