"""Building the environment map of a mapping run (paper 2, sec. 2).

``build_map(run, out, poses=...)`` turns one mapping run into a map directory
(``map_store.py``: grid map, spatial feature map, ceiling feature map, manifest).
It runs in named stages:

1. :func:`detect_source`: what ``run`` is;
2. the layers of that source:

   - :func:`laser_layers`: a CARMEN laser log (known by its records, e.g. the Intel
     lab's ``*.log.gz``): the scans at the log's corrected poses (or ``slam:PATH``) -> grid map only
     (``laser_grid.py``);
   - :func:`depth_layers`: a simulated/logged run with ``kinect/`` (TUM RGB-D), a TUM
     RGB-D directory or the slambook2 sample: depth frames placed with the mapping
     poses (:func:`camera_poses`) -> grid map and SIFT spatial layer
     (``depth_grid.py``), and for a run the ceiling layer (:func:`ceiling_layer`:
     the ``landmarks.csv`` beside a SLAM trajectory, or the run's true landmarks);

3. the grid checked against a true floor plan when the caller gives one
   (``map_quality.py``);
4. the files written (``map_store.py``), then the localizer's lookups precomputed from
   the grid as written (range table, distance field: ``map_tables.py``), then the
   manifest.

A laser map may use ``all``, ``even`` or ``odd`` scans of the log (:func:`select_scans`)
and is refused when fewer than ``LaserGridConfig.min_scans`` scans went into it; its scans
are cross-checked at their poses and a log whose poses disagree (raw odometry) is
warned about (``grid.scan_consistency`` in the manifest, ``laser_consistency.py``).

World frame: docs/conventions.md (``x, y`` on the floor, ``z`` up, metres).
"""

from __future__ import annotations

import dataclasses
import logging
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from lampsam.arrays import FloatArray
from lampsam.datasets.carmen import sniff_carmen
from lampsam.datasets.rgbd import RgbdSequence
from lampsam.localization.ceiling_map import CeilingFeatureMap
from lampsam.localization.depth_grid import build_depth_layers
from lampsam.localization.grid import LogOddsConfig, OccupancyGrid, free_mask, load_map_server
from lampsam.localization.laser_grid import build_checked_laser_grid
from lampsam.localization.map_config import EnvMapConfig
from lampsam.localization.map_poses import (
    camera_poses_from_planar,
    parse_pose_source,
    planar_poses_at,
)
from lampsam.localization.map_quality import FloorPlan, grid_checks
from lampsam.localization.map_store import GRID_STEM, EnvMapError, save_layers, write_manifest
from lampsam.localization.map_tables import write_tables
from lampsam.localization.spatial_map import SpatialFeatureMap

log = logging.getLogger(__name__)

#: The ``scans`` selections of a laser log (:func:`select_scans`).
SCAN_SELECTIONS = ("all", "even", "odd")
#: The grid's YAML file in a map directory.
GRID_STEM_YAML = f"{GRID_STEM}.yaml"


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


@dataclass
class Layers:
    """The layers one source gives, before they are written.

    Attributes:
        grid: the grid map.
        log_odds: the inverse sensor model it was built with (its thresholds).
        grid_info: sensor-specific entries of the manifest's grid layer.
        n_frames: frames or scans used.
        timings: stage -> seconds.
        spatial: the spatial feature map, or None.
        ceiling: the ceiling feature map, or None.
    """

    grid: OccupancyGrid
    log_odds: LogOddsConfig
    grid_info: dict[str, Any]
    n_frames: int
    timings: dict[str, float] = field(default_factory=dict)
    spatial: SpatialFeatureMap | None = None
    ceiling: CeilingFeatureMap | None = None


def detect_source(run: Path) -> tuple[str, Path]:
    """Kind of input and the path to read.

    Args:
        run: a CARMEN log file (recognised by its content:
            :func:`lampsam.datasets.carmen.sniff_carmen`, whatever its name), or a
            directory: with ``kinect/`` (a run), slambook2 (``pose.txt`` + ``color/``),
            TUM RGB-D (``rgb.txt`` + ``depth.txt``), or holding exactly one
            ``*.log``/``*.log.gz`` CARMEN log.

    Returns:
        ``(kind, path)`` with kind ``run``, ``slambook2``, ``tum_rgbd`` or ``laser``.

    Raises:
        EnvMapError: none of these (a file: naming what it starts with).
        DatasetError: a file that cannot be read.
    """
    if run.is_file():
        is_carmen, found = sniff_carmen(run)
        if is_carmen:
            return "laser", run
        raise EnvMapError(f"{run}: not a run directory or a CARMEN log: {found} (a CARMEN "
                          "log's lines start with PARAM, ODOM, FLASER, ROBOTLASER1, ...)")
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


