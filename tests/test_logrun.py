"""Logged-run format: rig YAML, camera conventions, readers' validation, TUM via evo."""

from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np
import pytest

from lampsam.datasets.logrun import (
    CameraModel,
    ImageWriter,
    LandmarkTable,
    OdometryLog,
    OdometryModel,
    ProjectionTable,
    ProjectionWriter,
    RangeBearingLog,
    Rig,
    Trajectory,
    read_image_index,
    read_landmarks,
    read_odometry,
    read_projections,
    read_range_bearing,
    read_run,
    read_tum,
    write_range_bearing,
    write_run,
    write_tum,
)
from lampsam.errors import DatasetError, LampsamError

F_120 = 160.0 / math.tan(math.radians(60.0))  # 92.3760430703 px: 320 px over 120 deg


def _write(path: Path, text: str) -> Path:
    path.write_text(text)
    return path


# --------------------------------------------------------------------------- rig / camera
def test_rig_yaml_round_trip(tmp_path: Path) -> None:
    cam = CameraModel(
        fx=90.0, fy=91.0, cx=160.2, cy=118.7, dist=[0.1, -0.02, 0.001, -0.002, 0.003],
        body_t_camera=[0.12, -0.01, 0.31],
    )  # fmt: skip
    rig = Rig(cam, OdometryModel(wheel_base=0.35, k_r=1e-5, k_l=3e-5))
    rig.to_yaml(tmp_path / "rig.yaml")
    back = Rig.from_yaml(tmp_path / "rig.yaml")
    assert back.odometry == rig.odometry
    for name in ("width", "height", "fx", "fy", "cx", "cy"):
        assert getattr(back.camera, name) == getattr(cam, name)
    np.testing.assert_array_equal(back.camera.dist, cam.dist)
    np.testing.assert_array_equal(back.camera.body_t_camera, cam.body_t_camera)
    np.testing.assert_array_equal(back.camera.body_R_camera, cam.body_R_camera)


def test_rig_yaml_errors_name_file(tmp_path: Path) -> None:
    bad = _write(tmp_path / "rig.yaml", "camera: {fx: -3}\nodometry: {}\n")
    with pytest.raises(DatasetError, match="rig.yaml") as exc:
        Rig.from_yaml(bad)
    assert exc.value.path == bad
    with pytest.raises(DatasetError, match="not found"):
        Rig.from_yaml(tmp_path / "absent.yaml")
    bad2 = _write(tmp_path / "rig2.yaml", "camera: {fx: 1, wheels: 3}\n")
    with pytest.raises(DatasetError, match="invalid rig"):
        Rig.from_yaml(bad2)


def test_default_camera_conventions() -> None:
    """conventions.md: image top = robot forward, image right = robot LEFT (mirror)."""
    cam = CameraModel()
    assert cam.fx == pytest.approx(F_120, abs=1e-9)
    m = cam.normalized_from_pixels(np.array([[159.5 + 10.0, 119.5], [159.5, 119.5 - 20.0]]))
    # 10 px right of centre: u = 0 (not forward), v = +10/f (robot's left).
    np.testing.assert_allclose(m[0], [0.0, 10.0 / F_120], atol=1e-12)
    # 20 px above centre: forward, u = +20/f.
    np.testing.assert_allclose(m[1], [20.0 / F_120, 0.0], atol=1e-12)


def test_normalized_pixels_round_trip_with_distortion() -> None:
    cam = CameraModel(dist=[-0.05, 0.004, 0.0005, -0.0005, 0.0])  # monotonic over 120 deg
    rng = np.random.default_rng(7)
    px = np.column_stack([rng.uniform(20, 300, 50), rng.uniform(20, 220, 50)])
    m = cam.normalized_from_pixels(px)
    np.testing.assert_allclose(cam.pixels_from_normalized(m), px, atol=1e-6)
    # Distortion changes the answer (the test is not vacuous).
    assert np.max(np.abs(CameraModel().normalized_from_pixels(px) - m)) > 1e-2


