"""Depth images to point clouds with Open3D, placed in the world with poses.

Paper 2, sec. 2.1: the grid map is made from the Kinect's 3-D points projected
to the floor. The back-projection of pixel ``(u, v)`` with depth ``z`` is
``p_cam = z ((u - cx) / fx, (v - cy) / fy, 1)`` (OpenCV camera frame: ``x``
right, ``y`` down, ``z`` optical axis), and ``p_world = world_T_camera p_cam``.
Open3D's ``PointCloud.create_from_depth_image`` / ``create_from_rgbd_image``
do exactly this (their ``extrinsic`` is ``camera_T_world``).
"""

from __future__ import annotations

import logging
from typing import Any

import numpy as np

from lampsam.arrays import FloatArray, ImageU8, ImageU16
from lampsam.datasets.rgbd import RgbdCamera, RgbdSequence
from lampsam.errors import LocalizationError

log = logging.getLogger(__name__)


class PointCloudError(LocalizationError):
    """Bad depth or pose input (wrong size or type, non-finite pose)."""


def check_depth(depth: np.ndarray, camera: RgbdCamera, name: str = "depth") -> ImageU16:
    """Validate a depth image against a camera.

    Args:
        depth: the image; must be uint16 (H, W) with the camera's size.
        camera: the camera.
        name: what to call it in the error (e.g. the file).

    Returns:
        ``depth`` as a C-contiguous uint16 array.

    Raises:
        PointCloudError: wrong dtype, number of channels or size.
    """
    if not isinstance(depth, np.ndarray) or depth.dtype != np.uint16:
        dtype = getattr(depth, "dtype", type(depth).__name__)
        raise PointCloudError(
            f"{name}: depth must be uint16 (value / depth_scale = metres), got {dtype}"
        )
    if depth.ndim != 2 or depth.shape != (camera.height, camera.width):
        raise PointCloudError(
            f"{name}: depth is {depth.shape}, camera expects ({camera.height}, {camera.width})"
        )
    return np.ascontiguousarray(depth)


def check_pose(world_T_camera: FloatArray, name: str = "pose") -> FloatArray:  # noqa: N803
    """Validate a (4, 4) rigid transform; raises :class:`PointCloudError` if bad."""
    T = np.asarray(world_T_camera, dtype=np.float64)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise PointCloudError(f"{name}: expected a finite (4, 4) transform, got shape {T.shape}")
    if abs(np.linalg.det(T[:3, :3]) - 1.0) > 1e-3:
        raise PointCloudError(
            f"{name}: rotation part is not a rotation (det {np.linalg.det(T[:3, :3]):.4f})"
        )
    return T


def _intrinsic(camera: RgbdCamera) -> Any:
    """Open3D ``PinholeCameraIntrinsic`` of the camera."""
    import open3d as o3d

    return o3d.camera.PinholeCameraIntrinsic(
        camera.width, camera.height, camera.fx, camera.fy, camera.cx, camera.cy
    )


def _depth_in_range(depth: ImageU16, camera: RgbdCamera) -> ImageU16:
    """Zero the pixels nearer than ``min_depth`` (Open3D only truncates the far side)."""
    near = depth < camera.min_depth * camera.depth_scale
    if np.any(near & (depth > 0)):
        depth = depth.copy()
        depth[near] = 0
    return depth


def depth_to_points(
    depth: ImageU16,
    camera: RgbdCamera,
    world_T_camera: FloatArray | None = None,  # noqa: N803
    stride: int = 1,
) -> FloatArray:
    """Back-project a depth image with Open3D ``create_from_depth_image``.

    Args:
        depth: uint16 (H, W), metres = value / ``camera.depth_scale``; 0 = no depth.
        camera: the camera; pixels outside ``[min_depth, max_depth]`` are dropped.
        world_T_camera: (4, 4) camera pose; None gives camera-frame points.
        stride: use every ``stride``-th pixel in both directions.

    Returns:
        (N, 3) points, metres, in the world frame (or camera frame), in row-major
        pixel order of the valid pixels.

    Raises:
        PointCloudError: bad depth or pose.
    """
    import open3d as o3d

    depth = _depth_in_range(check_depth(depth, camera), camera)
    extrinsic = np.eye(4) if world_T_camera is None else np.linalg.inv(check_pose(world_T_camera))
    pcd = o3d.geometry.PointCloud.create_from_depth_image(
        o3d.geometry.Image(depth),  # type: ignore[call-overload]
        _intrinsic(camera),
        extrinsic,
        depth_scale=float(camera.depth_scale),
        depth_trunc=float(camera.max_depth),
        stride=int(stride),
        project_valid_depth_only=True,
    )
    return np.asarray(pcd.points, dtype=np.float64)