def select_scans(n: int, scans: str) -> np.ndarray:
    """Indices of the scans a map uses: ``all``, ``even`` (0, 2, 4, ...) or ``odd``.

    Even and odd split a log into a mapping half and a held-out half for
    localization trials on the same log.

    Raises:
        EnvMapError: another value.
    """
    if scans not in SCAN_SELECTIONS:
        raise EnvMapError(f"scans must be one of {', '.join(SCAN_SELECTIONS)}, got {scans!r}")
    start, stride = {"all": (0, 1), "even": (0, 2), "odd": (1, 2)}[scans]
    return np.arange(start, n, stride)


def laser_layers(
    log_path: Path,
    pose_kind: str,
    pose_path: Path | None,
    config: EnvMapConfig,
    scans: str = "all",
) -> Layers:
    """Grid map of a CARMEN log at its corrected poses or a SLAM trajectory's.

    Args:
        log_path: the log.
        pose_kind: ``groundtruth`` (the log's own poses) or ``slam``.
        pose_path: the planar TUM trajectory for ``slam``.
        config: parameters (``config.laser``, ``config.pose_tolerance``).
        scans: which scans (:func:`select_scans`).

    Returns:
        The grid layer.

    Raises:
        EnvMapError: fewer than ``config.laser.min_scans`` scans used, or a grid with
            no free cell.
    """
    from lampsam.datasets.carmen import read_carmen
    from lampsam.datasets.logrun import read_tum

    t0 = time.perf_counter()
    carmen = read_carmen(log_path)
    n_read = len(carmen.scans)
    chosen = carmen.scans.subset(select_scans(n_read, scans))
    timings = {"read": time.perf_counter() - t0}
    if pose_kind == "slam":
        assert pose_path is not None  # parse_pose_source gives a path for "slam"
        traj = read_tum(pose_path)
        scan_poses = planar_poses_at(
            traj.t, traj.poses, chosen.t, config.pose_tolerance, str(pose_path)
        )
    else:
        scan_poses = chosen.poses
    t0 = time.perf_counter()
    grid, n_used, consistency = build_checked_laser_grid(chosen, scan_poses, config.laser)
    timings["grid"] = time.perf_counter() - t0
    if n_used < config.laser.min_scans:
        raise EnvMapError(
            f"{log_path}: a map from {n_used} scans ({len(chosen)} selected with "
            f"--scans {scans} of {n_read} read, used when the laser moved "
            f"{config.laser.min_move} m or turned {config.laser.min_turn} rad) is refused: "
            f"at least {config.laser.min_scans} are needed (check the log's poses and time "
            "stamps, or lower [envmap.laser] min_scans)"
        )
    if not free_mask(grid, config.laser.log_odds).any():
        raise EnvMapError(f"{log_path}: the grid from {n_used} scans has no free cell")
    grid_info = {
        "sensor": "planar laser",
        "max_range": config.laser.max_range,
        "scans": scans,
        "scans_used": n_used,
        "scans_selected": len(chosen),
        "scans_total": n_read,
        "laser_message": carmen.message,
        "beams": int(len(chosen.angles)),
        "beam_angles_deg": [round(float(np.degrees(chosen.angles[0])), 4),
                            round(float(np.degrees(chosen.angles[-1])), 4)],
        "time_source": chosen.time_source,
    }
    if consistency is not None:
        grid_info["scan_consistency"] = consistency.as_dict()
        if consistency.poor:
            log.warning(
                "%s: the scans disagree with each other at the %s poses: %s: the poses look "
                "like raw odometry, not corrected ones, or the beam angles are wrong (a FLASER "
                "scanner that is not 180 deg needs PARAM laser_front_laser_fov), so this map "
                "shows walls twice and localization on it will be wrong; give corrected poses "
                "(--poses slam:TUM) or a '-corrected' log (manifest: grid.scan_consistency)",
                log_path, "log's" if pose_kind != "slam" else "SLAM", consistency.reason())
    return Layers(grid, config.laser.log_odds, grid_info, n_used, timings)


