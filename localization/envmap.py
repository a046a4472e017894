"""The environment map: grid map, spatial feature map, ceiling feature map (paper 2, sec. 2).

``build_map(run, out, poses=...)`` turns one mapping run into a self-describing
map directory::

    manifest.yaml            format, versions, units, frames, layers, config, checks
    map.pgm + map.yaml       grid map (ROS map_server, via lampsam.localization.grid)
    spatial_features.npz     SIFT points with world positions (spatial_map.py)
    ceiling_features.csv     lamps and corners (ceiling_map.py)

Sources (detected from ``run``):

- a simulated/logged run with ``kinect/`` (TUM RGB-D): Kinect depth -> points
  with Open3D (pointcloud.py), placed with the mapping poses (``groundtruth``:
  the run's ``groundtruth.tum``; ``slam:PATH``: a backend's planar TUM
  trajectory, whose ``landmarks.csv`` next to it gives the ceiling layer);
  points in a height band above the floor are obstacles projected to the floor,
  floor points and the rays to obstacles clear free space (grid.integrate_points,
  log-odds); SIFT features -> spatial layer;
- a TUM RGB-D directory, or the slambook2 sample (its own camera poses);
- a CARMEN laser log (``*.log``/``*.log.gz``, e.g. the Intel lab): the scans at
  the log's corrected poses (or ``slam:PATH``) -> grid map only.

World frame: docs/conventions.md (``x, y`` on the floor, ``z`` up, metres).
"""

from __future__ import annotations

import dataclasses
import logging
import math
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from lampsam.arrays import FloatArray
from lampsam.datasets.rgbd import RgbdSequence
from lampsam.localization.ceiling_map import CeilingFeatureMap
from lampsam.localization.grid import (
    OccupancyGrid,
    integrate_points,
    integrate_scan,
)
from lampsam.localization.map_config import (
    DepthGridConfig,
    EnvMapConfig,
    LaserGridConfig,
)
from lampsam.localization.map_poses import (
    camera_poses_from_planar,
    parse_pose_source,
    planar_poses_at,
)
from lampsam.localization.map_quality import FloorPlan, grid_checks
from lampsam.localization.map_store import (
    EnvironmentMap,  # noqa: F401 - re-exported while callers move to map_store
    EnvMapError,
    load_env_map,  # noqa: F401 - re-exported while callers move to map_store
    save_layers,
    write_manifest,
)
from lampsam.localization.pointcloud import depth_to_points
from lampsam.localization.spatial_map import (
    SpatialFeatureMap,
    SpatialMapBuilder,
)

log = logging.getLogger(__name__)

@dataclass(frozen=True)
class BuildReport:
    """What ``build_map`` did.

    Attributes:
        out: the map directory.
        source: ``run``, ``tum_rgbd``, ``slambook2`` or ``laser``.
        n_frames: frames or scans used.
        timings: stage -> seconds.
        checks: figures against the truth when known (e.g. grid precision/recall).
    """

    out: Path
    source: str
    n_frames: int
    timings: dict[str, float]
    checks: dict[str, Any]


# ---------------------------------------------------------------------------- small pure helpers
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


def _grid_around(xy: FloatArray, reach: float, resolution: float) -> OccupancyGrid:
    """An empty grid covering points (N, 2) grown by ``reach`` metres."""
    lo = xy.min(axis=0) - reach
    hi = xy.max(axis=0) + reach
    lo = np.floor(lo / resolution) * resolution
    return OccupancyGrid.empty(float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1]), resolution)


# ---------------------------------------------------------------------------- poses
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


# ---------------------------------------------------------------------------- builders
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
    grid = _grid_around(poses[:, :2, 3], cam.max_depth + cfg.margin, cfg.resolution)
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


