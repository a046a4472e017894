"""Pixel measurements of lamps -> normalised ceiling coordinates (docs/conventions.md).

The observation model of paper 1 (eqs. 17-18, DESIGN.md sec. 1) works in the
normalised image point ``m = (u, v) / f`` of an upward camera whose axes are
(robot forward, robot left). The detector measures in pixels ``(col, row)``;
the camera model maps pixels to ``m`` (undistortion, and undoing the image
mirroring of the mounting).

A lamp's centre and axis are those of its blob's shape *on the ceiling*
(:func:`ceiling_shapes`): the coverage moments taken in ``m``
(:mod:`lampsam.frontend.ceiling_grid`) when the map is not affine, else the
pixel moments mapped by the local Jacobian ``J = dm/dpx`` (central
differences; exact for an affine map): centre ``m_c``, shape ``C_m``
(second central moments), the long axis ``alpha = 0.5 atan2(2 C_uv, C_uu - C_vv)``
(eq. 5 on the ceiling) and ``R_ori = sqrt(lambda_max / lambda_min)`` of ``C_m``
(eq. 7). Uncertainty goes through ``J`` at the pixel centroid (first order):

* centroid: ``cov_m = J cov_c J^T``;
* axis: the image direction ``e = (cos theta, sin theta)`` becomes ``J e``, and
  ``var_alpha = (det J / |J e|^2)^2 var_theta`` (the derivative of the mapped
  angle with respect to ``theta``).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import NamedTuple, Protocol

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


class CeilingShapes(NamedTuple):
    """Blobs' shapes on the ceiling (normalised ceiling coordinates ``m``).

    Attributes:
        m: shape (N, 2) area centroids.
        cov: shape (N, 2, 2) second central moments, pixel-box term included
            (``m`` units squared).
        area: shape (N,) coverage areas on the ceiling (``m`` units squared).
    """

    m: FloatArray
    cov: FloatArray
    area: FloatArray

    def select(self, keep: Sequence[bool]) -> CeilingShapes:
        """The shapes where ``keep`` is True."""
        idx = np.flatnonzero(np.asarray(keep, dtype=bool))
        return CeilingShapes(self.m[idx], self.cov[idx], self.area[idx])


def ceiling_shapes(moments: Sequence[BlobMoments], m: FloatArray, m_D_px: FloatArray) -> CeilingShapes:
    """Centroid, shape and area of each blob on the ceiling (module docstring).

    A blob measured on the ceiling (:attr:`BlobMoments.ceiling`) keeps those
    moments, plus the pixel-box term ``J (I / 12) J^T``; the others (affine
    map) get their pixel moments mapped: ``m(p)``, ``J C J^T`` (``C`` includes
    the pixel-box term) and ``|det J| area_px``.

    Args:
        moments: N pixel-space blob measurements.
        m: shape (N, 2) ``m`` of their pixel centroids.
        m_D_px: shape (N, 2, 2) Jacobians ``dm/dpx`` at the pixel centroids.
    """
    n = len(moments)
    cen = np.array(m, dtype=np.float64).reshape(n, 2)
    cov = np.empty((n, 2, 2))
    area = np.empty(n)
    for i, (mo, jac) in enumerate(zip(moments, m_D_px, strict=True)):
        on = mo.ceiling
        if on is None:
            cov[i] = jac @ mo.cov_shape @ jac.T
            area[i] = abs(jac[0, 0] * jac[1, 1] - jac[0, 1] * jac[1, 0]) * mo.area_px
        else:
            cen[i] = on.centroid
            cov[i] = on.cov_shape + (jac @ jac.T) / 12.0
            area[i] = on.area
    return CeilingShapes(cen, cov, area)


def shape_axis_ratio(cov: FloatArray) -> tuple[float, float]:
    """Long-axis angle (rad, wrapped to ``(-pi/2, pi/2]``) and ``R_ori`` of a 2x2 shape covariance."""
    a, b, c = float(cov[0, 0]), float(cov[0, 1]), float(cov[1, 1])
    disc = math.sqrt(max((a - c) * (a - c) + 4.0 * b * b, 0.0))
    lam1 = 0.5 * (a + c + disc)
    lam2 = max(0.5 * (a + c - disc), 1e-300)
    return wrap_axis(0.5 * math.atan2(2.0 * b, a - c)), math.sqrt(lam1 / lam2)


def to_observation(
    mom: BlobMoments, shape_m: FloatArray, shape_cov: FloatArray, m_D_px: FloatArray,
    config: LampDetectorConfig,
) -> LampObservation:
    """Convert a pixel-space blob measurement and its shape on the ceiling to a :class:`LampObservation`.

    Args:
        mom: the blob's pixel measurement.
        shape_m: shape (2,), its centroid on the ceiling (:func:`ceiling_shapes`).
        shape_cov: shape (2, 2), its shape on the ceiling.
        m_D_px: shape (2, 2), Jacobian of ``m`` with respect to the pixel at the pixel centroid.
        config: detector settings (ratio threshold).

    Returns:
        The observation (module docstring); ``axis`` None for a point lamp.
    """
    cov_m = m_D_px @ mom.cov_centroid @ m_D_px.T
    alpha, ratio = shape_axis_ratio(shape_cov)
    axis: float | None = None
    var_axis = math.inf
    if ratio > config.ratio_threshold:
        e = np.array([math.cos(mom.theta), math.sin(mom.theta)])
        je = m_D_px @ e
        axis = alpha
        gain = float(np.linalg.det(m_D_px)) / float(je @ je)
        var_axis = gain * gain * mom.var_theta
    return LampObservation(
        m=np.asarray(shape_m, dtype=np.float64),
        cov_m=cov_m,
        axis=axis,
        var_axis=var_axis,
        ratio=ratio,
        area_px=mom.area_px,
        pixel=mom.centroid,
        landmark_id=None,
        touches_border=mom.touches_border,
    )


def to_observations(
    moments: Sequence[BlobMoments],
    shapes: CeilingShapes,
    m_D_px: FloatArray,
    config: LampDetectorConfig,
) -> tuple[LampObservation, ...]:
    """:func:`to_observation` of many blobs at once (the same formulas on Python floats).

    Args:
        moments: N pixel measurements.
        shapes: their shapes on the ceiling (:func:`ceiling_shapes`).
        m_D_px: shape (N, 2, 2), Jacobians of ``m`` at the pixel centroids.
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
    ratios: list[float] = []
    for mo, ((j00, j01), (j10, j11)), ((c00, c01), (c10, c11)), ((a, b), (_, c)) in zip(
        moments, m_D_px.tolist(), cov_c, shapes.cov.tolist(), strict=True
    ):
        # cov_m = J cov_c J^T
        t00, t01 = j00 * c00 + j01 * c10, j00 * c01 + j01 * c11
        t10, t11 = j10 * c00 + j11 * c10, j10 * c01 + j11 * c11
        covs.append(((t00 * j00 + t01 * j01, t00 * j10 + t01 * j11),
                     (t10 * j00 + t11 * j01, t10 * j10 + t11 * j11)))  # fmt: skip
        disc = math.sqrt(max((a - c) * (a - c) + 4.0 * b * b, 0.0))
        ratio = math.sqrt(0.5 * (a + c + disc) / max(0.5 * (a + c - disc), 1e-300))
        ratios.append(ratio)
        if ratio > threshold:
            cos_t, sin_t = math.cos(mo.theta), math.sin(mo.theta)
            je0, je1 = j00 * cos_t + j01 * sin_t, j10 * cos_t + j11 * sin_t
            axes.append(wrap_axis(0.5 * math.atan2(2.0 * b, a - c)))
            gain = (j00 * j11 - j01 * j10) / (je0 * je0 + je1 * je1)
            var_axes.append(gain * gain * mo.var_theta)
        else:
            axes.append(None)
            var_axes.append(math.inf)
    m = np.asarray(shapes.m, dtype=np.float64)
    # (positional: the frozen dataclass's __init__ is about twice as fast)
    return tuple(
        LampObservation(mi, ci, ax, va, r, mo.area_px, mo.centroid, None, mo.touches_border)
        for mo, mi, ci, ax, va, r in zip(moments, m, np.array(covs), axes, var_axes, ratios, strict=True)
    )
