"""Ceiling-lamp detection: threshold, connected components, second moments.

Paper 1 (``seeds/ceiling-lamp-ekf-slam.txt``), eqs. 1-7, with the corrections of
DESIGN.md sec. 1:

1. Threshold the grey image at ``k`` (eq. 1): the paper's fixed ``k``, or an
   automatic ``k`` (:func:`auto_threshold`) for real images whose ceilings are
   bright too.
2. Label connected regions (the paper's grassfire labelling is
   ``cv2.connectedComponentsWithStats``, 8-connected).
3. Per region, the centroid and the central second moments ``a = mu20``,
   ``b = mu11``, ``c = mu02`` (eqs. 2-4); the long-axis angle
   ``theta = 0.5 atan2(2b, a - c)`` modulo pi (eq. 5 with the quadrant kept);
   the axis lengths from the covariance eigenvalues (eq. 6) and
   ``R_ori = sigma1 / sigma2`` (eq. 7). ``R_ori > ratio_threshold`` (1.5): an
   oriented lamp, else a point lamp.

Sub-pixel accuracy: the moments are not taken over the binary region but over
*coverage weights* ``w = clip((I - bg) / (top - bg), 0, 1)`` inside the region
dilated by ``support_px``, where ``bg`` is the median grey level of a ring
around the blob and ``top`` the median inside it. On an anti-aliased (area
sampled) edge the grey level is ``bg + coverage (top - bg)``, so ``w`` is the
fraction of the pixel the lamp covers and the weighted centroid is the true
area centroid.

Uncertainty (first-order propagation of independent grey-level noise
``sigma_n`` through the weights; only unclipped pixels, ``0 < w < 1``, carry
it): with ``W = sum w``, ``d_i = x_i - c``,

* centroid: ``cov_c = sigma_w^2 sum_i d_i d_i^T / W^2 + sigma_floor^2 I``,
  ``sigma_w = sigma_n / (top - bg)``;
* axis: ``var_theta = sigma_w^2 sum_i (dtheta/dw_i)^2 + sigma_axis_floor^2`` with
  ``dtheta/dw_i = [x (2 d_xi d_yi - 2b) - y ((d_xi^2 - a) - (d_yi^2 - c))]
  / (2 W (x^2 + y^2))``, ``x = a - c``, ``y = 2b``.

``sigma_n`` is the robust spread (1.4826 MAD) of the ring, floored at
``noise_floor_grey``. The floors stand for what the model leaves out (blur,
non-flat lamps, compression).

Pixel quantities are converted to normalised ceiling coordinates
(docs/conventions.md) with the camera model and the local Jacobian
``J = dm/dpx`` of its pixel -> ``m`` map at the centroid (central differences):
``cov_m = J cov_c J^T``; the axis direction ``e = (cos theta, sin theta)``
becomes ``J e`` (this undoes the image mirroring of the default mounting and
the distortion), and ``var_alpha = (det J / |J e|^2)^2 var_theta``.

Border blobs: a blob touching the image border is cut, so its centroid and
axis are biased; it is flagged (``touches_border``) and left out by
:func:`lampsam.frontend.pipeline.process_image` unless asked for.

Glare: a saturated halo can bridge two lamps into one region. Such a region
fills its moment ellipse poorly (``fill = area / (4 pi sqrt(det Sigma)) < min_fill``;
about 0.95 for a rectangle, 1 for a disc). It is re-thresholded at higher
levels between ``k`` and its maximum (the halo is dimmer than the tubes); if
that separates it into at least two large-enough parts each is measured on
its own, otherwise the region is rejected (its centroid would be of the
union, not of a lamp) and a debug message is logged. Two lamps joined end to
end fill their ellipse like one long lamp and are not split; glare that grows
a region past ``max_area_fraction`` of the image rejects it.

Not lamps: blobs smaller than ``min_area_px`` or larger than
``max_area_fraction`` of the image, blobs less than ``min_blob_contrast_grey``
above their ring, and blobs too dim to be a light source (their fifth-brightest
pixel more than ``max_peak_drop_grey`` below the image's lamp peak: smoke
detectors, specular highlights on ducts).

All per-blob sums are vectorised over the blobs (segment sums over the pixels
grouped by label, medians from per-label cumulative level histograms), so the
cost hardly grows with the number of lamps; only glare splits go region by
region, and the closing formulas of each blob run on Python floats (a handful
of blobs: cheaper than numpy calls on tiny arrays). Labelling, checks and
moments work inside the bounding box of the thresholded pixels (lamps are
sparse); a benchmark is ``scripts/bench/bench_frontend.py``.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import NamedTuple, Protocol

import cv2
import numpy as np

from lampsam.angles import wrap_axis
from lampsam.arrays import BoolArray, FloatArray, ImageU8, IntArray
from lampsam.frontend.dilation import dilate_disk, disk
from lampsam.frontend.label_stats import (
    group_by_label,
    label_blobs,
    label_levels,
    label_sums,
    levels_at,
    lower_median_rank,
)
from lampsam.frontend.lamp_config import DEFAULT_CONFIG, LampDetectorConfig
from lampsam.frontend.measurements import LampObservation
from lampsam.frontend.threshold import grey_histogram, threshold_and_peak

log = logging.getLogger(__name__)


class PixelToCeiling(Protocol):
    """What the frontend needs from a camera model (``lampsam.datasets.logrun.CameraModel``)."""

    width: int
    height: int

    def normalized_from_pixels(self, px: FloatArray) -> FloatArray:
        """Pixels ``(N, 2)`` (col, row) -> normalised ceiling coordinates ``(N, 2)``."""
        ...


@dataclass(frozen=True)
class BlobMoments:
    """Pixel-space measurement of one blob (before the camera model).

    Attributes:
        centroid: shape (2,), ``(col, row)`` pixels.
        cov_centroid: shape (2, 2), covariance of ``centroid``, px^2.
        cov_shape: shape (2, 2), second central moments of the coverage
            (``[[a, b], [b, c]]``, px^2, with the 1/12 px^2 pixel-box term added).
        theta: long-axis angle in the image, ``0.5 atan2(2b, a - c)`` (eq. 5),
            rad in ``(-pi/2, pi/2]``, measured from image ``+col`` towards ``+row``.
        var_theta: variance of ``theta``, rad^2.
        sigma1: long semi-axis spread ``sqrt(lambda_max)`` px (eq. 6).
        sigma2: short one ``sqrt(lambda_min)`` px.
        ratio: ``sigma1 / sigma2`` (eq. 7).
        area_px: coverage-weighted area, px.
        touches_border: the region touches the image border.
        contrast: lamp level minus background level (``top - bg``), grey levels.
    """

    centroid: FloatArray
    cov_centroid: FloatArray
    cov_shape: FloatArray
    theta: float
    var_theta: float
    sigma1: float
    sigma2: float
    ratio: float
    area_px: float
    touches_border: bool
    contrast: float


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


def _hist(grey: FloatArray, mask: np.ndarray) -> FloatArray:
    """Histogram (256,) of the integer grey levels of ``grey`` where ``mask``."""
    u8 = np.ascontiguousarray(grey.astype(np.uint8))
    h = cv2.calcHist([u8], [0], mask.astype(np.uint8), [256], [0, 256])
    return h.ravel().astype(np.float64)


def _hist_median(hist: FloatArray) -> float:
    """Median grey level of a histogram (lower median)."""
    cum = np.cumsum(hist)
    return float(np.searchsorted(cum, 0.5 * cum[-1]))


def _abs_dev_median(hist: FloatArray, centre: float) -> float:
    """Median absolute deviation from ``centre`` of a grey-level histogram."""
    dev = np.abs(np.arange(256) - round(centre))
    folded = np.bincount(dev, weights=hist, minlength=256)
    cum = np.cumsum(folded)
    return float(np.searchsorted(cum, 0.5 * cum[-1]))


def _median(grey: FloatArray, mask: np.ndarray) -> float:
    """Median grey level of ``grey`` (integer-valued) where ``mask``."""
    return _hist_median(_hist(grey, mask))


def coverage_moments(
    grey: FloatArray,
    core: np.ndarray,
    support: np.ndarray,
    ring: np.ndarray,
    origin: tuple[int, int],
    config: LampDetectorConfig,
) -> tuple[FloatArray, FloatArray, FloatArray, float, float, float, float] | None:
    """Coverage-weighted centroid and second moments of one blob, with uncertainty.

    Args:
        grey: shape (h, w) float grey levels of a region of interest.
        core: shape (h, w) bool, the thresholded blob.
        support: shape (h, w) bool, where weights may be non-zero (dilated blob).
        ring: shape (h, w) bool, background ring.
        origin: ``(col, row)`` of ``grey[0, 0]`` in the image.
        config: detector settings (noise and floors).

    Returns:
        ``(centroid (2,), cov_centroid (2, 2), moments (3,) = (a, b, c), var_theta,
        theta, area, contrast)`` in pixels (see the module docstring for the formulas),
        or None when the blob has no contrast against its ring.
    """
    top = _median(grey, core)
    if ring.any():
        ring_hist = _hist(grey, ring)
        bg = _hist_median(ring_hist)
        sigma_n = 1.4826 * _abs_dev_median(ring_hist, bg)
    else:
        bg, sigma_n = float(grey[~core].min()) if (~core).any() else 0.0, 0.0
    sigma_n = max(sigma_n, config.noise_floor_grey)
    span = top - bg
    if span < config.min_blob_contrast_grey:
        return None
    w = np.clip((grey - bg) / span, 0.0, 1.0)
    w[~support] = 0.0
    rows, cols = np.nonzero(w)
    wv = w[rows, cols]
    total = float(wv.sum())
    xs = cols.astype(np.float64)
    ys = rows.astype(np.float64)
    cx = float(wv @ xs) / total
    cy = float(wv @ ys) / total
    dx = xs - cx
    dy = ys - cy
    a = float(wv @ (dx * dx)) / total
    b = float(wv @ (dx * dy)) / total
    c = float(wv @ (dy * dy)) / total
    theta = 0.5 * math.atan2(2.0 * b, a - c)
    # First-order noise propagation through the unclipped weights.
    free = (wv > 0.0) & (wv < 1.0)
    sigma_w2 = (sigma_n / span) ** 2
    fdx, fdy = dx[free], dy[free]
    cov_c = sigma_w2 * np.array([[fdx @ fdx, fdx @ fdy], [fdx @ fdy, fdy @ fdy]]) / (
        total * total
    ) + config.sigma_centroid_floor_px**2 * np.eye(2)
    x = a - c
    y = 2.0 * b
    den = x * x + y * y
    if den > 1e-18:
        dth = (x * (2.0 * fdx * fdy - 2.0 * b) - y * ((fdx * fdx - a) - (fdy * fdy - c))) / (
            2.0 * total * den
        )
        var_theta = sigma_w2 * float(dth @ dth) + config.sigma_axis_floor**2
    else:
        var_theta = math.inf
    centroid = np.array([cx + origin[0], cy + origin[1]])
    return centroid, cov_c, np.array([a, b, c]), var_theta, theta, total, span


def _measure_region(
    grey_roi: FloatArray,
    core: np.ndarray,
    others: np.ndarray,
    origin: tuple[int, int],
    touches_border: bool,
    config: LampDetectorConfig,
) -> BlobMoments | None:
    """Measure one region of a region of interest (see :func:`coverage_moments`)."""
    support = cv2.dilate(core.astype(np.uint8), disk(config.support_px)).astype(bool)
    outer = cv2.dilate(core.astype(np.uint8), disk(config.support_px + config.ring_px))
    ring = outer.astype(bool) & ~support & ~others
    support &= ~others
    res = coverage_moments(grey_roi, core, support, ring, origin, config)
    if res is None:
        return None
    centroid, cov_c, (a, b, c), var_theta, theta, area, span = res
    # Pixel-box term: the coverage of a pixel is spread uniformly over it.
    a += 1.0 / 12.0
    c += 1.0 / 12.0
    tr = a + c
    disc = math.sqrt(max((a - c) ** 2 + 4.0 * b * b, 0.0))
    lam1 = 0.5 * (tr + disc)
    lam2 = max(0.5 * (tr - disc), 1e-12)
    sigma1, sigma2 = math.sqrt(lam1), math.sqrt(lam2)
    return BlobMoments(
        centroid=centroid,
        cov_centroid=cov_c,
        cov_shape=np.array([[a, b], [b, c]]),
        theta=wrap_axis(theta),
        var_theta=var_theta,
        sigma1=sigma1,
        sigma2=sigma2,
        ratio=sigma1 / sigma2,
        area_px=area,
        touches_border=touches_border,
        contrast=span,
    )


def _split_glare(
    grey_roi: FloatArray, core: np.ndarray, k: float, config: LampDetectorConfig
) -> list[np.ndarray] | None:
    """Try to separate a glare-merged region by thresholding it higher.

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