def build_laser_grid(
    scans: Any, poses: FloatArray, config: LaserGridConfig | None = None
) -> tuple[OccupancyGrid, int]:
    """Grid map from planar scans at given poses (keyframes by motion).

    Args:
        scans: :class:`lampsam.datasets.carmen.LaserScans` (``ranges`` (N, B), ``angles`` (B,),
            ``max_range``).
        poses: (N, 3) laser poses ``(x, y, theta)``, metres/rad.
        config: parameters (default: the dataclass defaults).

    Returns:
        The grid and the number of scans used.
    """
    config = config if config is not None else LaserGridConfig()
    # the grid holds the poses and every endpoint that returned within max_range
    r = np.where(scans.ranges < min(config.max_range, scans.max_range), scans.ranges, np.nan)
    phi = poses[:, 2:3] + scans.angles[None, :]
    ex = poses[:, 0:1] + r * np.cos(phi)
    ey = poses[:, 1:2] + r * np.sin(phi)
    ok = np.isfinite(ex)
    ends = np.stack([ex[ok], ey[ok]], axis=1)
    grid = _grid_around(np.vstack([ends, poses[:, :2]]), config.margin, config.resolution)
    used = 0
    last: FloatArray | None = None
    for i in range(len(poses)):
        p = poses[i]
        if last is not None:
            moved = math.hypot(p[0] - last[0], p[1] - last[1])
            turned = abs((p[2] - last[2] + math.pi) % (2 * math.pi) - math.pi)
            if moved < config.min_move and turned < config.min_turn:
                continue
        ranges = np.where(scans.ranges[i] >= scans.max_range, np.inf, scans.ranges[i])
        integrate_scan(grid, p, ranges, scans.angles, config.max_range, config.log_odds)
        last = p
        used += 1
    return grid, used


# ---------------------------------------------------------------------------- build_map
def _detect_source(run: Path) -> tuple[str, Path]:
    """Kind of input (``run``, ``slambook2``, ``tum_rgbd``, ``laser``) and the path to read."""
    if run.is_file():
        if ".log" in run.name:
            return "laser", run
        raise EnvMapError(f"{run}: not a run directory or a CARMEN log")
    if not run.is_dir():
        raise EnvMapError(f"{run}: not found")
    if (run / "kinect").is_dir():
        return "run", run
    if (run / "pose.txt").is_file() and (run / "color").is_dir():
        return "slambook2", run
    if (run / "rgb.txt").is_file() and (run / "depth.txt").is_file():
        return "tum_rgbd", run
    logs = sorted(run.glob("*.log")) + sorted(run.glob("*.log.gz"))
    if len(logs) == 1:
        return "laser", logs[0]
    raise EnvMapError(
        f"{run}: no kinect/, TUM RGB-D lists, slambook2 pose.txt or single CARMEN log found"
    )


