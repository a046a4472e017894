"""FAST corners on the ceiling and normalised cross-correlation (NCC) matching.

Paper 1, sec. II: corners are FAST features; association is a gate on the
predicted position (Mahalanobis, eqs. 19-20) followed by NCC of image patches
among the gated candidates (DESIGN.md sec. 1).

* Detection: OpenCV's FAST with its non-maximum suppression, never within
  ``lamp_margin_px`` of the lamp mask (3x3 L2 distance; glare edges move with
  exposure and are not ceiling structure; tested at the keypoints,
  :func:`_near_mask`), then a minimum spacing: a corner survives only
  if it has the largest response within ``min_spacing_px`` (a second, wider
  non-maximum suppression: all pairs for a few points, a dilation of the
  rank image by the disk for many, :func:`strongest_spaced_pixels`), then the
  ``max_corners`` strongest are kept and refined to sub-pixel with
  ``cv2.cornerSubPix`` (moves of more than ``subpix_win`` px are undone).
* Patches: ``P x P`` grey levels centred on the corner, stored zero-mean and
  unit-norm so that NCC of two patches is their dot product. Corners closer
  than ``P // 2`` to the border or on a flat patch are dropped.
* Uncertainty: isotropic ``sigma_px`` in pixels, mapped to normalised ceiling
  coordinates with the local Jacobian of the camera model.
"""

from __future__ import annotations

import functools
import logging
import math
import operator
from dataclasses import dataclass

import cv2
import numpy as np
from scipy.spatial import cKDTree

from lampsam.arrays import BoolArray, FloatArray, ImageU8, IntArray
from lampsam.frontend.ceiling_coords import PixelToCeiling, ceiling_jacobians
from lampsam.frontend.measurements import CornerObservation

log = logging.getLogger(__name__)

_RESPONSE = operator.attrgetter("response")  # of a cv2.KeyPoint


@dataclass(frozen=True)
class CornerDetectorConfig:
    """Settings of the corner detector.

    Attributes:
        fast_threshold: FAST intensity threshold, grey levels (default 20).
        min_spacing_px: minimum distance between kept corners (default 8 px).
        max_corners: keep at most this many, strongest first (default 150).
        lamp_margin_px: no corner within this distance of a lamp blob (default 4 px).
        patch_size: ``P``, odd, side of the NCC patch (default 11 px).
        subpix_win: half window of ``cv2.cornerSubPix`` refinement (default 3;
            0 disables). FAST fires 1-2 px inside a corner; the gradient-based
            refinement moves it to the vertex (0.2 px RMS on rendered corners).
        min_patch_std_grey: patches flatter than this are dropped (default 3).
        sigma_px: position noise of a corner, px (default 0.5).
        jacobian_step_px: central-difference step for ``dm/dpx`` (default 0.5 px).
    """

    fast_threshold: int = 20
    min_spacing_px: int = 8
    max_corners: int = 150
    lamp_margin_px: int = 4
    patch_size: int = 11
    subpix_win: int = 3
    min_patch_std_grey: float = 3.0
    sigma_px: float = 0.5
    jacobian_step_px: float = 0.5


_DEFAULT_CONFIG = CornerDetectorConfig()  # frozen: one shared instance


@dataclass(frozen=True)
class CornerDetections:
    """Corners of one image in array form (for matching and drawing).

    Attributes:
        pixels: shape (N, 2) float ``(col, row)``.
        scores: shape (N,) FAST responses.
        patches: shape (N, P, P) float32, zero-mean unit-norm.
    """

    pixels: FloatArray
    scores: FloatArray
    patches: np.ndarray


# Spacing by all pairs up to this many points, by a k-d tree above (the measured
# crossover; all-pairs arrays past it also outgrow the cache).
_BRUTE_FORCE_MAX = 128


def spacing_nms(pts: FloatArray, score: FloatArray, spacing: float) -> BoolArray:
    """Keep the points that are the strongest within ``spacing`` of themselves.

    A point is dropped when another point within ``spacing`` has a higher
    score (ties: the lower index wins). Vectorised and independent of the
    image size (:func:`strongest_spaced`).

    Args:
        pts: shape (N, 2) positions, px.
        score: shape (N,) scores.
        spacing: minimum distance, px.

    Returns:
        shape (N,) bool mask of the kept points.
    """
    keep = np.zeros(pts.shape[0], dtype=bool)
    keep[strongest_spaced(pts, score, spacing)] = True
    return keep


