"""Grid-map quality against a known floor plan: occupied-cell precision and recall.

The truth is plain data (:class:`FloorPlan`: obstacle outlines and the room's
bounds in world metres), so this module needs no simulator; the caller that has a
simulated world turns it into a ``FloorPlan`` (``lampsam.evaluation.map_truth``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from lampsam.arrays import BoolArray, FloatArray
from lampsam.localization.grid import LogOddsConfig, OccupancyGrid, occupied_mask


@dataclass(frozen=True)
class FloorPlan:
    """The true floor plan of a world, as the grid map should show it.

    Attributes:
        footprints: obstacle outlines that reach into the map's obstacle height
            band, one (K, 2) polygon each, world metres.
        bounds: ``(x_min, y_min, x_max, y_max)`` of the room's floor, world metres.
    """

    footprints: list[FloatArray]
    bounds: tuple[float, float, float, float]


def footprint_mask(grid: OccupancyGrid, polygons: list[FloatArray]) -> BoolArray:
    """(H, W) cells whose centres lie inside any world polygon ((K, 2) metres each)."""
    import cv2

    img = np.zeros((grid.height, grid.width), np.uint8)
    shift = 4
    for poly in polygons:
        uv = grid.world_to_map(poly) - 0.5  # pixel (ix, iy) centre at integer coords
        pts = np.rint(uv * (1 << shift)).astype(np.int32)
        cv2.fillPoly(img, [pts], 1, lineType=cv2.LINE_8, shift=shift)
    return img.astype(bool)


def occupancy_truth(grid: OccupancyGrid, plan: FloorPlan) -> tuple[BoolArray, BoolArray]:
    """True occupied cells and the visible-surface cells of a floor plan.

    Args:
        grid: defines the cells.
        plan: the true obstacle outlines and room bounds.

    Returns:
        ``occupied`` (H, W): cells inside an obstacle footprint;
        ``surface`` (H, W): occupied cells with a 4-neighbour that is free and inside
        the room (what a sensor in the room can see).
    """
    occ = footprint_mask(grid, plan.footprints)
    centres = grid.cell_centres()
    x0, y0, x1, y1 = plan.bounds
    inside = (
        (centres[..., 0] > x0)
        & (centres[..., 0] < x1)
        & (centres[..., 1] > y0)
        & (centres[..., 1] < y1)
    )
    free_in = inside & ~occ
    nb = np.zeros_like(occ)
    nb[1:, :] |= free_in[:-1, :]
    nb[:-1, :] |= free_in[1:, :]
    nb[:, 1:] |= free_in[:, :-1]
    nb[:, :-1] |= free_in[:, 1:]
    return occ, occ & nb


def _dilate(mask: BoolArray, cells: int) -> BoolArray:
    """Square dilation of a mask by ``cells`` (Chebyshev radius)."""
    if cells <= 0:
        return mask
    import cv2

    k = np.ones((2 * cells + 1, 2 * cells + 1), np.uint8)
    return cv2.dilate(mask.astype(np.uint8), k).astype(bool)


def grid_precision_recall(
    occupied: BoolArray,
    truth_occupied: BoolArray,
    truth_surface: BoolArray,
    tolerance_cells: int = 0,
) -> tuple[float, float]:
    """Occupied-cell precision and recall of a grid map against the truth.

    precision = share of the map's occupied cells within ``tolerance_cells`` of a true
    obstacle cell; recall = share of the true visible-surface cells within
    ``tolerance_cells`` of a map occupied cell.

    Args:
        occupied: (H, W) the map's occupied cells.
        truth_occupied: (H, W) true obstacle cells.
        truth_surface: (H, W) true visible-surface cells.
        tolerance_cells: Chebyshev distance allowed, cells.

    Returns:
        ``(precision, recall)`` in [0, 1] (NaN when undefined).
    """
    n_occ = int(occupied.sum())
    n_surf = int(truth_surface.sum())
    precision = (
        float((occupied & _dilate(truth_occupied, tolerance_cells)).sum() / n_occ)
        if n_occ
        else math.nan
    )
    recall = (
        float((truth_surface & _dilate(occupied, tolerance_cells)).sum() / n_surf)
        if n_surf
        else math.nan
    )
    return precision, recall


def grid_checks(grid: OccupancyGrid, plan: FloorPlan, config: LogOddsConfig) -> dict[str, float]:
    """Precision/recall at 0 and 1 cell tolerance (:func:`grid_precision_recall`).

    Args:
        grid: the built map.
        plan: the truth.
        config: the log-odds thresholds that decide "occupied".

    Returns:
        ``resolution`` (m) and ``precision_tol{0,1}``, ``recall_tol{0,1}`` (4 decimals).
    """
    occ, surf = occupancy_truth(grid, plan)
    mask = occupied_mask(grid, config)
    out: dict[str, float] = {"resolution": float(grid.resolution)}
    for tol in (0, 1):
        p, r = grid_precision_recall(mask, occ, surf, tol)
        out[f"precision_tol{tol}"] = round(p, 4)
        out[f"recall_tol{tol}"] = round(r, 4)
    return out
