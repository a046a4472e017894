"""Lamp size against the lamp models a ceiling is known to carry, so that daylight is not taken for a lamp.

A lamp of face area ``A`` (m^2) at ``h`` metres above the camera covers
``A / h^2`` in normalised ceiling coordinates ``m`` (docs/conventions.md),
whatever the camera's tilt: the pixel -> ``m`` map is the projection onto the
ceiling plane, and its Jacobian ``J = dm/dpx`` (:mod:`lampsam.frontend.ceiling_coords`)
turns a blob's pixel area into ``|det J| area_px`` (or its coverage is summed on the
ceiling: :mod:`lampsam.frontend.ceiling_grid`). A world (or a map) whose
lamp models and heights are known bounds that area; bright blobs outside the
bounds are not lamps (patches of sky through a skylight, reflections, a whole
window).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from lampsam.arrays import FloatArray
from lampsam.frontend.ceiling_coords import CeilingShapes, shape_axis_ratio


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
    shapes: CeilingShapes,
    gate: LampGate | None,
    ratio_tolerance: float = 0.3,
) -> list[bool]:
    """Which blobs look like one of the lamp models on the ceiling (all if ``gate`` is None).

    A blob matches a model when its area on the ceiling lies in the model's
    range and its elongation on the ceiling (``R_ori`` of its shape
    covariance in ``m``, so that a tilted camera's foreshortening and a
    fisheye's bending are undone) is within ``ratio_tolerance`` (relative) of
    the model's.

    Args:
        shapes: N blobs' shapes on the ceiling
            (:func:`lampsam.frontend.ceiling_coords.ceiling_shapes`).
        gate: from :func:`size_gate_from_models`, or None.
        ratio_tolerance: relative margin on the elongation (default 0.3).
    """
    if gate is None:
        return [True] * len(shapes.area)
    out = []
    for area, cov in zip(shapes.area.tolist(), shapes.cov, strict=True):
        _, ratio = shape_axis_ratio(cov)
        out.append(
            any(
                lo <= area <= hi and r / (1 + ratio_tolerance) <= ratio <= r * (1 + ratio_tolerance)
                for lo, hi, r in gate
            )
        )
    return out
