"""Ceiling-lamp detection on one grey image: the stages of paper 1, eqs. 1-7, in order.

Paper 1 (``seeds/ceiling-lamp-ekf-slam.txt``) with the corrections of DESIGN.md
sec. 1. :func:`detect_lamps` runs, each stage in its own module:

1. threshold at ``k`` (eq. 1): the paper's fixed ``k`` or an automatic one for
   bright real ceilings (:mod:`lampsam.frontend.threshold`);
2. label 8-connected regions (the paper's grassfire labelling,
   :func:`lampsam.frontend.label_stats.label_blobs`);
3. reject what is not a lamp (below), flag glare mergers and split them by
   thresholding higher (:mod:`lampsam.frontend.glare`);
4. coverage-weighted centroid, second moments, axis ``theta`` (eq. 5),
   ``R_ori`` (eq. 7) and their uncertainty, in pixels
   (:mod:`lampsam.frontend.blob_moments`), and the same moments taken on the
   ceiling when the camera's pixel -> ``m`` map is not affine (a fisheye, a
   tilted camera, lens distortion: :mod:`lampsam.frontend.ceiling_grid`);
5. conversion to normalised ceiling coordinates with the camera model
   (:mod:`lampsam.frontend.ceiling_coords`): centroid, axis and ``R_ori`` of
   the blob's shape on the ceiling, ``R_ori > ratio_threshold`` (1.5): an
   oriented lamp, else a point lamp; and, when the lamp models are known, the
   size check against them (:mod:`lampsam.frontend.lamp_models`).

Not lamps: blobs smaller than ``min_area_px`` or larger than
``max_area_fraction`` of the image (glare, a window), blobs less than
``min_blob_contrast_grey`` above their ring, blobs too dim to be a light
source (their fifth-brightest pixel more than ``max_peak_drop_grey`` below the
image's lamp peak: smoke detectors, specular highlights on ducts), blobs
crowded by other bright pixels just beyond their edge (``max_crowding``: the
panes of a skylight between glazing bars), glare mergers that no higher
threshold separates, and (``size_gate``) blobs whose area on the ceiling fits
no lamp model.

Border blobs: a blob touching the image border is cut, so its centroid and
axis are biased; it is flagged (``touches_border``) and left out by
:func:`lampsam.frontend.pipeline.process_image` unless asked for.

Cost: the per-blob work is vectorised over blobs and done inside the bounding
box of the thresholded pixels (lamps are sparse); only glare splits go region
by region. Benchmark: ``scripts/bench/bench_frontend.py``.
"""

from __future__ import annotations

import dataclasses
import logging
import math
from dataclasses import dataclass

import cv2
import numpy as np

from lampsam.arrays import BoolArray, ImageU8
from lampsam.frontend.blob_moments import (
    BlobMoments,
    measure_labels,
    measure_region,
    shape_checks,
)
from lampsam.frontend.blob_reach import gather_reach, reaches_may_overlap
from lampsam.frontend.ceiling_coords import (
    PixelToCeiling,
    ceiling_jacobians,
    ceiling_shapes,
    to_observations,
)
from lampsam.frontend.ceiling_grid import CeilingGrid, ceiling_grid
from lampsam.frontend.dilation import disk
from lampsam.frontend.glare import split_glare
from lampsam.frontend.label_stats import label_blobs
from lampsam.frontend.lamp_config import DEFAULT_CONFIG, LampDetectorConfig
from lampsam.frontend.lamp_models import within_size_gate
from lampsam.frontend.lamp_noise import edge_phase_cov
from lampsam.frontend.measurements import LampObservation
from lampsam.frontend.threshold import grey_histogram, threshold_and_peak

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class LampDetections:
    """The lamps of one image with the intermediate products (for drawing).

    Attributes:
        lamps: every accepted lamp, border blobs included (flagged).
        moments: the pixel-space measurement of each lamp, same order.
        threshold: the grey-level threshold used, or None (no lamps possible).
        mask: shape (H, W) bool, the accepted blobs' pixels (before dilation).
        n_rejected: regions rejected (size or unresolved glare merger).
    """

    lamps: tuple[LampObservation, ...]
    moments: tuple[BlobMoments, ...]
    threshold: float | None
    mask: BoolArray
    n_rejected: int