# --------------------------------------------------------------------------- odometry errors
ODO_OK = "t,d_left,d_right\n0.0,0,0\n0.1,0.01,0.012\n0.2,0.011,0.010\n"


@pytest.mark.parametrize(
    ("text", "line", "pattern"),
    [
        ("t,d_left,d_right\n0.0,0,0\n0.1,0.01\n", 3, "malformed line"),
        ("t,d_left,d_right\n0.0,0,0\n0.1,abc,0.01\n", 3, "not a number"),
        ("t,d_left,d_right\n0.0,0,0\n0.2,0.01,0.01\n0.1,0.01,0.01\n", 4, "does not increase"),
        ("t,d_left,d_right\n0.0,0,0\n0.1,nan,0.01\n", 3, "non-finite"),
        ("t,d_left,d_right\n0.0,0,0\n0.1,0.01,inf\n", 3, "non-finite"),
        ("t,d_left,d_right\n0.0,0,0\n0.0,0.01,0.01\n", 3, "does not increase"),
        ("time,left,right\n0.0,0,0\n", 1, "expected header"),
    ],
)
def test_odometry_reader_errors_name_file_and_line(
    tmp_path: Path, text: str, line: int, pattern: str
) -> None:
    path = _write(tmp_path / "odometry.csv", text)
    with pytest.raises(DatasetError, match=pattern) as exc:
        read_odometry(path)
    assert exc.value.path == path
    assert exc.value.line == line
    assert f"odometry.csv:{line}" in str(exc.value)


def test_odometry_reader_time_error_line_with_comments(tmp_path: Path) -> None:
    """The fast path's time check still names the right line when comments intervene."""
    text = "# run 1\nt,d_left,d_right\n0.0,0,0\n# pause\n\n0.3,0.01,0.01\n0.2,0.01,0.01\n"
    path = _write(tmp_path / "odometry.csv", text)
    with pytest.raises(DatasetError) as exc:
        read_odometry(path)
    assert exc.value.line == 7


def test_odometry_reader_missing_and_empty(tmp_path: Path) -> None:
    with pytest.raises(DatasetError, match="not found") as exc:
        read_odometry(tmp_path / "odometry.csv")
    assert exc.value.path == tmp_path / "odometry.csv"
    empty = _write(tmp_path / "empty.csv", "")
    with pytest.raises(DatasetError, match="empty file"):
        read_odometry(empty)
    header_only = _write(tmp_path / "h.csv", "t,d_left,d_right\n")
    with pytest.raises(DatasetError, match="empty log"):
        read_odometry(header_only)
    assert issubclass(DatasetError, LampsamError)


def test_odometry_reader_ok(tmp_path: Path) -> None:
    odo = read_odometry(_write(tmp_path / "odometry.csv", ODO_OK))
    np.testing.assert_allclose(odo.t, [0.0, 0.1, 0.2])
    np.testing.assert_allclose(odo.d_right, [0.0, 0.012, 0.010])


# --------------------------------------------------------------------------- images
def test_image_index_errors(tmp_path: Path) -> None:
    writer = ImageWriter(tmp_path)
    writer.write(0.0, np.full((240, 320), 7, np.uint8))
    writer.write(0.1, np.zeros((240, 320), np.uint8))
    writer.write(0.2, np.zeros((240, 320), np.uint8))
    writer.close()
    (tmp_path / "images" / "000001.png").write_bytes(b"not a png at all")
    cv2.imwrite(str(tmp_path / "images" / "000002.png"), np.zeros((10, 10), np.uint8))
    index = read_image_index(tmp_path / "images.csv", shape=(240, 320))
    assert index.load(0)[5, 5] == 7
    with pytest.raises(DatasetError, match="cannot decode") as exc:
        index.load(1)
    assert exc.value.path == tmp_path / "images" / "000001.png"
    assert "line 3" in str(exc.value)
    with pytest.raises(DatasetError, match="size"):
        index.load(2)
    (tmp_path / "images" / "000000.png").unlink()
    with pytest.raises(DatasetError, match="not found"):
        index.load(0)
    bad = _write(tmp_path / "bad.csv", "t,file\n0.0,a.png\n-1.0,b.png\n")
    with pytest.raises(DatasetError) as exc2:
        read_image_index(bad)
    assert exc2.value.line == 3


