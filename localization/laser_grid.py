"""Grid map from planar laser scans at known poses (CARMEN logs, LaserScan runs).

Each used scan is ray-cast into a log-odds grid (``grid.integrate_scan``): cells
along a beam become freer, the cell of its endpoint more occupied. Scans are used
as keyframes, when the laser moved or turned enough since the last used one, so a
robot standing still does not count its view many times. In the same pass the
keyframes are split into chunks in time and each chunk's grid is kept, for the
check that the log's poses agree with each other
(:mod:`lampsam.localization.laser_consistency`).

World frame: ``x, y`` on the floor, metres; headings in rad, CCW.
"""

from __future__ import annotations

import math

import numpy as np

from lampsam.arrays import FloatArray, IntArray
from lampsam.datasets.carmen import LaserScans
from lampsam.localization.grid import (
    GridMapError,
    OccupancyGrid,
    apply_update,
    grid_around,
    point_cells,
    scan_points,
)
from lampsam.localization.laser_consistency import (
    ScanConsistency,
    chunk_of,
    cross_chunk_consistency,
)
from lampsam.localization.map_config import LaserGridConfig


def keyframe_indices(poses: FloatArray, config: LaserGridConfig) -> IntArray:
    """Indices of the scans used: the first, then each that moved ``min_move`` or
    turned ``min_turn`` since the last used one.

    Args:
        poses: (N, 3) laser poses ``(x, y, theta)``, metres/rad.
        config: ``min_move`` (m), ``min_turn`` (rad).

    Returns:
        (M,) increasing indices.
    """
    used: list[int] = []
    last: FloatArray | None = None
    for i in range(len(poses)):
        p = poses[i]
        if last is not None:
            moved = math.hypot(p[0] - last[0], p[1] - last[1])
            turned = abs((p[2] - last[2] + math.pi) % (2 * math.pi) - math.pi)
            if moved < config.min_move and turned < config.min_turn:
                continue
        used.append(i)
        last = p
    return np.array(used, dtype=np.int64)


def build_laser_grid(
    scans: LaserScans, poses: FloatArray, config: LaserGridConfig | None = None
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
    grid, used, _ = build_checked_laser_grid(scans, poses, config, check=False)
    return grid, used


def build_checked_laser_grid(
    scans: LaserScans, poses: FloatArray, config: LaserGridConfig | None = None,
    check: bool = True,
) -> tuple[OccupancyGrid, int, ScanConsistency | None]:
    """:func:`build_laser_grid` and, in the same pass, the poses' consistency.

    Args:
        scans: the scans.
        poses: (N, 3) laser poses, metres/rad.
        config: parameters; ``consistency_chunks`` (0: no check),
            ``min_consistency`` and ``min_chunk_consistency``.
        check: False skips the check whatever the config says.

    Returns:
        The grid, the number of scans used, and the :class:`ScanConsistency` (None
        when not checked or fewer keyframes than twice the chunks).
    """
    config = config if config is not None else LaserGridConfig()
    # the grid holds the poses and every endpoint that returned within max_range
    r = np.where(scans.ranges < min(config.max_range, scans.max_range), scans.ranges, np.nan)
    phi = poses[:, 2:3] + scans.angles[None, :]
    ex = poses[:, 0:1] + r * np.cos(phi)
    ey = poses[:, 1:2] + r * np.sin(phi)
    ok = np.isfinite(ex)
    ends = np.stack([ex[ok], ey[ok]], axis=1)
    grid = grid_around(np.vstack([ends, poses[:, :2]]), config.margin, config.resolution)
    keys = keyframe_indices(poses, config)
    k = config.consistency_chunks
    check = check and k >= 2 and len(keys) >= 2 * k
    chunk = chunk_of(len(keys), k) if check else np.zeros(len(keys), dtype=np.int64)
    chunk_grids = [np.zeros_like(grid.log_odds) for _ in range(k)] if check else []
    chunk_hits: list[list[IntArray]] = [[] for _ in range(k)] if check else []
    for j, i in enumerate(keys):
        p = poses[i]
        if not np.all(np.isfinite(p)):
            raise GridMapError(f"laser pose {i} is not finite: {p}")
        ranges = np.where(scans.ranges[i] >= scans.max_range, np.inf, scans.ranges[i])
        pts = scan_points(p, ranges, scans.angles, config.max_range)
        if len(pts) == 0:
            continue
        free_flat, hit_flat = point_cells(grid, p[:2], pts, config.max_range, config.log_odds)
        apply_update(grid, free_flat, hit_flat, config.log_odds)
        if check:
            c = int(chunk[j])
            apply_update(OccupancyGrid(chunk_grids[c], grid.resolution, grid.origin),
                         free_flat, hit_flat, config.log_odds)
            chunk_hits[c].append(np.unique(hit_flat))
    consistency = None
    if check:
        hits = [np.concatenate(h) if h else np.zeros(0, np.int64) for h in chunk_hits]
        consistency = cross_chunk_consistency(chunk_grids, hits, config.log_odds,
                                              config.min_consistency,
                                              config.min_chunk_consistency)
    return grid, len(keys), consistency
