"""Pixel measurements of lamps -> normalised ceiling coordinates (docs/conventions.md).

The observation model of paper 1 (eqs. 17-18, DESIGN.md sec. 1) works in the
normalised image point ``m = (u, v) / f`` of an upward camera whose axes are
(robot forward, robot left). The detector measures in pixels ``(col, row)``;
the camera model maps pixels to ``m`` (undistortion, and undoing the image
mirroring of the mounting). Uncertainty goes through the local Jacobian
``J = dm/dpx`` at the centroid (central differences):

* centroid: ``cov_m = J cov_c J^T``;
* axis: the image direction ``e = (cos theta, sin theta)`` becomes ``J e``, so
  the ceiling axis is ``atan2(J e)`` modulo pi, and
  ``var_alpha = (det J / |J e|^2)^2 var_theta`` (the derivative of the mapped
  angle with respect to ``theta``).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Protocol

import numpy as np

from lampsam.angles import wrap_axis
from lampsam.arrays import FloatArray
from lampsam.frontend.blob_moments import BlobMoments
from lampsam.frontend.lamp_config import LampDetectorConfig
from lampsam.frontend.measurements import LampObservation


class PixelToCeiling(Protocol):
    """What the frontend needs from a camera model (``lampsam.datasets.logrun.CameraModel``)."""

    @property
    def width(self) -> int:
        """Image width, px."""
        ...

    @property
    def height(self) -> int:
        """Image height, px."""
        ...

    def normalized_from_pixels(self, px: FloatArray) -> FloatArray:
        """Pixels ``(N, 2)`` (col, row) -> normalised ceiling coordinates ``(N, 2)``."""
        ...


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
    moments: list[BlobMoments],
    m: FloatArray,
    m_D_px: FloatArray,
    config: LampDetectorConfig,
    ceiling_axes: Sequence[float | None] | None = None,
) -> tuple[LampObservation, ...]:
    """:func:`to_observation` of many blobs at once (the same formulas, batched).

    Args:
        moments: N pixel measurements.
        m: shape (N, 2), their centroids in normalised ceiling coordinates.
        m_D_px: shape (N, 2, 2), Jacobians of ``m`` with respect to the pixel.
        config: detector settings (ratio threshold).
        ceiling_axes: per blob, its axis taken on the ceiling (the principal
            axis of ``J cov_shape J^T``, :func:`perspective_terms`) to use
            instead of ``J e``, or None (default: ``J e`` for all).

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
    over = ceiling_axes if ceiling_axes is not None else [None] * len(moments)
    for mo, ((j00, j01), (j10, j11)), ((c00, c01), (c10, c11)), ax_c in zip(
        moments, m_D_px.tolist(), cov_c, over, strict=True
    ):
        # cov_m = J cov_c J^T
        t00, t01 = j00 * c00 + j01 * c10, j00 * c01 + j01 * c11
        t10, t11 = j10 * c00 + j11 * c10, j10 * c01 + j11 * c11
        covs.append(((t00 * j00 + t01 * j01, t00 * j10 + t01 * j11),
                     (t10 * j00 + t11 * j01, t10 * j10 + t11 * j11)))  # fmt: skip
        if mo.ratio > threshold:
            cos_t, sin_t = math.cos(mo.theta), math.sin(mo.theta)
            je0, je1 = j00 * cos_t + j01 * sin_t, j10 * cos_t + j11 * sin_t
            axes.append(wrap_axis(math.atan2(je1, je0)) if ax_c is None else ax_c)
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


def perspective_terms(
    camera: PixelToCeiling, px: FloatArray, cov_shapes: FloatArray, m_D_px: FloatArray, step: float
) -> tuple[FloatArray, list[float | None]]:
    """Second-order corrections for a pixel -> ``m`` map that is not affine (tilted camera, distortion).

    A blob's pixel centroid ``p`` maps to ``m(p)``, but the lamp's centre is
    the area centroid *on the ceiling*: with ``g = |det J|`` the ceiling area
    of a pixel and ``C`` the blob's pixel covariance (``cov_shape``), to
    second order

        ``m_centre = m(p) + 1/2 [tr(H_u C), tr(H_v C)] + J C grad(log g)``

    (``H_u``, ``H_v`` the Hessians of the two components of ``m``). For an
    upward pinhole camera ``m`` is affine in the pixel: ``H = 0``, ``g``
    constant, nothing changes. Likewise the lamp's axis is the principal axis
    of ``J C J^T`` (the blob's shape on the ceiling) rather than the image of
    the pixel principal axis ``J e``; they agree for a similarity ``J``.
    Derivatives by central differences on a 5 x 5 grid of spacing ``step``.

    Args:
        camera: the camera model.
        px: shape (N, 2) pixel centroids.
        cov_shapes: shape (N, 2, 2) pixel shape covariances, px^2.
        m_D_px: shape (N, 2, 2) Jacobians at the centroids.
        step: grid spacing, px.

    Returns:
        ``(dm (N, 2), axes)``: the centroid corrections and, per blob, its
        ceiling axis (rad, mod pi) where the map is not affine, else None.
    """
    n = px.shape[0]
    a = np.arange(-2, 3, dtype=np.float64) * step
    offs = np.stack(np.meshgrid(a, a, indexing="ij"), axis=-1).reshape(-1, 2)  # [i, j] -> (dx, dy)
    pts = (px[:, None, :] + offs[None, :, :]).reshape(-1, 2)
    g = np.asarray(camera.normalized_from_pixels(pts), dtype=np.float64).reshape(n, 5, 5, 2)
    s2 = step * step
    hxx = (g[:, 3, 2] - 2 * g[:, 2, 2] + g[:, 1, 2]) / s2
    hyy = (g[:, 2, 3] - 2 * g[:, 2, 2] + g[:, 2, 1]) / s2
    hxy = (g[:, 3, 3] - g[:, 3, 1] - g[:, 1, 3] + g[:, 1, 1]) / (4 * s2)

    def det_j(i: int, j: int) -> FloatArray:
        jx = (g[:, i + 1, j] - g[:, i - 1, j]) / (2 * step)
        jy = (g[:, i, j + 1] - g[:, i, j - 1]) / (2 * step)
        return np.abs(jx[:, 0] * jy[:, 1] - jx[:, 1] * jy[:, 0])

    g0 = det_j(2, 2)
    grad = np.stack([det_j(3, 2) - det_j(1, 2), det_j(2, 3) - det_j(2, 1)], axis=-1) / (2 * step)
    grad = grad / g0[:, None]
    c = cov_shapes
    second = 0.5 * (hxx * c[:, None, 0, 0] + 2 * hxy * c[:, None, 0, 1] + hyy * c[:, None, 1, 1])
    first = np.einsum("nij,njk,nk->ni", m_D_px, c, grad)
    dm = second + first
    scale = np.abs(m_D_px).max(axis=(1, 2))
    curved = (np.abs(np.stack([hxx, hyy, hxy], 1)).max(axis=(1, 2)) * step > 1e-9 * scale)
    axes: list[float | None] = []
    for k in range(n):
        if not curved[k]:
            axes.append(None)
            continue
        cm = m_D_px[k] @ c[k] @ m_D_px[k].T
        axes.append(wrap_axis(0.5 * math.atan2(2 * cm[0, 1], cm[0, 0] - cm[1, 1])))
    dm[~curved] = 0.0
    return dm, axes
