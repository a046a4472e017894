"""Audit 2: RGB-D folders as a new user brings them (docs/failures.md, "audit 2").

Each case used to run silently or stop on a format the reader could have read:
32-bit float depth in metres was refused; a ``groundtruth.txt`` that starts after the
first frames lost every pose ("the sequence has no camera poses"); an all-zero depth
frame, a wrong ``depth_scale`` and a slambook2 ``pose.txt`` shorter than ``color/``
went without a word.
"""

from __future__ import annotations

import logging
from pathlib import Path

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from lampsam.datasets import rgbd
from lampsam.datasets.rgbd import read_slambook2, read_tum_rgbd

W, H = 32, 24
YAML = f"""width: {W}
height: {H}
fx: 30.0
fy: 30.0
cx: 15.5
cy: 11.5
depth_scale: {{scale}}
body_t_camera: [0, 0, 0]
body_R_camera: [[1, 0, 0], [0, 1, 0], [0, 0, 1]]
"""


def make_tum(root: Path, depth_m: list[np.ndarray], scale: float = 5000.0, ext: str = "png",
             gt_times: list[float] | None = None, quat: str = "0.5 -0.5 0.5 -0.5") -> Path:
    """A TUM RGB-D folder: colour 11 ms after each depth frame, poses 3 ms after."""
    (root / "rgb").mkdir(parents=True)
    (root / "depth").mkdir()
    rgb_lines, depth_lines = [], []
    for k, d in enumerate(depth_m):
        t = 100.0 + 0.5 * k
        cv2.imwrite(str(root / "rgb" / f"{k}.png"), np.full((H, W, 3), 90, np.uint8))
        if ext == "tiff":
            cv2.imwrite(str(root / "depth" / f"{k}.tiff"), d.astype(np.float32))
        else:
            cv2.imwrite(str(root / "depth" / f"{k}.png"), np.rint(np.nan_to_num(d) * scale).astype(np.uint16))
        rgb_lines.append(f"{t + 0.011:.6f} rgb/{k}.png\n")
        depth_lines.append(f"{t:.6f} depth/{k}.{ext}\n")
    (root / "rgb.txt").write_text("# timestamp filename\n" + "".join(rgb_lines))
    (root / "depth.txt").write_text("# timestamp filename\n" + "".join(depth_lines))
    (root / "kinect.yaml").write_text(YAML.format(scale=scale))
    times = gt_times if gt_times is not None else [100.0 + 0.5 * k for k in range(len(depth_m))]
    (root / "groundtruth.txt").write_text("# t tx ty tz qx qy qz qw\n" + "".join(
        f"{t + 0.003:.4f} {0.1 * k} 0 0.5 {quat}\n" for k, t in enumerate(times)))
    return root


# camera upright in a z-up world, looking along x (image down = -z): kinect_sim's mounting
UPRIGHT = "0.5 -0.5 0.5 -0.5"


def ramp(rng: np.random.Generator) -> np.ndarray:
    """(H, W) depth in metres, 1-3 m, with a few holes."""
    d = rng.uniform(1.0, 3.0, (H, W))
    d[rng.random((H, W)) < 0.1] = 0.0
    return d


@pytest.fixture(autouse=True)
def _fresh_warnings() -> None:
    for name in ("_RANGE_WARNED", "_EMPTY_WARNED"):
        getattr(rgbd, name, set()).clear()


def test_float_depth_in_metres_reads_as_the_16_bit_frame(tmp_path: Path) -> None:
    rng = np.random.default_rng(1)
    frames = [ramp(rng) for _ in range(2)]
    frames[0][0, 0] = np.nan  # no depth, as a ROS 32FC1 image writes it
    u16 = read_tum_rgbd(make_tum(tmp_path / "u16", frames))
    f32 = read_tum_rgbd(make_tum(tmp_path / "f32", frames, ext="tiff"))
    for i in range(2):
        a, b = u16.load_depth(i), f32.load_depth(i)
        assert b.dtype == np.uint16
        assert np.abs(a.astype(int) - b.astype(int)).max() <= 1  # 0.2 mm at 5000 per metre
    assert f32.load_depth(0)[0, 0] == 0


