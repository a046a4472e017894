"""Coverage-weighted moments of lamp blobs, with their uncertainty (paper 1, eqs. 2-7).

Per blob, the centroid and the central second moments ``a = mu20``,
``b = mu11``, ``c = mu02`` (eqs. 2-4), the long-axis angle
``theta = 0.5 atan2(2b, a - c)`` (eq. 5 with the quadrant kept, DESIGN.md
sec. 1), the axis spreads from the covariance eigenvalues (eq. 6) and
``R_ori = sigma1 / sigma2`` (eq. 7). Pixels are ``(col, row)``, moments px^2.

Sub-pixel accuracy: the moments are not taken over the binary region but over
*coverage weights* ``w = clip((I - bg) / (top - bg), 0, 1)`` inside the region
dilated by ``support_px``, where ``bg`` is the median grey level of a ring
around the blob and ``top`` the median inside it. On an anti-aliased (area
sampled) edge the grey level is ``bg + coverage (top - bg)``, so ``w`` is the
fraction of the pixel the lamp covers and the weighted centroid is the true
area centroid. A pixel's coverage is spread uniformly over it, so the shape
moments gain the pixel-box term 1/12 px^2. A lamp above full scale breaks the
linear reading at its edges: :mod:`lampsam.frontend.saturated_edges` (all-blob path).

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

Two implementations of the same formulas: :func:`coverage_moments` /
:func:`measure_region` for one region of interest (glare splits), and
:func:`measure_labels` for all the blobs of an image at once (per-label sums,
:mod:`lampsam.frontend.label_stats`, over the pixels near the blobs that
:mod:`lampsam.frontend.blob_reach` gathers), whose closing formulas run per blob on
Python floats (a handful of blobs: cheaper than numpy calls on tiny arrays).
:func:`shape_checks` holds the per-blob tests made before measuring (too dim
for a light source, glare-merger candidate).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import cv2
import numpy as np

from lampsam.angles import wrap_axis
from lampsam.arrays import BoolArray, FloatArray, IntArray
from lampsam.frontend.blob_reach import Reach
from lampsam.frontend.ceiling_grid import (
    CeilingGrid,
    CeilingMoments,
    label_ceiling_moments,
    region_ceiling_moments,
)
from lampsam.frontend.dilation import disk
from lampsam.frontend.label_stats import (
    group_by_label,
    label_levels,
    label_sums,
    levels_at,
    lower_median_rank,
)
from lampsam.frontend.lamp_config import LampDetectorConfig
from lampsam.frontend.saturated_edges import FULL_SCALE, label_edge_weights


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
        ceiling: the same coverage's moments taken in normalised ceiling
            coordinates (:mod:`lampsam.frontend.ceiling_grid`) when measured with
            the camera's table, else None (the pixel -> ``m`` map is affine).
        clip_coverage: ``c_s`` of a saturated blob (:mod:`lampsam.frontend.saturated_edges`),
            NaN when unsaturated or not measured.
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
    ceiling: CeilingMoments | None = None
    clip_coverage: float = math.nan


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
) -> tuple[FloatArray, FloatArray, FloatArray, float, float, float, float, FloatArray] | None:
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
        theta, area, contrast, weights (h, w))`` in pixels (see the module docstring
        for the formulas; ``weights``: the coverage, 0 off the support), or None
        when the blob has no contrast against its ring.
    """
    top = _median(grey, core)
    if ring.any():
        ring_hist = _hist(grey, ring)
        bg = _hist_median(ring_hist)
        sigma_n = 1.4826 * _abs_dev_median(ring_hist, bg)
    else:
        bg, sigma_n = float(grey[~core].min()) if (~core).any() else 0.0, 0.0
    span = top - bg
    if span < config.min_blob_contrast_grey:
        return None
    sigma_n = max(sigma_n, config.noise_floor_grey)
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
    return centroid, cov_c, np.array([a, b, c]), var_theta, theta, total, span, w


