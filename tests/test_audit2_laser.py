"""Audit 2: the laser consistency check's worst-chunk rule (docs/envmap.md, docs/failures.md).

The whole-log fraction missed drift that spoils one stretch of a long drive (the
simulated campus with 4.75 m of drift: 0.761 against the 0.75 threshold; its worst time
chunk 0.543). A log is now also flagged when its worst chunk is below
``min_chunk_consistency`` (0.70).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from lampsam.datasets.carmen import carmen_beam_angles, read_carmen
from lampsam.localization.grid import OccupancyGrid
from lampsam.localization.laser_consistency import ScanConsistency
from lampsam.localization.laser_grid import build_checked_laser_grid
from lampsam.localization.map_config import LaserGridConfig
from tests.conftest import boxed_room, cast_grid_ranges, rectangle_laps, write_flaser_log

ANGLES = carmen_beam_angles(180)


def test_worst_chunk_rule_on_its_own() -> None:
    mild = ScanConsistency(0.80, (0.95, 0.90, 0.55, 0.85, 0.80, 0.75), 100, 200, 0.75, 0.70)
    assert mild.poor and mild.worst_chunk == pytest.approx(0.55)
    assert "worst of its 6 time chunks 55 %" in mild.reason() and "80 % over" in mild.reason()
    assert not ScanConsistency(0.80, mild.per_chunk, 100, 200, 0.75).poor  # no chunk rule
    fine = ScanConsistency(0.86, (0.95, 0.76, 0.88, 0.93, 0.87, 0.79), 100, 200, 0.75, 0.70)
    assert not fine.poor
    d = mild.as_dict()
    assert d["worst_chunk"] == 0.55 and d["chunk_threshold"] == 0.7 and d["poor"] is True
    nothing = ScanConsistency(math.nan, (math.nan,) * 6, 0, 0, 0.75, 0.70)
    assert not nothing.poor and nothing.as_dict()["worst_chunk"] is None


def _room() -> OccupancyGrid:
    """A 16 m x 10 m hall with walls and five boxes, 0.1 m cells."""
    return boxed_room(16.0, 10.0, ((3.0, 3.0, 5.0, 4.5), (7.5, 2.5, 8.5, 5.5), (10.0, 6.0, 11.0, 7.0),
                                   (12.5, 2.5, 14.0, 3.5), (5.5, 6.8, 6.5, 7.6)))


def _cast(grid: OccupancyGrid, poses: np.ndarray, max_range: float) -> np.ndarray:
    """(N, 180) ranges to the first occupied cell, marched in 3 cm steps."""
    return cast_grid_ranges(grid, poses, ANGLES, max_range, 0.03)


def _laps(laps: int, step: float = 0.4) -> np.ndarray:
    """(N, 3) poses around the rectangle x in [1.5, 14.5], y in [1.5, 8.5], ``laps`` times."""
    return rectangle_laps((1.5, 1.5), (14.5, 8.5), laps, step)



def test_drift_in_one_stretch_is_flagged_by_the_worst_chunk(
        tmp_path: Path) -> None:
    rng = np.random.default_rng(3)
    poses = _laps(3)
    ranges = _cast(_room(), poses, 8.0)
    ranges = np.where(ranges >= 8.0 - 1e-6, 81.83, ranges + rng.normal(0, 0.01, ranges.shape))
    # the last sixth of the drive shifted sideways by up to 0.6 m (a stretch of bad poses)
    bad = poses.copy()
    n = len(poses)
    ramp = np.clip((np.arange(n) - 5 * n // 6) / (n / 12), 0.0, 1.0)
    bad[:, 1] += 0.6 * ramp
    good = read_carmen(write_flaser_log(tmp_path / "good.log", poses, ranges)).scans
    drifted = read_carmen(write_flaser_log(tmp_path / "stretch.log", bad, ranges)).scans
    _, _, c_good = build_checked_laser_grid(good, good.poses)
    _, _, c_bad = build_checked_laser_grid(drifted, drifted.poses)
    assert c_good is not None and c_bad is not None
    assert not c_good.poor and c_good.worst_chunk > 0.9
    assert c_bad.score >= 0.75, "the whole-log rule alone must miss this case"
    assert c_bad.worst_chunk < 0.70 and c_bad.poor
    assert int(np.nanargmin(c_bad.per_chunk)) == 5
    _, _, c_off = build_checked_laser_grid(
        drifted, drifted.poses, LaserGridConfig(min_chunk_consistency=0.0))
    assert c_off is not None and not c_off.poor