def rgbd_to_cloud(
    rgb: ImageU8,
    depth: ImageU16,
    camera: RgbdCamera,
    world_T_camera: FloatArray | None = None,  # noqa: N803
) -> Any:
    """Coloured point cloud with Open3D ``create_from_rgbd_image``.

    Args:
        rgb: uint8 (H, W, 3) RGB.
        depth: uint16 (H, W) (see :func:`depth_to_points`).
        camera: the camera.
        world_T_camera: (4, 4) camera pose; None gives the camera frame.

    Returns:
        ``open3d.geometry.PointCloud`` with colours in [0, 1], points in metres.

    Raises:
        PointCloudError: bad images or pose.
    """
    import open3d as o3d

    depth = _depth_in_range(check_depth(depth, camera), camera)
    if rgb.dtype != np.uint8 or rgb.shape != (camera.height, camera.width, 3):
        raise PointCloudError(
            f"colour must be uint8 ({camera.height}, {camera.width}, 3), "
            f"got {rgb.dtype} {rgb.shape}"
        )
    rgbd = o3d.geometry.RGBDImage.create_from_color_and_depth(
        o3d.geometry.Image(np.ascontiguousarray(rgb)),  # type: ignore[call-overload]
        o3d.geometry.Image(depth),  # type: ignore[call-overload]
        depth_scale=float(camera.depth_scale),
        depth_trunc=float(camera.max_depth),
        convert_rgb_to_intensity=False,
    )
    extrinsic = np.eye(4) if world_T_camera is None else np.linalg.inv(check_pose(world_T_camera))
    return o3d.geometry.PointCloud.create_from_rgbd_image(rgbd, _intrinsic(camera), extrinsic)


def backproject_pixels(
    depth: ImageU16,
    camera: RgbdCamera,
    pixels: FloatArray,
) -> tuple[FloatArray, np.ndarray]:
    """3-D camera-frame points of selected pixels (e.g. SIFT keypoints).

    The depth is read at the nearest pixel; ``p = z ((u - cx)/fx, (v - cy)/fy, 1)``.

    Args:
        depth: uint16 (H, W).
        camera: the camera.
        pixels: (N, 2) ``(col, row)`` sub-pixel positions.

    Returns:
        ``points`` (N, 3) metres in the camera frame (NaN where invalid) and
        ``valid`` (N,) bool: depth present and within ``[min_depth, max_depth]``.
    """
    depth = check_depth(depth, camera)
    px = np.asarray(pixels, dtype=np.float64).reshape(-1, 2)
    col = np.clip(np.rint(px[:, 0]).astype(int), 0, camera.width - 1)
    row = np.clip(np.rint(px[:, 1]).astype(int), 0, camera.height - 1)
    z = depth[row, col].astype(np.float64) / camera.depth_scale
    valid = (z >= camera.min_depth) & (z <= camera.max_depth)
    pts = np.stack(
        [(px[:, 0] - camera.cx) / camera.fx * z, (px[:, 1] - camera.cy) / camera.fy * z, z], axis=1
    )
    pts[~valid] = np.nan
    return pts, valid


def transform_points(T: FloatArray, points: FloatArray) -> FloatArray:  # noqa: N803
    """Apply a (4, 4) transform to (N, 3) points."""
    return points @ T[:3, :3].T + T[:3, 3]


def overlap_agreement(
    points_a: FloatArray, points_b: FloatArray, overlap_radius: float = 0.10
) -> tuple[float, int]:
    """How well two world-frame clouds agree where they overlap.

    Each point of ``a`` finds its nearest neighbour in ``b``; pairs closer than
    ``overlap_radius`` are the overlap.

    Args:
        points_a: (N, 3) metres.
        points_b: (M, 3) metres.
        overlap_radius: what counts as overlapping, metres.

    Returns:
        Median nearest-neighbour distance in the overlap (metres; NaN if none)
        and the number of overlapping points.
    """
    from scipy.spatial import cKDTree

    if len(points_a) == 0 or len(points_b) == 0:
        return float("nan"), 0
    dist, _ = cKDTree(points_b).query(points_a, distance_upper_bound=overlap_radius)
    inside = np.isfinite(dist)
    if not np.any(inside):
        return float("nan"), 0
    return float(np.median(dist[inside])), int(inside.sum())


def fuse_sequence(
    seq: RgbdSequence,
    world_T_cameras: FloatArray | None = None,  # noqa: N803
    voxel: float = 0.01,
) -> Any:
    """Fuse all frames of an RGB-D sequence into one coloured world cloud.

    Each frame goes through :func:`rgbd_to_cloud` at its pose; the union is voxel
    downsampled (Open3D ``voxel_down_sample``) so that overlapping frames do not
    pile up points.

    Args:
        seq: the frames.
        world_T_cameras: (N, 4, 4) poses; default the sequence's own.
        voxel: voxel size, metres (0 keeps every point).

    Returns:
        ``open3d.geometry.PointCloud`` in the world frame.

    Raises:
        PointCloudError: no poses, or a pose count that differs from the frames.
    """
    import open3d as o3d

    poses = seq.world_T_camera if world_T_cameras is None else np.asarray(world_T_cameras, float)
    if poses is None or len(poses) != len(seq):
        raise PointCloudError(f"{seq.root}: need one pose per frame ({len(seq)} frames)")
    fused = o3d.geometry.PointCloud()
    for i in range(len(seq)):
        fused += rgbd_to_cloud(seq.load_rgb(i), seq.load_depth(i), seq.camera, poses[i])
    return fused.voxel_down_sample(voxel) if voxel > 0 else fused
