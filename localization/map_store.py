"""The environment map directory: its files, its manifest, reading and writing it.

A map directory (paper 2, sec. 2: grid map, spatial feature map, ceiling feature map)::

    manifest.yaml            format, versions, units, frames, layers, config, timings, checks
    map.pgm + map.yaml       grid map (ROS map_server, via lampsam.localization.grid)
    spatial_features.npz     SIFT points with world positions (spatial_map.py)
    ceiling_features.csv     lamps and corners (ceiling_map.py)

``lampsam.localization.map_build.build_map`` writes one; :func:`load_env_map`
reads it. World frame: docs/conventions.md (``x, y`` on the floor, ``z`` up, metres).
"""

from __future__ import annotations

import datetime
import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from lampsam.datasets.textio import read_yaml
from lampsam.errors import LocalizationError
from lampsam.localization.ceiling_map import CEILING_FILE, CeilingFeatureMap
from lampsam.localization.grid import LogOddsConfig, OccupancyGrid, save_map_server
from lampsam.localization.spatial_map import SPATIAL_FILE, SpatialFeatureMap, SpatialMapConfig
from lampsam.safe_io import write_text_atomic

log = logging.getLogger(__name__)

#: The manifest's file name inside a map directory.
MANIFEST_FILE = "manifest.yaml"
#: The grid's file stem (``map.pgm`` + ``map.yaml``).
GRID_STEM = "map"
#: The manifest's ``format`` value.
ENVMAP_FORMAT = "lampsam-envmap"
#: The manifest format version this code writes and the newest it reads.
ENVMAP_VERSION = 1


class EnvMapError(LocalizationError):
    """The environment map could not be built or read (bad source, missing pose, ...)."""


@dataclass(frozen=True, eq=False)
class EnvironmentMap:
    """A loaded map directory.

    Attributes:
        grid: the grid map.
        spatial: the spatial feature map, or None.
        ceiling: the ceiling feature map, or None.
        manifest: the parsed manifest.
        path: the map directory it was read from (where the precomputed lookups of
            ``map_tables.py`` are found), or None.
    """

    grid: OccupancyGrid
    spatial: SpatialFeatureMap | None
    ceiling: CeilingFeatureMap | None
    manifest: dict[str, Any]
    path: Path | None = None


def _package_version() -> str:
    """The installed lampsam version, or ``unknown``."""
    try:
        from importlib.metadata import version

        return version("lampsam")
    except Exception:  # noqa: BLE001
        return "unknown"


