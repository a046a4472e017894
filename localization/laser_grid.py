"""Grid map from planar laser scans at known poses (CARMEN logs, LaserScan runs).

Each used scan is ray-cast into a log-odds grid (``grid.integrate_scan``): cells
along a beam become freer, the cell of its endpoint more occupied. Scans are used
as keyframes, when the laser moved or turned enough since the last used one, so a
robot standing still does not count its view many times.

World frame: ``x, y`` on the floor, metres; headings in rad, CCW.
"""

from __future__ import annotations

import math

import numpy as np

from lampsam.arrays import FloatArray
from lampsam.datasets.carmen import LaserScans
from lampsam.localization.grid import OccupancyGrid, grid_around, integrate_scan
from lampsam.localization.map_config import LaserGridConfig


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
    config = config if config is not None else LaserGridConfig()
    # the grid holds the poses and every endpoint that returned within max_range
    r = np.where(scans.ranges < min(config.max_range, scans.max_range), scans.ranges, np.nan)
    phi = poses[:, 2:3] + scans.angles[None, :]
    ex = poses[:, 0:1] + r * np.cos(phi)
    ey = poses[:, 1:2] + r * np.sin(phi)
    ok = np.isfinite(ex)
    ends = np.stack([ex[ok], ey[ok]], axis=1)
    grid = grid_around(np.vstack([ends, poses[:, :2]]), config.margin, config.resolution)
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
