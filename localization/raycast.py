"""Expected ranges in a grid map, for many poses x many beams, vectorised.

Paper 2, sec. 4 (eq. 8) compares each particle's ray-cast scan with the
measured one. Two ways to get the expected ranges are here (a third, the
likelihood field, skips ray casting: :mod:`lampsam.localization.likelihood`):

- :func:`cast_rays`: marching along every ray in numpy. To keep the number of
  steps small it is *sphere tracing* on the Euclidean distance transform: from
  a point whose cell centre is ``D`` cells away from the nearest occupied cell
  centre, no occupied cell can be nearer than ``D - sqrt(2)`` cells, so the ray
  may jump that far; near obstacles it walks cell by cell (exact traversal,
  Amanatides & Woo 1987), so no cell is skipped. The returned range is the
  distance at which the ray enters the first occupied cell (exact up to 1e-6
  cells). Rays that end are dropped from the working set each iteration.
- :class:`RangeTable`: the same ray caster run once for every free cell
  centre and ``n_angles`` heading bins; a lookup is then one gather per beam
  (nearest cell, nearest angle bin). Memory ``n_free x n_angles x 2`` bytes
  (ranges stored as uint16 millimetres).

Occupied = :func:`lampsam.localization.grid.occupied_mask`; unknown cells do not
stop rays; a ray leaving the grid or running past ``max_range`` returns
``max_range``.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from lampsam.arrays import BoolArray, FloatArray, IntArray
from lampsam.errors import LocalizationError
from lampsam.localization.grid import LogOddsConfig, OccupancyGrid, free_mask, occupied_mask

log = logging.getLogger(__name__)

_SQRT2 = math.sqrt(2.0)


class RaycastError(LocalizationError):
    """Bad input to the ray caster (shapes, empty map, range too long for the table)."""


def distance_field(occupied: BoolArray) -> FloatArray:
    """Distance from every cell centre to the nearest occupied cell centre, in cells.

    Args:
        occupied: (H, W) bool.

    Returns:
        (H, W) float32, 0 on occupied cells; ``inf`` everywhere if nothing is occupied.
    """
    if not occupied.any():
        return np.full(occupied.shape, np.inf, dtype=np.float32)
    return ndimage.distance_transform_edt(~occupied).astype(np.float32)


@dataclass(frozen=True)
class RayMarchConfig:
    """Sphere-tracing settings.

    Attributes:
        chunk: rays processed together (default 400,000, about 50 MB of temporaries).
    """

    chunk: int = 400_000


def _march(dist: FloatArray, occupied_flat: BoolArray, width: int, origin_uv: FloatArray,
           direction: FloatArray, max_cells: float) -> FloatArray:
    """Sphere-trace rays in map cell units.

    Args:
        dist: (H, W) distance field, cells.
        occupied_flat: (H*W,) occupied cells.
        width: grid width W.
        origin_uv: (R, 2) ray origins, map cell coordinates.
        direction: (R, 2) unit directions in map coordinates.
        max_cells: maximum range, cells.

    Returns:
        (R,) ranges in cells (``max_cells`` when nothing is hit).
    """
    height = dist.shape[0]
    dist_flat = dist.reshape(-1)
    n = origin_uv.shape[0]
    out = np.full(n, max_cells, dtype=np.float64)
    active = np.arange(n)
    t = np.zeros(n, dtype=np.float64)
    ox, oy = origin_uv[:, 0].copy(), origin_uv[:, 1].copy()
    with np.errstate(divide="ignore"):
        inv_dx = 1.0 / direction[:, 0]
        inv_dy = 1.0 / direction[:, 1]
    # Offset of the exit boundary within a cell along each axis: 1 going up, 0 going down.
    ex = (inv_dx > 0).astype(np.float64)
    ey = (inv_dy > 0).astype(np.float64)
    while active.size:
        u = ox + t / inv_dx
        v = oy + t / inv_dy
        iu = np.floor(u)
        iv = np.floor(v)
        inside = (iu >= 0) & (iu < width) & (iv >= 0) & (iv < height) & (t < max_cells)
        flat = np.where(inside, iv * width + iu, 0).astype(np.int64)
        hit = inside & occupied_flat[flat]
        out[active[hit]] = t[hit]
        keep = inside & ~hit
        # Exact cell traversal (Amanatides & Woo 1987) near obstacles: step to the
        # exit of the current cell; far from them, jump by the safe distance.
        with np.errstate(invalid="ignore"):
            tx = np.where(np.isfinite(inv_dx), (iu + ex - u) * inv_dx, np.inf)
            ty = np.where(np.isfinite(inv_dy), (iv + ey - v) * inv_dy, np.inf)
        exit_step = np.minimum(tx, ty)[keep] + 1e-6
        step = np.maximum(dist_flat[flat[keep]] - _SQRT2, exit_step)
        active, ox, oy = active[keep], ox[keep], oy[keep]
        inv_dx, inv_dy, ex, ey = inv_dx[keep], inv_dy[keep], ex[keep], ey[keep]
        t = t[keep] + step
    return np.minimum(out, max_cells)


def cast_rays(grid: OccupancyGrid, poses: FloatArray, angles: FloatArray, max_range: float,
              config: RayMarchConfig = RayMarchConfig(),
              occupied: BoolArray | None = None, dist: FloatArray | None = None) -> FloatArray:
    """Expected ranges for every pose and beam by marching along the rays.

    Args:
        grid: the map.
        poses: (P, 3) sensor poses ``(x, y, theta)`` in the world, metres/rad.
        angles: (B,) beam angles in the sensor frame, rad, CCW from forward.
        max_range: metres.
        config: marching settings.
        occupied: (H, W) occupied mask (default: :func:`occupied_mask` of ``grid``).
        dist: (H, W) its :func:`distance_field` (computed if None; pass it when
            calling repeatedly).

    Returns:
        (P, B) ranges, metres, in ``[0, max_range]``.
    """
    poses = np.asarray(poses, dtype=np.float64).reshape(-1, 3)
    angles = np.asarray(angles, dtype=np.float64).reshape(-1)
    if occupied is None:
        occupied = occupied_mask(grid, LogOddsConfig())
    if dist is None:
        dist = distance_field(occupied)
    origin_uv = grid.world_to_map(poses[:, :2])
    phi = poses[:, 2:3] + angles[None, :] - grid.origin[2]
    n_rays = phi.size
    out = np.empty(n_rays, dtype=np.float64)
    phi_flat = phi.reshape(-1)
    occ_flat = occupied.reshape(-1)
    n_beams = angles.size
    max_cells = max_range / grid.resolution
    for start in range(0, n_rays, config.chunk):
        sl = slice(start, min(start + config.chunk, n_rays))
        idx = np.arange(sl.start, sl.stop)
        d = np.stack([np.cos(phi_flat[sl]), np.sin(phi_flat[sl])], axis=1)
        out[sl] = _march(dist, occ_flat, grid.width, origin_uv[idx // n_beams], d, max_cells)
    return out.reshape(phi.shape) * grid.resolution


@dataclass(frozen=True)
class RangeTable:
    """Precomputed ranges for every free cell and heading bin.

    Attributes:
        grid_shape: (H, W) of the map.
        resolution: cell size, metres.
        origin: (3,) map origin (x, y, yaw).
        row_of_cell: (H*W,) int32 row of each cell in ``ranges_mm``; cells
            without a row (occupied or unknown) point at the last row, all zeros.
        ranges_mm: (n_rows + 1, n_angles) uint16 ranges in millimetres from the
            cell centre, bin ``k`` at world heading ``k * 2 pi / n_angles``.
        max_range: metres.
    """

    grid_shape: tuple[int, int]
    resolution: float
    origin: FloatArray
    row_of_cell: np.ndarray
    ranges_mm: np.ndarray
    max_range: float

    @property
    def n_angles(self) -> int:
        """Number of heading bins."""
        return int(self.ranges_mm.shape[1])

    @property
    def nbytes(self) -> int:
        """Memory held by the table, bytes."""
        return int(self.ranges_mm.nbytes + self.row_of_cell.nbytes)

    @classmethod
    def build(cls, grid: OccupancyGrid, n_angles: int = 360, max_range: float = 10.0,
              cells: BoolArray | None = None,
              config: RayMarchConfig = RayMarchConfig()) -> RangeTable:
        """Ray-cast the table.

        Args:
            grid: the map.
            n_angles: heading bins over 360 deg (default 360, 1 deg).
            max_range: metres, at most 65.5 (uint16 millimetres).
            cells: (H, W) cells to tabulate (default: every non-occupied cell
                that is free, i.e. :func:`~lampsam.localization.grid.free_mask`).
            config: marching settings.

        Returns:
            The table.
        """
        if max_range > 65.5:
            raise RaycastError(f"max_range {max_range} m does not fit uint16 millimetres")
        occupied = occupied_mask(grid)
        if cells is None:
            cells = free_mask(grid)
        cells = cells & ~occupied
        iy, ix = np.nonzero(cells)
        if iy.size == 0:
            raise RaycastError("no free cells to tabulate")
        centres = grid.cell_to_world(np.stack([ix, iy], axis=1))
        heading = np.arange(n_angles, dtype=np.float64) * (2 * math.pi / n_angles)
        dist = distance_field(occupied)
        rows = np.empty((iy.size + 1, n_angles), dtype=np.uint16)
        rows[-1] = 0
        block = max(1, config.chunk // n_angles)
        for start in range(0, iy.size, block):
            sl = slice(start, min(start + block, iy.size))
            poses = np.column_stack([centres[sl], np.zeros(sl.stop - sl.start)])
            r = cast_rays(grid, poses, heading, max_range, config, occupied, dist)
            rows[sl] = np.rint(r * 1000.0).astype(np.uint16)
        row_of_cell = np.full(grid.height * grid.width, iy.size, dtype=np.int32)
        row_of_cell[iy * grid.width + ix] = np.arange(iy.size, dtype=np.int32)
        log.info("range table: %d cells x %d bins, %.1f MB", iy.size, n_angles,
                 rows.nbytes / 1e6)
        return cls((grid.height, grid.width), grid.resolution, grid.origin.copy(), row_of_cell,
                   rows, float(max_range))

    def cell_rows(self, xy: FloatArray) -> IntArray:
        """Table row of each position (the last, all-zero row outside the table).

        Args:
            xy: (P, 2) world positions, metres.

        Returns:
            (P,) int row indices.
        """
        c, s = math.cos(self.origin[2]), math.sin(self.origin[2])
        dx = xy[:, 0] - self.origin[0]
        dy = xy[:, 1] - self.origin[1]
        iu = np.floor((c * dx + s * dy) / self.resolution).astype(np.int64)
        iv = np.floor((-s * dx + c * dy) / self.resolution).astype(np.int64)
        h, w = self.grid_shape
        inside = (iu >= 0) & (iu < w) & (iv >= 0) & (iv < h)
        return np.where(inside, self.row_of_cell[np.where(inside, iv * w + iu, 0)],
                        self.ranges_mm.shape[0] - 1)

    def lookup(self, poses: FloatArray, angles: FloatArray) -> FloatArray:
        """Expected ranges (nearest cell, nearest heading bin).

        Args:
            poses: (P, 3) world poses, metres/rad.
            angles: (B,) beam angles in the sensor frame, rad.

        Returns:
            (P, B) float32 ranges, metres (0 for poses outside the free cells).
        """
        poses = np.asarray(poses, dtype=np.float64).reshape(-1, 3)
        rows = self.cell_rows(poses[:, :2])
        scale = self.n_angles / (2 * math.pi)
        theta_bins = poses[:, 2] * scale
        beam_bins = np.asarray(angles, dtype=np.float64) * scale
        k = np.rint(theta_bins[:, None] + beam_bins[None, :]).astype(np.int64) % self.n_angles
        flat = k + (rows.astype(np.int64) * self.n_angles)[:, None]
        return self.ranges_mm.reshape(-1)[flat].astype(np.float32) * np.float32(1e-3)