def _plain(obj: Any) -> Any:
    """Tuples -> lists, numpy scalars -> Python, for YAML."""
    if isinstance(obj, dict):
        return {str(k): _plain(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_plain(v) for v in obj]
    if isinstance(obj, np.generic):
        return obj.item()
    return obj


def save_layers(
    out: Path,
    grid: OccupancyGrid,
    log_odds: LogOddsConfig,
    grid_info: dict[str, Any],
    spatial: SpatialFeatureMap | None = None,
    spatial_config: SpatialMapConfig | None = None,
    ceiling: CeilingFeatureMap | None = None,
) -> dict[str, Any]:
    """Write the layers' files into ``out`` (created) and describe them for the manifest.

    Args:
        out: the map directory.
        grid: the grid map (saved trinary with ``log_odds``' thresholds).
        log_odds: the inverse sensor model the grid was built with.
        grid_info: sensor-specific entries of the grid layer (sensor, ranges, band).
        spatial: the spatial feature map, or None.
        spatial_config: its merge parameters (recorded with it).
        ceiling: the ceiling feature map, or None.

    Returns:
        The manifest's ``layers`` section.
    """
    out.mkdir(parents=True, exist_ok=True)
    save_map_server(grid, out / GRID_STEM, log_odds)
    layers: dict[str, Any] = {
        "grid": {
            "file": f"{GRID_STEM}.yaml",
            "image": f"{GRID_STEM}.pgm",
            "format": "ROS map_server (trinary)",
            "resolution_m": float(grid.resolution),
            "origin": [float(v) for v in grid.origin],
            "size_cells": [grid.width, grid.height],
            **grid_info,
        }
    }
    if spatial is not None:
        spatial.save(out / SPATIAL_FILE)
        merge = spatial_config if spatial_config is not None else SpatialMapConfig()
        layers["spatial_features"] = {
            "file": SPATIAL_FILE,
            "count": len(spatial),
            "descriptor": "OpenCV SIFT, 128 float32, L2",
            "arrays": {
                "xyz": "(N, 3) world m",
                "descriptors": "(N, 128)",
                "size_px": "(N,)",
                "angle_deg": "(N,)",
                "n_obs": "(N,)",
            },
            "merge_radius_m": merge.merge_radius,
            "merge_descriptor_dist": merge.merge_descriptor_dist,
        }
    if ceiling is not None:
        ceiling.save(out / CEILING_FILE)
        layers["ceiling_features"] = {
            "file": CEILING_FILE,
            "count": len(ceiling),
            "lamps": int(ceiling.is_lamp().sum()),
            "corners": int((~ceiling.is_lamp()).sum()),
            "source": ceiling.source,
            "z_reference": "height above the floor, m",
        }
    return layers


def write_manifest(
    out: Path,
    source: dict[str, Any],
    layers: dict[str, Any],
    config: dict[str, Any],
    timings: dict[str, float],
    checks: dict[str, Any],
) -> Path:
    """Write ``out/manifest.yaml``.

    Args:
        out: the map directory (exists).
        source: ``kind``, ``path``, ``poses``, ``frames_used``.
        layers: from :func:`save_layers`.
        config: the build configuration as a plain dict.
        timings: stage -> seconds.
        checks: figures against the truth, when known.

    Returns:
        The manifest's path.
    """
    manifest = {
        "format": ENVMAP_FORMAT,
        "format_version": ENVMAP_VERSION,
        "created_by": f"lampsam {_package_version()}",
        "created_utc": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        "source": source,
        "frames": {
            "world": "x, y on the floor, z up, metres (docs/conventions.md)",
            "grid": "ROS map_server: origin = world pose of the lower-left cell corner",
            "camera": "OpenCV: x right, y down, z optical axis",
        },
        "units": {"length": "m", "angle": "rad (suffix _deg: degrees)", "time": "s"},
        "layers": layers,
        "config": _plain(config),
        "timings_s": timings,
        "checks": _plain(checks),
    }
    path = out / MANIFEST_FILE
    write_text_atomic(path, yaml.safe_dump(manifest, sort_keys=False))
    return path


def load_env_map(path: str | Path) -> EnvironmentMap:
    """Read a map directory (:func:`lampsam.localization.map_build.build_map` writes them).

    Args:
        path: the map directory.

    Returns:
        The grid and whichever feature layers the manifest lists.

    Raises:
        EnvMapError: no manifest or wrong format.
    """
    from lampsam.localization.grid import load_map_server

    path = Path(path)
    mf = path / MANIFEST_FILE
    if not mf.is_file():
        raise EnvMapError(f"{mf}: manifest not found (not a lampsam map directory)")
    manifest = read_yaml(mf)  # DatasetError naming the file for binary / invalid YAML
    if not isinstance(manifest, dict) or manifest.get("format") != ENVMAP_FORMAT:
        raise EnvMapError(f"{mf}: not a {ENVMAP_FORMAT} manifest")
    version = manifest.get("format_version", 0)
    if isinstance(version, bool) or not isinstance(version, int):
        raise EnvMapError(f"{mf}: format_version must be an integer, got {version!r}")
    if version > ENVMAP_VERSION:
        raise EnvMapError(
            f"{mf}: format_version {manifest['format_version']} is newer than "
            f"this lampsam's ({ENVMAP_VERSION})"
        )
    layers = manifest.get("layers", {})
    consistency = layers.get("grid", {}).get("scan_consistency") or {}
    if isinstance(consistency, dict) and consistency.get("poor") is True:
        why = consistency.get("reason") or (  # maps written before the worst-chunk rule
            f"{100 * float(consistency.get('score') or 0.0):.0f} % of the hits checked on "
            f"walls the rest of the log saw, below "
            f"{100 * float(consistency.get('threshold') or 0.0):.0f} %")
        log.warning("%s: this map was built from laser scans whose poses disagree (%s): its "
                    "walls may be doubled and localization on it is unreliable", path, why)
    grid = load_map_server(path / layers.get("grid", {}).get("file", f"{GRID_STEM}.yaml"))
    spatial = (
        SpatialFeatureMap.load(path / layers["spatial_features"]["file"])
        if "spatial_features" in layers
        else None
    )
    ceiling = (
        CeilingFeatureMap.load(
            path / layers["ceiling_features"]["file"],
            source=layers["ceiling_features"].get("source"),
        )
        if "ceiling_features" in layers
        else None
    )
    return EnvironmentMap(grid, spatial, ceiling, manifest, path)