# --------------------------------------------------------------------------- TUM
def _poses(rng: np.random.Generator, n: int) -> Trajectory:
    t = np.cumsum(rng.uniform(0.01, 0.1, n))
    poses = np.column_stack(
        [rng.normal(0, 3, n), rng.normal(0, 3, n), rng.uniform(-np.pi, np.pi, n)]
    )
    return Trajectory(t, poses)


def test_tum_round_trip_through_evo(tmp_path: Path) -> None:
    from evo.core.trajectory import PoseTrajectory3D
    from evo.tools import file_interface

    traj = _poses(np.random.default_rng(3), 40)
    write_tum(tmp_path / "gt.tum", traj)
    evo_traj = file_interface.read_tum_trajectory_file(str(tmp_path / "gt.tum"))
    np.testing.assert_allclose(evo_traj.timestamps, traj.t, atol=1e-6)
    np.testing.assert_allclose(evo_traj.positions_xyz[:, :2], traj.poses[:, :2], atol=1e-8)
    np.testing.assert_allclose(evo_traj.positions_xyz[:, 2], 0.0, atol=0)
    yaw = np.array([math.atan2(R[1, 0], R[0, 0]) for R in (p[:3, :3] for p in evo_traj.poses_se3)])
    np.testing.assert_allclose(np.angle(np.exp(1j * (yaw - traj.poses[:, 2]))), 0.0, atol=1e-9)
    # And back: a file evo writes is read by read_tum.
    out = PoseTrajectory3D(poses_se3=evo_traj.poses_se3, timestamps=evo_traj.timestamps)
    file_interface.write_tum_trajectory_file(str(tmp_path / "evo.tum"), out)
    back = read_tum(tmp_path / "evo.tum")
    np.testing.assert_allclose(back.poses[:, :2], traj.poses[:, :2], atol=1e-6)
    np.testing.assert_allclose(
        np.angle(np.exp(1j * (back.poses[:, 2] - traj.poses[:, 2]))), 0, atol=1e-6
    )


def test_tum_reader_errors(tmp_path: Path) -> None:
    bad = _write(tmp_path / "a.tum", "# c\n0 0 0 0 0 0 0 1\n1 0 0 0 0 0 1\n")
    with pytest.raises(DatasetError, match="8 fields") as exc:
        read_tum(bad)
    assert exc.value.line == 3
    back = _write(tmp_path / "b.tum", "1 0 0 0 0 0 0 1\n0.5 0 0 0 0 0 0 1\n")
    with pytest.raises(DatasetError, match="does not increase") as exc:
        read_tum(back)
    assert exc.value.line == 2
    nan = _write(tmp_path / "c.tum", "1 nan 0 0 0 0 0 1\n")
    with pytest.raises(DatasetError, match="non-finite"):
        read_tum(nan)
    with pytest.raises(DatasetError, match="empty"):
        read_tum(_write(tmp_path / "d.tum", "# nothing\n"))


# --------------------------------------------------------------------------- other tables
def test_range_bearing_round_trip_and_errors(tmp_path: Path) -> None:
    rb = RangeBearingLog(np.array([0.0, 0.0, 0.5]), np.array([3, 7, -1]), np.array([1.5, 2.0, 0.7]),
                         np.array([0.1, -2.0, 3.1]))  # fmt: skip
    write_range_bearing(tmp_path / "rangebearing.csv", rb)
    back = read_range_bearing(tmp_path / "rangebearing.csv")
    np.testing.assert_array_equal(back.landmark_id, rb.landmark_id)
    np.testing.assert_allclose(back.bearing, rb.bearing, atol=1e-9)
    bad = _write(tmp_path / "rb.csv", "t,landmark_id,range,bearing\n1,3,1,0\n0.5,3,1,0\n")
    with pytest.raises(DatasetError, match="goes backwards") as exc:
        read_range_bearing(bad)
    assert exc.value.line == 3
    bad_id = _write(tmp_path / "rb2.csv", "t,landmark_id,range,bearing\n1,3.5,1,0\n")
    with pytest.raises(DatasetError, match="not an integer") as exc:
        read_range_bearing(bad_id)
    assert exc.value.line == 2


