"""Angle wrapping shared by the estimator stages (docs/conventions.md, "Angles").

Pure functions with no imports from any stage, so that ``frontend``, ``factors``,
``backend``, ``localization`` and ``evaluation`` can all use the same
definitions. The simulator (``datasets/``) keeps its own copy on purpose: the
truth it writes must stay independent of estimator code (docs/architecture.md).

* Headings (arrows) live in ``(-pi, pi]``: :func:`wrap_angle`.
* Lamp axes are lines, defined modulo ``pi`` (DESIGN sec. 1), and live in
  ``(-pi/2, pi/2]``: :func:`wrap_axis`.
"""

from __future__ import annotations

import math
from typing import overload

import numpy as np

from lampsam.arrays import FloatArray

TWO_PI = 2.0 * math.pi


@overload
def wrap_angle(angle: float) -> float: ...
@overload
def wrap_angle(angle: FloatArray) -> FloatArray: ...


def wrap_angle(angle: float | FloatArray) -> float | FloatArray:
    """Wrap an angle (or array of angles) to ``(-pi, pi]``.

    Args:
        angle: radians, scalar or any-shaped array.

    Returns:
        A float for a scalar (or 0-d) input, else an array of the same shape;
        each value in ``(-pi, pi]`` (``pi`` and ``-pi`` both map to ``pi``).
    """
    if type(angle) is float:  # plain floats: Python's modulo is numpy's, minus the call cost
        return math.pi - (math.pi - angle) % TWO_PI
    wrapped = math.pi - np.mod(math.pi - np.asarray(angle, dtype=float), TWO_PI)
    if np.ndim(wrapped) == 0:
        return float(wrapped)
    return wrapped


@overload
def wrap_axis(angle: float) -> float: ...
@overload
def wrap_axis(angle: FloatArray) -> FloatArray: ...


def wrap_axis(angle: float | FloatArray) -> float | FloatArray:
    """Wrap a line direction (defined modulo ``pi``) to ``(-pi/2, pi/2]``.

    A lamp's long axis is a line, not an arrow (DESIGN sec. 1): ``phi`` and
    ``phi + pi`` are the same axis, and residuals of axis observations are
    wrapped with this function so that they never exceed ``pi/2`` in magnitude.

    Args:
        angle: radians, scalar or any-shaped array.

    Returns:
        A float for a scalar (or 0-d) input, else an array of the same shape;
        each value in ``(-pi/2, pi/2]``.
    """
    half = 0.5 * math.pi
    if type(angle) is float:  # plain floats: Python's modulo is numpy's, minus the call cost
        return half - (half - angle) % math.pi
    wrapped = half - np.mod(half - np.asarray(angle, dtype=float), math.pi)
    if np.ndim(wrapped) == 0:
        return float(wrapped)
    return wrapped