def build_map(
    run: str | Path,
    out: str | Path,
    poses: str = "groundtruth",
    config: EnvMapConfig | None = None,
    truth: FloorPlan | None = None,
) -> BuildReport:
    """Build the environment map of a mapping run (module docstring).

    Args:
        run: a run directory with ``kinect/``, a TUM RGB-D or slambook2 directory, or a
            CARMEN log (or a directory holding exactly one).
        out: the map directory to write.
        poses: ``"groundtruth"`` or ``"slam:PATH"`` (a planar TUM trajectory; a
            ``landmarks.csv`` beside it gives the ceiling layer).
        config: parameters (default: the dataclass defaults).
        truth: the world's true floor plan (for a simulated run:
            :func:`lampsam.evaluation.map_truth.floor_plan_of_run` with the config's
            height band); when given, the grid of a ``run`` source is checked against
            it (``checks["grid_vs_world"]``).

    Returns:
        The :class:`BuildReport` (also written into the manifest).

    Raises:
        EnvMapError: unknown source, missing pose, unusable input.
        DatasetError: unreadable files (naming file and line).
    """
    config = config if config is not None else EnvMapConfig()
    from lampsam.datasets.logrun import read_landmarks, read_tum
    from lampsam.datasets.rgbd import read_slambook2, read_tum_rgbd
    from lampsam.localization.ceiling_map import from_landmark_table, read_landmark_csv

    t_start = time.perf_counter()
    run = Path(run)
    out = Path(out)
    kind, src = _detect_source(run)
    pose_kind, pose_path = parse_pose_source(poses)
    checks: dict[str, Any] = {}
    spatial: SpatialFeatureMap | None = None
    ceiling: CeilingFeatureMap | None = None
    grid_info: dict[str, Any] = {}
    timings: dict[str, float] = {}

    if kind == "laser":
        from lampsam.datasets.carmen import read_carmen

        t0 = time.perf_counter()
        carmen = read_carmen(src)
        scans = carmen.scans
        timings["read"] = time.perf_counter() - t0
        if pose_kind == "slam":
            traj = read_tum(pose_path)  # type: ignore[arg-type]
            scan_poses = planar_poses_at(
                traj.t, traj.poses, scans.t, config.pose_tolerance, str(pose_path)
            )
        else:
            scan_poses = scans.poses
        t0 = time.perf_counter()
        grid, n_used = build_laser_grid(scans, scan_poses, config.laser)
        timings["grid"] = time.perf_counter() - t0
        n_frames = n_used
        lo = config.laser.log_odds
        grid_info = {
            "sensor": "planar laser",
            "max_range": config.laser.max_range,
            "scans_used": n_used,
            "scans_total": len(scans),
        }
    else:
        if kind == "slambook2":
            seq = read_slambook2(src)
        elif kind == "tum_rgbd":
            seq = read_tum_rgbd(src)
        else:
            seq = read_tum_rgbd(src / "kinect")
        cfg = config
        if kind != "run" and config.depth.band_reference == "floor":
            # no floor known: fit it (falls back to the first camera's height)
            cfg = dataclasses.replace(
                config, depth=dataclasses.replace(config.depth, band_reference="fit")
            )
        if kind == "run":
            if pose_kind == "slam":
                traj = read_tum(pose_path)  # type: ignore[arg-type]
                traj_name = str(pose_path)
            elif (src / "groundtruth.tum").is_file():
                traj = read_tum(src / "groundtruth.tum")
                traj_name = str(src / "groundtruth.tum")
            else:
                traj = None
            if traj is not None:
                planar = planar_poses_at(traj.t, traj.poses, seq.t, cfg.pose_tolerance, traj_name)
                cams = camera_poses_from_planar(planar, seq.camera.body_T_camera)
            elif seq.world_T_camera is not None:
                cams = seq.world_T_camera
            else:
                raise EnvMapError(
                    f"{src}: no groundtruth.tum and no kinect/groundtruth.txt: "
                    "pass --poses slam:PATH"
                )
        else:
            if pose_kind == "slam":
                raise EnvMapError(f"{src}: --poses slam:PATH needs a run directory with kinect/")
            if seq.world_T_camera is None:
                raise EnvMapError(f"{src}: the sequence has no camera poses")
            cams = seq.world_T_camera
        grid, spatial, timings = build_depth_layers(seq, cams, cfg)
        n_frames = len(seq)
        lo = cfg.depth.log_odds
        grid_info = {
            "sensor": "RGB-D depth",
            "height_band": list(cfg.depth.height_band),
            "band_reference": cfg.depth.band_reference,
            "max_range": seq.camera.max_depth,
            "world_up_of_source": [float(v) for v in seq.world_up],
        }
        if kind == "run":
            if pose_kind == "slam" and (pose_path.parent / "landmarks.csv").is_file():  # type: ignore[union-attr]
                assert pose_path is not None  # parse_pose_source gives a path for "slam"
                # backend/slam.py writes z above the floor (backend/ceiling.py; checked:
                # 2.681 m for a lamp at 2.68 m), so no camera-height offset
                ceiling = read_landmark_csv(
                    pose_path.parent / "landmarks.csv",
                    z_cam=0.0,
                    source=f"slam:{pose_path.parent / 'landmarks.csv'}",
                )
            elif (src / "landmarks.csv").is_file():
                if pose_kind == "slam":
                    log.warning(
                        "no landmarks.csv beside %s: ceiling layer from the run's true landmarks",
                        pose_path,
                    )
                ceiling = from_landmark_table(
                    read_landmarks(src / "landmarks.csv"), source="groundtruth"
                )
            if truth is not None:
                checks["grid_vs_world"] = grid_checks(grid, truth, lo)
                checks["grid_vs_world"]["poses"] = poses

    layers = save_layers(out, grid, lo, grid_info, spatial, config.spatial, ceiling)
    timings["total"] = time.perf_counter() - t_start
    timings = {k: round(v, 3) for k, v in timings.items()}
    source = {"kind": kind, "path": str(src), "poses": poses, "frames_used": int(n_frames)}
    write_manifest(out, source, layers, asdict(config), timings, checks)
    log.info("environment map %s: %s, %d frames, %.1f s", out, kind, n_frames, timings["total"])
    return BuildReport(out, kind, int(n_frames), timings, checks)


