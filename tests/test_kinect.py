"""Kinect simulator: depth geometry, drop-outs, noise, TUM RGB-D round trip, scene3d."""

from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np
import pytest

from lampsam.datasets.kinect_sim import (
    KinectConfig,
    KinectRenderer,
    MappingDrive,
    TumRgbdWriter,
    world_T_camera,
    zigzag_waypoints,
)
from lampsam.datasets.rgbd import read_tum_rgbd
from lampsam.datasets.scene3d import apply_changes, load_scene, scene_from_dict
from lampsam.errors import DatasetError

CFG = KinectConfig(width=160, height=120)


def _wall_scene(x_wall: float) -> dict[str, object]:
    """One wall along y at x = x_wall (its face toward the origin at x_wall - 0.05)."""
    return {
        "height": 3.0,
        "walls": [{"id": "w", "start": [x_wall, -5.0], "end": [x_wall, 5.0], "thickness": 0.1}],
    }


def test_wall_at_known_distance_gives_that_depth() -> None:
    scene = scene_from_dict(_wall_scene(3.0), bounds=[-1, -5, 4, 5])
    r = KinectRenderer(scene, CFG)
    pose = np.array([0.0, 0.0, 0.0])  # facing +x
    z_true = 2.95 - CFG.body_t_camera[0]
    _, depth = r.render_pose(pose)  # noise-free
    centre = depth[50:70, 70:90].astype(float) / CFG.depth_scale
    np.testing.assert_allclose(centre, z_true, atol=1.0 / CFG.depth_scale)
    # a fronto-parallel wall has the same depth (z, not range) across the image where it is seen
    wall_rows = depth[20:100, :].astype(float) / CFG.depth_scale
    np.testing.assert_allclose(wall_rows[wall_rows > 0], z_true, atol=1.0 / CFG.depth_scale)
    # with noise: sigma = 1.5e-3 z^2, checked over 2400 pixels (3-sigma of the mean / spread)
    _, noisy = r.render_pose(pose, np.random.default_rng(7))
    z = noisy[40:80, 50:110].astype(float) / CFG.depth_scale
    sigma = CFG.sigma_depth_k * z_true**2
    assert abs(z.mean() - z_true) < 3 * sigma / math.sqrt(z.size) + 1e-4
    assert 0.8 * sigma < z.std() < 1.25 * sigma


def test_out_of_range_and_grazing_angles_have_no_depth() -> None:
    r = KinectRenderer(scene_from_dict(_wall_scene(6.0), bounds=[-1, -5, 7, 5]), CFG)
    _, depth = r.render_pose(np.zeros(3))
    assert np.all(depth[:55, :] == 0)  # wall at 5.8 m: beyond max_depth 4.5 m, no depth
    # floor rows: the ray meets the floor at incidence 90 deg - elevation; the bottom row
    # (21.5 deg down, incidence 68.5 deg) has depth, rows above 15 deg down (> 75 deg) do not
    v = np.arange(CFG.height)
    down = np.degrees(np.arctan((v - CFG.cy) / CFG.fy))
    col = depth[:, CFG.width // 2]
    assert np.all(col[(down > 16.0)] > 0)
    assert np.all(col[(down > 0.5) & (down < 14.0)] == 0)
    # the floor points lie at z = 0: depth * tan(angle) = camera height
    rows = np.flatnonzero(down > 16.0)
    z = col[rows].astype(float) / CFG.depth_scale
    h = z * (rows - CFG.cy) / CFG.fy
    np.testing.assert_allclose(h, CFG.body_t_camera[2], atol=0.01)


def test_picture_is_textured_and_wall_is_plain() -> None:
    section = _wall_scene(3.0)
    section["pictures"] = [
        {
            "id": "p",
            "center": [2.94, 0.0, 0.45],
            "width": 1.2,
            "height": 0.8,
            "facing_deg": 180,
            "seed": 3,
        }
    ]
    r = KinectRenderer(scene_from_dict(section, bounds=[-1, -5, 4, 5]), CFG)
    rgb, _ = r.render_pose(np.zeros(3))
    grey = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)
    sift = cv2.SIFT_create()
    kps = sift.detect(grey, None)
    assert len(kps) >= 20
    # every keypoint lies on the picture (image centre region), none on the plain wall
    cols = np.array([k.pt[0] for k in kps])
    half_w_px = 0.6 / (2.95 - CFG.body_t_camera[0]) * CFG.fx
    assert np.all(np.abs(cols - CFG.cx) < half_w_px + 4)


def test_tum_rgbd_round_trip(tmp_path: Path) -> None:
    rng = np.random.default_rng(11)
    writer = TumRgbdWriter(tmp_path / "kinect", CFG)
    frames = []
    for k in range(3):
        rgb = rng.integers(0, 256, (CFG.height, CFG.width, 3), dtype=np.uint8)
        depth = rng.integers(0, 20000, (CFG.height, CFG.width), dtype=np.uint16)
        T = world_T_camera(np.array([k * 0.5, 1.0, 0.3 * k]), CFG)
        writer.write(0.5 * k, rgb, depth, T)
        frames.append((rgb, depth, T))
    writer.close()
    seq = read_tum_rgbd(tmp_path / "kinect")
    assert len(seq) == 3
    assert seq.camera.depth_scale == CFG.depth_scale
    assert seq.camera.fx == pytest.approx(CFG.fx)
    np.testing.assert_allclose(seq.camera.body_T_camera, CFG.body_T_camera(), atol=1e-12)
    for k, (rgb, depth, T) in enumerate(frames):
        np.testing.assert_array_equal(seq.load_rgb(k), rgb)
        np.testing.assert_array_equal(seq.load_depth(k), depth)
        np.testing.assert_allclose(seq.world_T_camera[k], T, atol=1e-6)


