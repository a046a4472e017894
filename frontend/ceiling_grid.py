"""Blob moments taken on the ceiling: a per-pixel table of ``m`` for lenses that bend lamps (issue 16).

A lamp's face is flat and horizontal, so in normalised ceiling coordinates
``m`` (docs/conventions.md: forward and left per metre of height) its image
is the face itself scaled by ``1 / h``: the coverage-area centroid and second
moments of its blob *taken in m* are the face's centre and shape (paper 1,
eqs. 2-7), under any lens and mounting. Taken in pixels they are not, once the
pixel -> ``m`` map is not affine: a fisheye bends a lamp's image and a tilted
camera foreshortens it, and the pixel centroid mapped through the camera lands
off the lamp's centre (about 0.027 per metre of height near the edge of a
150 deg fisheye; docs/experiments/fisheye.md).

Pixel ``i`` with coverage ``w_i`` (:mod:`lampsam.frontend.blob_moments`)
covers the ceiling area ``w_i g_i``, ``g_i = |det dm/dpx|`` at the pixel (its
footprint), so with ``W = sum w_i g_i``:

    ``m_c = sum w_i g_i m_i / W``,
    ``C_m = sum w_i g_i (m_i - m_c)(m_i - m_c)^T / W + J (I / 12) J^T``

(the last term, added by :func:`lampsam.frontend.ceiling_coords.ceiling_shapes`:
each pixel's coverage spread uniformly over its footprint, as the 1/12 px^2
term of the pixel moments; ``J`` at the blob's centroid). The table holds
``m`` and ``g`` at every pixel centre, computed once per camera; pixels whose
ray does not reach the ceiling (a fisheye's corners beyond 90 deg) are NaN
and a blob with weight on one gets no ceiling moments (it is rejected).

When ``m`` is affine in the pixel (an upward pinhole camera without
distortion) the moments in ``m`` are exactly the pixel moments mapped by
``J``: no table is built (:attr:`CeilingGrid.affine`) and the detector maps
the pixel moments instead, which is cheaper and gives the same numbers.
"""

from __future__ import annotations

import functools
from collections.abc import Hashable
from dataclasses import dataclass
from typing import TYPE_CHECKING, NamedTuple, cast

import numpy as np

from lampsam.arrays import FloatArray, IntArray
from lampsam.frontend.label_stats import Groups, label_sums

if TYPE_CHECKING:  # (ceiling_coords imports the blob moments, which import this module)
    from lampsam.frontend.ceiling_coords import PixelToCeiling


class CeilingMoments(NamedTuple):
    """A blob's coverage moments on the ceiling, before the pixel-box term.

    Attributes:
        centroid: shape (2,), area centroid ``m_c`` in normalised ceiling coordinates.
        cov_shape: shape (2, 2), second central moments in ``m`` (units of ``m`` squared).
        area: ``W = sum w_i g_i``, the blob's coverage area on the ceiling (``m`` units squared).
    """

    centroid: FloatArray
    cov_shape: FloatArray
    area: float


@dataclass(frozen=True, eq=False)
class CeilingGrid:
    """Normalised ceiling coordinates and footprint of every pixel centre of one camera.

    Attributes:
        width: image width, px.
        height: image height, px.
        affine: ``m`` is affine in the pixel; then ``u``, ``v``, ``g`` are empty.
        u: shape (H * W,) ``m`` forward component per pixel (row-major), NaN off the ceiling.
        v: shape (H * W,) ``m`` left component per pixel.
        g: shape (H * W,) ``|det dm/dpx|``, the pixel's footprint (``m`` units squared per px).
    """

    width: int
    height: int
    affine: bool
    u: FloatArray
    v: FloatArray
    g: FloatArray


_STEP = 0.25
"""Step of the central differences of the footprint, px."""


def _is_affine(camera: PixelToCeiling) -> bool:
    """True when ``m`` is affine in the pixel over the image (to 1e-9 of its range)."""
    w, h = camera.width, camera.height
    xs, ys = np.meshgrid(np.linspace(0.0, w - 1.0, 5), np.linspace(0.0, h - 1.0, 5))
    px = np.column_stack([xs.ravel(), ys.ravel()])
    m = np.asarray(camera.normalized_from_pixels(px), dtype=np.float64)
    if not np.all(np.isfinite(m)):
        return False
    design = np.column_stack([px, np.ones(len(px))])
    coef, *_ = np.linalg.lstsq(design, m, rcond=None)
    resid = float(np.abs(design @ coef - m).max())
    return resid <= 1e-9 * max(float(np.abs(m).max()), 1e-12)


