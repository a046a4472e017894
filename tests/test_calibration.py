"""Strict rig.yaml, calibration files (ROS camera_info, OpenCV FileStorage) and the fisheye lens."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

from lampsam.datasets.calibration import (
    Intrinsics,
    intrinsics_of,
    read_calibration,
    write_camera_info,
)
from lampsam.datasets.camera import CameraModel
from lampsam.datasets.rig import Rig
from lampsam.errors import DatasetError

FISHEYE_D = np.array([0.02, -0.01, 0.003, -0.0005])
RATIONAL_D = np.array([0.1, -0.05, 0.001, -0.002, 0.01, 0.02, -0.01, 0.005])


def _rig_dict() -> dict:
    return Rig().to_dict()


# --------------------------------------------------------------------------- strict rig
@pytest.mark.parametrize(
    ("section", "key", "pattern"),
    [
        ("odometry", "wheel_base", r"odometry\.wheel_base is missing"),
        ("odometry", "k_r", r"odometry\.k_r is missing"),
        ("camera", "cx", r"camera\.cx is missing"),
        ("camera", "width", r"camera\.width is missing"),
        ("camera", "body_t_camera", r"camera\.body_t_camera is missing"),
        ("camera", None, r"section 'camera' is missing"),
        ("odometry", None, r"section 'odometry' is missing"),
    ],
)
def test_rig_yaml_missing_key_names_key_and_file(
    tmp_path: Path, section: str, key: str | None, pattern: str
) -> None:
    """A run's rig.yaml without a required key or section is an error naming both."""
    d = _rig_dict()
    if key is None:
        del d[section]
    else:
        del d[section][key]
    path = tmp_path / "rig.yaml"
    path.write_text(yaml.safe_dump(d))
    with pytest.raises(DatasetError, match=pattern) as exc:
        Rig.from_yaml(path)
    assert exc.value.path == path


@pytest.mark.parametrize(
    ("section", "key", "value", "pattern"),
    [
        ("camera", "width", 320.5, r"camera\.width: must be an integer"),
        ("camera", "fx", "90", r"camera\.fx: must be a number"),
        ("camera", "fx", float("nan"), r"camera\.fx: must be a number, got nan"),
        ("camera", "body_t_camera", [0.1, 0.0], r"body_t_camera must have shape \(3,\)"),
        ("odometry", "wheel_base", True, r"odometry\.wheel_base: must be a number"),
        ("camera", "lens", 3, r"camera\.lens: unknown key"),
        ("camera", "model", "orthographic", r"model must be one of"),
        ("odometry", "wheel_base", -0.1, r"wheel_base must be > 0"),
    ],
)
def test_rig_yaml_bad_value_names_key(
    tmp_path: Path, section: str, key: str, value: object, pattern: str
) -> None:
    d = _rig_dict()
    d[section][key] = value
    path = tmp_path / "rig.yaml"
    path.write_text(yaml.safe_dump(d))
    with pytest.raises(DatasetError, match=pattern):
        Rig.from_yaml(path)


def test_rig_documented_defaults_and_hfov(tmp_path: Path) -> None:
    """dist, body_R_camera and model may be left out; hfov_deg replaces fx..cy."""
    d = _rig_dict()
    for k in ("dist", "body_R_camera", "model", "fx", "fy", "cx", "cy"):
        del d["camera"][k]
    d["camera"]["hfov_deg"] = 120.0
    path = tmp_path / "rig.yaml"
    path.write_text(yaml.safe_dump(d))
    cam = Rig.from_yaml(path).camera
    ref = CameraModel()
    assert cam.model == "pinhole" and not cam.has_distortion
    assert cam.fx == pytest.approx(ref.fx, rel=1e-12) and cam.cx == ref.cx
    np.testing.assert_array_equal(cam.body_R_camera, ref.body_R_camera)


# --------------------------------------------------------------------------- calibration files
def _ros_yaml(path: Path, model: str, d: np.ndarray) -> None:
    """A camera_info YAML as camera_calibration writes it (hand-built here, not by our writer)."""
    path.write_text(
        "image_width: 320\nimage_height: 240\ncamera_name: ceiling\n"
        "camera_matrix:\n  rows: 3\n  cols: 3\n  data: [100.5, 0, 158.2, 0, 101.0, 121.7, 0, 0, 1]\n"
        f"distortion_model: {model}\n"
        f"distortion_coefficients:\n  rows: 1\n  cols: {len(d)}\n  data: {list(map(float, d))}\n"
        "rectification_matrix:\n  rows: 3\n  cols: 3\n  data: [1, 0, 0, 0, 1, 0, 0, 0, 1]\n"
        "projection_matrix:\n  rows: 3\n  cols: 4\n  data: [100.5, 0, 158.2, 0, 0, 101.0, 121.7, 0, 0, 0, 1, 0]\n"
    )


