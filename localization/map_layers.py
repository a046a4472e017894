"""The environment map's layers as the global localizer uses them (paper 2, sec. 2).

:class:`EnvironmentMaps` holds the grid map, the spatial (SIFT) feature map and
the ceiling feature map, adapted from a map directory
(:func:`lampsam.localization.map_store.load_env_map`) or built directly (tests,
experiments). It also owns the map's precomputed expected-range table, which
is map preparation: built once on first use and reused by every localization
on the same maps object, and read from / stored in the map directory through
:mod:`~lampsam.localization.map_tables` (the one store of the map's lookups).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from lampsam.arrays import BoolArray, FloatArray
from lampsam.localization.grid import OccupancyGrid
from lampsam.localization.map_tables import build_range_table, range_table_for_map
from lampsam.localization.raycast import RangeTable

if TYPE_CHECKING:
    from lampsam.localization.map_store import EnvironmentMap

#: heading bins of the expected-range table (1 degree)
RANGE_TABLE_BINS = 360


@dataclass(frozen=True)
class EnvironmentMaps:
    """The three layers of the environment map the localizer uses.

    The layers must not be modified after construction: the range table built
    from ``grid`` is kept with the object (:meth:`range_table`).

    Attributes:
        grid: the grid map (Kinect depth or laser scans projected to the floor).
        spatial_xyz: (M, 3) spatial feature map points, world frame (m).
        spatial_descriptors: (M, 128) their SIFT descriptors.
        ceiling_xyz: (L, 3) ceiling feature map (lamps, corners), world (m).
        ceiling_body_t_camera: (3,) ceiling camera offset and height (m).
        ceiling_is_lamp: (L,) bool, which ceiling features are lamps (None: unknown).
        ceiling_phi: (L,) lamps' long axes in the world (rad, mod pi), NaN for
            none (None: axes not checked).
        ceiling_camera: the upward camera (``lampsam.datasets.logrun.CameraModel``):
            with it, map lamps predicted inside the image must be seen too.
        cache_dir: where the range table is stored once built (the map
            directory; None: kept in memory only).
    """

    grid: OccupancyGrid
    spatial_xyz: FloatArray
    spatial_descriptors: FloatArray
    ceiling_xyz: FloatArray
    ceiling_body_t_camera: FloatArray
    ceiling_is_lamp: BoolArray | None = None
    ceiling_phi: FloatArray | None = None
    ceiling_camera: Any = None
    cache_dir: Path | None = field(default=None, compare=False)
    _range_tables: dict[float, RangeTable] = field(
        default_factory=dict, init=False, repr=False, compare=False
    )

    @classmethod
    def from_env_map(
        cls, env: EnvironmentMap, body_t_camera: FloatArray, camera: Any = None,
        cache_dir: Path | None = None,
    ) -> EnvironmentMaps:
        """Adapt a loaded map directory (:func:`lampsam.localization.map_store.load_env_map`).

        Args:
            env: the map; a missing spatial or ceiling layer gives empty arrays
                (no candidates / no verification evidence).
            body_t_camera: (3,) the ceiling camera's mounting (from the run's rig).
            camera: the run's ``CameraModel`` (optional, see ``ceiling_camera``).
            cache_dir: see ``cache_dir`` (pass the map directory).
        """
        sp, ce = env.spatial, env.ceiling
        return cls(
            env.grid,
            np.zeros((0, 3)) if sp is None else np.asarray(sp.xyz, dtype=float),
            np.zeros((0, 128), np.float32) if sp is None else np.asarray(sp.descriptors),
            np.zeros((0, 3)) if ce is None else np.asarray(ce.xyz, dtype=float),
            np.asarray(body_t_camera, dtype=float).reshape(3),
            None if ce is None else np.asarray(ce.is_lamp(), dtype=bool),
            None if ce is None else np.asarray(ce.phi, dtype=float),
            camera,
            cache_dir,
        )

    @classmethod
    def grid_only(cls, grid: OccupancyGrid) -> EnvironmentMaps:
        """Maps with the grid layer only (a laser map: no spatial or ceiling features)."""
        return cls(grid, np.zeros((0, 3)), np.zeros((0, 128), np.float32), np.zeros((0, 3)),
                   np.zeros(3))  # fmt: skip

    def range_table(self, max_range: float) -> RangeTable:
        """The grid's :class:`RangeTable` (360 heading bins, every non-occupied cell), built once.

        A table takes seconds to build (office map: 110,000 cells x 360 bins,
        about 20 s on a loaded machine, 77 MB), so it is kept with these maps for
        every later localization on them, and with a ``cache_dir`` it is the map
        directory's table for this ``max_range``
        (:func:`~lampsam.localization.map_tables.range_table_for_map`: loaded
        when it was built from this grid, else built and stored there beside
        the tables of other ranges: the one store of the map's lookups).

        Args:
            max_range: metres (the beam model's).
        """
        key = float(max_range)
        table = self._range_tables.get(key)
        if table is None:
            if self.cache_dir is None:
                table = build_range_table(self.grid, key, RANGE_TABLE_BINS)
            else:
                table = range_table_for_map(self.cache_dir, self.grid, key, RANGE_TABLE_BINS)
            self._range_tables[key] = table
        return table