def measure_blobs(
    image: ImageU8, config: LampDetectorConfig, grid: CeilingGrid | None = None
) -> tuple[list[BlobMoments], float | None, BoolArray, int]:
    """Threshold, label and measure the lamp blobs of an image, in pixels.

    Size, dimness and glare checks and the moments of ordinary blobs are
    vectorised over blobs; only glare-merger candidates go through the
    per-region path (:func:`split_glare`, :func:`measure_region`).

    Everything after the threshold works inside the bounding box of the
    thresholded pixels, grown by the reach of a blob (support + ring + 1 px).
    The box starts at even coordinates: OpenCV labels 2x2 blocks in raster
    order, so the blobs are numbered (and listed) as on the whole image.

    Args:
        image: shape (H, W) uint8 grey image.
        config: detector settings.
        grid: the camera's per-pixel table (:func:`lampsam.frontend.ceiling_grid.ceiling_grid`):
            when it is not affine the moments are also taken on the ceiling
            (:attr:`BlobMoments.ceiling`); None: pixels only.

    Returns:
        ``(moments, threshold, mask (H, W) bool, n_rejected)``; moments in label order.
    """
    h, w = image.shape
    if grid is not None and (grid.width, grid.height) != (w, h):
        raise ValueError(f"image is {w}x{h} but the camera's table is {grid.width}x{grid.height}")
    hist = grey_histogram(image)  # one histogram for the threshold and the lamp peak
    k, peak = threshold_and_peak(hist, config)
    mask = np.zeros((h, w), dtype=bool)
    if k is None:
        return [], None, mask, 0
    _, binary = cv2.threshold(image, k, 1, cv2.THRESH_BINARY)  # 1 where image > k
    pad = config.support_px + config.ring_px + 1
    x, y, bw, bh = cv2.boundingRect(binary)
    if bw == 0:
        return [], k, mask, 0
    bx0, by0 = max(x - pad, 0) & ~1, max(y - pad, 0) & ~1
    bx1, by1 = min(x + bw + pad, w), min(y + bh + pad, h)
    box = (slice(by0, by1), slice(bx0, bx1))
    n, labels, stats = label_blobs(binary[box])
    areas = stats[:, cv2.CC_STAT_AREA]
    valid = (areas >= config.min_area_px) & (areas <= config.max_area_fraction * h * w)
    valid[0] = False
    n_keep = int(np.count_nonzero(valid))
    n_rejected = n - 1 - n_keep
    if n_keep == 0:
        return [], k, mask, n_rejected
    if n_keep >= 65535:  # pathological noise: far more blobs than lamps
        log.warning("%d candidate blobs: image too noisy for lamp detection", n_keep)
        return [], k, mask, n_rejected + n_keep
    # Candidates renumbered 1..m in label order (the others 0) with one pass over
    # their pixels; uint8 labels dilate about twice as fast as uint16.
    label_dtype: type[np.unsignedinteger] = np.uint8 if n_keep < 256 else np.uint16
    flat = labels.reshape(-1)
    pix = (flat > 0).nonzero()[0]
    if n_rejected == 0:  # every blob is a candidate: the labels already are 1..m
        comp: np.ndarray = labels.astype(label_dtype)
        pix_lab = flat.take(pix).astype(np.intp)
        cand = np.arange(1, n)
    else:
        cand = valid.nonzero()[0]
        lut = np.zeros(n, dtype=np.intp)
        lut[cand] = np.arange(1, n_keep + 1)
        pix_lab = lut.take(flat.take(pix))
        comp = np.zeros(labels.shape, dtype=label_dtype)
        comp.reshape(-1)[pix] = pix_lab  # comp is contiguous: reshape is a view
        keep = pix_lab > 0
        pix, pix_lab = pix.compress(keep), pix_lab.compress(keep)
    # Candidate boxes in the image: (left, top) and (right, bottom) exclusive, (m, 2) each.
    lo = stats[cand, :2] + (bx0, by0)
    hi = lo + stats[cand, 2:4]
    border = np.zeros(n_keep + 1, dtype=bool)
    border[1:] = (lo == 0).any(axis=1) | (hi == (w, h)).any(axis=1)
    # Measure inside the union box of the candidates (plus the reach): lamps are sparse.
    (mx0, my0), (mx1, my1) = lo.min(axis=0).tolist(), hi.max(axis=0).tolist()
    mx0, my0, mx1, my1 = max(mx0 - pad, 0), max(my0 - pad, 0), min(mx1 + pad, w), min(my1 + pad, h)
    rr, cc = np.divmod(pix, labels.shape[1])
    pix_image = (rr + by0) * w + (cc + bx0)  # flat index in the image
    too_dim, merged, top = shape_checks(
        pix_lab,
        (cc - (mx0 - bx0)).astype(np.float64),
        (rr - (my0 - by0)).astype(np.float64),
        image.reshape(-1).take(pix_image),
        n_keep + 1,
        peak,
        config,
    )
    n_rejected += int(np.count_nonzero(too_dim))
    good = ~too_dim & ~merged
    good[0] = False
    if not good[1:].all():  # the others leave the label image
        comp.reshape(-1)[pix.compress(~good.take(pix_lab))] = 0

    def default_bg() -> float:
        """Median grey level of the candidates' box (background of a blob without ring)."""
        return float(np.median(image[my0:my1, mx0:mx1]))

    out: list[BlobMoments] = []
    ids = np.flatnonzero(good)
    if ids.size:
        sub = (my0 - by0, my1 - by0, mx0 - bx0, mx1 - bx0)
        sel = good[1:].nonzero()[0]  # the blobs left in comp
        overlap = reaches_may_overlap(lo[sel], hi[sel], config.support_px + config.ring_px)
        reach = gather_reach(comp, sub, (bx0, by0), binary, image, config, overlap)
        res = measure_labels(reach, top, ids, border, default_bg, config, (mx0, my0), grid)
        ok_lab = np.zeros(n_keep + 1, dtype=bool)
        for i, mom in zip(ids.tolist(), res, strict=True):
            if mom is None:
                n_rejected += 1
            else:
                out.append(mom)
                ok_lab[i] = True
        mask.reshape(-1)[pix_image.compress(ok_lab.take(pix_lab))] = True
    # Glare-merger candidates: per region, re-thresholded higher.
    for j in np.flatnonzero(merged[1:] & ~too_dim[1:]).tolist():
        idx = int(cand[j])
        (c0, r0), (c1, r1) = lo[j].tolist(), hi[j].tolist()
        c0, r0, c1, r1 = max(c0 - pad, 0), max(r0 - pad, 0), min(c1 + pad, w), min(r1 + pad, h)
        lab_roi = labels[r0 - by0 : r1 - by0, c0 - bx0 : c1 - bx0]
        core = lab_roi == idx
        others = (lab_roi != 0) & ~core
        grey = image[r0:r1, c0:c1].astype(np.float64)
        split = split_glare(grey, core, k, config)
        if split is None:
            log.debug("rejected a glare-merged region at (%d, %d)", c0, r0)
            n_rejected += 1
            continue
        for reg in split:
            others_reg = others | (core & ~cv2.dilate(reg.astype(np.uint8), disk(1)).astype(bool))
            mom = measure_region(
                grey, reg, others_reg & ~reg, (c0, r0), bool(border[j + 1]), config, grid
            )
            if mom is None:
                n_rejected += 1
                continue
            out.append(mom)
            mask[r0:r1, c0:c1] |= reg
    if config.edge_phase_noise:
        out = [with_edge_phase_noise(mo, config.ratio_threshold, config.saturated_edges)
               for mo in out]
    return out, k, mask, n_rejected


