"""Audit 2: KITTI stereo folders as a new user brings them (docs/failures.md, "audit 2").

The reader knew only the shared folder's layout (``image_l``/``image_r``, two unlabelled
lines in ``calib.txt``): the odometry benchmark's ``image_0``..``image_3`` folders and the
raw recordings' ``calib_cam_to_cam.txt`` were refused, colour images were measured with
the grey cameras' P0/P1, a missing right image was not named, and a calibration made for
another image size ran to a wrong answer (1.1 m median error on half-size images of
``kitti_stereo_seq1``, against 3 cm) without a word.
"""

from __future__ import annotations

import logging
from pathlib import Path

import cv2
import numpy as np
import pytest

from lampsam.datasets.kitti import KittiError, read_kitti_sequence

W, H = 120, 40
FX, CX, CY = 100.0, 60.0, 20.0


def p_row(tx_px: float) -> str:
    """A rectified projection matrix with ``P[0, 3] = tx_px``, as 12 numbers."""
    return f"{FX} 0 {CX} {tx_px} 0 {FX} {CY} 0 0 0 1 0"


# baselines: grey pair 0.5 m, colour pair 0.6 m (P2 sits 0.06 m from camera 0)
P_LINES = {"P0": p_row(0.0), "P1": p_row(-50.0), "P2": p_row(6.0), "P3": p_row(-54.0)}
TR = "0 -1 0 0 0 0 -1 0 1 0 0 0"


def make(root: Path, left: str, right: str, colour: bool = False, n: int = 3,
         size: tuple[int, int] = (W, H)) -> Path:
    (root / left).mkdir(parents=True)
    (root / right).mkdir()
    rng = np.random.default_rng(0)
    for k in range(n):
        for d in (left, right):
            img = rng.integers(0, 255, (size[1], size[0], 3 if colour else 1), np.uint8)
            cv2.imwrite(str(root / d / f"{k:06d}.png"), img)
    (root / "poses.txt").write_text("1 0 0 0 0 1 0 0 0 0 1 0\n" * n)
    return root


def labelled_calib(root: Path) -> None:
    (root / "calib.txt").write_text(
        "".join(f"{k}: {v}\n" for k, v in P_LINES.items()) + f"Tr: {TR}\n")


def test_odometry_benchmark_grey_folders_use_p0_p1(tmp_path: Path) -> None:
    root = make(tmp_path / "seq", "image_0", "image_1")
    labelled_calib(root)
    seq = read_kitti_sequence(root)
    assert len(seq) == 3 and seq.left_files[0].parent.name == "image_0"
    assert seq.baseline == pytest.approx(0.5)


def test_odometry_benchmark_colour_folders_use_p2_p3(tmp_path: Path) -> None:
    root = make(tmp_path / "seq", "image_2", "image_3", colour=True)
    labelled_calib(root)
    assert read_kitti_sequence(root).baseline == pytest.approx(0.6)


def test_colour_images_in_image_l_use_the_colour_cameras(tmp_path: Path) -> None:
    root = make(tmp_path / "seq", "image_l", "image_r", colour=True)
    labelled_calib(root)
    assert read_kitti_sequence(root).baseline == pytest.approx(0.6)
    grey = make(tmp_path / "grey", "image_l", "image_r")
    labelled_calib(grey)
    assert read_kitti_sequence(grey).baseline == pytest.approx(0.5)


RAW = """calib_time: 09-Jan-2012 13:57:47
corner_dist: 9.950000e-02
S_00: 1.392000e+03 5.120000e+02
K_00: 9.842439e+02 0.000000e+00 6.900000e+02 0.000000e+00 9.808141e+02 2.331966e+02 0 0 1
D_00: -3.728755e-01 2.037299e-01 2.219027e-03 1.383707e-03 -7.233722e-02
S_rect_00: {w} {h}
R_rect_00: 1 0 0 0 1 0 0 0 1
P_rect_00: {p0}
S_rect_01: {w} {h}
P_rect_01: {p1}
"""


def test_raw_calib_cam_to_cam_is_read_and_its_size_checked(tmp_path: Path) -> None:
    root = make(tmp_path / "raw", "image_l", "image_r")
    (root / "calib_cam_to_cam.txt").write_text(
        RAW.format(w=f"{W}.0", h=f"{H}.0", p0=P_LINES["P0"], p1=P_LINES["P1"]))
    assert read_kitti_sequence(root).baseline == pytest.approx(0.5)
    (root / "calib_cam_to_cam.txt").write_text(
        RAW.format(w="1242.0", h="375.0", p0=P_LINES["P0"], p1=P_LINES["P1"]))
    with pytest.raises(KittiError, match=r"calib_cam_to_cam.txt:6: S_rect_00 is 1242x375 but"):
        read_kitti_sequence(root)


def test_missing_right_image_is_named(tmp_path: Path) -> None:
    root = make(tmp_path / "seq", "image_l", "image_r")
    labelled_calib(root)
    (root / "image_r" / "000001.png").unlink()
    with pytest.raises(KittiError, match="1 left images have no right image .first 000001.png"):
        read_kitti_sequence(root)


def test_calibration_of_another_image_size_is_warned(
        tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    root = make(tmp_path / "seq", "image_l", "image_r", size=(W // 2, H // 2))  # resized
    labelled_calib(root)
    with caplog.at_level(logging.WARNING):
        read_kitti_sequence(root)
    assert "principal point (60.0, 20.0) px lies outside" in caplog.text
    caplog.clear()
    ok = make(tmp_path / "ok", "image_l", "image_r")
    labelled_calib(ok)
    with caplog.at_level(logging.WARNING):
        read_kitti_sequence(ok)
    assert caplog.text == ""


def test_stereo_experiment_takes_a_kitti_folder_and_refuses_a_bad_one_first(
        tmp_path: Path) -> None:
    from lampsam.cli import main

    root = make(tmp_path / "seq", "image_0", "image_1")
    labelled_calib(root)
    (root / "image_1" / "000002.png").unlink()
    # refused before the simulated seeds run (they take seconds), naming the missing image
    assert main(["stereo-experiment", "--seeds", "1", "--kitti", str(root),
                 "--out", str(tmp_path / "out")]) == 2
    assert not (tmp_path / "out" / "stereo_rms.md").exists()
    assert main(["stereo-experiment", "--kitti", str(root), "--no-kitti",
                 "--out", str(tmp_path / "out2")]) == 2


def test_benchmark_layout_finds_its_poses_and_a_missing_pose_file_says_why(
        tmp_path: Path) -> None:
    seq = make(tmp_path / "dataset" / "sequences" / "07", "image_0", "image_1")
    labelled_calib(seq)
    poses = seq / "poses.txt"
    (tmp_path / "dataset" / "poses").mkdir()
    poses.rename(tmp_path / "dataset" / "poses" / "07.txt")
    assert len(read_kitti_sequence(seq)) == 3
    (tmp_path / "dataset" / "poses" / "07.txt").unlink()  # sequences 11-21: no ground truth
    with pytest.raises(KittiError, match=r"07/poses.txt: no poses.txt: the check scores against "
                                         r"ground-truth poses .*sequences 00-10"):
        read_kitti_sequence(seq)
