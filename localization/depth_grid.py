"""Grid map and spatial feature map from RGB-D frames (paper 2, sec. 2.1-2.2).

Each depth frame becomes world points (``pointcloud.depth_to_points``, Open3D);
points in a height band above the floor are obstacles projected to the floor,
floor points and the rays to the obstacles clear free space (log-odds,
``grid.integrate_points``). The floor is ``z = 0`` for simulated runs, or fitted
with Open3D RANSAC for hand-held data (:func:`fit_floor`). SIFT features of the
colour frames with their depth give the spatial feature map (``spatial_map.py``).

World frame: ``x, y`` on the floor, ``z`` up, metres (docs/conventions.md).
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable

import numpy as np

from lampsam.arrays import FloatArray
from lampsam.datasets.rgbd import RgbdSequence
from lampsam.localization.grid import OccupancyGrid, grid_around, integrate_points
from lampsam.localization.map_config import DepthGridConfig, EnvMapConfig
from lampsam.localization.map_store import EnvMapError
from lampsam.localization.pointcloud import depth_to_points
from lampsam.localization.spatial_map import SpatialFeatureMap, SpatialMapBuilder

log = logging.getLogger(__name__)


def up_alignment(world_up: FloatArray) -> FloatArray:
    """(3, 3) rotation taking the world's up direction to ``+z``."""
    from scipy.spatial.transform import Rotation

    up = np.asarray(world_up, float) / np.linalg.norm(world_up)
    if np.allclose(up, [0.0, 0.0, 1.0]):
        return np.eye(3)
    rot, _ = Rotation.align_vectors([[0.0, 0.0, 1.0]], [up])
    return rot.as_matrix()


def split_by_height(
    points: FloatArray, floor_z: float, band: tuple[float, float]
) -> tuple[FloatArray, FloatArray]:
    """Obstacle and floor points of a z-up cloud, projected to the floor.

    Args:
        points: (N, 3) world points, metres, ``z`` up.
        floor_z: height of the floor (or the band's reference), metres.
        band: ``(lo, hi)`` obstacle heights above ``floor_z``, metres.

    Returns:
        ``obstacles_xy`` (K, 2): points with ``lo <= z - floor_z <= hi``;
        ``floor_xy`` (F, 2): points below ``lo`` (floor: seen, so free).
    """
    h = points[:, 2] - floor_z
    return points[(h >= band[0]) & (h <= band[1]), :2], points[h < band[0], :2]


def unique_cells(grid: OccupancyGrid, xy: FloatArray) -> FloatArray:
    """One point per grid cell (the first), (K, 2), to bound the cost of ray casting."""
    if len(xy) == 0:
        return xy
    cells = grid.world_to_cell(xy)
    flat = cells[:, 1] * (grid.width + 1) + cells[:, 0]
    _, first = np.unique(flat, return_index=True)
    return xy[np.sort(first)]


def farthest_per_bearing(
    sensor_xy: FloatArray, xy: FloatArray, bin_rad: float
) -> tuple[FloatArray, FloatArray]:
    """The farthest point in each bearing bin around the sensor.

    Args:
        sensor_xy: (2,) metres.
        xy: (N, 2) points, metres.
        bin_rad: bin width, rad.

    Returns:
        ``points`` (B, 2) and their distances (B,).
    """
    if len(xy) == 0:
        return xy, np.zeros(0)
    d = xy - sensor_xy
    dist = np.hypot(d[:, 0], d[:, 1])
    b = np.floor(np.arctan2(d[:, 1], d[:, 0]) / bin_rad).astype(np.int64)
    order = np.lexsort((-dist, b))
    _, first = np.unique(b[order], return_index=True)
    pick = order[first]
    return xy[pick], dist[pick]


def integrate_depth_frame(
    grid: OccupancyGrid,
    sensor_xy: FloatArray,
    obstacles_xy: FloatArray,
    floor_xy: FloatArray,
    max_range: float,
    config: DepthGridConfig,
) -> None:
    """Fuse one depth frame's floor projection into the grid (in place).

    Free space first: for each bearing bin the farthest floor point; the ray to it is
    cleared (in buckets of ``free_bucket`` metres, as ``grid.integrate_points``
    cuts rays beyond its ``max_range`` and marks no hit there). Then the obstacle
    points (one per cell): the rays to them are cleared and their cells hit, so an
    obstacle seen in this frame wins over the frame's own free rays.

    Args:
        grid: the map, modified in place.
        sensor_xy: (2,) camera position projected to the floor, metres.
        obstacles_xy: (K, 2) obstacle points on the floor plane, metres.
        floor_xy: (F, 2) floor points, metres.
        max_range: the sensor's range, metres.
        config: the parameters.
    """
    far_xy, far_d = farthest_per_bearing(sensor_xy, floor_xy, math.radians(config.bearing_bin_deg))
    bucket = np.floor(far_d / config.free_bucket).astype(np.int64)
    for k in np.unique(bucket):
        if k <= 0:
            continue
        sel = bucket == k
        integrate_points(
            grid, sensor_xy, far_xy[sel], k * config.free_bucket - 1e-6, config.log_odds
        )
    obstacles_xy = unique_cells(grid, obstacles_xy)
    if len(obstacles_xy):
        integrate_points(grid, sensor_xy, obstacles_xy, max_range, config.log_odds)