def with_edge_phase_noise(mom: BlobMoments, ratio_threshold: float, model_on: bool) -> BlobMoments:
    """The blob with its straight edges' clip error added to the centroid covariance
    (:func:`lampsam.frontend.lamp_noise.edge_phase_cov`; oriented saturated blobs only)."""
    if mom.ratio <= ratio_threshold or not math.isfinite(mom.clip_coverage):
        return mom
    extra = edge_phase_cov(mom.theta, mom.sigma1, mom.sigma2, mom.clip_coverage, model_on)
    return dataclasses.replace(mom, cov_centroid=np.asarray(mom.cov_centroid) + extra)


def detect_lamps(
    image: ImageU8, camera: PixelToCeiling, config: LampDetectorConfig | None = None
) -> LampDetections:
    """Detect the ceiling lamps of one grey image (paper 1, eqs. 1-7).

    Args:
        image: shape (H, W) uint8 grey image, already validated
            (:func:`lampsam.frontend.pipeline.check_image`).
        camera: pixel -> normalised ceiling coordinates map.
        config: detector settings (defaults if None).

    Returns:
        All accepted lamps, border blobs included and flagged.
    """
    config = config or DEFAULT_CONFIG
    moments, k, mask, n_rej = measure_blobs(image, config, ceiling_grid(camera))
    return lamps_from_moments(moments, k, mask, n_rej, camera, config)


def lamps_from_moments(
    moments: list[BlobMoments],
    k: float | None,
    mask: BoolArray,
    n_rej: int,
    camera: PixelToCeiling,
    config: LampDetectorConfig,
) -> LampDetections:
    """Step 5 of :func:`detect_lamps`: pixel measurements -> ceiling observations.

    Args:
        moments: the accepted blobs' pixel measurements (:func:`measure_blobs`).
        k: the threshold used (None: no lamps possible).
        mask: shape (H, W) bool, the accepted blobs' pixels.
        n_rej: regions rejected so far.
        camera: pixel -> normalised ceiling coordinates map.
        config: detector settings (ratio threshold, size gate).
    """
    if not moments:
        return LampDetections((), (), k, mask, n_rej)
    px = np.array([mo.centroid for mo in moments])
    m, jac = ceiling_jacobians(camera, px, config.jacobian_step_px)
    shapes = ceiling_shapes(moments, m, jac)
    if config.size_gate is not None:
        keep = within_size_gate(shapes, config.size_gate)
        n_rej += keep.count(False)
        moments = [mo for mo, ok in zip(moments, keep, strict=True) if ok]
        shapes, jac = shapes.select(keep), jac[keep]
        if not moments:
            return LampDetections((), (), k, mask, n_rej)
    obs = to_observations(moments, shapes, jac, config)
    return LampDetections(obs, tuple(moments), k, mask, n_rej)