def read_sequence(kind: str, src: Path) -> RgbdSequence:
    """The RGB-D frames of a ``run``, ``slambook2`` or ``tum_rgbd`` source."""
    from lampsam.datasets.rgbd import read_slambook2, read_tum_rgbd

    if kind == "slambook2":
        return read_slambook2(src)
    if kind == "tum_rgbd":
        return read_tum_rgbd(src)
    return read_tum_rgbd(src / "kinect")


def camera_poses(
    kind: str,
    src: Path,
    seq: RgbdSequence,
    pose_kind: str,
    pose_path: Path | None,
    tolerance: float,
) -> FloatArray:
    """The mapping camera poses of an RGB-D source.

    A run is placed with a planar trajectory (``slam:PATH``, else its
    ``groundtruth.tum``) sampled at the frame times and the rig's mounting, else with
    the sequence's own camera poses; a TUM RGB-D or slambook2 directory always uses
    its own.

    Args:
        kind: the source kind (:func:`detect_source`).
        src: its path.
        seq: its frames.
        pose_kind: ``groundtruth`` or ``slam``.
        pose_path: the planar TUM trajectory for ``slam``.
        tolerance: how far a frame may lie outside the trajectory's span, s.

    Returns:
        (N, 4, 4) ``world_T_camera``, one per frame.

    Raises:
        EnvMapError: no poses, ``slam:`` for a source that is not a run, or a frame
            without a pose.
    """
    from lampsam.datasets.logrun import read_tum

    if kind != "run":
        if pose_kind == "slam":
            raise EnvMapError(f"{src}: --poses slam:PATH needs a run directory with kinect/")
        if seq.world_T_camera is None:
            raise EnvMapError(f"{src}: the sequence has no camera poses")
        return seq.world_T_camera
    if pose_kind == "slam":
        assert pose_path is not None  # parse_pose_source gives a path for "slam"
        traj_path: Path | None = pose_path
    elif (src / "groundtruth.tum").is_file():
        traj_path = src / "groundtruth.tum"
    else:
        traj_path = None
    if traj_path is not None:
        traj = read_tum(traj_path)
        planar = planar_poses_at(traj.t, traj.poses, seq.t, tolerance, str(traj_path))
        return camera_poses_from_planar(planar, seq.camera.body_T_camera)
    if seq.world_T_camera is not None:
        return seq.world_T_camera
    raise EnvMapError(
        f"{src}: no groundtruth.tum and no kinect/groundtruth.txt: pass --poses slam:PATH"
    )


def ceiling_layer(src: Path, pose_kind: str, pose_path: Path | None) -> CeilingFeatureMap | None:
    """The ceiling feature map of a run: the SLAM landmarks, else the run's true ones.

    Args:
        src: the run directory.
        pose_kind: ``groundtruth`` or ``slam``.
        pose_path: the SLAM trajectory for ``slam``; a ``landmarks.csv`` beside it
            (``backend/slam.py``'s columns) is the layer.

    Returns:
        The layer, or None when neither file exists.
    """
    from lampsam.datasets.logrun import read_landmarks
    from lampsam.localization.ceiling_map import from_landmark_table, read_landmark_csv

    if pose_kind == "slam" and pose_path is not None:
        slam_csv = pose_path.parent / "landmarks.csv"
        if slam_csv.is_file():
            # backend/slam.py writes z above the floor (backend/ceiling.py), so no
            # camera-height offset
            return read_landmark_csv(slam_csv, z_cam=0.0, source=f"slam:{slam_csv}")
    if (src / "landmarks.csv").is_file():
        if pose_kind == "slam":
            log.warning(
                "no landmarks.csv beside %s: ceiling layer from the run's true landmarks",
                pose_path,
            )
        return from_landmark_table(read_landmarks(src / "landmarks.csv"), source="groundtruth")
    return None


