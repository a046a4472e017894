"""Coverage of the edge pixels of saturated lamps: a clipped pixel is not a covered pixel.

The coverage weights of :mod:`lampsam.frontend.blob_moments` read a pixel's grey level
``I`` as ``bg + w (top - bg)``. A lamp brighter than the sensor's full scale ``S``
(255) breaks this: the lamp's radiance ``L > S`` is unknown, ``top`` reads ``S``, and a
pixel that the lamp covers by ``c`` reads ``min(S, bg + c (L - bg))``. With
``c_s = (S - bg) / (L - bg)`` (the coverage at which a pixel clips):

* an unclipped edge pixel has ``w = c / c_s``, too large by ``1 / c_s``; its coverage
  is ``c = c_s w``;
* a clipped edge pixel (a saturated pixel next to the background) has any coverage in
  ``[c_s, 1]`` and reads ``w = 1``; its expected coverage is ``(1 + c_s) / 2``.

Along a straight edge every row's edge pixel has the same sub-pixel phase, so the edge's
error does not average along it: with ``w`` as read, an edge sits ``min(1, phi / c_s) -
phi`` px outward for a phase ``phi``, between 0 and ``1 - c_s`` (0.45 px on the
simulated lab: lamps at 320, ceiling at 175), and the centroid moves by half the
difference of its two edges' errors. Both corrections above take that to 0 for
``phi < c_s`` and ``+-(1 - c_s) / 2`` for ``phi >= c_s`` (docs/lamp-bias.md).

``c_s`` is measured on the image, not assumed: across a sharp saturated edge a row
or column of pixels goes from clipped to background either directly (the edge pixel
clipped: probability ``1 - c_s`` for a uniform phase) or through exactly one unclipped
pixel (probability ``c_s``). Counting both kinds of step over all saturated blobs of the
image gives ``c_s = n_one / (n_direct + n_one)``, and the lamps' radiance
``L = bg + (S - bg) / c_s`` (one radiance for the image's lamps: each blob then gets its
``c_s`` from its own background). A blurred edge (a real lens) passes through two or
more unclipped pixels: when such steps are as many as the sharp ones, or there are fewer
than ``min_steps`` sharp ones or fewer than ``MIN_ONE_STEPS`` through one pixel (edges
on the pixel grid, a drawn blob), nothing is changed (the weights as read are then right
to first order: a blurred clipped edge's coverage sum is a constant outward offset).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from lampsam.arrays import FloatArray, IntArray

FULL_SCALE = 255
"""Grey level of a saturated pixel (8-bit images)."""

MIN_ONE_STEPS = 4
"""Fewest steps through one unclipped pixel for ``c_s`` to be measured: without them the
edges show no sub-pixel coverage at all (a blob drawn on the pixel grid), not a lamp's."""


@dataclass(frozen=True)
class EdgeSteps:
    """Steps from saturated pixels to the background counted on one image.

    Attributes:
        direct: clipped pixel next to a background pixel (along a row or column).
        one: clipped, one unclipped pixel, background (collinear).
        wide: clipped, unclipped, unclipped (a resolved, blurred edge).
        bg_mean: mean background level of the blobs the steps were counted on.
    """

    direct: int
    one: int
    wide: int
    bg_mean: float

    def clip_coverage(self, min_steps: int) -> float | None:
        """``c_s`` of the image's lamps (module docstring), or None: no sharp clipped edges."""
        sharp = self.direct + self.one
        if sharp < min_steps or self.wide >= sharp or self.one < MIN_ONE_STEPS:
            return None
        return max(self.one / sharp, 0.05)


_PAD = 2
"""Padding of the box images, px (steps look two pixels away)."""

_CROSS = np.array([[0, 1, 0], [1, 1, 1], [0, 1, 0]], np.uint8)
"""4-neighbourhood structuring element."""