def ceiling_jacobians(
    camera: PixelToCeiling, px: FloatArray, step: float
) -> tuple[FloatArray, FloatArray]:
    """Normalised ceiling coordinates and their pixel Jacobians, by central differences.

    Args:
        camera: the camera model (pixel -> ``m`` map).
        px: shape (N, 2) pixels ``(col, row)``.
        step: difference step, px.

    Returns:
        ``m`` shape (N, 2) and ``m_D_px`` shape (N, 2, 2).
    """
    n = px.shape[0]
    offs = np.array([[0, 0], [step, 0], [-step, 0], [0, step], [0, -step]], dtype=np.float64)
    pts = (px[:, None, :] + offs[None, :, :]).reshape(-1, 2)
    mm = np.asarray(camera.normalized_from_pixels(pts), dtype=np.float64).reshape(n, 5, 2)
    jac = np.empty((n, 2, 2))
    jac[:, :, 0] = (mm[:, 1] - mm[:, 2]) / (2 * step)
    jac[:, :, 1] = (mm[:, 3] - mm[:, 4]) / (2 * step)
    return mm[:, 0], jac


def to_observation(
    mom: BlobMoments, m: FloatArray, m_D_px: FloatArray, config: LampDetectorConfig
) -> LampObservation:
    """Convert a pixel-space blob measurement to a :class:`LampObservation`.

    Args:
        mom: the blob's pixel measurement.
        m: shape (2,), its centroid in normalised ceiling coordinates.
        m_D_px: shape (2, 2), Jacobian of ``m`` with respect to the pixel.
        config: detector settings (ratio threshold).

    Returns:
        The observation; ``axis`` is ``atan2`` of ``J e`` wrapped to
        ``(-pi/2, pi/2]``, ``var_axis = (det J / |J e|^2)^2 var_theta``.
    """
    cov_m = m_D_px @ mom.cov_centroid @ m_D_px.T
    axis: float | None = None
    var_axis = math.inf
    if mom.ratio > config.ratio_threshold:
        e = np.array([math.cos(mom.theta), math.sin(mom.theta)])
        je = m_D_px @ e
        axis = wrap_axis(math.atan2(je[1], je[0]))
        gain = float(np.linalg.det(m_D_px)) / float(je @ je)
        var_axis = gain * gain * mom.var_theta
    return LampObservation(
        m=np.asarray(m, dtype=np.float64),
        cov_m=cov_m,
        axis=axis,
        var_axis=var_axis,
        ratio=mom.ratio,
        area_px=mom.area_px,
        pixel=mom.centroid,
        landmark_id=None,
        touches_border=mom.touches_border,
    )