def strongest_spaced(pts: FloatArray, score: FloatArray, spacing: float) -> IntArray:
    """Indices of the points kept by :func:`spacing_nms`, strongest first.

    In rank order (score descending, ties by index: a stable sort), a point is
    dropped exactly when an earlier-ranked point lies within ``spacing``. Up to
    ``_BRUTE_FORCE_MAX`` points every pair is tested at once (cheaper than
    building a k-d tree for a few dozen); above, the pairs come from a k-d tree.

    Args:
        pts: shape (N, 2) positions, px.
        score: shape (N,) scores.
        spacing: minimum distance, px (``<= 0``: every point is kept).

    Returns:
        shape (K,) int indices into ``pts``, by decreasing score (stable).
    """
    rank = np.argsort(-score, kind="stable")
    n = rank.shape[0]
    if n < 2 or spacing <= 0:
        return rank
    ranked = pts.take(rank, axis=0)
    if n <= _BRUTE_FORCE_MAX:
        x, y = ranked[:, 0], ranked[:, 1]
        dx, dy = x[:, None] - x, y[:, None] - y
        # Row i is beaten by an earlier-ranked column j < i within the spacing: its
        # first close column (the diagonal is always close) comes before i.
        beaten = (dx * dx + dy * dy <= spacing * spacing).argmax(axis=1) < np.arange(n)
    else:
        pairs = cKDTree(ranked).query_pairs(spacing, output_type="ndarray")
        beaten = np.zeros(n, dtype=bool)
        beaten[pairs.max(axis=1)] = True  # the later-ranked point of each pair
    return rank.compress(~beaten)


@functools.lru_cache(maxsize=8)
def _disk_rects(spacing: float) -> tuple[np.ndarray, ...]:
    """Rectangles whose union is the disk of integer offsets ``dx^2 + dy^2 <= spacing^2``.

    One per step of the disk's staircase: rows ``|dy| <= d`` with the half-width
    of row ``d``. A dilation by each (OpenCV filters rectangles separably) and
    the maximum of the results is a dilation by the disk.
    """
    s2 = float(spacing) * float(spacing)
    r = int(math.floor(float(spacing)))
    half = []
    for dy in range(r + 1):
        w = int(math.floor(math.sqrt(max(s2 - dy * dy, 0.0))))
        while (w + 1) * (w + 1) + dy * dy <= s2:
            w += 1
        while w > 0 and w * w + dy * dy > s2:
            w -= 1
        half.append(w)
    return tuple(
        np.ones((2 * d + 1, 2 * half[d] + 1), np.uint8)
        for d in range(r + 1)
        if d == r or half[d + 1] < half[d]
    )


def strongest_spaced_pixels(
    ij: IntArray, score: FloatArray, spacing: float, shape: tuple[int, int]
) -> IntArray | None:
    """:func:`strongest_spaced` for distinct integer pixels, by dilating a rank image.

    Each pixel gets its priority (``N`` for the strongest down to 1); after a
    grey dilation by the disk of radius ``spacing``, a point is beaten exactly
    when the dilated priority at it exceeds its own. The cost is a few
    separable passes over the image, whatever the number of points (a k-d
    tree's pairs grow with their density).

    Args:
        ij: shape (N, 2) int pixels ``(col, row)`` inside an image of ``shape``.
        score: shape (N,) scores.
        spacing: minimum distance, px.
        shape: ``(H, W)`` of the image.

    Returns:
        As :func:`strongest_spaced`, or None when two points share a pixel.
    """
    rank = np.argsort(-score, kind="stable")
    n = rank.shape[0]
    if n < 2 or spacing <= 0:
        return rank
    cols, rows = ij.take(rank, axis=0).T
    priority = np.zeros(shape, np.uint16 if n < 65535 else np.float32)
    priority[rows, cols] = np.arange(n, 0, -1)
    if cv2.countNonZero(priority) != n:
        return None
    near = None
    for rect in _disk_rects(spacing):
        grown = cv2.dilate(priority, rect)
        near = grown if near is None else np.maximum(near, grown, out=near)
    assert near is not None
    beaten = near[rows, cols] > priority[rows, cols]
    return rank.compress(~beaten)


