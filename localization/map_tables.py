"""Lookup tables precomputed from the grid and stored in the map directory.

Global localization scores thousands of particles per scan against the grid
(paper 2, sec. 4, eq. 8). Two lookups make that cheap, and both depend only on the
grid's occupied cells:

- the **range table** (:class:`~lampsam.localization.raycast.RangeTable`): the
  ray-cast range from every non-occupied cell centre in ``n_angles`` heading bins
  (uint16 millimetres). It takes seconds to tens of seconds to cast and tens of MB
  (office map: 110,000 cells x 360 bins, 77 MB);
- the **distance field** (:func:`~lampsam.localization.raycast.distance_field`):
  the distance from every cell centre to the nearest occupied cell centre, the input
  of the likelihood-field model (Thrun et al., *Probabilistic Robotics*, sec. 6.4).

This module is the one store of these lookups: ``build_map`` writes them once
beside ``map.yaml`` (atomically); the localizers load them
(:meth:`~lampsam.localization.map_layers.EnvironmentMaps.range_table` for the
Kinect localizer, which rebuilds and stores a table made for another
``max_range``; the laser trials' likelihood field and branch-and-bound score
pyramid, :mod:`~lampsam.localization.correlative`, from the distance field) with
:func:`load_range_table` / :func:`load_distance_field`, which return None (and say
why in the log) when a file is absent, of an older format, built for another
``max_range`` or bin count, or built from a different grid. Validity is checked
with :func:`grid_fingerprint`: a SHA-256 of the grid's shape, resolution, origin
and occupied-cell mask (:func:`~lampsam.localization.grid.occupied_mask` with the
default thresholds, the mask both lookups are built from), so a map edited after
the build is never paired with stale tables.

Files (NumPy ``.npz``, uncompressed so that loading is a plain read):

- ``range_table_<max_range in mm>mm_<bins>.npz`` (:func:`range_table_file`, e.g.
  ``range_table_4500mm_360.npz``): one file per ``(max_range, n_angles)``, so
  localizers with different beam ranges each keep their table instead of
  rebuilding each other's; ``ranges_mm`` (R + 1, A) uint16, ``row_of_cell`` (H*W,)
  int32, ``grid_shape`` (2,), ``resolution`` (), ``origin`` (3,), ``max_range`` () m,
  ``fingerprint`` () str, ``format_version`` (). A ``range_table.npz`` of an earlier
  version (one file for whichever ``max_range`` came last) is still read when its
  parameters match;
- ``distance_field.npz``: ``distance_cells`` (H, W) float32 (cells; ``inf`` when the
  grid has no occupied cell), ``fingerprint``, ``format_version``.
"""

from __future__ import annotations

import hashlib
import logging
import time
import zipfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from lampsam.arrays import FloatArray
from lampsam.localization.grid import OccupancyGrid, occupied_mask
from lampsam.localization.raycast import RangeTable, distance_field
from lampsam.safe_io import atomic_path

log = logging.getLogger(__name__)

#: The range table's file name in a map directory before tables were keyed by their
#: parameters (read when its parameters match; never written).
RANGE_TABLE_FILE = "range_table.npz"
#: The distance field's file name in a map directory.
DISTANCE_FIELD_FILE = "distance_field.npz"
#: Version of both files' layout.
TABLES_VERSION = 1


@dataclass(frozen=True)
class TableConfig:
    """Which lookups ``build_map`` precomputes.

    Attributes:
        range_table: write the range table for maps from depth (default True).
        laser_range_table: also for maps from laser logs (default False: the laser
            localizer scores scans with the likelihood field, and Intel's table is
            83 MB and about 25 s of CPU).
        range_max_range: its maximum range, metres: the beam model's ``max_range`` it
            will serve (default 4.5, the global localizer's default Kinect beam; at
            most 65.5, uint16 millimetres). A localizer with another ``max_range``
            rebuilds its table.
        n_angles: heading bins over 360 deg (default 360, 1 deg).
        distance_field: write the distance field (default True).
    """

    range_table: bool = True
    laser_range_table: bool = False
    range_max_range: float = 4.5
    n_angles: int = 360
    distance_field: bool = True