def to_observations(
    moments: list[BlobMoments], m: FloatArray, m_D_px: FloatArray, config: LampDetectorConfig
) -> tuple[LampObservation, ...]:
    """:func:`to_observation` of many blobs at once (the same formulas, batched).

    Args:
        moments: N pixel measurements.
        m: shape (N, 2), their centroids in normalised ceiling coordinates.
        m_D_px: shape (N, 2, 2), Jacobians of ``m`` with respect to the pixel.
        config: detector settings (ratio threshold).

    Returns:
        N observations, same order; equal to :func:`to_observation` up to
        floating-point rounding (the 2x2 determinant is expanded, not LU).
    """
    threshold = config.ratio_threshold
    cov_c = np.array([mo.cov_centroid for mo in moments]).tolist()
    # Per lamp on Python floats (a handful of 2x2 products: cheaper than numpy calls).
    covs: list[tuple[tuple[float, float], tuple[float, float]]] = []
    axes: list[float | None] = []
    var_axes: list[float] = []
    for mo, ((j00, j01), (j10, j11)), ((c00, c01), (c10, c11)) in zip(
        moments, m_D_px.tolist(), cov_c, strict=True
    ):
        # cov_m = J cov_c J^T
        t00, t01 = j00 * c00 + j01 * c10, j00 * c01 + j01 * c11
        t10, t11 = j10 * c00 + j11 * c10, j10 * c01 + j11 * c11
        covs.append(((t00 * j00 + t01 * j01, t00 * j10 + t01 * j11),
                     (t10 * j00 + t11 * j01, t10 * j10 + t11 * j11)))  # fmt: skip
        if mo.ratio > threshold:
            cos_t, sin_t = math.cos(mo.theta), math.sin(mo.theta)
            je0, je1 = j00 * cos_t + j01 * sin_t, j10 * cos_t + j11 * sin_t
            axes.append(wrap_axis(math.atan2(je1, je0)))
            gain = (j00 * j11 - j01 * j10) / (je0 * je0 + je1 * je1)
            var_axes.append(gain * gain * mo.var_theta)
        else:
            axes.append(None)
            var_axes.append(math.inf)
    m = np.asarray(m, dtype=np.float64)
    # (positional: the frozen dataclass's __init__ is about twice as fast)
    return tuple(
        LampObservation(mi, ci, ax, va, mo.ratio, mo.area_px, mo.centroid, None, mo.touches_border)
        for mo, mi, ci, ax, va in zip(moments, m, np.array(covs), axes, var_axes, strict=True)
    )


