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
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

from lampsam.localization.ceiling_map import CeilingFeatureMap
from lampsam.localization.depth_grid import build_depth_layers
from lampsam.localization.laser_grid import build_laser_grid
from lampsam.localization.map_config import (
    EnvMapConfig,
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
from lampsam.localization.spatial_map import (
    SpatialFeatureMap,
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