def depth_config(kind: str, config: EnvMapConfig) -> EnvMapConfig:
    """``config`` with the floor fitted for sources whose floor is not at ``z = 0``.

    Only simulated/logged runs put the floor at ``z = 0``; for TUM RGB-D and slambook2
    a ``band_reference="floor"`` becomes ``"fit"`` (which falls back to the first
    camera's height when no floor plane is found).
    """
    if kind != "run" and config.depth.band_reference == "floor":
        return dataclasses.replace(
            config, depth=dataclasses.replace(config.depth, band_reference="fit")
        )
    return config


def depth_layers(
    kind: str, src: Path, pose_kind: str, pose_path: Path | None, config: EnvMapConfig
) -> Layers:
    """Grid, spatial and (for a run) ceiling layers of an RGB-D source.

    Args:
        kind: ``run``, ``slambook2`` or ``tum_rgbd``.
        src: its path.
        pose_kind: ``groundtruth`` or ``slam``.
        pose_path: the planar TUM trajectory for ``slam``.
        config: parameters (already passed through :func:`depth_config`).

    Returns:
        The layers.
    """
    seq = read_sequence(kind, src)
    cams = camera_poses(kind, src, seq, pose_kind, pose_path, config.pose_tolerance)
    grid, spatial, timings = build_depth_layers(seq, cams, config)
    grid_info = {
        "sensor": "RGB-D depth",
        "height_band": list(config.depth.height_band),
        "band_reference": config.depth.band_reference,
        "max_range": seq.camera.max_depth,
        "world_up_of_source": [float(v) for v in seq.world_up],
    }
    ceiling = ceiling_layer(src, pose_kind, pose_path) if kind == "run" else None
    return Layers(grid, config.depth.log_odds, grid_info, len(seq), timings, spatial, ceiling)


def build_map(
    run: str | Path,
    out: str | Path,
    poses: str = "groundtruth",
    config: EnvMapConfig | None = None,
    truth: FloorPlan | None = None,
    scans: str = "all",
) -> BuildReport:
    """Build the environment map of a mapping run (the stages: module docstring).

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
        scans: for a laser log, ``all``, ``even`` or ``odd`` scans (:func:`select_scans`);
            other sources take ``all`` only.

    Returns:
        The :class:`BuildReport` (also written into the manifest).

    Raises:
        EnvMapError: unknown source, missing pose, unusable input, a laser map from
            fewer than ``config.laser.min_scans`` scans.
        DatasetError: unreadable files (naming file and line).
    """
    config = config if config is not None else EnvMapConfig()
    t_start = time.perf_counter()
    run, out = Path(run), Path(out)
    select_scans(0, scans)  # a bad value fails before any work
    kind, src = detect_source(run)
    pose_kind, pose_path = parse_pose_source(poses)
    if kind == "laser":
        layers = laser_layers(src, pose_kind, pose_path, config, scans)
    elif scans != "all":
        raise EnvMapError(f"{src}: --scans {scans} applies to laser logs only ({kind} source)")
    else:
        layers = depth_layers(kind, src, pose_kind, pose_path, depth_config(kind, config))
    checks: dict[str, Any] = {}
    if kind == "run" and truth is not None:
        checks["grid_vs_world"] = {**grid_checks(layers.grid, truth, layers.log_odds),
                                   "poses": poses}  # fmt: skip
    described = save_layers(
        out, layers.grid, layers.log_odds, layers.grid_info, layers.spatial, config.spatial,
        layers.ceiling,
    )  # fmt: skip
    t0 = time.perf_counter()
    # the lookups are built from the grid as the localizer will read it (trinary PGM)
    grid_as_read = load_map_server(out / GRID_STEM_YAML)
    described.update(write_tables(out, grid_as_read, config.tables, laser=kind == "laser"))
    tables_s = time.perf_counter() - t0
    timings = {**layers.timings, "tables": tables_s, "total": time.perf_counter() - t_start}
    timings = {k: round(v, 3) for k, v in timings.items()}
    source = {"kind": kind, "path": str(src), "poses": poses, "frames_used": layers.n_frames}
    write_manifest(out, source, described, asdict(config), timings, checks)
    log.info("environment map %s: %s, %d frames, %.1f s", out, kind, layers.n_frames,
             timings["total"])  # fmt: skip
    return BuildReport(out, kind, layers.n_frames, timings, checks)