class _Reach(NamedTuple):
    """The pixels within reach of the labelled blobs of a box, gathered in one pass.

    One entry per pixel within ``support_px + ring_px`` of a blob, in
    row-major order of the box; labels are those of the label image given to
    :func:`_gather_reach` (0: none).

    Attributes:
        xy: shape (2, P) float ``(col, row)`` in the box, px.
        grey: shape (P,) uint8 grey level.
        sup: shape (P,) label of the support the pixel lies in (the label
            image's 8- or 16-bit dtype).
        ring: shape (P,) int label of the background ring the pixel lies in.
    """

    xy: FloatArray
    grey: IntArray
    sup: IntArray
    ring: IntArray


def _gather_reach(
    comp: np.ndarray,
    sub: tuple[int, int, int, int],
    origin: tuple[int, int],
    binary: np.ndarray,
    image: ImageU8,
    config: LampDetectorConfig,
) -> _Reach:
    """Support and ring labels of every pixel near a blob (one pass over the box).

    Support: the blob dilated by ``support_px``; ring: dilated by
    ``support_px + ring_px`` minus the support (elliptic disks). Where the
    dilations of two blobs overlap the larger label wins (grey dilation of the
    label image); a blob's own pixels keep its label, and other thresholded
    pixels belong to no support and no ring.

    Args:
        comp: shape (h, w) C-contiguous uint8 or uint16 labels of the blobs to
            measure (0 elsewhere), a crop of the image.
        sub: ``(row0, row1, col0, col1)``, the box to work in, in ``comp``.
        origin: ``(col, row)`` of ``comp[0, 0]`` in the image.
        binary: shape (H, W) uint8, non-zero where thresholded (measured blobs or not).
        image: shape (H, W) uint8 grey levels.
        config: detector settings (``support_px``, ``ring_px``).

    Returns:
        The gathered pixels, coordinates in the box.
    """
    r0, r1, c0, c1 = sub
    region = comp[r0:r1, c0:c1]
    outer = dilate_disk(region, config.support_px + config.ring_px).ravel()
    near = dilate_disk(region, config.support_px).ravel()
    # Flat nonzero of a flat boolean array: about 10x faster than the 2-D np.nonzero.
    idx = (outer > 0).nonzero()[0]
    rows, cols = np.divmod(idx, c1 - c0)
    # Flat indices in the crop and in the image (no copies of the box views).
    in_comp = idx + rows * (comp.shape[1] - (c1 - c0)) + (r0 * comp.shape[1] + c0)
    width = image.shape[1]
    in_image = idx + rows * (width - (c1 - c0)) + ((r0 + origin[1]) * width + c0 + origin[0])
    free = binary.reshape(-1).take(in_image) == 0
    near_v = near.take(idx)
    sup = np.where(free, near_v, comp.reshape(-1).take(in_comp))
    ring = np.where(free & (near_v == 0), outer.take(idx), 0).astype(np.intp)
    xy = np.array([cols, rows], dtype=np.float64)
    return _Reach(xy, image.reshape(-1).take(in_image), sup, ring)


