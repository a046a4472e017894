"""A new user's laser logs (audit): a log whose poses drift (raw odometry) is told apart.

Every log here is built from code: a small room ray-cast at known poses
(``raycast.cast_rays``), written as CARMEN lines.
"""

from __future__ import annotations

import logging
import math
from pathlib import Path

import numpy as np
import pytest

from lampsam.datasets.carmen import carmen_beam_angles, read_carmen
from lampsam.localization.grid import OccupancyGrid, integrate_scan
from lampsam.localization.laser_grid import build_checked_laser_grid, keyframe_indices
from lampsam.localization.map_config import LaserGridConfig
from tests.conftest import boxed_room, cast_grid_ranges, rectangle_laps, write_flaser_log

ANGLES = carmen_beam_angles(180)


def _room() -> OccupancyGrid:
    """A 12 m x 8 m room with walls and three boxes, 0.1 m cells."""
    return boxed_room(12.0, 8.0, ((3.0, 3.0, 5.0, 4.5), (7.5, 2.5, 8.5, 5.5), (10.0, 6.0, 11.0, 7.0)))


def _cast(grid: OccupancyGrid, poses: np.ndarray, max_range: float) -> np.ndarray:
    """(N, 180) ranges to the first occupied cell, marched in 2 cm steps."""
    return cast_grid_ranges(grid, poses, ANGLES, max_range, 0.02)


def _loop_poses(laps: int = 2, step: float = 0.2) -> np.ndarray:
    """(N, 3) poses around the rectangle x in [1.5, 10.5], y in [1.5, 6.5], ``laps`` times."""
    return rectangle_laps((1.5, 1.5), (10.5, 6.5), laps, step)


def _drift(poses: np.ndarray, heading_bias: float) -> np.ndarray:
    """The poses as odometry with a heading bias per step integrates them, rad."""
    out = [poses[0].copy()]
    for a, b in zip(poses[:-1], poses[1:], strict=True):
        c, s = math.cos(a[2]), math.sin(a[2])
        d = b[:2] - a[:2]
        lx, ly = c * d[0] + s * d[1], -s * d[0] + c * d[1]
        dth = (b[2] - a[2] + math.pi) % (2 * math.pi) - math.pi
        q = out[-1]
        c, s = math.cos(q[2]), math.sin(q[2])
        out.append(np.array([q[0] + c * lx - s * ly, q[1] + s * lx + c * ly,
                             q[2] + dth + heading_bias]))
    return np.array(out)



@pytest.fixture(scope="module")
def scans_and_poses() -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(0)
    poses = _loop_poses()
    ranges = _cast(_room(), poses, 10.0)
    ranges = np.where(ranges >= 10.0 - 1e-6, 81.83, ranges + rng.normal(0, 0.01, ranges.shape))
    return poses, ranges


def test_true_poses_are_consistent_and_drifting_ones_are_not(
        tmp_path: Path, scans_and_poses: tuple[np.ndarray, np.ndarray]) -> None:
    poses, ranges = scans_and_poses
    good = read_carmen(write_flaser_log(tmp_path / "good.log", poses, ranges)).scans
    # 0.01 rad per 0.2 m step: 2.4 rad over the two laps, a raw odometry log's poses
    bad = read_carmen(write_flaser_log(tmp_path / "raw.log", _drift(poses, 0.01), ranges)).scans
    _, _, c_good = build_checked_laser_grid(good, good.poses)
    _, _, c_bad = build_checked_laser_grid(bad, bad.poses)
    assert c_good is not None and c_bad is not None
    assert c_good.score > 0.9 and not c_good.poor
    assert c_bad.score < 0.6 and c_bad.poor
    assert c_good.as_dict()["poor"] is False and len(c_good.per_chunk) == 6


def test_the_check_leaves_the_grid_as_it_was(
        tmp_path: Path, scans_and_poses: tuple[np.ndarray, np.ndarray]) -> None:
    """The grid built with the check is the scan-by-scan ``integrate_scan`` grid."""
    poses, ranges = scans_and_poses
    scans = read_carmen(write_flaser_log(tmp_path / "good.log", poses, ranges)).scans
    cfg = LaserGridConfig()
    grid, used, _ = build_checked_laser_grid(scans, scans.poses, cfg)
    ref = OccupancyGrid(np.zeros_like(grid.log_odds), grid.resolution, grid.origin)
    keys = keyframe_indices(scans.poses, cfg)
    for i in keys:
        r = np.where(scans.ranges[i] >= scans.max_range, np.inf, scans.ranges[i])
        integrate_scan(ref, scans.poses[i], r, scans.angles, cfg.max_range, cfg.log_odds)
    assert used == len(keys) and np.array_equal(grid.log_odds, ref.log_odds)
    _, _, off = build_checked_laser_grid(scans, scans.poses, LaserGridConfig(consistency_chunks=0))
    assert off is None


def test_build_map_warns_on_a_raw_odometry_log(
        tmp_path: Path, scans_and_poses: tuple[np.ndarray, np.ndarray],
        caplog: pytest.LogCaptureFixture) -> None:
    import yaml

    from lampsam.localization.map_build import build_map
    from lampsam.localization.map_store import load_env_map

    poses, ranges = scans_and_poses
    log_path = write_flaser_log(tmp_path / "raw.log", _drift(poses, 0.01), ranges)
    with caplog.at_level(logging.WARNING):
        build_map(log_path, tmp_path / "map")
    assert "the scans disagree with each other" in caplog.text and "raw.log" in caplog.text
    manifest = yaml.safe_load((tmp_path / "map" / "manifest.yaml").read_text())
    assert manifest["layers"]["grid"]["scan_consistency"]["poor"] is True
    caplog.clear()
    with caplog.at_level(logging.WARNING):
        load_env_map(tmp_path / "map")
    assert "whose poses disagree" in caplog.text and "unreliable" in caplog.text