def grid_fingerprint(grid: OccupancyGrid) -> str:
    """SHA-256 (hex) of the grid's shape, resolution, origin and occupied-cell mask."""
    h = hashlib.sha256()
    h.update(np.array([grid.height, grid.width], dtype=np.int64).tobytes())
    h.update(np.array([grid.resolution, *np.asarray(grid.origin, float)],
                      dtype=np.float64).tobytes())
    h.update(np.packbits(occupied_mask(grid)).tobytes())
    return h.hexdigest()


def range_table_file(max_range: float, n_angles: int = 360) -> str:
    """The file name of the range table for ``max_range`` (m, to the millimetre) and ``n_angles`` bins."""
    return f"range_table_{int(round(float(max_range) * 1000))}mm_{int(n_angles)}.npz"


def build_range_table(grid: OccupancyGrid, max_range: float, n_angles: int = 360) -> RangeTable:
    """The range table the localizer uses: every non-occupied cell, ``n_angles`` bins."""
    return RangeTable.build(grid, n_angles, max_range, cells=~occupied_mask(grid))


def save_range_table(map_dir: str | Path, grid: OccupancyGrid, table: RangeTable) -> Path:
    """Write the table's file (:func:`range_table_file`) for ``grid`` (as loaded from the map directory).

    Args:
        map_dir: the map directory.
        grid: the grid the table was built from.
        table: the table.

    Returns:
        The file written.
    """
    path = Path(map_dir) / range_table_file(table.max_range, table.ranges_mm.shape[1])
    with atomic_path(path) as tmp, open(tmp, "wb") as fh:
        np.savez(fh, ranges_mm=table.ranges_mm, row_of_cell=table.row_of_cell,
                 grid_shape=np.array(table.grid_shape, dtype=np.int64),
                 resolution=np.float64(table.resolution),
                 origin=np.asarray(table.origin, dtype=np.float64),
                 max_range=np.float64(table.max_range),
                 fingerprint=np.array(grid_fingerprint(grid)),
                 format_version=np.int64(TABLES_VERSION))
    return path


def _open_checked(path: Path, grid: OccupancyGrid) -> dict[str, Any] | None:
    """The arrays of a table file when it exists and matches ``grid``, else None (logged)."""
    if not path.is_file():
        log.info("%s: absent, the lookup will be computed", path)
        return None
    try:
        with np.load(path, allow_pickle=False) as z:
            data = {k: z[k] for k in z.files}
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as exc:  # empty / cut short / not a zip
        log.warning("%s: unreadable (%s), the lookup will be computed", path, exc)
        return None
    if int(data.get("format_version", -1)) != TABLES_VERSION:
        log.info("%s: format version %s, not %d: recomputed", path,
                 data.get("format_version"), TABLES_VERSION)
        return None
    if str(data.get("fingerprint", "")) != grid_fingerprint(grid):
        log.warning("%s: built from a different grid (fingerprint differs): recomputed", path)
        return None
    return data


def load_range_table(map_dir: str | Path, grid: OccupancyGrid, max_range: float,
                     n_angles: int = 360) -> RangeTable | None:
    """The stored range table of ``grid`` for ``max_range`` and ``n_angles``, when present and valid.

    Reads :func:`range_table_file`, else an earlier version's ``range_table.npz``
    when that was built for the same parameters.

    Args:
        map_dir: the map directory (``build_map`` wrote its table there).
        grid: the grid the localizer uses (loaded from the same directory).
        max_range: the beam model's maximum range, metres.
        n_angles: heading bins.

    Returns:
        The table, or None when absent, unreadable, of another format, built from a
        different grid or for another ``max_range`` / ``n_angles`` (the reason is
        logged); the caller then builds it (:func:`build_range_table`).
    """
    path = Path(map_dir) / range_table_file(max_range, n_angles)
    legacy = Path(map_dir) / RANGE_TABLE_FILE
    if not path.is_file() and legacy.is_file():
        path = legacy
    data = _open_checked(path, grid)
    if data is None:
        return None
    ranges = data["ranges_mm"]
    rows = data["row_of_cell"]
    if abs(float(data["max_range"]) - float(max_range)) > 1e-9 or ranges.shape[1] != n_angles:
        log.info("%s: built for max_range %.3g m / %d bins, %.3g m / %d wanted: recomputed",
                 path, float(data["max_range"]), ranges.shape[1], max_range, n_angles)
        return None
    if (ranges.dtype != np.uint16 or rows.shape != (grid.height * grid.width,)
            or int(rows.max(initial=0)) >= ranges.shape[0]):
        log.warning("%s: inconsistent arrays: recomputed", path)
        return None
    return RangeTable((grid.height, grid.width), float(data["resolution"]),
                      np.asarray(data["origin"], dtype=np.float64), rows, ranges,
                      float(data["max_range"]))