def _shape_checks(
    lab: IntArray,
    x: FloatArray,
    y: FloatArray,
    grey: IntArray,
    n: int,
    peak: float,
    config: LampDetectorConfig,
) -> tuple[BoolArray, BoolArray, FloatArray]:
    """Vectorised per-blob checks on the thresholded regions.

    Args:
        lab: shape (P,) label ``1..n-1`` of each candidate-blob pixel.
        x: shape (P,) its column, px.
        y: shape (P,) its row, px.
        grey: shape (P,) its grey level.
        n: number of labels (one more than the largest).
        peak: the image's lamp peak level (:func:`peak_level`).
        config: detector settings.

    Returns:
        ``(too_dim (n,), merged (n,), top (n,))``: too dim to be a light
        source (``max_peak_drop_grey``), glare-merger candidates (fill below
        ``min_fill``), and each blob's level (lower median of its grey levels).
        Row 0 is meaningless.
    """
    dist = label_levels(lab, grey, n)
    count = dist.count
    groups = group_by_label(lab, n, count)
    xg, yg = x.take(groups.order), y.take(groups.order)
    sums = label_sums(groups, np.array([xg, yg, xg * xg, xg * yg, yg * yg]), n)
    # Lamp level (lower median), fifth-brightest and brightest level of each blob.
    fifth_rank = count - np.minimum(5, np.maximum(count, 1))
    levels = levels_at(dist, np.array([lower_median_rank(count), fifth_rank, count - 1]))
    too_dim, merged = [False] * n, [False] * n
    # Per blob on Python floats (a handful of blobs: cheaper than thirty numpy calls).
    rows = zip(count.tolist(), *sums.tolist(), *levels[1:].tolist(), strict=True)
    for j, (cnt, sx, sy, sxx, sxy, syy, fifth, brightest) in enumerate(rows):
        if j == 0:
            continue
        s0 = float(max(cnt, 1))
        cx, cy = sx / s0, sy / s0
        a = sxx / s0 - cx * cx + 1.0 / 12.0
        b = sxy / s0 - cx * cy
        c = syy / s0 - cy * cy + 1.0 / 12.0
        merged[j] = s0 / (4.0 * math.pi * math.sqrt(max(a * c - b * b, 1e-12))) < config.min_fill
        if config.max_peak_drop_grey is not None:
            # Thin blobs (area sampling dims them) are judged by their brightest pixel.
            lam_min = 0.5 * (a + c - math.sqrt(max((a - c) * (a - c) + 4 * b * b, 0.0)))
            if math.sqrt(12.0 * max(lam_min, 0.0)) < config.thin_width_px:
                too_dim[j] = brightest < peak - config.max_peak_drop_thin_grey
            else:
                too_dim[j] = fifth < peak - config.max_peak_drop_grey
    return np.array(too_dim), np.array(merged), levels[0].astype(np.float64)