def measure_region(
    grey_roi: FloatArray,
    core: np.ndarray,
    others: np.ndarray,
    origin: tuple[int, int],
    touches_border: bool,
    config: LampDetectorConfig,
    grid: CeilingGrid | None = None,
) -> BlobMoments | None:
    """Measure one region of a region of interest (see :func:`coverage_moments`).

    With ``grid`` (a camera's table, not affine) the moments are also taken on
    the ceiling (:attr:`BlobMoments.ceiling`); None when that fails (weight on
    a pixel off the ceiling).
    """
    support = cv2.dilate(core.astype(np.uint8), disk(config.support_px)).astype(bool)
    outer = cv2.dilate(core.astype(np.uint8), disk(config.support_px + config.ring_px))
    ring = outer.astype(bool) & ~support & ~others
    support &= ~others
    res = coverage_moments(grey_roi, core, support, ring, origin, config)
    if res is None:
        return None
    centroid, cov_c, (a, b, c), var_theta, theta, area, span, weights = res
    on_ceiling = None
    if grid is not None and not grid.affine:
        rows, cols = np.nonzero(weights)
        on_ceiling = region_ceiling_moments(
            grid, rows + origin[1], cols + origin[0], weights[rows, cols]
        )
        if on_ceiling is None:
            return None
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
        ceiling=on_ceiling,
    )


