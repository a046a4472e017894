"""Depth -> points (Open3D) against hand-made depth images, bad input, slambook2 overlap."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from lampsam.datasets.rgbd import RgbdCamera, read_slambook2
from lampsam.localization.depth_grid import build_depth_layers, fit_floor
from lampsam.localization.grid import free_mask, occupied_mask
from lampsam.localization.map_config import DepthGridConfig, EnvMapConfig
from lampsam.localization.pointcloud import (
    PointCloudError,
    backproject_pixels,
    depth_to_points,
    fuse_sequence,
    overlap_agreement,
    rgbd_to_cloud,
)
from tests.conftest import require_shared

CAM = RgbdCamera(
    width=6,
    height=4,
    fx=10.0,
    fy=20.0,
    cx=2.5,
    cy=1.5,
    depth_scale=1000.0,
    min_depth=0.3,
    max_depth=5.0,
)


def _hand_depth() -> np.ndarray:
    d = np.zeros((4, 6), np.uint16)
    d[0, 0] = 1000  # 1 m at pixel (col 0, row 0)
    d[1, 4] = 2500  # 2.5 m at (col 4, row 1)
    d[3, 5] = 4000  # 4 m at (col 5, row 3)
    d[2, 2] = 200  # 0.2 m: nearer than min_depth, dropped
    d[2, 3] = 6000  # 6 m: beyond max_depth, dropped
    return d


def test_depth_projection_matches_hand_made_image() -> None:
    pts = depth_to_points(_hand_depth(), CAM)
    expected = np.array(
        [
            [(0 - 2.5) / 10 * 1.0, (0 - 1.5) / 20 * 1.0, 1.0],
            [(4 - 2.5) / 10 * 2.5, (1 - 1.5) / 20 * 2.5, 2.5],
            [(5 - 2.5) / 10 * 4.0, (3 - 1.5) / 20 * 4.0, 4.0],
        ]
    )
    np.testing.assert_allclose(pts, expected, atol=1e-6)


def test_depth_projection_with_pose_is_world_frame() -> None:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("z", 30, degrees=True).as_matrix()
    T[:3, 3] = [1.0, -2.0, 0.5]
    cam_pts = depth_to_points(_hand_depth(), CAM)
    world = depth_to_points(_hand_depth(), CAM, T)
    np.testing.assert_allclose(world, cam_pts @ T[:3, :3].T + T[:3, 3], atol=1e-6)


def test_backproject_pixels_agrees_with_open3d() -> None:
    px = np.array([[0.0, 0.0], [4.0, 1.0], [5.0, 3.0], [2.0, 2.0], [1.0, 1.0]])
    pts, valid = backproject_pixels(_hand_depth(), CAM, px)
    np.testing.assert_array_equal(valid, [True, True, True, False, False])
    np.testing.assert_allclose(pts[valid], depth_to_points(_hand_depth(), CAM), atol=1e-9)
    assert np.all(np.isnan(pts[~valid]))


def test_coloured_cloud_has_the_same_points_and_colours() -> None:
    rgb = np.zeros((4, 6, 3), np.uint8)
    rgb[1, 4] = (255, 0, 0)
    cloud = rgbd_to_cloud(rgb, _hand_depth(), CAM)
    pts = np.asarray(cloud.points)
    np.testing.assert_allclose(pts, depth_to_points(_hand_depth(), CAM), atol=1e-6)
    np.testing.assert_allclose(np.asarray(cloud.colors)[1], [1.0, 0.0, 0.0], atol=1e-6)


@pytest.mark.parametrize(
    ("depth", "match"),
    [
        (np.zeros((4, 6), np.float32), "uint16"),
        (np.zeros((4, 6), np.uint8), "uint16"),
        (np.zeros((5, 6), np.uint16), r"camera expects \(4, 6\)"),
        (np.zeros((4, 6, 3), np.uint16), r"camera expects"),
    ],
)
def test_bad_depth_raises_clear_error(depth: np.ndarray, match: str) -> None:
    with pytest.raises(PointCloudError, match=match):
        depth_to_points(depth, CAM)


def test_bad_pose_raises_clear_error() -> None:
    with pytest.raises(PointCloudError, match=r"\(4, 4\)"):
        depth_to_points(_hand_depth(), CAM, np.eye(3))
    bad = np.eye(4)
    bad[0, 3] = math.nan
    with pytest.raises(PointCloudError, match="finite"):
        depth_to_points(_hand_depth(), CAM, bad)


def test_slambook2_consecutive_clouds_agree_in_overlap() -> None:
    """Consecutive frames' world clouds: median NN distance in the overlap under 4 cm.

    The overlap is the set of points of frame i with a neighbour in frame i+1 within
    10 cm; the tolerance (4 cm) is what the data's README measured (2-4 cm). With a
    wrong pose (frame i's pose used for frame i+1) the agreement must be clearly worse.
    """
    seq = read_slambook2(require_shared("rgbd_slambook2"))
    assert len(seq) == 5
    clouds = [
        depth_to_points(seq.load_depth(i), seq.camera, seq.world_T_camera[i], stride=4)
        for i in range(5)
    ]
    for i in range(4):
        med, n = overlap_agreement(clouds[i], clouds[i + 1], overlap_radius=0.10)
        assert n > 1000
        assert med < 0.04, f"frames {i + 1}-{i + 2}: median {med:.3f} m"
    wrong = depth_to_points(seq.load_depth(4), seq.camera, seq.world_T_camera[0], stride=4)
    med_wrong, _ = overlap_agreement(clouds[3], wrong, overlap_radius=0.5)
    med_right, _ = overlap_agreement(clouds[3], clouds[4], overlap_radius=0.5)
    assert med_wrong > 2.0 * med_right


def test_slambook2_fused_cloud_floor_and_grid_map() -> None:
    """The 5 frames fused into one cloud and one grid map.

    The fitted floor is about 18 deg from the data's -y axis (the reference camera
    looks down); the hand-held camera stays at one height above it (within 10 cm,
    between 0.8 and 2 m). The grid map has free floor and occupied furniture/walls.
    """
    seq = read_slambook2(require_shared("rgbd_slambook2"))
    cloud = fuse_sequence(seq, voxel=0.02)
    pts = np.asarray(cloud.points)
    assert 20_000 < len(pts) < 300_000 and len(cloud.colors) == len(pts)
    fitted = fit_floor(seq, seq.world_T_camera, seq.world_up)
    assert fitted is not None
    up, offset = fitted
    assert np.degrees(np.arccos(up @ seq.world_up)) < 30.0
    heights = seq.world_T_camera[:, :3, 3] @ up + offset
    assert 0.8 < heights.min() and heights.max() < 2.0 and np.ptp(heights) < 0.10
    # the fused cloud's lowest large mass is the floor: 5 % of points within 3 cm of it
    assert np.mean(np.abs(pts @ up + offset) < 0.03) > 0.05
    cfg = EnvMapConfig(depth=DepthGridConfig(band_reference="fit", depth_stride=4))
    grid, spatial, _ = build_depth_layers(seq, seq.world_T_camera, cfg, with_features=False)
    assert spatial is None
    assert occupied_mask(grid).sum() > 500 and free_mask(grid).sum() > 2000