def _measure_labels(
    reach: _Reach,
    top: FloatArray,
    ids: IntArray,
    border: BoolArray,
    default_bg: Callable[[], float],
    config: LampDetectorConfig,
    origin: tuple[int, int],
) -> list[BlobMoments | None]:
    """Coverage moments of many blobs at once (see the module docstring).

    The same computation as :func:`coverage_moments`, vectorised over blobs with
    per-label sums over the gathered pixels (:func:`label_sums`).

    Args:
        reach: the pixels near the blobs to measure (:func:`_gather_reach`).
        top: shape (n,) each blob's level (median grey level inside).
        ids: shape (B,) the labels to measure, increasing.
        border: shape (n,) bool, blob touches the image border.
        default_bg: background level of a blob without any ring pixel.
        config: detector settings.
        origin: ``(col, row)`` of the box's ``[0, 0]`` in the full image.

    Returns:
        One :class:`BlobMoments` (or None: no contrast) per label of ``ids``,
        centroids in full-image pixels.
    """
    n = top.size
    # Background (median of the ring) and its spread (1.4826 MAD) per blob, from
    # the level distributions of all gathered pixels by ring label (label 0: the
    # pixels in no ring, never used; it always has pixels: the supports).
    ring = reach.ring
    dist = label_levels(ring, reach.grey, n)
    has_ring = dist.count > 0
    median_rank = lower_median_rank(dist.count)
    bg_level = levels_at(dist, median_rank)
    dev = np.abs(reach.grey - bg_level.take(ring))
    mad = levels_at(label_levels(ring, dev, n), median_rank).astype(np.float64)
    bg = bg_level.astype(np.float64)
    if not has_ring.take(ids).all():
        bg = np.where(has_ring, bg, default_bg())
        mad = np.where(has_ring, mad, 0.0)
    sigma_n = np.maximum(1.4826 * mad, config.noise_floor_grey)
    span = top - bg
    ok = span >= config.min_blob_contrast_grey
    span_safe = np.where(ok, span, 1.0)
    # Coverage weights on the support pixels, grouped by label.
    sup = (reach.sup > 0).nonzero()[0]
    groups = group_by_label(reach.sup.take(sup), n)
    sup = sup.take(groups.order)
    lab = reach.sup.take(sup)
    xy = reach.xy.take(sup, axis=1)
    level = np.array([bg, span_safe]).take(lab, axis=1)
    wv = ((reach.grey.take(sup) - level[0]) / level[1]).clip(0.0, 1.0)
    wxy = wv * xy
    s0, sx, sy = label_sums(groups, np.array([wv, wxy[0], wxy[1]]), n)
    s0 = np.maximum(s0, 1e-12)
    cx, cy = sx / s0, sy / s0
    d = xy - np.array([cx, cy]).take(lab, axis=1)
    q = np.empty((3, d.shape[1]))  # dx^2, dx dy, dy^2 (no fancy-indexed copies of d)
    np.multiply(d[0], d, out=q[:2])
    np.multiply(d[1], d[1], out=q[2])
    free = ((wv > 0.0) & (wv < 1.0)).astype(np.float64)
    sums = label_sums(groups, np.concatenate([wv * q, free * q]), n)
    a, b, c = sums[:3] / s0
    fxx, fxy, fyy = sums[3:]
    xx, yy = a - c, 2.0 * b
    px, pb, py, pa, pc = np.array([xx, b, yy, a, c]).take(lab, axis=1)
    num = px * (2.0 * q[1] - 2.0 * pb) - py * ((q[0] - pa) - (q[2] - pc))
    (dth2,) = label_sums(groups, (free * num * num)[None, :], n)
    # The closing formulas per blob on Python floats (a handful of blobs: cheaper
    # than another twenty numpy calls); the blobs' small arrays are built at once.
    table = np.array([s0, cx, cy, a, b, c, fxx, fxy, fyy, dth2, sigma_n, span])
    closed = [
        _close_blob(row, config) if good else None
        for row, good in zip(table.take(ids, axis=1).T.tolist(), ok.take(ids).tolist(), strict=True)
    ]
    done = [cl for cl in closed if cl is not None]
    if not done:
        return [None] * len(closed)
    ox, oy = origin
    centroids = np.array([(cl[0] + ox, cl[1] + oy) for cl in done])
    covs = np.array([cl[2] for cl in done])
    shapes = np.array([cl[3] for cl in done])
    touches = border.take(ids).tolist()
    out: list[BlobMoments | None] = []
    j = 0
    for cl, edge in zip(closed, touches, strict=True):
        if cl is None:
            out.append(None)
            continue
        # (positional: the frozen dataclass's __init__ is about twice as fast)
        out.append(BlobMoments(centroids[j], covs[j], shapes[j], *cl[4:10], edge, cl[10]))
        j += 1
    return out


