"""Log-odds occupancy grids and ROS map_server files.

The grid is the environment map's first layer (paper 2, section 2; DESIGN.md
sec. 2): obstacles from laser scans or from Kinect depth projected to the floor,
free space by traversing the rays, each cell holding the log-odds of being
occupied (Thrun, Burgard & Fox, *Probabilistic Robotics*, eq. 9.7-9.8).

Layout (follows ROS ``nav_msgs/OccupancyGrid`` and ``map_server``):

- ``log_odds[iy, ix]``: row ``iy`` grows with world ``y`` (row 0 = lowest y),
  column ``ix`` grows with world ``x`` (both in the map frame).
- ``origin = (x, y, yaw)``: the world pose of the lower-left corner of cell
  ``(ix, iy) = (0, 0)``, like ``origin`` in a map_server YAML. Cell centres are at
  ``origin_xy + R(yaw) @ ((ix + 0.5) res, (iy + 0.5) res)``.
- On disk (``map.pgm``), image row 0 is the TOP of the map, i.e. the highest
  ``y``: the array is flipped up-down when written and read.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
import yaml

from lampsam.arrays import BoolArray, FloatArray, IntArray
from lampsam.datasets.textio import read_yaml
from lampsam.errors import InputError
from lampsam.safe_io import atomic_path, write_text_atomic

log = logging.getLogger(__name__)

#: PGM values written by ``map_saver`` in trinary mode.
PGM_OCCUPIED = 0
PGM_FREE = 254
PGM_UNKNOWN = 205


class GridMapError(InputError):
    """A map_server map (PGM + YAML) could not be read or written, or bad grid input."""


@dataclass(frozen=True)
class LogOddsConfig:
    """Inverse sensor model of the grid update, in log-odds.

    Attributes:
        l_occ: added to a cell where a beam ends (default 0.85, p = 0.70).
        l_free: added to a cell a beam passes through (default -0.4, p = 0.40).
        l_min: lower clamp (default -4.0), so that a cell can change its mind.
        l_max: upper clamp (default 4.0).
        occupied_thresh: probability above which a cell is occupied (default 0.65,
            map_server's default).
        free_thresh: probability below which a cell is free (default 0.196,
            map_server's default).
        step_fraction: ray sampling step as a fraction of the cell size
            (default 0.5): free cells are those containing a sample.
    """

    l_occ: float = 0.85
    l_free: float = -0.4
    l_min: float = -4.0
    l_max: float = 4.0
    occupied_thresh: float = 0.65
    free_thresh: float = 0.196
    step_fraction: float = 0.5


@dataclass
class OccupancyGrid:
    """A 2-D log-odds occupancy grid (mutable: the map is built in place).

    Attributes:
        log_odds: (H, W) float64, ``log(p / (1 - p))`` per cell; 0 = unknown.
            Row = y index, column = x index (module docstring).
        resolution: cell size, metres per cell.
        origin: (3,) world pose ``(x, y, yaw)`` of the lower-left corner of cell
            (0, 0), metres and radians.
    """

    log_odds: FloatArray
    resolution: float
    origin: FloatArray = field(default_factory=lambda: np.zeros(3))

    def __post_init__(self) -> None:
        self.log_odds = np.asarray(self.log_odds, dtype=np.float64)
        self.origin = np.asarray(self.origin, dtype=np.float64).reshape(3)
        if self.log_odds.ndim != 2 or self.log_odds.size == 0:
            raise GridMapError(
                f"log_odds must be a non-empty 2-D array, got shape {self.log_odds.shape}")
        if not (self.resolution > 0 and math.isfinite(self.resolution)):
            raise GridMapError(f"resolution must be positive, got {self.resolution}")

    # ------------------------------------------------------------------ construction
    @classmethod
    def empty(cls, x_min: float, y_min: float, x_max: float, y_max: float,
              resolution: float) -> OccupancyGrid:
        """An all-unknown, axis-aligned grid covering a world rectangle.

        Args:
            x_min, y_min, x_max, y_max: the rectangle, world metres.
            resolution: metres per cell.

        Returns:
            A grid with ``origin = (x_min, y_min, 0)`` and
            ``ceil((x_max - x_min) / resolution)`` columns (at least one).
        """
        if not (x_max > x_min and y_max > y_min):
            raise GridMapError(f"empty grid bounds: x [{x_min}, {x_max}], y [{y_min}, {y_max}]")
        width = max(1, int(math.ceil((x_max - x_min) / resolution - 1e-9)))
        height = max(1, int(math.ceil((y_max - y_min) / resolution - 1e-9)))
        return cls(np.zeros((height, width)), float(resolution), np.array([x_min, y_min, 0.0]))

    @property
    def height(self) -> int:
        """Number of rows (cells along map y)."""
        return int(self.log_odds.shape[0])

    @property
    def width(self) -> int:
        """Number of columns (cells along map x)."""
        return int(self.log_odds.shape[1])

    # ------------------------------------------------------------------ conversions
    def world_to_map(self, xy: FloatArray) -> FloatArray:
        """World points to continuous map coordinates in cells.

        Args:
            xy: (..., 2) world points, metres.

        Returns:
            (..., 2) ``(u, v)``: cell ``(ix, iy) = floor(u, v)``; cell centres at
            half-integers.
        """
        xy = np.asarray(xy, dtype=np.float64)
        c, s = math.cos(self.origin[2]), math.sin(self.origin[2])
        dx = xy[..., 0] - self.origin[0]
        dy = xy[..., 1] - self.origin[1]
        return np.stack([(c * dx + s * dy), (-s * dx + c * dy)], axis=-1) / self.resolution

    def world_to_cell(self, xy: FloatArray) -> IntArray:
        """World points to integer cell indices (may fall outside the grid).

        Args:
            xy: (..., 2) world points, metres.

        Returns:
            (..., 2) int64 ``(ix, iy)`` (column, row); check with :meth:`in_bounds`.
        """
        return np.floor(self.world_to_map(xy)).astype(np.int64)

    def cell_to_world(self, cells: IntArray | FloatArray) -> FloatArray:
        """Cell centres in the world.

        Args:
            cells: (..., 2) ``(ix, iy)`` indices (fractional values are points in
                cell units).

        Returns:
            (..., 2) world coordinates of the cell centres, metres.
        """
        uv = (np.asarray(cells, dtype=np.float64) + 0.5) * self.resolution
        c, s = math.cos(self.origin[2]), math.sin(self.origin[2])
        x = self.origin[0] + c * uv[..., 0] - s * uv[..., 1]
        y = self.origin[1] + s * uv[..., 0] + c * uv[..., 1]
        return np.stack([x, y], axis=-1)

    def in_bounds(self, cells: IntArray) -> BoolArray:
        """Whether ``(ix, iy)`` indices (..., 2) lie inside the grid."""
        cells = np.asarray(cells)
        return ((cells[..., 0] >= 0) & (cells[..., 0] < self.width)
                & (cells[..., 1] >= 0) & (cells[..., 1] < self.height))

    def cell_centres(self) -> FloatArray:
        """World coordinates (H, W, 2) of every cell centre."""
        iy, ix = np.mgrid[0:self.height, 0:self.width]
        return self.cell_to_world(np.stack([ix, iy], axis=-1))

    def copy(self) -> OccupancyGrid:
        """A deep copy."""
        return OccupancyGrid(self.log_odds.copy(), self.resolution, self.origin.copy())


# ---------------------------------------------------------------------- probabilities
def occupancy_probabilities(grid: OccupancyGrid) -> FloatArray:
    """Occupancy probability of every cell, ``1 / (1 + exp(-l))``, shape (H, W)."""
    return 1.0 / (1.0 + np.exp(-grid.log_odds))


def logit(p: float) -> float:
    """Log-odds ``log(p / (1 - p))`` of a probability ``0 < p < 1``."""
    return math.log(p / (1.0 - p))


def occupied_cells(log_odds: FloatArray, config: LogOddsConfig = LogOddsConfig()) -> BoolArray:
    """map_server's occupied rule, ``p > occupied_thresh``, on log-odds: ``l > logit(thresh)``.

    The one form of the rule (grids, their chunks in the consistency check): the
    logistic function is increasing, so the two forms differ only for a value within
    rounding of the threshold; log-odds sums of ``l_occ`` / ``l_free`` do not come
    near it (nearest 0.011 on the Intel map, docs/architecture.md).

    Args:
        log_odds: (...) cell log-odds.
        config: ``occupied_thresh``.

    Returns:
        (...) bool.
    """
    return np.asarray(log_odds) > logit(config.occupied_thresh)


def free_cells(log_odds: FloatArray, config: LogOddsConfig = LogOddsConfig()) -> BoolArray:
    """map_server's free rule, ``p < free_thresh``, on log-odds: ``l < logit(thresh)``,
    (...) bool (:func:`occupied_cells`)."""
    return np.asarray(log_odds) < logit(config.free_thresh)


def occupied_mask(grid: OccupancyGrid, config: LogOddsConfig = LogOddsConfig()) -> BoolArray:
    """Cells with occupancy probability above ``config.occupied_thresh``, (H, W) bool."""
    return occupied_cells(grid.log_odds, config)


def free_mask(grid: OccupancyGrid, config: LogOddsConfig = LogOddsConfig()) -> BoolArray:
    """Cells with occupancy probability below ``config.free_thresh``, (H, W) bool."""
    return free_cells(grid.log_odds, config)


# ---------------------------------------------------------------------- updates
def _ray_cells(grid: OccupancyGrid, start_xy: FloatArray, end_xy: FloatArray,
               step_fraction: float, chunk: int = 2_000_000) -> IntArray:
    """Flat indices of the in-bounds cells crossed by segments, endpoint cells excluded.

    The segments are sampled every ``step_fraction * resolution`` metres
    (vectorised; a cell only grazed at a corner may be missed, which errs on the
    side of "unknown").

    Args:
        grid: the grid.
        start_xy: (N, 2) or (2,) segment starts (sensor), world metres.
        end_xy: (N, 2) segment ends, world metres.
        step_fraction: sampling step in cells.
        chunk: maximum number of samples held at once.

    Returns:
        (K,) unique flat indices ``iy * W + ix``.
    """
    start_uv = grid.world_to_map(np.broadcast_to(start_xy, end_xy.shape))
    end_uv = grid.world_to_map(end_xy)
    delta = end_uv - start_uv
    length = np.hypot(delta[:, 0], delta[:, 1])
    n_steps = np.ceil(length / step_fraction).astype(np.int64)
    end_cell = np.floor(end_uv).astype(np.int64)
    out: list[IntArray] = []
    # Sorted by length, so each padded (rays, samples) block wastes little.
    order = np.argsort(n_steps)
    batch = max(1, chunk // max(int(n_steps.max(initial=1)), 1))
    for begin in range(0, len(order), batch):
        idx = order[begin:begin + batch]
        n_max = max(int(n_steps[idx].max()), 1)
        t = np.arange(n_max, dtype=np.float64)[None, :] / np.maximum(n_steps[idx], 1)[:, None]
        valid = t < 1.0
        uv = start_uv[idx, None, :] + t[..., None] * delta[idx, None, :]
        cells = np.floor(uv).astype(np.int64)
        not_end = np.any(cells != end_cell[idx, None, :], axis=-1)
        keep = valid & not_end & grid.in_bounds(cells)
        cells = cells[keep]
        out.append(cells[:, 1] * grid.width + cells[:, 0])
    if not out:
        return np.zeros(0, dtype=np.int64)
    return np.unique(np.concatenate(out))


def apply_update(grid: OccupancyGrid, free_flat: IntArray, hit_flat: IntArray,
                 config: LogOddsConfig) -> None:
    """Add ``l_free`` to free cells, ``l_occ`` to hit cells (hits win), then clamp."""
    hit_flat = np.unique(hit_flat)
    free_flat = np.setdiff1d(free_flat, hit_flat, assume_unique=True)
    flat = grid.log_odds.reshape(-1)
    flat[free_flat] += config.l_free
    flat[hit_flat] += config.l_occ
    touched = np.concatenate([free_flat, hit_flat])
    flat[touched] = np.clip(flat[touched], config.l_min, config.l_max)


def integrate_points(grid: OccupancyGrid, sensor_xy: FloatArray, points_xy: FloatArray,
                     max_range: float, config: LogOddsConfig = LogOddsConfig()) -> None:
    """Fuse obstacle points (e.g. Kinect depth projected to the floor) into the grid.

    Each cell is updated at most once per call: cells traversed by the segment
    sensor -> point get ``l_free``; the point's cell gets ``l_occ`` (occupied
    wins where both apply). Points farther than ``max_range`` are cut to
    ``max_range`` and only clear free space (no hit). Non-finite points are
    skipped with a logged warning. The grid is modified in place.

    Args:
        grid: the map, modified in place.
        sensor_xy: (2,) sensor position on the floor, world metres.
        points_xy: (N, 2) obstacle points on the floor, world metres.
        max_range: metres; beyond it a point is not trusted as an obstacle.
        config: the inverse sensor model.
    """
    sensor_xy = np.asarray(sensor_xy, dtype=np.float64).reshape(2)
    points_xy = np.asarray(points_xy, dtype=np.float64).reshape(-1, 2)
    if not np.all(np.isfinite(sensor_xy)):
        raise GridMapError(f"sensor position is not finite: {sensor_xy}")
    finite = np.all(np.isfinite(points_xy), axis=1)
    if not np.all(finite):
        log.warning("integrate_points: skipping %d non-finite points", int((~finite).sum()))
        points_xy = points_xy[finite]
    if len(points_xy) == 0:
        return
    free_flat, hit_flat = point_cells(grid, sensor_xy, points_xy, max_range, config)
    apply_update(grid, free_flat, hit_flat, config)


def point_cells(grid: OccupancyGrid, sensor_xy: FloatArray, points_xy: FloatArray,
                max_range: float, config: LogOddsConfig = LogOddsConfig()
                ) -> tuple[IntArray, IntArray]:
    """The cells :func:`integrate_points` updates, without updating them.

    Args:
        grid: the map (only its geometry is used).
        sensor_xy: (2,) sensor position, world metres (finite).
        points_xy: (N, 2) finite obstacle points, world metres.
        max_range: metres; farther points only clear free space.
        config: the inverse sensor model (its ray step).

    Returns:
        ``(free_flat, hit_flat)``: flat indices ``iy * W + ix`` of the cells a beam
        passes through and of the cells where a beam ends (hits win where both apply
        when they are applied).
    """
    delta = points_xy - sensor_xy
    dist = np.hypot(delta[:, 0], delta[:, 1])
    hit = dist <= max_range
    scale = np.where(hit, 1.0, max_range / np.maximum(dist, 1e-12))
    ends = sensor_xy + delta * scale[:, None]
    free_flat = _ray_cells(grid, sensor_xy, ends, config.step_fraction)
    # A cut ray's end cell is free too (it is not an obstacle).
    cut_cells = grid.world_to_cell(ends[~hit])
    cut_cells = cut_cells[grid.in_bounds(cut_cells)]
    hit_cells = grid.world_to_cell(points_xy[hit])
    hit_cells = hit_cells[grid.in_bounds(hit_cells)]
    free_flat = np.union1d(free_flat, cut_cells[:, 1] * grid.width + cut_cells[:, 0])
    return free_flat, hit_cells[:, 1] * grid.width + hit_cells[:, 0]


def integrate_scan(grid: OccupancyGrid, sensor_pose: FloatArray, ranges: FloatArray,
                   angles: FloatArray, max_range: float,
                   config: LogOddsConfig = LogOddsConfig()) -> None:
    """Fuse one planar range scan into the grid.

    Beam ``b`` ends at ``(x, y) + r_b (cos(theta + a_b), sin(theta + a_b))``.
    Ranges ``>= max_range`` (or ``inf``) mean "no return": the beam clears
    free space up to ``max_range`` and marks no obstacle. NaN or non-positive
    ranges are skipped. See :func:`integrate_points` for the update rule.

    Args:
        grid: the map, modified in place.
        sensor_pose: (3,) world pose ``(x, y, theta)`` of the scanner, metres/rad.
        ranges: (B,) measured ranges, metres.
        angles: (B,) beam angles in the scanner frame, radians, CCW from forward.
        max_range: the scanner's maximum usable range, metres.
        config: the inverse sensor model.
    """
    sensor_pose = np.asarray(sensor_pose, dtype=np.float64).reshape(3)
    ranges = np.asarray(ranges, dtype=np.float64).reshape(-1)
    angles = np.asarray(angles, dtype=np.float64).reshape(-1)
    if ranges.shape != angles.shape:
        raise GridMapError(f"ranges {ranges.shape} and angles {angles.shape} differ in shape")
    if not np.all(np.isfinite(sensor_pose)):
        raise GridMapError(f"sensor pose is not finite: {sensor_pose}")
    pts = scan_points(sensor_pose, ranges, angles, max_range)
    integrate_points(grid, sensor_pose[:2], pts, max_range, config)


def scan_points(sensor_pose: FloatArray, ranges: FloatArray, angles: FloatArray,
                max_range: float) -> FloatArray:
    """World points of a scan's beams as :func:`integrate_scan` fuses them.

    NaN and non-positive ranges are left out; ranges at or beyond ``max_range``
    (``inf``: no return) are cut to just beyond it, so they clear free space only.

    Args:
        sensor_pose: (3,) finite scanner pose ``(x, y, theta)``, metres/rad.
        ranges: (B,) ranges, metres.
        angles: (B,) beam angles in the scanner frame, rad.
        max_range: metres.

    Returns:
        (K, 2) world points, metres.
    """
    usable = ~np.isnan(ranges) & (ranges > 0)
    r = np.minimum(ranges[usable], max_range * (1.0 + 1e-9))
    phi = sensor_pose[2] + angles[usable]
    return sensor_pose[:2] + r[:, None] * np.stack([np.cos(phi), np.sin(phi)], axis=1)


def grid_from_scans(poses: FloatArray, ranges: FloatArray, angles: FloatArray,
                    resolution: float, max_range: float, margin: float = 1.0,
                    config: LogOddsConfig = LogOddsConfig()) -> OccupancyGrid:
    """Build a grid map from planar scans taken at known poses (e.g. the Intel lab).

    The grid is axis-aligned and covers every pose and every usable beam
    endpoint (cut to ``max_range``) plus ``margin``. Each scan is fused with
    :func:`integrate_scan`; NaN ranges are skipped (pass NaN for "no return"
    readings that should not clear space).

    Args:
        poses: (N, 3) world poses of the scanner ``(x, y, theta)``.
        ranges: (N, B) ranges, metres.
        angles: (B,) beam angles in the scanner frame, rad.
        resolution: cell size, metres.
        max_range: usable range, metres (see :func:`integrate_scan`).
        margin: extra border, metres.
        config: the inverse sensor model.

    Returns:
        The grid.
    """
    poses = np.asarray(poses, dtype=np.float64).reshape(-1, 3)
    ranges = np.asarray(ranges, dtype=np.float64).reshape(len(poses), -1)
    if len(poses) == 0:
        raise GridMapError("no scans to build a grid from")
    r = np.minimum(np.where(np.isnan(ranges) | (ranges <= 0), 0.0, ranges), max_range)
    phi = poses[:, 2:3] + np.asarray(angles)[None, :]
    xs = np.concatenate([poses[:, 0], (poses[:, 0:1] + r * np.cos(phi)).ravel()])
    ys = np.concatenate([poses[:, 1], (poses[:, 1:2] + r * np.sin(phi)).ravel()])
    grid = OccupancyGrid.empty(xs.min() - margin, ys.min() - margin, xs.max() + margin,
                               ys.max() + margin, resolution)
    for pose, scan in zip(poses, ranges, strict=True):
        integrate_scan(grid, pose, scan, angles, max_range, config)
    log.info("grid from %d scans: %d x %d cells of %.3f m", len(poses), grid.width,
             grid.height, resolution)
    return grid


def grid_around(xy: FloatArray, reach: float, resolution: float) -> OccupancyGrid:
    """An empty grid covering world points grown by a margin.

    Args:
        xy: (N, 2) world points, metres (sensor positions, scan endpoints).
        reach: margin around them, metres.
        resolution: cell size, metres; the lower-left corner is snapped to a multiple of it.

    Returns:
        The all-unknown grid.
    """
    lo = xy.min(axis=0) - reach
    hi = xy.max(axis=0) + reach
    lo = np.floor(lo / resolution) * resolution
    return OccupancyGrid.empty(float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1]), resolution)


# ---------------------------------------------------------------------- map_server I/O
def save_map_server(grid: OccupancyGrid, path_stem: str | Path,
                    config: LogOddsConfig = LogOddsConfig()) -> Path:
    """Write ``<stem>.pgm`` and ``<stem>.yaml`` like ROS ``map_saver`` (trinary mode).

    Occupied cells (p > occupied_thresh) are written 0 (black), free cells
    (p < free_thresh) 254, unknown 205; ``negate: 0``; image row 0 is the top
    (highest y) of the map.

    Args:
        grid: the map.
        path_stem: path without suffix, e.g. ``out/map`` -> ``out/map.pgm``.
        config: the thresholds.

    Returns:
        The YAML path.
    """
    stem = Path(path_stem)
    stem.parent.mkdir(parents=True, exist_ok=True)
    img = np.full(grid.log_odds.shape, PGM_UNKNOWN, dtype=np.uint8)
    img[free_mask(grid, config)] = PGM_FREE
    img[occupied_mask(grid, config)] = PGM_OCCUPIED
    pgm = stem.with_suffix(".pgm")
    with atomic_path(pgm) as tmp:
        if not cv2.imwrite(str(tmp), np.flipud(img)):
            raise GridMapError("could not write the map image", path=pgm)
    meta = {
        "image": pgm.name,
        "mode": "trinary",
        "resolution": float(grid.resolution),
        "origin": [float(v) for v in grid.origin],
        "negate": 0,
        "occupied_thresh": float(config.occupied_thresh),
        "free_thresh": float(config.free_thresh),
    }
    yaml_path = stem.with_suffix(".yaml")
    write_text_atomic(yaml_path, yaml.safe_dump(meta, sort_keys=False))
    return yaml_path


def load_map_server(yaml_path: str | Path,
                    config: LogOddsConfig = LogOddsConfig()) -> OccupancyGrid:
    """Read a ROS map_server map (YAML + image) into a log-odds grid.

    Follows map_server's interpretation: ``p = (255 - v) / 255`` (or ``v / 255``
    with ``negate: 1``); in ``trinary`` mode p > occupied_thresh becomes
    ``config.l_max``, p < free_thresh ``config.l_min``, else 0 (unknown);
    in ``scale`` mode the cell gets ``logit(p)`` clamped to the config limits
    (unknown between the thresholds); in ``raw`` mode the value is the
    occupancy in percent (255 = unknown). Colour images are averaged to grey.

    Args:
        yaml_path: the YAML file; its ``image`` is relative to it.
        config: the log-odds limits assigned to occupied / free cells.

    Returns:
        The grid (row 0 = lowest y, module docstring).

    Raises:
        GridMapError: missing file, missing or bad key, unreadable image.
    """
    yaml_path = Path(yaml_path)
    if not yaml_path.is_file():
        raise GridMapError("map YAML not found", path=yaml_path)
    meta = read_yaml(yaml_path)  # DatasetError naming file and line: binary, invalid YAML
    if not isinstance(meta, dict):
        raise GridMapError("map YAML is not a mapping", path=yaml_path)
    for key in ("image", "resolution", "origin"):
        if key not in meta:
            raise GridMapError(f"missing key {key!r}", path=yaml_path)
    try:
        resolution = float(meta["resolution"])
        origin = np.array([float(v) for v in meta["origin"]], dtype=np.float64)
        negate = int(meta.get("negate", 0))
        occ_t = float(meta.get("occupied_thresh", config.occupied_thresh))
        free_t = float(meta.get("free_thresh", config.free_thresh))
    except (TypeError, ValueError) as exc:
        raise GridMapError(f"bad value: {exc}", path=yaml_path) from exc
    if origin.shape != (3,) or not np.all(np.isfinite(origin)):
        raise GridMapError(f"origin must be [x, y, yaw], got {meta['origin']}", path=yaml_path)
    if not (math.isfinite(resolution) and resolution > 0):
        raise GridMapError(f"resolution must be a positive number, got {meta['resolution']}",
                           path=yaml_path)
    mode = str(meta.get("mode", "trinary"))
    if mode not in ("trinary", "scale", "raw"):
        raise GridMapError(f"unknown mode {mode!r}", path=yaml_path)
    img_path = Path(meta["image"])
    if not img_path.is_absolute():
        img_path = yaml_path.parent / img_path
    img = cv2.imread(str(img_path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise GridMapError("map image missing or unreadable", path=img_path)
    if img.dtype != np.uint8:
        raise GridMapError(f"map image must be 8-bit, got {img.dtype}", path=img_path)
    if img.ndim == 3:
        img = img[..., :3].mean(axis=2)
    value = np.flipud(img).astype(np.float64)
    if mode == "raw":
        unknown = value == 255
        p = np.clip(value / 100.0, 0.0, 1.0)
    else:
        p = value / 255.0 if negate else (255.0 - value) / 255.0
        unknown = (p <= occ_t) & (p >= free_t)
    if mode == "trinary":
        log_odds = np.where(p > occ_t, config.l_max, np.where(p < free_t, config.l_min, 0.0))
    else:
        pc = np.clip(p, 1e-6, 1 - 1e-6)
        log_odds = np.clip(np.log(pc / (1 - pc)), config.l_min, config.l_max)
    log_odds = np.where(unknown, 0.0, log_odds)
    return OccupancyGrid(np.ascontiguousarray(log_odds), resolution, origin)
