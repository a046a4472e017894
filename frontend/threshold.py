"""The lamp threshold ``k`` of paper 1, eq. 1, chosen per image from its grey-level histogram.

Paper 1 (DESIGN.md sec. 1) thresholds the grey image at a fixed ``k``; real
ceilings are bright too, so :func:`auto_threshold` chooses ``k`` per image:
Otsu's threshold, repeated on the upper class while too much of the image lies
above it, and never below a floor relative to the lamp peak. Everything works
on the 256-bin histogram of a uint8 image (grey levels 0..255).
"""

from __future__ import annotations

import math

import cv2
import numpy as np

from lampsam.arrays import FloatArray, ImageU8
from lampsam.frontend.lamp_config import LampDetectorConfig


def grey_histogram(image: ImageU8) -> FloatArray:
    """Histogram of a uint8 image, shape (256,) float counts."""
    hist = cv2.calcHist([np.ascontiguousarray(image)], [0], None, [256], [0, 256])
    return hist.ravel().astype(np.float64)


def otsu_level(hist: FloatArray, lo: int = 0) -> float:
    """Otsu's threshold of the grey levels ``>= lo`` of a histogram.

    Args:
        hist: shape (256,) counts per grey level.
        lo: only levels ``lo..255`` take part (the upper class of an earlier step).

    Returns:
        ``t`` maximising the between-class variance, classes ``<= t`` and ``> t``
        (OpenCV's rule); ``lo`` when fewer than two levels are occupied.
    """
    h = hist[lo:]
    return _otsu_cumulative(np.cumsum(h), np.cumsum(h * np.arange(lo, 256, dtype=np.float64)), lo)


def _otsu_cumulative(w0: FloatArray, s0: FloatArray, lo: int) -> float:
    """:func:`otsu_level` from cumulative counts ``w0`` and level sums ``s0`` of levels ``lo..255``.

    Both classes are non-empty exactly on ``first <= t < last`` (``first``: the
    first occupied level, ``last``: the first level holding every pixel), so
    only that range is scored.
    """
    total = w0[-1]
    if total <= 0:
        return float(lo)
    first = int(np.searchsorted(w0, 0.0, side="right"))
    last = int(np.searchsorted(w0, total, side="left"))
    if last <= first:
        return float(lo)
    w0v, s0v = w0[first:last], s0[first:last]
    w1v = total - w0v
    between = w0v * w1v * (s0v / w0v - (s0[-1] - s0v) / w1v) ** 2
    best = int(between.argmax())
    if between[best] <= 0:
        return float(lo)
    return float(lo + first + best)


def peak_level(hist: FloatArray, min_count: int) -> float:
    """The brightest grey level reached by at least ``min_count`` pixels.

    Args:
        hist: shape (256,) counts per grey level.
        min_count: pixel count (a lamp's minimum area; ignores hot pixels).
    """
    above = hist[::-1].cumsum()[::-1]  # pixels >= level
    hits = np.flatnonzero(above >= min_count)
    return float(hits[-1]) if hits.size else 0.0


def auto_threshold(
    image: ImageU8, config: LampDetectorConfig, hist: FloatArray | None = None
) -> float | None:
    """Choose the lamp threshold ``k`` for one image.

    Otsu's threshold of the image; while more than ``max_bright_fraction`` of
    the pixels lie above it and less than ``light_share`` of those are at a
    light source's level (within ``max_peak_drop_grey`` of the peak: an upper
    class mostly that bright is light sources, a window beside the lamps, not
    ceiling) (a bright ceiling: Otsu separated dark structure
    from the ceiling, not the ceiling from the lamps), Otsu again on the upper
    class only; never below ``median + min_relative_level (peak - median)``.
    Images whose peak is within ``min_contrast_grey`` of the median have no
    lamps. Everything works on the 256-bin histogram.

    Args:
        image: shape (H, W) uint8 grey image.
        config: detector settings.
        hist: shape (256,) the image's :func:`grey_histogram` when the caller
            already has it (None: computed here).

    Returns:
        The threshold (lamp pixels are ``> k``), or None when no lamp can be
        told from the background.
    """
    if hist is None:
        hist = grey_histogram(image)
    return threshold_and_peak(hist, config, use_fixed=False)[0]


def threshold_and_peak(
    hist: FloatArray, config: LampDetectorConfig, use_fixed: bool = True
) -> tuple[float | None, float]:
    """:func:`auto_threshold` (or the fixed threshold) and :func:`peak_level` from one histogram.

    The cumulative sums are computed once: those of an upper class ``lo..255``
    are differences of the whole image's, exact because pixel counts and
    count x level sums are integers far below 2^53 in float64.

    Args:
        hist: shape (256,) integer counts per grey level.
        config: detector settings.
        use_fixed: return ``config.threshold`` when it is set (False: always
            the automatic threshold).

    Returns:
        ``(k, peak)``: the threshold (None: no lamp can be told from the
        background) and the lamp peak level.
    """
    cum = hist.cumsum()
    total = cum[-1]
    # The brightest level reached by min_area_px pixels: a few steps down from 255.
    peak, above = 0.0, 0.0
    for level, count in zip(range(255, -1, -1), hist[::-1].tolist(), strict=True):
        above += count
        if above >= config.min_area_px:
            peak = float(level)
            break
    if use_fixed and config.threshold is not None:
        return float(config.threshold), peak
    median = float(np.searchsorted(cum, 0.5 * total))
    if peak - median < config.min_contrast_grey:
        return None, peak
    sums = (hist * np.arange(256, dtype=np.float64)).cumsum()
    k = _otsu_cumulative(cum, sums, 0)
    # An upper class made mostly of pixels at a light source's level (within
    # max_peak_drop_grey of the peak, the blobs' dimness test; clipped when that is off)
    # is light sources (lamps, a sunlit window), not ceiling: splitting it again would
    # only cut the brightest lights from the others.
    share = config.light_share
    drop = config.max_peak_drop_grey
    light_from = 255 if drop is None else min(max(math.ceil(peak - drop), 1), 255)
    n_light = total - cum[light_from - 1]
    for _ in range(config.max_otsu_iterations):
        above = total - cum[int(k)]
        if above <= config.max_bright_fraction * total:
            break
        if share is not None and n_light >= share * above:
            break
        lo = int(k) + 1
        k_next = _otsu_cumulative(cum[lo:] - cum[lo - 1], sums[lo:] - sums[lo - 1], lo)
        if k_next <= k:
            break
        k = k_next
    # Lamps are the brightest things on the ceiling: never below the relative floor.
    floor = median + max(
        config.min_relative_level * (peak - median), 0.5 * config.min_contrast_grey
    )
    return max(k, floor), peak