def _close_blob(
    row: list[float], config: LampDetectorConfig
) -> tuple[float, float, tuple, tuple, float, float, float, float, float, float, float]:
    """One blob's measurement from its coverage sums (the end of :func:`coverage_moments`).

    Args:
        row: ``[W, cx, cy, a, b, c, free_xx, free_xy, free_yy, dth_sum, sigma_n, span]``:
            ``W = sum w_i`` (coverage area, px); the weighted centroid in the
            box, px; ``(a, b, c) = (mu20, mu11, mu02) / W``, px^2 (eqs. 2-4);
            ``sum (d_x^2, d_x d_y, d_y^2)`` over the unclipped pixels
            (``0 < w_i < 1``), px^2; ``sum num_i^2`` over them
            (``dtheta/dw_i = num_i / (2 W (x^2 + y^2))``); the grey-level noise
            sigma; the lamp level minus background (``top - bg``), grey levels.
        config: detector settings (floors).

    Returns:
        ``(cx, cy, cov_centroid 2x2 rows, cov_shape 2x2 rows, theta, var_theta,
        sigma1, sigma2, ratio, area_px, contrast)``, the fields of
        :class:`BlobMoments` (eqs. 2-7 with the pixel-box term; ``theta``
        (eq. 5) wrapped to ``(-pi/2, pi/2]`` as :func:`lampsam.angles.wrap_axis`).
    """
    w, cx, cy, a, b, c, free_xx, free_xy, free_yy, dth_sum, sigma_n, span = row
    sigma_w = sigma_n / span
    sigma_w2 = sigma_w * sigma_w
    scale = sigma_w2 / (w * w)
    floor2 = config.sigma_centroid_floor_px**2
    cov_xy = scale * free_xy
    cov_c = ((scale * free_xx + floor2, cov_xy), (cov_xy, scale * free_yy + floor2))
    xx, yy = a - c, 2.0 * b
    den = xx * xx + yy * yy
    if den > 1e-18:
        norm = 2.0 * w * den
        var_theta = sigma_w2 * (dth_sum / (norm * norm)) + config.sigma_axis_floor**2
    else:
        var_theta = math.inf
    theta = wrap_axis(0.5 * math.atan2(yy, xx))
    # Pixel-box term: the coverage of a pixel is spread uniformly over it.
    a12, c12 = a + 1.0 / 12.0, c + 1.0 / 12.0
    disc = math.sqrt(max((a12 - c12) * (a12 - c12) + 4.0 * b * b, 0.0))
    lam1 = 0.5 * (a12 + c12 + disc)
    lam2 = max(0.5 * (a12 + c12 - disc), 1e-12)
    cov_shape = ((a12, b), (b, c12))
    sigma1, sigma2 = math.sqrt(lam1), math.sqrt(lam2)
    return (cx, cy, cov_c, cov_shape, theta, var_theta, sigma1, sigma2,
            math.sqrt(lam1 / lam2), w, span)  # fmt: skip