def fit_floor(
    seq: RgbdSequence,
    world_T_cameras: FloatArray,  # noqa: N803
    up_hint: FloatArray,
    max_tilt_deg: float = 35.0,
    stride: int = 8,
) -> tuple[FloatArray, float] | None:
    """The floor plane of a sequence: the lowest large plane roughly normal to ``up_hint``.

    Up to four planes are peeled off the fused, subsampled cloud with Open3D's
    RANSAC ``segment_plane`` (3 cm threshold); among those whose normal is within
    ``max_tilt_deg`` of ``up_hint`` and that hold at least 5 % of the points, the
    lowest along the normal is the floor.

    Args:
        seq: the frames.
        world_T_cameras: (N, 4, 4) camera poses.
        up_hint: (3,) approximate up direction, world.
        max_tilt_deg: largest angle between the plane normal and ``up_hint``.
        stride: pixel stride of the cloud.

    Returns:
        ``(up, offset)``: unit normal pointing up, and ``offset`` with the height of a
        point ``p`` above the floor ``up . p + offset``; None when no plane qualifies.
    """
    import open3d as o3d

    pts = np.vstack(
        [
            depth_to_points(seq.load_depth(i), seq.camera, world_T_cameras[i], stride)
            for i in range(len(seq))
        ]
    )
    if len(pts) < 100:
        return None
    hint = np.asarray(up_hint, float) / np.linalg.norm(up_hint)
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
    best: tuple[FloatArray, float] | None = None
    for _ in range(4):
        if len(cloud.points) < 0.05 * len(pts):
            break
        model, inliers = cloud.segment_plane(0.03, 3, 500)
        n, d = np.asarray(model[:3], float), float(model[3])
        scale = float(np.linalg.norm(n))
        n, d = n / scale, d / scale
        if n @ hint < 0:
            n, d = -n, -d
        if len(inliers) >= 0.05 * len(pts) and n @ hint > math.cos(math.radians(max_tilt_deg)):
            # the offset d is minus the plane's height along n: the floor has the largest d
            if best is None or d > best[1]:
                best = (n, d)
        cloud = cloud.select_by_index(inliers, invert=True)
    if best is not None:
        log.info(
            "%s: floor plane fitted, up %s, %.3f m below the origin",
            seq.root,
            np.round(best[0], 3),
            best[1],
        )
    return best


def build_depth_layers(
    seq: RgbdSequence,
    world_T_cameras: FloatArray,  # noqa: N803
    config: EnvMapConfig | None = None,
    with_features: bool = True,
    progress: Callable[[int, int], None] | None = None,
) -> tuple[OccupancyGrid, SpatialFeatureMap | None, dict[str, float]]:
    """Grid map and spatial feature map from an RGB-D sequence.

    Args:
        seq: the frames (camera, depth scale).
        world_T_cameras: (N, 4, 4) camera poses, one per frame.
        config: parameters (default: the dataclass defaults).
        with_features: also build the spatial feature map.
        progress: called with ``(i, N)`` after each frame.

    Returns:
        ``(grid, spatial map or None, timings)``; timings in seconds per stage.

    Raises:
        EnvMapError: pose count differs from the frame count, or a pose is not finite.
    """
    config = config if config is not None else EnvMapConfig()
    n = len(seq)
    poses = np.asarray(world_T_cameras, float)
    if poses.shape != (n, 4, 4):
        raise EnvMapError(f"{seq.root}: {n} frames but poses of shape {poses.shape}")
    bad = ~np.all(np.isfinite(poses.reshape(n, -1)), axis=1)
    if np.any(bad):
        raise EnvMapError(f"{seq.root}: pose of frame {int(np.flatnonzero(bad)[0])} is not finite")
    cfg = config.depth
    cam = seq.camera
    up = np.asarray(seq.world_up, float)
    fitted = fit_floor(seq, poses, up) if cfg.band_reference == "fit" else None
    if fitted is not None:
        up = fitted[0]
    align = np.eye(4)
    align[:3, :3] = up_alignment(up)
    poses = align @ poses
    if fitted is not None:
        floor_z = -fitted[1]  # after the alignment, z = up . p
    elif cfg.band_reference == "floor":
        floor_z = 0.0
    else:  # "camera", or a floor that could not be fitted
        floor_z = float(poses[0, 2, 3])
    grid = grid_around(poses[:, :2, 3], cam.max_depth + cfg.margin, cfg.resolution)
    builder = SpatialMapBuilder(config.spatial) if with_features else None
    timings = {"read": 0.0, "points": 0.0, "grid": 0.0, "features": 0.0, "merge": 0.0}
    for i in range(n):
        t0 = time.perf_counter()
        depth = seq.load_depth(i)
        rgb = seq.load_rgb(i) if builder is not None and i % config.feature_every == 0 else None
        t1 = time.perf_counter()
        pts = depth_to_points(depth, cam, poses[i], stride=cfg.depth_stride)
        obst, floor = split_by_height(pts, floor_z, cfg.height_band)
        t2 = time.perf_counter()
        integrate_depth_frame(grid, poses[i, :2, 3], obst, floor, cam.max_depth, cfg)
        t3 = time.perf_counter()
        if rgb is not None and builder is not None:
            builder.add_frame(rgb, depth, cam, poses[i])
        t4 = time.perf_counter()
        timings["read"] += t1 - t0
        timings["points"] += t2 - t1
        timings["grid"] += t3 - t2
        timings["features"] += t4 - t3
        if progress is not None:
            progress(i + 1, n)
    spatial = None
    if builder is not None:
        t0 = time.perf_counter()
        spatial = builder.finish()
        timings["merge"] = time.perf_counter() - t0
    return grid, spatial, timings