@pytest.mark.parametrize(
    ("model", "d", "lens"),
    [("plumb_bob", RATIONAL_D[:5], "pinhole"), ("rational_polynomial", RATIONAL_D, "pinhole"),
     ("equidistant", FISHEYE_D, "fisheye")],
)
def test_ros_camera_info(tmp_path: Path, model: str, d: np.ndarray, lens: str) -> None:
    _ros_yaml(tmp_path / "cam.yaml", model, d)
    cal = read_calibration(tmp_path / "cam.yaml")
    assert (cal.width, cal.height, cal.model) == (320, 240, lens)
    assert (cal.fx, cal.fy, cal.cx, cal.cy) == (100.5, 101.0, 158.2, 121.7)
    np.testing.assert_array_equal(cal.dist, d)
    # our writer round-trips
    write_camera_info(tmp_path / "back.yaml", cal)
    back = read_calibration(tmp_path / "back.yaml")
    np.testing.assert_array_equal(back.dist, d)
    assert back.model == lens


@pytest.mark.parametrize("fisheye", [False, True])
def test_opencv_filestorage(tmp_path: Path, fisheye: bool) -> None:
    """A FileStorage YAML written by cv2.FileStorage itself."""
    k = np.array([[100.5, 0, 158.2], [0, 101.0, 121.7], [0, 0, 1]])
    d = FISHEYE_D if fisheye else RATIONAL_D[:5]
    fs = cv2.FileStorage(str(tmp_path / "cv.yaml"), cv2.FILE_STORAGE_WRITE)
    fs.write("image_width", 320)
    fs.write("image_height", 240)
    fs.write("camera_matrix", k)
    fs.write("distortion_coefficients", d.reshape(-1, 1))
    if fisheye:
        fs.write("fisheye_model", 1)
    fs.release()
    cal = read_calibration(tmp_path / "cv.yaml")
    assert cal.model == ("fisheye" if fisheye else "pinhole")
    assert (cal.fx, cal.cy) == (100.5, 121.7)
    np.testing.assert_allclose(cal.dist, d)


def test_calibration_errors_name_file_and_key(tmp_path: Path) -> None:
    _ros_yaml(tmp_path / "cam.yaml", "equidistant", RATIONAL_D[:5])
    with pytest.raises(DatasetError, match=r"cam\.yaml.*equidistant.*4"):
        read_calibration(tmp_path / "cam.yaml")
    _ros_yaml(tmp_path / "cam.yaml", "unified", FISHEYE_D)
    with pytest.raises(DatasetError, match="'unified' is not supported"):
        read_calibration(tmp_path / "cam.yaml")
    (tmp_path / "nok.yaml").write_text("image_width: 320\nimage_height: 240\n")
    with pytest.raises(DatasetError, match="camera_matrix"):
        read_calibration(tmp_path / "nok.yaml")
    with pytest.raises(DatasetError, match="not found"):
        read_calibration(tmp_path / "absent.yaml")


def test_rig_with_calibration_file(tmp_path: Path) -> None:
    """rig.yaml's camera may name a calibration file (relative) plus the mounting."""
    _ros_yaml(tmp_path / "cam.yaml", "equidistant", FISHEYE_D)
    d = _rig_dict()
    d["camera"] = {"calibration": "cam.yaml", "body_t_camera": [0.1, 0.0, 0.3]}
    (tmp_path / "rig.yaml").write_text(yaml.safe_dump(d))
    cam = Rig.from_yaml(tmp_path / "rig.yaml").camera
    assert cam.model == "fisheye" and cam.fx == 100.5
    np.testing.assert_array_equal(cam.dist, FISHEYE_D)
    d["camera"]["cx"] = 3.0
    (tmp_path / "rig.yaml").write_text(yaml.safe_dump(d))
    with pytest.raises(DatasetError, match=r"camera\.cx given together with camera\.calibration"):
        Rig.from_yaml(tmp_path / "rig.yaml")
    # a written rig keeps the lens model
    Rig(camera=cam).to_yaml(tmp_path / "rig2.yaml")
    assert Rig.from_yaml(tmp_path / "rig2.yaml").camera.model == "fisheye"


