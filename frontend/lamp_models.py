"""Lamp size against the lamp models a ceiling is known to carry, so that daylight is not taken for a lamp.

A lamp of face area ``A`` (m^2) at ``h`` metres above the camera covers
``A / h^2`` in normalised ceiling coordinates ``m`` (docs/conventions.md),
whatever the camera's tilt: the pixel -> ``m`` map is the projection onto the
ceiling plane, and its Jacobian ``J = dm/dpx`` (:mod:`lampsam.frontend.ceiling_coords`)
turns a blob's pixel area into ``|det J| area_px``. A world (or a map) whose
lamp models and heights are known bounds that area; bright blobs outside the
bounds are not lamps (patches of sky through a skylight, reflections, a whole
window).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from lampsam.arrays import FloatArray
from lampsam.frontend.blob_moments import BlobMoments


def lamp_face_area(kind: str, length: float, width: float) -> float:
    """Face area of a lamp model, m^2 (``lamp_round``: a disc of diameter ``length``)."""
    if kind == "lamp_round":
        return math.pi * length * length / 4.0
    return length * width


LampGate = tuple[tuple[float, float, float], ...]
"""Per lamp model: ``(min_area, max_area, ratio)``, areas in ``m`` units squared (m^2 per m^2
of height), ``ratio`` the model's ``R_ori = sigma1 / sigma2`` (eq. 7 of paper 1)."""


def model_ratio(kind: str, length: float, width: float) -> float:
    """``R_ori`` of a uniform lamp face: ``length / width`` (a rectangle), 1 for a disc or square."""
    return 1.0 if kind != "lamp_rect" else length / width


def size_gate_from_models(
    kinds: Sequence[str],
    length: FloatArray,
    width: FloatArray,
    height_above_camera: FloatArray,
    tolerance: float = 0.5,
) -> LampGate:
    """What the given lamps can look like on the ceiling: area range and elongation per model.

    Lamps of the same type and size form one model; its area range spans the
    heights it is mounted at.

    Args:
        kinds: N landmark types (``lamp_rect``, ``lamp_round``, ``lamp_square``).
        length: shape (N,) lamp lengths (round: diameter), m.
        width: shape (N,) lamp widths, m.
        height_above_camera: shape (N,) lamp face heights above the camera, m (> 0).
        tolerance: relative margin on the area range (blur, partial
            saturation, oblique views; default 0.5: ``[min / 1.5, max * 1.5]``).

    Returns:
        One ``(min_area, max_area, ratio)`` per model.

    Raises:
        ValueError: no lamps, or a height not above the camera.
    """
    h = np.asarray(height_above_camera, dtype=np.float64)
    if len(kinds) == 0:
        raise ValueError("size gate: no lamp models")
    if np.any(h <= 0):
        raise ValueError("size gate: every lamp must be above the camera")
    models: dict[tuple[str, float, float], list[float]] = {}
    for k, ln, w, hh in zip(kinds, length, width, h, strict=True):
        key = (k, round(float(ln), 6), round(float(w), 6))
        models.setdefault(key, []).append(lamp_face_area(k, float(ln), float(w)) / (hh * hh))
    return tuple(
        (min(a) / (1.0 + tolerance), max(a) * (1.0 + tolerance), model_ratio(*key))
        for key, a in sorted(models.items())
    )


def within_size_gate(
    moments: Sequence[BlobMoments],
    m_D_px: FloatArray,
    gate: LampGate | None,
    ratio_tolerance: float = 0.3,
) -> list[bool]:
    """Which blobs look like one of the lamp models on the ceiling (all if ``gate`` is None).

    A blob matches a model when its area on the ceiling ``|det J| area_px``
    lies in the model's range and its elongation on the ceiling (``R_ori`` of
    ``J cov_shape J^T``, so that a tilted camera's foreshortening is undone)
    is within ``ratio_tolerance`` (relative) of the model's.

    Args:
        moments: N pixel-space blob measurements.
        m_D_px: shape (N, 2, 2) Jacobians ``dm/dpx`` at their centroids.
        gate: from :func:`size_gate_from_models`, or None.
        ratio_tolerance: relative margin on the elongation (default 0.3).
    """
    if gate is None:
        return [True] * len(moments)
    out = []
    for mo, jac in zip(moments, m_D_px, strict=True):
        area = abs(float(np.linalg.det(jac))) * mo.area_px
        ratio = ceiling_ratio(mo.cov_shape, jac)
        out.append(
            any(
                lo <= area <= hi and r / (1 + ratio_tolerance) <= ratio <= r * (1 + ratio_tolerance)
                for lo, hi, r in gate
            )
        )
    return out


def ceiling_ratio(cov_shape: FloatArray, m_D_px: FloatArray) -> float:
    """``R_ori = sqrt(lambda_max / lambda_min)`` of a blob's shape covariance mapped to the ceiling.

    Args:
        cov_shape: shape (2, 2) second central moments in pixels, px^2.
        m_D_px: shape (2, 2) Jacobian ``dm/dpx`` at the centroid.
    """
    c = m_D_px @ cov_shape @ m_D_px.T
    tr, det = float(c[0, 0] + c[1, 1]), float(np.linalg.det(c))
    disc = math.sqrt(max(tr * tr / 4.0 - det, 0.0))
    lam2 = max(tr / 2.0 - disc, 1e-300)
    return math.sqrt((tr / 2.0 + disc) / lam2)