def save_distance_field(map_dir: str | Path, grid: OccupancyGrid,
                        dist_cells: FloatArray) -> Path:
    """Write ``distance_field.npz`` ((H, W) float32 distances in cells) for ``grid``."""
    path = Path(map_dir) / DISTANCE_FIELD_FILE
    with atomic_path(path) as tmp, open(tmp, "wb") as fh:
        np.savez(fh, distance_cells=np.asarray(dist_cells, dtype=np.float32),
                 fingerprint=np.array(grid_fingerprint(grid)),
                 format_version=np.int64(TABLES_VERSION))
    return path


def load_distance_field(map_dir: str | Path, grid: OccupancyGrid) -> FloatArray | None:
    """The stored distance field of ``grid`` ((H, W) float32, cells), or None (logged)."""
    path = Path(map_dir) / DISTANCE_FIELD_FILE
    data = _open_checked(path, grid)
    if data is None:
        return None
    dist: FloatArray = data["distance_cells"]
    if dist.shape != (grid.height, grid.width):
        log.warning("%s: shape %s is not the grid's: recomputed", path, dist.shape)
        return None
    return dist


def range_table_for_map(map_dir: str | Path, grid: OccupancyGrid, max_range: float,
                        n_angles: int = 360, store: bool = True) -> RangeTable:
    """The range table of a map's grid: loaded when valid, else built (and stored).

    Args:
        map_dir: the map directory.
        grid: its grid as the localizer uses it.
        max_range: the beam model's maximum range, metres.
        n_angles: heading bins.
        store: write a rebuilt table back into ``map_dir`` (skipped with a warning
            when the directory is not writable).

    Returns:
        The table.
    """
    table = load_range_table(map_dir, grid, max_range, n_angles)
    if table is not None:
        return table
    table = build_range_table(grid, max_range, n_angles)
    if store:
        try:
            save_range_table(map_dir, grid, table)
        except OSError as exc:
            log.warning("%s: range table not stored (%s)", map_dir, exc)
    return table


def write_tables(map_dir: Path, grid: OccupancyGrid, config: TableConfig,
                 laser: bool = False) -> dict[str, Any]:
    """Precompute and write the lookups ``config`` asks for; describe them for the manifest.

    Args:
        map_dir: the map directory.
        grid: the grid as read back from ``map_dir`` (what the localizer will load).
        config: which lookups.
        laser: the map is from a laser log (``config.laser_range_table`` decides the
            range table).

    Returns:
        The manifest's entries, one per lookup written (file, parameters, size,
        seconds to build).
    """
    out: dict[str, Any] = {}
    fingerprint = grid_fingerprint(grid)
    if config.distance_field:
        t0 = time.perf_counter()
        path = save_distance_field(map_dir, grid, distance_field(occupied_mask(grid)))
        out["distance_field"] = {
            "file": path.name, "units": "cells (x resolution for metres)",
            "array": "distance_cells (H, W) float32", "grid_sha256": fingerprint,
            "build_s": round(time.perf_counter() - t0, 3),
        }
    if config.laser_range_table if laser else config.range_table:
        t0 = time.perf_counter()
        table = build_range_table(grid, config.range_max_range, config.n_angles)
        build_s = time.perf_counter() - t0
        path = save_range_table(map_dir, grid, table)
        out["range_table"] = {
            "file": path.name, "max_range_m": float(config.range_max_range),
            "n_angles": int(config.n_angles), "cells": "every non-occupied cell",
            "ranges": "uint16 millimetres", "rows": int(table.ranges_mm.shape[0] - 1),
            "size_mb": round(path.stat().st_size / 1e6, 1), "grid_sha256": fingerprint,
            "build_s": round(build_s, 3),
        }
    return out