def test_landmarks_errors(tmp_path: Path) -> None:
    head = "id,type,x,y,z,phi,length,width\n"
    dup = _write(tmp_path / "l.csv", head + "1,corner,0,0,2.7,0,0,0\n1,corner,1,0,2.7,0,0,0\n")
    with pytest.raises(DatasetError, match="duplicate") as exc:
        read_landmarks(dup)
    assert exc.value.line == 3
    typ = _write(tmp_path / "l2.csv", head + "1,lamp_oval,0,0,2.7,0,0,0\n")
    with pytest.raises(DatasetError, match="unknown landmark type") as exc:
        read_landmarks(typ)
    assert exc.value.line == 2


def test_projections_round_trip(tmp_path: Path) -> None:
    table = ProjectionTable(
        frame=np.zeros(2, np.int64), t=np.zeros(2), ids=np.array([4, 1001]),
        types=("lamp_rect", "corner"), pixel=np.array([[10.25, 20.5], [300.0, 1.0]]),
        angle_px=np.array([0.5, np.nan]), visible=np.array([True, False]),
        fully_visible=np.array([False, False]),
    )  # fmt: skip
    writer = ProjectionWriter(tmp_path / "truth" / "projections.csv")
    writer.write_frame(0, 0.0, table)
    writer.write_frame(1, 0.1, table)
    writer.close()
    back = read_projections(tmp_path / "truth" / "projections.csv")
    np.testing.assert_array_equal(back.frame, [0, 0, 1, 1])
    np.testing.assert_allclose(back.pixel[2:], table.pixel)
    assert back.types == ("lamp_rect", "corner") * 2
    assert back.angle_px[0] == pytest.approx(0.5) and np.isnan(back.angle_px[1])
    np.testing.assert_array_equal(back.visible, [True, False, True, False])
    np.testing.assert_array_equal(back.rows_of_frame(1), [2, 3])


def test_write_read_run(tmp_path: Path) -> None:
    rng = np.random.default_rng(11)
    t = np.arange(6) / 30.0
    odo = OdometryLog(t, rng.uniform(0, 0.02, 6), rng.uniform(0, 0.02, 6))
    gt = Trajectory(t, np.column_stack([t, 2 * t, np.linspace(-3, 3, 6)]))
    lms = LandmarkTable(np.array([1, 1000]), ("lamp_rect", "corner"),
                        np.array([[1.0, 2.0, 2.5], [0.0, 0.0, 2.7]]), np.array([0.3, 0.0]),
                        np.array([1.2, 0.0]), np.array([0.3, 0.0]))  # fmt: skip
    imgs = [(float(ti), rng.integers(0, 255, (240, 320), dtype=np.uint8)) for ti in t[::2]]
    write_run(tmp_path / "run", Rig(), odo, gt, lms, images=imgs, meta={"world": "unit"})
    run = read_run(tmp_path / "run")
    np.testing.assert_allclose(run.odometry.d_left, odo.d_left, atol=1e-9)
    assert run.groundtruth is not None and run.landmarks is not None and run.images is not None
    np.testing.assert_allclose(run.groundtruth.poses, gt.poses, atol=1e-8)
    np.testing.assert_array_equal(run.images.load(2), imgs[2][1])
    assert run.landmarks.types == lms.types
    assert run.meta["world"] == "unit" and run.meta["format_version"] == 1
    assert run.projections is None and run.range_bearing is None
    (tmp_path / "run" / "rig.yaml").unlink()
    with pytest.raises(DatasetError, match="rig.yaml"):
        read_run(tmp_path / "run")
    with pytest.raises(DatasetError, match="run directory not found"):
        read_run(tmp_path / "nope")