# --------------------------------------------------------------------------- lens models
@pytest.mark.parametrize(
    "camera",
    [
        CameraModel(dist=RATIONAL_D),
        CameraModel.from_fov(hfov_deg=160.0, model="fisheye", dist=FISHEYE_D),
        CameraModel.from_fov(hfov_deg=200.0, model="fisheye"),
    ],
)
def test_undistort_inverts_projection(camera: CameraModel) -> None:
    """pixels -> ceiling coordinates -> pixels is the identity wherever a ray points up."""
    rng = np.random.default_rng(5)
    px = np.column_stack([rng.uniform(0, camera.width - 1, 500), rng.uniform(0, camera.height - 1, 500)])
    m = camera.normalized_from_pixels(px)
    ok = np.all(np.isfinite(m), axis=1)
    assert ok.mean() > 0.5
    np.testing.assert_allclose(camera.pixels_from_normalized(m[ok]), px[ok], atol=1e-6)


def test_fisheye_is_equidistant_and_sees_wider_than_a_pinhole() -> None:
    """Without coefficients the fisheye radius is f * theta (cv2.fisheye's model)."""
    cam = CameraModel.from_fov(hfov_deg=180.0, model="fisheye")
    theta = np.linspace(0.05, 1.5, 20)
    pc = np.column_stack([np.sin(theta), np.zeros(20), np.cos(theta)])
    px, ok = cam.project_camera_points(pc)
    assert ok.all()
    np.testing.assert_allclose(px[:, 0] - cam.cx, cam.fx * theta, rtol=1e-9)
    # the image corner is beyond 90 deg for a 180 deg horizontal FOV: no ceiling coordinate
    assert np.isnan(cam.normalized_from_pixels(np.array([[0.0, 0.0]]))).all()
    assert np.isfinite(cam.normalized_from_pixels(np.array([[cam.cx, cam.cy]]))).all()


def test_intrinsics_round_trip_through_camera() -> None:
    cam = CameraModel.from_fov(hfov_deg=150.0, model="fisheye", dist=FISHEYE_D)
    cal = intrinsics_of(cam)
    assert isinstance(cal, Intrinsics)
    back = cal.camera(body_t_camera=cam.body_t_camera)
    assert (back.fx, back.model) == (cam.fx, "fisheye")
    np.testing.assert_array_equal(back.dist, cam.dist)


def test_fisheye_simulated_run_end_to_end(tmp_path: Path) -> None:
    """A 150 deg equidistant fisheye: rendered, its lamps found where the truth projects
    them, and ceiling SLAM (iSAM2 on images) tracks the robot."""
    import dataclasses

    from lampsam.backend.slam import run_slam
    from lampsam.datasets.logrun import read_run
    from lampsam.datasets.simulator import simulate_world
    from lampsam.datasets.world import load_world
    from lampsam.frontend.lamps import detect_lamps

    w = load_world("lab")
    cam = w.rig.camera
    fish = CameraModel.from_fov(cam.width, cam.height, 150.0, model="fisheye",
                                body_t_camera=cam.body_t_camera, body_R_camera=cam.body_R_camera)
    world = dataclasses.replace(w, rig=dataclasses.replace(w.rig, camera=fish))
    out = simulate_world(world, tmp_path / "fish", seed=2, duration=2.0, workers=1)
    run = read_run(out)
    assert run.rig.camera.model == "fisheye" and run.images is not None and run.projections is not None
    img = run.images.load(0)
    found = [o.m for o in detect_lamps(img, run.rig.camera).lamps]
    rows = run.projections.rows_of_frame(0)
    full = rows[run.projections.fully_visible[rows] & np.array(
        [run.projections.types[r].startswith("lamp") for r in rows], dtype=bool)]
    assert len(full) >= 2
    truth_m = run.rig.camera.normalized_from_pixels(run.projections.pixel[full])
    # Each fully visible lamp is detected near its true centre. Not closer: the detector
    # takes blob moments in pixels, and a fisheye bends the blob (measured: 0.027 here).
    for m in truth_m:
        assert min(np.linalg.norm(np.asarray(found) - m, axis=1)) < 0.04
    res = run_slam(out, "isam2", frames="images")
    assert run.groundtruth is not None
    err = res.poses[:, :2] - run.groundtruth.interpolate(res.times)[:, :2]
    assert len(res.landmarks) >= 5
    assert float(np.sqrt(np.mean(np.sum(err**2, axis=1)))) < 0.02
