"""The environment map (paper 2, sec. 2): the names callers use, gathered from its modules.

The map is built and stored by modules of one job each:

- ``map_config.py``: the build configuration;
- ``map_build.py``: ``build_map`` and its stages (source detection, layers, checks);
- ``depth_grid.py`` / ``laser_grid.py``: the grid map from depth frames / laser scans;
- ``map_poses.py``: the mapping poses (truth or a SLAM trajectory);
- ``map_quality.py``: the grid against a true floor plan;
- ``map_store.py``: the map directory (files, manifest, ``load_env_map``).

This module only re-exports their public names, so that code written against the
former single module keeps working while it moves to the new ones.
"""

from __future__ import annotations

from lampsam.localization.map_build import BuildReport, build_map
from lampsam.localization.map_config import DepthGridConfig, EnvMapConfig, LaserGridConfig
from lampsam.localization.map_quality import FloorPlan, footprint_mask, grid_precision_recall
from lampsam.localization.map_store import (
    MANIFEST_FILE,
    EnvironmentMap,
    EnvMapError,
    load_env_map,
)

__all__ = [
    "MANIFEST_FILE",
    "BuildReport",
    "DepthGridConfig",
    "EnvMapConfig",
    "EnvMapError",
    "EnvironmentMap",
    "FloorPlan",
    "LaserGridConfig",
    "build_map",
    "footprint_mask",
    "grid_precision_recall",
    "load_env_map",
]
