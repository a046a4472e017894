"""Per-observation centroid noise of a lamp from its straight edges' alignment with the pixel grid.

A saturated lamp's edge pixel loses the edge's sub-pixel phase ``phi`` (docs/lamp-bias.md):
with the saturated-edge model (:mod:`lampsam.frontend.saturated_edges`) an edge is off by 0
for ``phi < c_s`` and uniformly in ``+-(1 - c_s) / 2`` above, variance
``(1 - c_s)^3 / 12`` px^2; with the coverage weights as read it is off by
``min(1, phi / c_s) - phi``, uniform on ``[0, 1 - c_s]``, variance ``(1 - c_s)^2 / 12``.
The centroid moves by half the difference of two opposite edges' errors, so a pair of
straight edges adds ``var_edge / 2`` across them.

That holds when every row (or column) the edge crosses has the same phase: an edge
parallel to the pixel grid. An edge of length ``L`` px tilted by ``beta`` from the grid
sweeps ``c = L |tan beta|`` phase cycles along its length; the mean of a periodic error over
``c`` cycles shrinks by about ``|sin(pi c)| / (pi c)`` (its first harmonic), whose smooth
envelope with the same mean square for large ``c`` is used here:
``A(c)^2 = 1 / (1 + 2 (pi c)^2)``. On the simulated lab the sightings' RMS error falls
from 0.076 px (rect lamps within 0.5 deg of the grid) to 0.025-0.03 px beyond 2 deg, as
this predicts (docs/lamp-bias.md, "The lamp noise model").

Only oriented blobs (``R_ori`` above the threshold, the rect lamps) have edges whose
direction the second moments give: the long edges run along the axis ``theta``
(length ``sqrt(12) sigma1``), the short ones across (``sqrt(12) sigma2``). Point lamps
(round or square: the same second moments) get no term; their covariance stays the floor.
An unsaturated blob (no clip: ``c_s`` NaN) gets none either.
"""

from __future__ import annotations

import math

import numpy as np

from lampsam.arrays import FloatArray


def edge_variance(clip_coverage: float, model_on: bool) -> float:
    """Variance (px^2) of one straight saturated edge's position over a uniform phase.

    Args:
        clip_coverage: ``c_s``, the coverage at which an edge pixel clips (0-1].
        model_on: the saturated-edge model reads the edge (True) or the weights as read.
    """
    lost = max(0.0, 1.0 - clip_coverage)
    return lost**3 / 12.0 if model_on else lost**2 / 12.0


def phase_averaging(cycles: float) -> float:
    """``A(c)^2``: the share of an edge's phase-error variance left after ``c`` phase cycles."""
    return 1.0 / (1.0 + 2.0 * (math.pi * cycles) ** 2)


def grid_tilt(theta: float) -> float:
    """Angle (rad, 0..pi/4) of a direction ``theta`` (rad) from the nearest pixel-grid axis."""
    t = math.fmod(abs(theta), math.pi / 2.0)
    return min(t, math.pi / 2.0 - t)


def edge_phase_cov(theta: float, sigma1: float, sigma2: float, clip_coverage: float,
                   model_on: bool) -> FloatArray:
    """Centroid covariance (2, 2), px^2 in ``(col, row)``, from an oriented blob's edge phases.

    Args:
        theta: the long axis in the image, rad from ``+col`` towards ``+row``.
        sigma1: long-axis spread, px (a rectangle's length is ``sqrt(12) sigma1``).
        sigma2: short-axis spread, px.
        clip_coverage: the blob's ``c_s``; NaN: unsaturated (zero covariance).
        model_on: the saturated-edge model is on.

    Returns:
        ``R diag(v_across_long_edges, v_across_short_edges) R^T`` with ``R`` the axis
        rotation: the long edges move the centroid across the axis, the short ones along.
    """
    if not math.isfinite(clip_coverage):
        return np.zeros((2, 2))
    pair = 0.5 * edge_variance(clip_coverage, model_on)
    tan_b = math.tan(grid_tilt(theta))
    v_across = pair * phase_averaging(math.sqrt(12.0) * sigma1 * tan_b)
    v_along = pair * phase_averaging(math.sqrt(12.0) * sigma2 * tan_b)
    c, s = math.cos(theta), math.sin(theta)
    along, across = np.array([c, s]), np.array([-s, c])
    return v_along * np.outer(along, along) + v_across * np.outer(across, across)