def build_ceiling_grid(camera: PixelToCeiling) -> CeilingGrid:
    """The per-pixel table of a camera (see the module docstring); ``g`` by central differences.

    Args:
        camera: the pixel -> ``m`` map and image size.

    Returns:
        The table; with ``affine`` True (and empty arrays) for an affine map.
    """
    w, h = int(camera.width), int(camera.height)
    empty = np.zeros(0)
    if _is_affine(camera):
        return CeilingGrid(w, h, True, empty, empty, empty)
    rows, cols = np.divmod(np.arange(w * h), w)
    px = np.column_stack([cols, rows]).astype(np.float64)
    # m at the pixel centres and at +-STEP px along both axes (footprint by central differences).
    offs = np.array([[0.0, 0.0], [_STEP, 0.0], [-_STEP, 0.0], [0.0, _STEP], [0.0, -_STEP]])
    pts = (offs[:, None, :] + px[None, :, :]).reshape(-1, 2)
    m = np.asarray(camera.normalized_from_pixels(pts), dtype=np.float64).reshape(5, w * h, 2)
    d_col = (m[1] - m[2]) / (2.0 * _STEP)
    d_row = (m[3] - m[4]) / (2.0 * _STEP)
    g = np.abs(d_col[:, 0] * d_row[:, 1] - d_col[:, 1] * d_row[:, 0])
    return CeilingGrid(w, h, False, m[0, :, 0].copy(), m[0, :, 1].copy(), g)


@functools.lru_cache(maxsize=8)
def _cached_grid(camera: Hashable) -> CeilingGrid:
    """:func:`build_ceiling_grid`, once per camera object (cameras are immutable)."""
    return build_ceiling_grid(cast("PixelToCeiling", camera))


def ceiling_grid(camera: PixelToCeiling) -> CeilingGrid:
    """The camera's table, built on first use and kept for the next frames.

    Cameras that cannot be hashed (a custom :class:`PixelToCeiling`) get a new table per call.
    """
    if isinstance(camera, Hashable):
        return _cached_grid(camera)
    return build_ceiling_grid(camera)  # (an unhashable camera object)


def label_ceiling_moments(
    grid: CeilingGrid, groups: Groups, lab: IntArray, flat: IntArray, weight: FloatArray, n: int
) -> tuple[FloatArray, FloatArray, FloatArray, np.ndarray]:
    """Ceiling moments of many blobs at once from their support pixels' coverage.

    Args:
        grid: the camera's table (not affine).
        groups: the support pixels grouped by label (:func:`lampsam.frontend.label_stats.group_by_label`),
            the arrays below already in that order.
        lab: shape (P,) each pixel's label.
        flat: shape (P,) each pixel's flat index in the image (``row * W + col``).
        weight: shape (P,) coverage ``w_i`` in [0, 1].
        n: number of labels.

    Returns:
        ``(centroid (n, 2), cov_shape (n, 2, 2), area (n,), ok (n,))``; ``ok`` is False
        for labels with weight on a pixel off the ceiling or without weight.
    """
    u, v, g = grid.u.take(flat), grid.v.take(flat), grid.g.take(flat)
    off = ~(np.isfinite(u) & np.isfinite(v) & np.isfinite(g))
    if off.any():
        u, v, g = np.where(off, 0.0, u), np.where(off, 0.0, v), np.where(off, 0.0, g)
    wg = weight * g
    s0, su, sv, n_off = label_sums(groups, np.array([wg, wg * u, wg * v, off * (weight > 0)]), n)
    ok = (s0 > 0.0) & (n_off == 0)
    s0 = np.where(ok, s0, 1.0)
    cu, cv = su / s0, sv / s0
    du, dv = u - cu.take(lab), v - cv.take(lab)
    suu, suv, svv = label_sums(groups, np.array([wg * du * du, wg * du * dv, wg * dv * dv]), n)
    cov = np.empty((n, 2, 2))
    cov[:, 0, 0], cov[:, 0, 1], cov[:, 1, 0], cov[:, 1, 1] = suu / s0, suv / s0, suv / s0, svv / s0
    return np.column_stack([cu, cv]), cov, np.where(ok, s0, 0.0), ok


def region_ceiling_moments(
    grid: CeilingGrid, rows: IntArray, cols: IntArray, weight: FloatArray
) -> CeilingMoments | None:
    """Ceiling moments of one blob from its pixels (image rows and columns) and coverage.

    Returns:
        The moments, or None when the blob has weight on a pixel off the ceiling.
    """
    flat = np.asarray(rows, dtype=np.intp) * grid.width + np.asarray(cols, dtype=np.intp)
    u, v, g = grid.u.take(flat), grid.v.take(flat), grid.g.take(flat)
    on = weight > 0
    if not (np.isfinite(u[on]).all() and np.isfinite(v[on]).all() and np.isfinite(g[on]).all()):
        return None
    wg = np.where(on, weight * np.where(on, g, 0.0), 0.0)
    total = float(wg.sum())
    if total <= 0.0:
        return None
    u, v = np.where(on, u, 0.0), np.where(on, v, 0.0)
    cu, cv = float(wg @ u) / total, float(wg @ v) / total
    du, dv = u - cu, v - cv
    cov = np.array([[wg @ (du * du), wg @ (du * dv)], [wg @ (du * dv), wg @ (dv * dv)]]) / total
    return CeilingMoments(np.array([cu, cv]), cov, total)