@functools.lru_cache(maxsize=8)
def margin_kernel(margin: float) -> np.ndarray:
    """Footprint of the pixels within ``margin`` of a pixel, by OpenCV's 3x3 L2 distance.

    Built from ``cv2.distanceTransform(..., cv2.DIST_L2, 3)`` of a single seed
    pixel, so that dilating a mask with it marks exactly the pixels whose
    distance transform to the mask is ``<= margin`` (the chamfer distance of a
    set is the minimum of its pixels' distances).

    Args:
        margin: distance, px (``>= 0``).

    Returns:
        shape (2r + 1, 2r + 1) uint8, 1 inside the footprint.
    """
    r = int(math.ceil(margin / 0.9)) + 1  # the 3x3 L2 step is 0.955 px per pixel or more
    probe = np.ones((2 * r + 1, 2 * r + 1), np.uint8)
    probe[r, r] = 0
    return (cv2.distanceTransform(probe, cv2.DIST_L2, 3) <= margin).astype(np.uint8)


def _empty(p: int) -> CornerDetections:
    """No corners: (0, 2) pixels, (0,) scores, (0, p, p) patches."""
    return CornerDetections(np.zeros((0, 2)), np.zeros(0), np.zeros((0, p, p), np.float32))


@functools.lru_cache(maxsize=16)
def _window_offsets(size: int, width: int) -> IntArray:
    """Flat-index offsets of a centred ``size x size`` window in a row of ``width`` pixels, (P*P,)."""
    off = np.arange(-(size // 2), size // 2 + 1)
    return (off[:, None] * width + off[None, :]).reshape(-1)


def _windows(image: ImageU8, pixels: IntArray, size: int) -> np.ndarray:
    """Raw ``size x size`` grey windows centred on integer pixels, flat: shape (N, P*P) float32.

    One flat gather (no strided view of the whole image, no 2-D fancy indexing).
    """
    width = image.shape[1]
    base = pixels[:, 1] * width + pixels[:, 0]
    return image.reshape(-1).take(base[:, None] + _window_offsets(size, width)).astype(np.float32)


def _centre_patches(raw: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Zero-mean copies of flat (N, P*P) float32 patches and their norms, shape (N,) float32.

    (Reductions along one contiguous axis: cheaper than over two, same sums.)
    """
    patches = raw - raw.mean(axis=1, keepdims=True)
    return patches, np.sqrt((patches * patches).sum(axis=1))


def _normalise_patches(raw: np.ndarray, size: int) -> np.ndarray:
    """Zero-mean, unit-norm copies of flat (N, P*P) float32 patches, shape (N, P, P) (flat ones all zero)."""
    patches, norms = _centre_patches(raw)
    nn = norms[:, None]
    out = np.divide(patches, nn, out=np.zeros_like(patches), where=nn > 0)
    return out.reshape(-1, size, size)


@functools.lru_cache(maxsize=8)
def _margin_offsets(margin: float) -> tuple[IntArray, int]:
    """Offsets ``(d_col, d_row)`` of the :func:`margin_kernel` footprint, shape (K, 2), and their reach."""
    kernel = margin_kernel(margin)
    r = kernel.shape[0] // 2
    rows, cols = np.nonzero(kernel)
    offsets = np.column_stack([cols - r, rows - r]).astype(np.intp)
    return offsets, int(np.abs(offsets).max()) if offsets.size else 0


def _near_mask(mask: BoolArray, pixels: IntArray, margin: float) -> BoolArray:
    """Which pixels lie within ``margin`` of the mask (3x3 L2 distance).

    The same test as dilating the mask with :func:`margin_kernel` and reading
    the pixels (the footprint is symmetric), done only at the pixels: one
    gather of the mask at every footprint offset around each.

    Args:
        mask: shape (H, W) bool.
        pixels: shape (N, 2) int ``(col, row)`` inside the image.
        margin: distance, px.

    Returns:
        shape (N,) bool.
    """
    offsets, r = _margin_offsets(margin)
    m = np.ascontiguousarray(mask, dtype=bool)
    h, w = m.shape
    if pixels.shape[0] == 0 or offsets.shape[0] == 0:
        return np.zeros(pixels.shape[0], dtype=bool)
    lo, hi = pixels.min(axis=0), pixels.max(axis=0)
    if min(lo[0], lo[1]) < r or hi[0] >= w - r or hi[1] >= h - r:
        # outside the image is not lamp (cv2 pads several times faster than np.pad)
        m = cv2.copyMakeBorder(m.view(np.uint8), r, r, r, r, cv2.BORDER_CONSTANT, value=0)
        pixels = pixels + r
        w += 2 * r
    flat = (pixels[:, 1] * w + pixels[:, 0])[:, None] + (offsets[:, 1] * w + offsets[:, 0])
    return m.reshape(-1).take(flat).any(axis=1)


def extract_patches(image: ImageU8, pixels: IntArray, size: int) -> np.ndarray:
    """Grey patches centred on integer pixels, zero-mean and unit-norm.

    Args:
        image: shape (H, W) uint8.
        pixels: shape (N, 2) int ``(col, row)``, all at least ``size // 2``
            from the border.
        size: odd patch side ``P``.

    Returns:
        shape (N, P, P) float32; flat patches come out all zero.
    """
    return _normalise_patches(_windows(image, pixels, size), size)


def detect_corner_pixels(
    image: ImageU8, lamp_mask: BoolArray | None, config: CornerDetectorConfig
) -> CornerDetections:
    """FAST corners with spacing, away from lamps, each with its NCC patch.

    Args:
        image: shape (H, W) uint8 grey image.
        lamp_mask: shape (H, W) bool, lamp pixels (None: no lamps).
        config: detector settings.

    Returns:
        The corners, strongest first.
    """
    h, w = image.shape
    p = config.patch_size
    half = p // 2
    # FAST over the whole image, then the border and lamp-margin filter on the
    # keypoints (what OpenCV does with a detection mask, without building one).
    kps = cv2.FastFeatureDetector.create(config.fast_threshold, True).detect(image)
    if not kps:
        return _empty(p)
    pts = np.asarray(cv2.KeyPoint.convert(kps), dtype=np.float64).reshape(-1, 2)
    resp = np.fromiter(map(_RESPONSE, kps), np.float64, len(kps))
    ij = pts.astype(np.intp)  # FAST keypoints lie on pixel centres
    keep = (ij[:, 0] >= half) & (ij[:, 0] < w - half) & (ij[:, 1] >= half) & (ij[:, 1] < h - half)
    # (compress: boolean-mask indexing of 2-D arrays is several times slower)
    if lamp_mask is not None:
        keep[keep] = ~_near_mask(lamp_mask, ij.compress(keep, axis=0), config.lamp_margin_px)
    if not keep.any():
        return _empty(p)
    pts, resp = pts.compress(keep, axis=0), resp.compress(keep)
    # Bound the work on large images: the strongest candidates only.
    cap = 20 * config.max_corners
    if resp.size > cap:
        top = np.argpartition(-resp, cap)[:cap]
        pts, resp = pts[top], resp[top]
    # Spacing, strongest first (the stable order of the kept ones), then the cap. FAST
    # keypoints are distinct pixel centres: many are spaced on the image grid.
    order = None
    if resp.size > _BRUTE_FORCE_MAX:
        order = strongest_spaced_pixels(pts.astype(np.intp), resp, config.min_spacing_px, (h, w))
    if order is None:
        order = strongest_spaced(pts, resp, config.min_spacing_px)
    order = order[: config.max_corners]
    ij = np.round(pts.take(order, axis=0)).astype(np.int64)
    resp = resp.take(order)
    pix = ij.astype(np.float64)
    if config.subpix_win > 0:
        win = config.subpix_win
        crit = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 20, 0.01)
        ref = (
            cv2.cornerSubPix(
                image, pix.astype(np.float32).reshape(-1, 1, 2), (win, win), (-1, -1), crit
            )
            .reshape(-1, 2)
            .astype(np.float64)
        )
        moved = np.abs(ref - pix).max(axis=1) <= win
        pix = np.where(moved[:, None], ref, pix)
        ij = np.round(pix).astype(np.int64)
        inside = (
            (ij[:, 0] >= half) & (ij[:, 0] < w - half) & (ij[:, 1] >= half) & (ij[:, 1] < h - half)
        )
        ij, pix = ij.compress(inside, axis=0), pix.compress(inside, axis=0)
        resp = resp.compress(inside)
    # Flat patches (std below the floor) are useless for NCC; the std is the
    # zero-mean patch's norm / P.
    centred, norms = _centre_patches(_windows(image, ij, p))
    ok = norms >= config.min_patch_std_grey * p
    nn = norms.compress(ok)[:, None]
    patches = np.divide(
        centred.compress(ok, axis=0),
        nn,
        out=np.zeros((nn.shape[0], p * p), np.float32),
        where=nn > 0,
    ).reshape(-1, p, p)
    return CornerDetections(pix.compress(ok, axis=0), resp.compress(ok), patches)


def detect_corners(
    image: ImageU8,
    camera: PixelToCeiling,
    lamp_mask: BoolArray | None = None,
    config: CornerDetectorConfig | None = None,
) -> tuple[CornerObservation, ...]:
    """FAST corners as :class:`CornerObservation` (normalised ceiling coordinates).

    Args:
        image: shape (H, W) uint8 grey image.
        camera: pixel -> normalised ceiling coordinates map.
        lamp_mask: shape (H, W) bool lamp pixels to keep away from, or None.
        config: detector settings (defaults if None).

    Returns:
        The corners, strongest first; ``cov_m = J (sigma_px^2 I) J^T``.
    """
    config = config or _DEFAULT_CONFIG
    det = detect_corner_pixels(image, lamp_mask, config)
    if det.pixels.shape[0] == 0:
        return ()
    m, jac = ceiling_jacobians(camera, det.pixels, config.jacobian_step_px)
    return corner_observations(det, m, jac, config)


def corner_observations(
    det: CornerDetections, m: FloatArray, m_D_px: FloatArray, config: CornerDetectorConfig
) -> tuple[CornerObservation, ...]:
    """Wrap detected corners as observations, given their camera conversion.

    Args:
        det: N corners in pixels.
        m: shape (N, 2), their normalised ceiling coordinates.
        m_D_px: shape (N, 2, 2), Jacobians of ``m`` with respect to the pixel.
        config: detector settings (``sigma_px``).

    Returns:
        N observations, strongest first; ``cov_m = J (sigma_px^2 I) J^T``.
    """
    cov = config.sigma_px**2 * (m_D_px @ m_D_px.transpose(0, 2, 1))
    # Iterating the arrays (row views) is cheaper than indexing them per corner, and
    # positional arguments halve the cost of the frozen dataclass's __init__.
    return tuple(map(CornerObservation, m, cov, det.pixels, det.patches, det.scores.tolist()))


def match_ncc(
    patches: np.ndarray,
    predicted: FloatArray,
    cand_patches: np.ndarray,
    cand_positions: FloatArray,
    gates: FloatArray | float,
    min_ncc: float = 0.8,
    chi2_gate: float = 9.21,
) -> tuple[IntArray, FloatArray]:
    """For each predicted feature, the best NCC candidate inside its gate.

    Args:
        patches: shape (N, P, P), reference patches (zero-mean, unit-norm).
        predicted: shape (N, 2), predicted positions (pixels or ``m``, same
            frame as ``cand_positions``).
        cand_patches: shape (M, P, P), candidate patches (zero-mean, unit-norm).
        cand_positions: shape (M, 2), candidate positions.
        gates: a radius (scalar, or shape (N,) per prediction) in the position
            units, or shape (N, 2, 2) innovation covariances ``S`` for a
            Mahalanobis gate ``d^T S^-1 d <= chi2_gate`` (eqs. 19-20).
        min_ncc: lowest NCC accepted (default 0.8).
        chi2_gate: chi-square bound of the Mahalanobis gate (default 9.21,
            99 % for 2 degrees of freedom).

    Returns:
        ``(index (N,) int, ncc (N,))``: the chosen candidate per prediction, or
        -1 and ``nan`` when no gated candidate reaches ``min_ncc``.
    """
    n = predicted.shape[0]
    m = cand_positions.shape[0]
    index = np.full(n, -1, dtype=np.int64)
    best = np.full(n, np.nan)
    if n == 0 or m == 0:
        return index, best
    ncc = patches.reshape(n, -1) @ cand_patches.reshape(m, -1).T  # (N, M)
    diff = cand_positions[None, :, :] - predicted[:, None, :]  # (N, M, 2)
    g = np.asarray(gates, dtype=np.float64)
    if g.ndim == 3:
        s_inv = np.linalg.inv(g)
        d2 = np.einsum("nmi,nij,nmj->nm", diff, s_inv, diff)
        inside = d2 <= chi2_gate
    else:
        radius = np.broadcast_to(g, (n,))
        inside = np.einsum("nmi,nmi->nm", diff, diff) <= (radius * radius)[:, None]
    score = np.where(inside, ncc, -np.inf)
    j = np.argmax(score, axis=1)
    s = score[np.arange(n), j]
    ok = s >= min_ncc
    index[ok] = j[ok]
    best[ok] = s[ok]
    return index, best