def measure_blobs(
    image: ImageU8, config: LampDetectorConfig
) -> tuple[list[BlobMoments], float | None, BoolArray, int]:
    """Threshold, label and measure the lamp blobs of an image, in pixels.

    Size, dimness and glare checks and the moments of ordinary blobs are
    vectorised over blobs; only glare-merger candidates go through the
    per-region path (:func:`_split_glare`, :func:`_measure_region`).

    Everything after the threshold works inside the bounding box of the
    thresholded pixels, grown by the reach of a blob (support + ring + 1 px).
    The box starts at even coordinates: OpenCV labels 2x2 blocks in raster
    order, so the blobs are numbered (and listed) as on the whole image.

    Args:
        image: shape (H, W) uint8 grey image.
        config: detector settings.

    Returns:
        ``(moments, threshold, mask (H, W) bool, n_rejected)``; moments in label order.
    """
    h, w = image.shape
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
    too_dim, merged, top = _shape_checks(
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
        reach = _gather_reach(comp, sub, (bx0, by0), binary, image, config)
        res = _measure_labels(reach, top, ids, border, default_bg, config, (mx0, my0))
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
        split = _split_glare(grey, core, k, config)
        if split is None:
            log.debug("rejected a glare-merged region at (%d, %d)", c0, r0)
            n_rejected += 1
            continue
        for reg in split:
            others_reg = others | (core & ~cv2.dilate(reg.astype(np.uint8), disk(1)).astype(bool))
            mom = _measure_region(
                grey, reg, others_reg & ~reg, (c0, r0), bool(border[j + 1]), config
            )
            if mom is None:
                n_rejected += 1
                continue
            out.append(mom)
            mask[r0:r1, c0:c1] |= reg
    return out, k, mask, n_rejected


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
    moments, k, mask, n_rej = measure_blobs(image, config)
    if not moments:
        return LampDetections((), (), k, mask, n_rej)
    px = np.array([mo.centroid for mo in moments])
    m, jac = ceiling_jacobians(camera, px, config.jacobian_step_px)
    return LampDetections(to_observations(moments, m, jac, config), tuple(moments), k, mask, n_rej)