def shape_checks(
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
    count = dist.counts
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
        lam_min = 0.5 * (a + c - math.sqrt(max((a - c) * (a - c) + 4 * b * b, 0.0)))
        thin = math.sqrt(12.0 * max(lam_min, 0.0)) < config.thin_width_px
        # A glare merger (two lamps joined by a halo) is wide; a thin blob's low fill is
        # the staircase of an oblique line a few pixels wide (distant lamps seen edge-on).
        fill = s0 / (4.0 * math.pi * math.sqrt(max(a * c - b * b, 1e-12)))
        merged[j] = not thin and fill < config.min_fill
        if config.max_peak_drop_grey is not None:
            # Thin blobs are judged by their brightest pixel (the others are edge pixels).
            # A thin line (a lamp seen edge-on) has no pixel wholly inside the lamp, so
            # area sampling dims it: the wider margin. A blob small both ways has few
            # pixels, but a light source still saturates its centre pixel: the usual
            # margin (a white detector 2-3 px across in a 160x120 frame is not a lamp).
            if thin and math.sqrt(12.0 * max(a + c - lam_min, 0.0)) >= config.thin_min_length_px:
                too_dim[j] = brightest < peak - config.max_peak_drop_thin_grey
            elif thin:
                too_dim[j] = brightest < peak - config.max_peak_drop_grey
            else:
                too_dim[j] = fifth < peak - config.max_peak_drop_grey
    return np.array(too_dim), np.array(merged), levels[0].astype(np.float64)


def measure_labels(
    reach: Reach,
    top: FloatArray,
    ids: IntArray,
    border: BoolArray,
    default_bg: Callable[[], float],
    config: LampDetectorConfig,
    origin: tuple[int, int],
    grid: CeilingGrid | None = None,
) -> list[BlobMoments | None]:
    """Coverage moments of many blobs at once (see the module docstring).

    The same computation as :func:`coverage_moments`, vectorised over blobs with
    per-label sums over the gathered pixels (:func:`label_sums`).

    Args:
        reach: the pixels near the blobs to measure
            (:func:`lampsam.frontend.blob_reach.gather_reach`).
        top: shape (n,) each blob's level (median grey level inside).
        ids: shape (B,) the labels to measure, increasing.
        border: shape (n,) bool, blob touches the image border.
        default_bg: background level of a blob without any ring pixel.
        config: detector settings.
        origin: ``(col, row)`` of the box's ``[0, 0]`` in the full image.
        grid: the camera's table (:mod:`lampsam.frontend.ceiling_grid`): the
            moments are also taken on the ceiling when it is not affine.

    Returns:
        One :class:`BlobMoments` (or None: no contrast, or weight on a pixel
        off the ceiling) per label of ``ids``, centroids in full-image pixels.
    """
    n = top.size
    # Background (median of the ring) and its spread (1.4826 MAD) per blob, from
    # the level distributions of all gathered pixels by ring label (label 0: the
    # pixels in no ring, never used; it always has pixels: the supports).
    ring = reach.ring
    dist = label_levels(ring, reach.grey, n)
    has_ring = dist.counts > 0
    median_rank = lower_median_rank(dist.counts)
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
    if config.max_crowding is not None:
        # A lamp hangs in front of a plain ceiling; a pane of a skylight or window is
        # ringed by glazing bars with the neighbouring panes just beyond them.
        crowd = np.bincount(reach.crowd, minlength=n).astype(np.float64)
        crowd[0] = 0.0
        ok &= crowd <= config.max_crowding * (crowd + dist.counts)
    span_safe = np.where(ok, span, 1.0)
    # Coverage weights on the support pixels, grouped by label.
    sup = (reach.sup > 0).nonzero()[0]
    groups = group_by_label(reach.sup.take(sup), n)
    sup = sup.take(groups.order)
    lab = reach.sup.take(sup)
    xy = reach.xy.take(sup, axis=1)
    level = np.array([bg, span_safe]).take(lab, axis=1)
    grey_sup = reach.grey.take(sup)
    wv = ((grey_sup - level[0]) / level[1]).clip(0.0, 1.0)
    free = ((wv > 0.0) & (wv < 1.0)).astype(np.float64)  # the pixels carrying the noise
    clip_cov = np.full(n, np.nan)
    if config.saturated_edges or config.edge_phase_noise:  # (frontend.saturated_edges)
        wv, clip_cov = label_edge_weights(
            wv, grey_sup, xy, lab, (top >= FULL_SCALE - 1) & ok, bg, 3.0 * sigma_n / span_safe,
            config.saturated_edge_min_steps, apply=config.saturated_edges)
    wxy = wv * xy
    s0, sx, sy = label_sums(groups, np.array([wv, wxy[0], wxy[1]]), n)
    s0 = np.maximum(s0, 1e-12)
    cx, cy = sx / s0, sy / s0
    d = xy - np.array([cx, cy]).take(lab, axis=1)
    q = np.empty((3, d.shape[1]))  # dx^2, dx dy, dy^2 (no fancy-indexed copies of d)
    np.multiply(d[0], d, out=q[:2])
    np.multiply(d[1], d[1], out=q[2])
    sums = label_sums(groups, np.concatenate([wv * q, free * q]), n)
    a, b, c = sums[:3] / s0
    fxx, fxy, fyy = sums[3:]
    xx, yy = a - c, 2.0 * b
    px, pb, py, pa, pc = np.array([xx, b, yy, a, c]).take(lab, axis=1)
    num = px * (2.0 * q[1] - 2.0 * pb) - py * ((q[0] - pa) - (q[2] - pc))
    (dth2,) = label_sums(groups, (free * num * num)[None, :], n)
    on_ceiling: list[CeilingMoments | None] = [None] * ids.size
    if grid is not None and not grid.affine:
        mc, mcov, marea, m_ok = label_ceiling_moments(
            grid, groups, lab, reach.flat.take(sup), wv, n
        )
        ok &= m_ok
        on_ceiling = [CeilingMoments(mc[i], mcov[i], float(marea[i])) for i in ids.tolist()]
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
    for cl, edge, on_c, cs in zip(closed, touches, on_ceiling, clip_cov.take(ids).tolist(),
                                  strict=True):
        if cl is None:
            out.append(None)
            continue
        # (positional: the frozen dataclass's __init__ is about twice as fast)
        out.append(BlobMoments(centroids[j], covs[j], shapes[j], *cl[4:10], edge, cl[10], on_c,
                               cs))
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
