"""Audit 2: MRCLAM folders as the dataset is distributed (docs/failures.md, "audit 2").

Before: robots 2-5 of ``MRCLAM_DatasetN`` were ignored without a word; measurements of a
barcode in no table were dropped at INFO level; a ``.dat`` whose last line was cut short
refused the whole robot; a ground-truth time stamp repeated with another pose was kept
twice (the position error of an 80 s run read 0.199 m instead of 0.102 m); a robot with
no measurements gave "no records".
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import pytest

from lampsam.datasets.mrclam import read_mrclam
from lampsam.errors import DatasetError

HEADER = "# UTIAS Multi-Robot Cooperative Localization and Mapping Dataset\n# Time [s] ...\n"
BARCODES = "1 5\n2 14\n3 41\n4 32\n5 23\n6 72\n7 27\n"
LANDMARKS = "6 1.0 2.0 0.001 0.001\n7 -1.0 0.5 0.001 0.001\n"


def write(root: Path, robots: tuple[int, ...] = (1,), meas: str | None = None,
          odo: str | None = None, gt: str | None = None) -> Path:
    root.mkdir(parents=True, exist_ok=True)
    t = np.arange(0.0, 2.0, 0.1)
    odo_text = "".join(f"{x:.3f} 0.2 0.05\n" for x in t)
    gt_text = "".join(f"{x:.3f} {0.2 * x:.4f} 0.0 {0.05 * x:.4f}\n" for x in t)
    meas_text = "".join(f"{x:.3f} 72 2.1 0.9\n{x:.3f} 27 1.2 2.7\n" for x in t[::2])
    for r in robots:
        (root / f"Robot{r}_Odometry.dat").write_text(HEADER + (odo if odo is not None else odo_text))
        (root / f"Robot{r}_Groundtruth.dat").write_text(HEADER + (gt if gt is not None else gt_text))
        (root / f"Robot{r}_Measurement.dat").write_text(
            HEADER + (meas if meas is not None else meas_text))
    (root / "Barcodes.dat").write_text(HEADER + BARCODES)
    (root / "Landmark_Groundtruth.dat").write_text(HEADER + LANDMARKS)
    return root


def test_other_robots_are_named_and_readable(
        tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    root = write(tmp_path / "ds", robots=(1, 2, 3))
    (root / "Robot3_Measurement.dat").write_text(HEADER + "0.5 27 3.3 0.1\n")
    with caplog.at_level(logging.WARNING):
        one = read_mrclam(root)
    assert "robots 2, 3 (Robot<i>_*.dat) are not used" in caplog.text
    three = read_mrclam(root, robot=3)
    assert len(one.meas_t) == 20 and len(three.meas_t) == 1
    assert three.meas_range[0] == pytest.approx(3.3)


def test_unknown_barcode_is_warned_with_its_count(
        tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    root = write(tmp_path / "ds", meas="0.1 72 2.0 0.1\n0.2 99 1.0 0.0\n0.3 99 1.1 0.0\n"
                                       "0.4 14 1.5 0.2\n")
    with caplog.at_level(logging.WARNING):
        data = read_mrclam(root)
    assert list(data.meas_id) == [6]
    assert data.n_dropped_unknown == 2 and data.n_dropped_robot == 1
    assert "2 of 4 measurements are of barcodes in neither" in caplog.text and "99: 2" in caplog.text


def test_last_line_cut_short_is_skipped_but_a_bad_middle_line_is_an_error(
        tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    root = write(tmp_path / "ds", meas="0.1 72 2.0 0.1\n0.2 27 1.0 0.0\n0.3 72 2.")
    with caplog.at_level(logging.WARNING):
        data = read_mrclam(root)
    assert len(data.meas_t) == 2
    assert "Robot1_Measurement.dat:5: the last line is cut short" in caplog.text
    write(root, meas="0.1 72 2.0 0.1\n0.2 27 1.0\n0.3 72 2.0 0.1\n")
    with pytest.raises(DatasetError, match=r"Robot1_Measurement.dat:4: expected 4 columns, got 3"):
        read_mrclam(root)
    write(root, meas="0.1 72 2.0 0.1\n0.3 72 2.\n")  # cut short but WITH its newline
    with pytest.raises(DatasetError, match=r"Robot1_Measurement.dat:4: expected 4 columns"):
        read_mrclam(root)


def test_repeated_ground_truth_stamp_keeps_the_first_pose(
        tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    gt = "0.0 0.0 0 0\n0.1 0.02 0 0\n0.1 0.52 0 0\n0.2 0.04 0 0\n0.2 0.04 0 0\n0.3 0.06 0 0\n"
    root = write(tmp_path / "ds", gt=gt)
    with caplog.at_level(logging.WARNING):
        data = read_mrclam(root)
    np.testing.assert_allclose(data.gt_t, [0.0, 0.1, 0.2, 0.3])
    np.testing.assert_allclose(data.gt_poses[:, 0], [0.0, 0.02, 0.04, 0.06])
    assert "Robot1_Groundtruth.dat:5: 1 time stamps repeated with different values" in caplog.text
    # several landmarks at one time are normal: measurements keep every row
    assert len(data.meas_t) == 20 and len(np.unique(data.meas_t)) == 10


def test_robot_without_measurements_says_so(tmp_path: Path) -> None:
    root = write(tmp_path / "ds", meas="")
    with pytest.raises(DatasetError, match="Robot1_Measurement.dat: no measurements .*saw no "
                                           "landmark"):
        read_mrclam(root)


def test_cli_robot_flag_reads_that_robot_and_refuses_one_the_folder_lacks(tmp_path: Path) -> None:
    """``slam --mrclam --robot N``: robot N of a MRCLAM_DatasetN folder as distributed; a
    robot the folder lacks, or any robot but 1 of the resampled copy, names the file."""
    from lampsam.datasets.mrclam import mrclam_files

    (tmp_path / "Robot2_Odometry.dat").write_text("")
    files = mrclam_files(tmp_path, robot=2)
    assert files["control"].name == "Robot2_Odometry.dat"
    with pytest.raises(DatasetError, match="Robot3_Odometry.dat"):
        mrclam_files(tmp_path, robot=3)
    rs = tmp_path / "rs"
    rs.mkdir()
    (rs / "ds0_RS_Control.dat").write_text("")
    with pytest.raises(DatasetError, match="holds robot 1 only"):
        mrclam_files(rs, robot=2)
    assert mrclam_files(rs, robot=1)["control"].name == "ds0_RS_Control.dat"
