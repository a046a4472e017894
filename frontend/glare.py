"""Separating lamps that a saturated glare halo has merged into one blob.

A saturated halo can bridge two lamps into one thresholded region. Such a
region fills its moment ellipse poorly (``fill = area / (4 pi sqrt(det Sigma))``
below ``min_fill``; about 0.95 for a rectangle, 1 for a disc;
:func:`lampsam.frontend.blob_moments.shape_checks`). It is re-thresholded at
higher levels between ``k`` and its maximum (the halo is dimmer than the
tubes); when that separates it into at least two large-enough parts each is
measured on its own, otherwise the detector rejects it (its centroid would be
that of the union, not of a lamp). Two lamps joined end to end fill their
ellipse like one long lamp and are not split.
"""

from __future__ import annotations

import cv2
import numpy as np

from lampsam.arrays import FloatArray
from lampsam.frontend.label_stats import label_blobs
from lampsam.frontend.lamp_config import LampDetectorConfig


def split_glare(
    grey_roi: FloatArray, core: np.ndarray, k: float, config: LampDetectorConfig
) -> list[np.ndarray] | None:
    """Try to separate a glare-merged region by thresholding it higher.

    The region is re-thresholded at ``k + f (peak - k)`` for ``f`` = 0.35,
    0.6, 0.8 (``peak``: its brightest grey level); the first level that
    leaves two or more parts of at least ``min_area_px`` pixels wins.

    Args:
        grey_roi: shape (h, w) float grey levels of the region's box.
        core: shape (h, w) bool, the merged region's pixels.
        k: the image's lamp threshold (grey level).
        config: detector settings (``min_area_px``).

    Returns:
        Two or more bool masks (one per lamp) or None when no split is found.
    """
    peak = float(grey_roi[core].max())
    for frac in (0.35, 0.6, 0.8):
        level = k + frac * (peak - k)
        n, lab, stats = label_blobs((core & (grey_roi > level)).astype(np.uint8))
        big = [i for i in range(1, n) if stats[i, cv2.CC_STAT_AREA] >= config.min_area_px]
        if len(big) >= 2:
            return [lab == i for i in big]
    return None
