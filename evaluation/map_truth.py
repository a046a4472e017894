"""The true floor plan of a simulated run, for the grid map's quality checks.

A run written by the simulators names its world in ``meta.yaml``; the world's
``scene3d`` section gives the obstacle boxes. This module turns them into the plain
:class:`~lampsam.localization.map_quality.FloorPlan` that ``build_map`` checks the
grid against, so that the localization package does not import the simulator.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import yaml

from lampsam.localization.map_quality import FloorPlan

log = logging.getLogger(__name__)


def floor_plan_of_run(run: str | Path, band: tuple[float, float]) -> FloorPlan | None:
    """The floor plan of a simulated run's world, or None when it has none.

    Args:
        run: a run directory with ``meta.yaml`` naming a world with a ``scene3d``
            section (``lampsam kinect-sim``); anything else gives None.
        band: ``(lo, hi)`` obstacle heights above the floor, metres: boxes reaching
            into the band are obstacles (the map's ``DepthGridConfig.height_band``).

    Returns:
        The obstacle outlines in the band and the floor's bounds (world metres), or
        None (no meta.yaml, no world, no scene3d, or an unreadable world: logged).
    """
    run = Path(run)
    meta_path = run / "meta.yaml"
    if not run.is_dir() or not meta_path.is_file():
        return None
    try:
        meta = yaml.safe_load(meta_path.read_text(encoding="utf-8")) or {}
        world = meta.get("world")
        if not world:
            return None
        from lampsam.datasets.scene3d import obstacle_footprints, scene_from_dict
        from lampsam.datasets.world import load_world

        w = load_world(world)
        if "scene3d" not in w.extra:
            return None
        scene = scene_from_dict(w.extra["scene3d"])
    except Exception as exc:  # noqa: BLE001 - the truth check is optional; say why it is skipped
        log.warning("%s: no truth geometry for the checks (%s)", run, exc)
        return None
    x0, y0, x1, y1 = (float(v) for v in np.asarray(scene.bounds, float))
    return FloorPlan(obstacle_footprints(scene, band[0], band[1]), (x0, y0, x1, y1))
