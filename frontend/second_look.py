"""A second, finer look inside lamp blobs that are long for their frame (two lamps end to end).

Two fittings mounted end to end are separated by a gap narrower than either
fitting; when the working image is too coarse for that gap to span a pixel,
the threshold (eq. 1 of paper 1) joins them into one long blob. Nothing at the
coarse scale tells that blob from one long fitting (its neck and its
brightness dip are those of a module seam: docs/photo-labels.md), so the
evidence is taken where it exists: the blob's box is cut from the
higher-resolution image, thresholded at the same grey level ``k`` and run
through the same detector (:func:`lampsam.frontend.lamps.measure_blobs`: the
same size, dimness, contrast, crowding and glare tests). The blob is replaced
by the fine blobs inside it only when they are two or more lamps each at least
``min_part_ratio`` of the frame's median lamp length (a lit fragment of a
tube is not a lamp), or, for a blob cut by the image border, when one such
lamp lies inside it clear of the border (the cut neighbour it was merged with
is too short or too small to pass at the fine scale; a cut blob is dropped,
so without this the whole lamp would be lost); otherwise it is kept as it
was. Only blobs at least ``long_ratio`` times the frame's median lamp
length, or cut by the border, get the second look (a merged pair is the sum
of two lamps), so the cost stays a few crops per photo.

Pixels: the coarse image is the fine one resized by ``1/f`` with area
averaging (``cv2.INTER_AREA``); a fine pixel centre ``x_f`` lies at
``x_c = (x_f + 0.5) / f - 0.5`` in the coarse image. Moments are pixel-space
(:class:`lampsam.frontend.blob_moments.BlobMoments`); the ceiling moments of
a non-affine camera are not carried over (the caller's camera is assumed affine
in the pixel, as the photo evaluation's pinhole is).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import cv2
import numpy as np

from lampsam.arrays import BoolArray, ImageU8
from lampsam.frontend.blob_moments import BlobMoments
from lampsam.frontend.lamp_config import LampDetectorConfig
from lampsam.frontend.lamps import measure_blobs

SQRT12 = math.sqrt(12.0)  # a uniform bar of length L has sigma = L / sqrt(12)


@dataclass(frozen=True)
class SecondLookConfig:
    """Settings of the second look.

    Attributes:
        long_ratio: a blob at least this many times the frame's median lamp
            length (``sqrt(12) sigma1``, non-border lamps) gets a second look
            (default 2: two equal lamps end to end).
        min_part_ratio: each fine blob replacing it must be at least this
            fraction of the frame's median lamp length (default 0.5).
        pad_px: margin around the blob's box in the fine image, px, added to
            the detector's reach (default 8).
        border: blobs touching the image border get a second look too
            (default True): a cut blob is dropped, so a lamp merged with a
            neighbour that the border cuts is lost with it.
    """

    long_ratio: float = 2.0
    min_part_ratio: float = 0.5
    pad_px: int = 8
    border: bool = True


def blob_length(m: BlobMoments) -> float:
    """Length of a blob along its axis, px: ``sqrt(12) sigma1`` (a uniform bar's length)."""
    return SQRT12 * m.sigma1


def long_blobs(
    moments: list[BlobMoments], long_ratio: float, border: bool = False
) -> tuple[list[int], float]:
    """Indices of the blobs at least ``long_ratio`` times the frame's median lamp length.

    The median is over the blobs not touching the border (all blobs when every
    one does); border blobs can be long too (a merged pair cut by the border),
    and with ``border`` every border blob is listed.

    Returns:
        ``(indices, median length px)``; no indices with fewer than two blobs.
    """
    if len(moments) < 2:
        return [], math.nan
    lengths = np.array([blob_length(m) for m in moments])
    inner = np.array([not m.touches_border for m in moments])
    med = float(np.median(lengths[inner] if inner.any() else lengths))
    pick = lengths >= long_ratio * med
    if border:
        pick |= ~inner
    return np.flatnonzero(pick).tolist(), med


def scale_moments(m: BlobMoments, f: float, touches_border: bool) -> BlobMoments:
    """A fine image's blob measurement in the pixels of the image ``f`` times coarser.

    Centroid ``(x + 0.5) / f - 0.5``; covariances divided by ``f^2`` (the
    shape covariance's 1/12 px^2 pixel-box term is taken out and put back);
    spreads from the scaled shape; ``theta``, ``ratio`` and the contrast unchanged
    up to the box term; ceiling moments dropped.
    """
    box = np.eye(2) / 12.0
    cov_shape = (m.cov_shape - box) / (f * f) + box
    lam = np.linalg.eigvalsh(cov_shape)
    sigma1, sigma2 = math.sqrt(max(lam[1], 0.0)), math.sqrt(max(lam[0], 1e-12))
    return replace(
        m,
        centroid=(np.asarray(m.centroid, dtype=np.float64) + 0.5) / f - 0.5,
        cov_centroid=m.cov_centroid / (f * f),
        cov_shape=cov_shape,
        sigma1=sigma1,
        sigma2=sigma2,
        ratio=sigma1 / sigma2,
        area_px=m.area_px / (f * f),
        touches_border=touches_border,
        ceiling=None,
    )


def _blob_regions(mask: BoolArray, moments: list[BlobMoments]) -> tuple[np.ndarray, list[int]]:
    """Label the accepted-blob mask and give each blob the label nearest its centroid."""
    _, lab = cv2.connectedComponents(mask.astype(np.uint8), connectivity=8)
    rows, cols = np.nonzero(lab)
    out = []
    for m in moments:
        cx, cy = float(m.centroid[0]), float(m.centroid[1])
        j = int(np.argmin((cols - cx) ** 2 + (rows - cy) ** 2)) if rows.size else -1
        out.append(int(lab[rows[j], cols[j]]) if j >= 0 else 0)
    return lab, out


def second_look(
    fine: ImageU8,
    f: float,
    moments: list[BlobMoments],
    mask: BoolArray,
    k: float,
    fine_config: LampDetectorConfig,
    look: SecondLookConfig | None = None,
) -> tuple[list[BlobMoments], int]:
    """Replace the long blobs of a coarse frame that split into lamps at the finer scale.

    Args:
        fine: shape (H f, W f) uint8 grey, the same view ``f`` times finer.
        f: fine px per coarse px (> 1).
        moments: the coarse frame's accepted blobs (:func:`lampsam.frontend.lamps.measure_blobs`).
        mask: shape (H, W) bool, their pixels.
        k: the coarse frame's threshold (grey level; lamp pixels are ``> k``).
        fine_config: detector settings at the fine scale (``min_area_px`` scaled).
        look: second-look settings (defaults if None).

    Returns:
        ``(moments, n_split)``: the coarse list with each split blob replaced
        by its parts (coarse pixels, same order otherwise), and how many blobs
        were split.
    """
    look = look or SecondLookConfig()
    idx, med = long_blobs(moments, look.long_ratio, look.border)
    if not idx:
        return list(moments), 0
    h, w = mask.shape
    fh, fw = fine.shape
    lab, blob_lab = _blob_regions(mask, moments)
    # pixels > floor(k) == pixels > k; the size cap is a share of the whole image (the coarse
    # blob passed it), not of a crop around one blob.
    cfg = replace(fine_config, threshold=math.floor(k), max_area_fraction=1.0)
    reach = cfg.support_px + cfg.ring_px + 1 + look.pad_px
    parts_of: dict[int, list[BlobMoments]] = {}
    for i in idx:
        rows, cols = np.nonzero(lab == blob_lab[i])
        if rows.size == 0:
            continue
        x0, x1 = max(int(cols.min() * f) - reach, 0), min(int(math.ceil((cols.max() + 1) * f)) + reach, fw)
        y0, y1 = max(int(rows.min() * f) - reach, 0), min(int(math.ceil((rows.max() + 1) * f)) + reach, fh)
        crop = np.ascontiguousarray(fine[y0:y1, x0:x1])
        found, _, _, _ = measure_blobs(crop, cfg)
        parts = []
        for q in found:
            xf, yf = float(q.centroid[0]) + x0, float(q.centroid[1]) + y0
            xc, yc = (xf + 0.5) / f - 0.5, (yf + 0.5) / f - 0.5
            r, c = min(max(round(yc), 0), h - 1), min(max(round(xc), 0), w - 1)
            if lab[r, c] != blob_lab[i]:
                continue  # a neighbour inside the box, or a piece off the coarse blob
            if blob_length(q) / f < look.min_part_ratio * med:
                continue
            # A part of a blob clear of the border is clear of it; the box's inner
            # edges lie a reach beyond the blob, so a part at an edge is at the image's.
            border = q.touches_border and moments[i].touches_border
            parts.append(scale_moments(replace(q, centroid=np.array([xf, yf])), f, border))
        if len(parts) >= 2 or (
            # a cut blob is dropped: one whole lamp clear of the border inside it is kept
            moments[i].touches_border and len(parts) == 1 and not parts[0].touches_border
        ):
            parts_of[i] = parts
    out: list[BlobMoments] = []
    for i, m in enumerate(moments):
        out.extend(parts_of.get(i, [m]))
    return out, len(parts_of)