def test_groundtruth_starting_late_drops_the_unposed_frames_with_a_warning(
        tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    rng = np.random.default_rng(2)
    root = make_tum(tmp_path / "s", [ramp(rng) for _ in range(5)],
                    gt_times=[101.0, 101.5, 102.0])  # motion capture starts at the third frame
    with caplog.at_level(logging.WARNING):
        seq = read_tum_rgbd(root)
    assert len(seq) == 3
    assert seq.world_T_camera is not None and seq.world_T_camera.shape == (3, 4, 4)
    np.testing.assert_allclose(seq.t, [101.0, 101.5, 102.0])
    np.testing.assert_allclose(seq.world_T_camera[:, 0, 3], [0.0, 0.1, 0.2])
    assert "2 of 5 frames have no pose" in caplog.text and "groundtruth.txt" in caplog.text


def test_groundtruth_covering_no_frame_is_said(
        tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    rng = np.random.default_rng(3)
    root = make_tum(tmp_path / "s", [ramp(rng) for _ in range(2)], gt_times=[500.0, 500.5])
    with caplog.at_level(logging.WARNING):
        seq = read_tum_rgbd(root)
    assert seq.world_T_camera is None and len(seq) == 2
    assert "no frame has a pose" in caplog.text


def test_all_zero_depth_frame_is_warned_once(
        tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    rng = np.random.default_rng(4)
    seq = read_tum_rgbd(make_tum(tmp_path / "s", [ramp(rng), np.zeros((H, W))]))
    with caplog.at_level(logging.WARNING):
        seq.load_depth(0)
        assert caplog.text == ""
        seq.load_depth(1)
        seq.load_depth(1)
    assert caplog.text.count("holds no depth") == 1 and "1.png" in caplog.text


def test_wrong_depth_scale_is_suspected_once_per_folder(
        tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    rng = np.random.default_rng(5)
    frames = [ramp(rng) for _ in range(3)]
    right = read_tum_rgbd(make_tum(tmp_path / "right", frames))
    # TUM data (5000 per metre) declared at 1000: every depth reads 5 x too far (5-15 m)
    root = make_tum(tmp_path / "wrong", frames)
    (root / "kinect.yaml").write_text(YAML.format(scale=1000.0))
    wrong = read_tum_rgbd(root)
    with caplog.at_level(logging.WARNING):
        for i in range(3):
            right.load_depth(i)
        assert caplog.text == ""
        for i in range(3):
            wrong.load_depth(i)
    assert caplog.text.count("is depth_scale right") == 1


def test_slambook2_with_fewer_poses_than_frames_says_so(
        tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    root = tmp_path / "sb"
    (root / "color").mkdir(parents=True)
    (root / "depth").mkdir()
    for k in range(1, 4):
        cv2.imwrite(str(root / "color" / f"{k}.png"), np.zeros((4, 4, 3), np.uint8))
        cv2.imwrite(str(root / "depth" / f"{k}.pgm"), np.zeros((4, 4), np.uint16))
    (root / "pose.txt").write_text("0 0 0 0 0 0 1\n0.1 0 0 0 0 0 1\n")
    with caplog.at_level(logging.WARNING):
        seq = read_slambook2(root)
    assert len(seq) == 2
    assert "3.png" in caplog.text and "not used" in caplog.text


def test_poses_in_a_camera_convention_are_warned_about(
        tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    rng = np.random.default_rng(6)
    frames = [ramp(rng) for _ in range(3)]
    with caplog.at_level(logging.WARNING):
        read_tum_rgbd(make_tum(tmp_path / "upright", frames))
        assert caplog.text == ""
        # pitched 28 deg down toward the floor (z-up, a handheld camera): no warning
        pitched = Rotation.from_euler("y", 28, degrees=True).as_matrix() @ Rotation.from_quat(
            [0.5, -0.5, 0.5, -0.5]).as_matrix()
        q = " ".join(f"{v:.6f}" for v in Rotation.from_matrix(pitched).as_quat())
        read_tum_rgbd(make_tum(tmp_path / "pitched", frames, quat=q))
        assert caplog.text == ""
        # looking straight down at the floor: no warning either
        read_tum_rgbd(make_tum(tmp_path / "floor", frames, quat="1 0 0 0"))
        assert caplog.text == ""
        # identity: the first camera's frame of a visual SLAM trajectory (y down, z forward)
        read_tum_rgbd(make_tum(tmp_path / "camframe", frames, quat="0 0 0 1"))
    assert "image-down axis lies 90 deg from the world's down (-z)" in caplog.text
    assert "camframe/groundtruth.txt" in caplog.text