def count_steps(
    wv: FloatArray, grey: IntArray, xy: FloatArray, saturated_blob: np.ndarray, bg: FloatArray,
    bg_tol: FloatArray,
) -> tuple[EdgeSteps, np.ndarray]:
    """Count the clipped-to-background steps of saturated blobs, and flag clipped edge pixels.

    Args:
        wv: shape (P,) coverage weights as read, support pixels of all blobs.
        grey: shape (P,) their grey levels.
        xy: shape (2, P) their ``(col, row)`` in a common box, px.
        saturated_blob: shape (P,) bool, the pixel's blob is saturated (its level is full scale).
        bg: shape (P,) the pixel's blob background level.
        bg_tol: shape (P,) weight up to which a pixel counts as background (noise).

    Returns:
        The counts, and shape (P,) bool: clipped pixels with a background 4-neighbour.
        Pixels outside the supports count as background.
    """
    sat = saturated_blob & (grey >= FULL_SCALE - 1)
    if not sat.any():
        return EdgeSteps(0, 0, 0, float("nan")), np.zeros(wv.shape, dtype=bool)
    partial = ~sat & (wv > bg_tol)
    # Box images (padded), flat: the steps are looked up at the clipped pixels on the
    # boundary of the clipped set only (4-neighbourhood erosion).
    cols, rows = xy[0].astype(np.intp) + _PAD, xy[1].astype(np.intp) + _PAD
    width = int(cols.max()) + 1 + _PAD
    shape = (int(rows.max()) + 1 + _PAD, width)
    flat = rows * width + cols
    s_img = np.zeros(shape, np.uint8)
    s_img.ravel()[flat.compress(sat)] = 1
    p_flat = np.zeros(shape[0] * width, dtype=bool)
    p_flat[flat.compress(partial)] = True
    boundary = ((s_img > 0) & (cv2.erode(s_img, _CROSS) == 0)).ravel().nonzero()[0]
    b_flat = (s_img.ravel() == 0) & ~p_flat
    direct = one = wide = 0
    at_edge = np.zeros(boundary.size, dtype=bool)
    for off in (1, -1, width, -width):
        at = b_flat.take(boundary + off)
        at_edge |= at
        direct += int(np.count_nonzero(at))
        step = p_flat.take(boundary + off)
        one += int(np.count_nonzero(step & b_flat.take(boundary + 2 * off)))
        wide += int(np.count_nonzero(step & p_flat.take(boundary + 2 * off)))
    edge_flat = np.zeros(shape[0] * width, dtype=bool)
    edge_flat[boundary.compress(at_edge)] = True
    edge = edge_flat.take(flat) & sat
    return EdgeSteps(direct, one, wide, float(bg[sat].mean())), edge


def clipped_edge_weights(
    wv: FloatArray, grey: IntArray, xy: FloatArray, saturated_blob: np.ndarray, bg: FloatArray,
    bg_tol: FloatArray, min_steps: int,
) -> tuple[FloatArray, np.ndarray, float | None]:
    """Coverage of every support pixel with saturated edges taken into account.

    Args: as :func:`count_steps`; ``min_steps``: fewest sharp steps to measure ``c_s``.

    Returns:
        ``(weights (P,), changed (P,) bool, radiance)``: ``c_s w`` on the unclipped
        pixels of saturated blobs, ``(1 + c_s) / 2`` on their clipped edge pixels, ``w``
        elsewhere and everywhere when ``c_s`` cannot be measured (``changed`` all False,
        ``radiance`` None); ``radiance``: the lamps' level ``L`` (grey, above full scale).
    """
    steps, edge = count_steps(wv, grey, xy, saturated_blob, bg, bg_tol)
    cs_image = steps.clip_coverage(min_steps)
    if cs_image is None:
        return wv, np.zeros(wv.shape, dtype=bool), None
    radiance = steps.bg_mean + (FULL_SCALE - steps.bg_mean) / cs_image
    cs = clip_coverage_at(radiance, bg)
    sat = saturated_blob & (grey >= FULL_SCALE - 1)
    out = np.where(saturated_blob & ~sat, wv * cs, wv)
    out = np.where(edge, 0.5 * (1.0 + cs), out)
    return out, saturated_blob & (edge | ~sat), radiance


def clip_coverage_at(radiance: float, bg: FloatArray) -> FloatArray:
    """``c_s = (S - bg) / (L - bg)`` of lamps at ``radiance`` over backgrounds ``bg`` (clipped 0.05-1)."""
    return np.clip((FULL_SCALE - bg) / np.maximum(radiance - bg, 1e-6), 0.05, 1.0)


def label_edge_weights(
    wv: FloatArray, grey: IntArray, xy: FloatArray, lab: IntArray, saturated: np.ndarray,
    bg: FloatArray, noise_w: FloatArray, min_steps: int, apply: bool = True,
) -> tuple[FloatArray, FloatArray]:
    """:func:`clipped_edge_weights` for the support pixels of many blobs, with per-label inputs.

    Args:
        wv: shape (P,) coverage weights as read.
        grey: shape (P,) grey levels.
        xy: shape (2, P) ``(col, row)`` in a common box, px.
        lab: shape (P,) each pixel's blob label.
        saturated: shape (n,) bool per label: the blob's level is full scale (and it is measured).
        bg: shape (n,) background level per label.
        noise_w: shape (n,) weight up to which a pixel is background, per label.
        min_steps: fewest sharp steps to measure ``c_s``.
        apply: change the weights (False: only measure ``c_s``, the weights as read).

    Returns:
        ``(weights (P,), c_s (n,))``: each label's clip coverage, NaN where the blob is not
        saturated or ``c_s`` could not be measured on the image.
    """
    out, _, radiance = clipped_edge_weights(
        wv, grey, xy, saturated.take(lab), bg.take(lab), noise_w.take(lab), min_steps
    )
    cs = np.full(bg.shape, np.nan)
    if radiance is not None:
        cs = np.where(saturated, clip_coverage_at(radiance, bg), np.nan)
    return (out if apply else wv), cs
