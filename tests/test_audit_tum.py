"""TUM files from other tools (audit): camera-frame poses, nanosecond stamps, commas."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from lampsam.datasets.tum import read_tum, tilt_deg
from lampsam.errors import DatasetError

#: camera optical frame in the body frame: z forward, x right, y down
BODY_R_OPTICAL = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


def _write(path: Path, t: np.ndarray, xyz: np.ndarray, rot: Rotation) -> Path:
    q = rot.as_quat()
    path.write_text("".join(f"{a} {p[0]:.6f} {p[1]:.6f} {p[2]:.6f} {v[0]:.8f} {v[1]:.8f} "
                            f"{v[2]:.8f} {v[3]:.8f}\n" for a, p, v in zip(t.tolist(), xyz, q, strict=True)))
    return path


def test_tilt_of_known_rotations() -> None:
    rots = Rotation.from_euler("zyx", [[0.7, 0.0, 0.0], [0.0, 0.3, 0.0], [1.0, 0.0, -0.2]])
    np.testing.assert_allclose(tilt_deg(rots.as_quat()), np.degrees([0.0, 0.3, 0.2]), atol=1e-9)


def test_a_camera_frame_trajectory_is_warned_about(
        tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    t = np.arange(10) * 0.1
    yaw = Rotation.from_euler("z", 0.1 * t[:, None])
    body = _write(tmp_path / "body.tum", t, np.c_[t, 0 * t, 0 * t], yaw)
    cam = _write(tmp_path / "cam.tum", t, np.c_[0 * t, 0 * t, t],
                 yaw * Rotation.from_matrix(BODY_R_OPTICAL))
    with caplog.at_level(logging.WARNING):
        read_tum(body)
    assert caplog.text == ""
    with caplog.at_level(logging.WARNING):
        read_tum(cam)
    assert "cam.tum:1: the pose tilts 90 deg from upright (10 of 10 poses" in caplog.text


def test_nanosecond_stamps_and_commas_are_named(
        tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    ns = _write(tmp_path / "ns.tum", np.array([1_700_000_000_000_000_000 + k * 100_000_000 for k in range(5)]), np.zeros((5, 3)),
                Rotation.identity(5))
    with caplog.at_level(logging.WARNING):
        read_tum(ns)
    assert "ns.tum:1: time stamp 1.7e+18 s" in caplog.text and "nanoseconds?" in caplog.text
    comma = tmp_path / "c.tum"
    comma.write_text("0,0,0,0,0,0,0,1\n")
    with pytest.raises(DatasetError, match=r"c.tum:1: .*got 1 \(comma-separated\? TUM is "
                                           r"space-separated\)"):
        read_tum(comma)
