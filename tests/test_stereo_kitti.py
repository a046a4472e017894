"""KITTI stereo reader and the two-point model on real rectified images (shared data)."""

from __future__ import annotations

import math
import shutil
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from lampsam.backend.stereo_kitti import KittiTwoPointResult, two_point_on_kitti
from lampsam.datasets.kitti import KittiError, KittiStereoSequence, read_kitti_sequence
from lampsam.frontend.stereo_tracking import track_sequence
from tests.conftest import require_shared

NAME = "kitti_stereo_seq1"


@pytest.fixture(scope="module")
def seq() -> KittiStereoSequence:
    return read_kitti_sequence(require_shared(NAME))


@pytest.fixture(scope="module")
def short_result(seq: KittiStereoSequence) -> KittiTwoPointResult:
    """The first 20 frames (about 23 m of driving), to keep the test fast."""
    n = 20
    sub = replace(seq, poses=seq.poses[:n], left_files=seq.left_files[:n],
                  right_files=seq.right_files[:n])
    return two_point_on_kitti(sub, track_sequence(sub))


@pytest.mark.shared_data
def test_reader(seq: KittiStereoSequence) -> None:
    assert len(seq) == 51 and (seq.width, seq.height) == (1226, 370)
    assert seq.fx == pytest.approx(707.0912)
    assert seq.baseline == pytest.approx(0.537, abs=1e-3)  # data README: 0.537 m
    left, right = seq.load_pair(3)
    assert left.dtype == np.uint8 and left.shape == right.shape == (370, 1226)
    planar = seq.planar_rig_poses()
    # poses.txt line 2: t = (-0.0140, -0.0282, 1.1990), R[0, 2] = -6.870876e-04
    np.testing.assert_allclose(planar[0], 0.0, atol=1e-9)
    assert planar[1, 0] == pytest.approx(1.199, abs=2e-3)
    assert planar[1, 1] == pytest.approx(0.0140, abs=1e-3)
    assert planar[1, 2] == pytest.approx(6.870876e-04, abs=1e-6)
    assert 55.0 < planar[-1, 0] < 65.0 and abs(planar[-1, 1]) < 3.0


@pytest.mark.shared_data
def test_reader_errors(tmp_path: Path) -> None:
    src = require_shared(NAME)
    with pytest.raises(KittiError, match="not found"):
        read_kitti_sequence(tmp_path / "absent")
    bad = tmp_path / "seq"
    bad.mkdir()
    lines = (src / "calib.txt").read_text().splitlines()
    (bad / "calib.txt").write_text(lines[0] + "\n" + " ".join(lines[1].split()[:11]) + "\n")
    with pytest.raises(KittiError, match=r"calib.txt:2: expected 12 numbers"):
        read_kitti_sequence(bad)
    (bad / "calib.txt").write_text("\n".join(lines) + "\n")
    (bad / "poses.txt").write_text((src / "poses.txt").read_text())
    (bad / "image_l").mkdir()
    (bad / "image_r").mkdir()
    shutil.copy(src / "image_l" / "000000.png", bad / "image_l" / "000000.png")
    shutil.copy(src / "image_r" / "000000.png", bad / "image_r" / "000000.png")
    with pytest.raises(KittiError, match="51 poses for 1 image pairs"):
        read_kitti_sequence(bad)


@pytest.mark.shared_data
def test_two_point_motion_against_ground_truth(short_result: KittiTwoPointResult) -> None:
    """Relative planar motion anchor -> k from two tracked points vs KITTI ground truth.

    Tolerances (measured on these 19 frames: median ~5 cm, ~3 cm, ~0.2 deg):
    median |error| below 0.15 m in x and y and 0.5 deg in heading; 80 % of frames scored.
    """
    r = short_result
    assert r.scored.sum() >= 0.8 * (len(r.scored) - 1)
    e = np.abs(r.rel_error[r.scored])
    med = np.median(e, axis=0)
    assert med[0] < 0.15 and med[1] < 0.15 and med[2] < math.radians(0.5)
    assert np.all(np.isfinite(r.estimate))


@pytest.mark.shared_data
def test_projection_model_on_real_points(short_result: KittiTwoPointResult) -> None:
    """Points triangulated at k-1 and moved by the true planar motion land on the
    measured horizontal coordinates at k (eq. 2): median within 1 px, 90 % within 3 px."""
    res = np.abs(short_result.model_residual_px)
    assert len(res) > 1000
    assert np.median(res) < 1.0
    assert np.percentile(res, 90) < 3.0