def test_tum_rgbd_bad_frames_are_named(tmp_path: Path) -> None:
    writer = TumRgbdWriter(tmp_path / "k", CFG)
    rgb = np.zeros((CFG.height, CFG.width, 3), np.uint8)
    writer.write(0.0, rgb, np.zeros((CFG.height, CFG.width), np.uint16), np.eye(4))
    writer.write(1.0, rgb, np.zeros((CFG.height, CFG.width), np.uint16), np.eye(4))
    writer.close()
    cv2.imwrite(
        str(tmp_path / "k" / "depth" / "0.000000.png"), np.zeros((CFG.height, CFG.width), np.uint8)
    )
    cv2.imwrite(str(tmp_path / "k" / "depth" / "1.000000.png"), np.zeros((10, 10), np.uint16))
    seq = read_tum_rgbd(tmp_path / "k")
    with pytest.raises(DatasetError, match=r"0\.000000\.png.*16-bit"):
        seq.load_depth(0)
    with pytest.raises(DatasetError, match=r"1\.000000\.png.*10x10"):
        seq.load_depth(1)
    (tmp_path / "k" / "depth.txt").write_text("0.0 depth/0.000000.png\n0.0 depth/1.000000.png\n")
    with pytest.raises(DatasetError, match=r"depth\.txt:2: time goes backwards"):
        read_tum_rgbd(tmp_path / "k")


def test_office_scene_doors_and_changes() -> None:
    scene = load_scene("office")
    ids = scene.ids()
    assert {"desk1", "sofa", "p1", "p8"} <= ids
    assert "door_east" in ids  # closed door is a box; the open south door is a gap
    assert not any(b.id == "door_south" for b in scene.boxes)
    moved = apply_changes(scene, ["furniture_moved", "pictures_down"])
    sofa = next(b for b in moved.boxes if b.id == "sofa")
    np.testing.assert_allclose(sofa.center[:2], [3.2, 9.5])
    assert {p.id for p in moved.pictures} == {"p2", "p4", "p6", "p8"}
    assert len(scene.pictures) == 8  # the original is unchanged
    with pytest.raises(DatasetError, match="unknown change"):
        apply_changes(scene, ["earthquake"])


@pytest.mark.parametrize(
    ("section", "match"),
    [
        ({"walls": [{"id": "w", "start": [0, 0], "end": [0, 0]}]}, "zero length"),
        (
            {
                "walls": [{"id": "w", "start": [0, 0], "end": [2, 0]}],
                "doors": [{"wall": "w", "along": 1.9, "width": 0.9}],
            },
            "outside wall",
        ),
        ({"furniture": [{"id": "a", "center": [0, 0], "size": [1, 1]}]}, r"furniture\[a\]\.size: must be 3 finite numbers"),
        (
            {
                "walls": [{"id": "w", "start": [0, 0], "end": [2, 0]}],
                "changes": [{"name": "c", "remove": ["nope"]}],
            },
            "unknown ids",
        ),
    ],
)
def test_bad_scene_raises(section: dict[str, object], match: str) -> None:
    with pytest.raises(DatasetError, match=match):
        scene_from_dict(section)


def test_zigzag_covers_the_lattice() -> None:
    wp = zigzag_waypoints(MappingDrive())
    assert wp.shape[1] == 2
    for lane in (1.6, 3.3, 5.0, 6.7, 8.4):
        # every lane is driven both along x and along y
        assert np.any((wp[:-1, 1] == lane) & (wp[1:, 1] == lane))
        assert np.any((wp[:-1, 0] == lane) & (wp[1:, 0] == lane))


def test_office_path_is_the_default_zigzag() -> None:
    from lampsam.datasets.world import load_world

    np.testing.assert_allclose(load_world("office").waypoints, zigzag_waypoints(MappingDrive()))


def test_rotation_to_quaternion_matches_scipy_including_half_turns() -> None:
    from scipy.spatial.transform import Rotation

    from lampsam.datasets.kinect_sim import rotation_to_quaternion

    mats = Rotation.random(500, random_state=np.random.default_rng(4)).as_matrix()
    half_turns = [np.diag([1.0, -1.0, -1.0]), np.diag([-1.0, 1.0, -1.0]), np.diag([-1.0, -1.0, 1.0])]
    for R in [*mats, np.eye(3), *half_turns]:
        q = rotation_to_quaternion(R)
        ref = Rotation.from_matrix(R).as_quat()
        ref = ref if ref[3] >= 0 else -ref
        assert q[3] >= 0 and np.linalg.norm(q) == pytest.approx(1.0, abs=1e-12)
        np.testing.assert_allclose(Rotation.from_quat(q).as_matrix(), R, atol=1e-12)
        if ref[3] > 1e-9:  # qw = 0: q and -q are the same rotation, either sign is right
            np.testing.assert_allclose(q, ref, atol=1e-12)
