"""The alias test: a range-bearing match must beat "a landmark not yet mapped" (no ids).

In a world whose landmarks repeat on a regular spacing (trees on a grid, lamps or
pillars in an office or a car park), a sighting of a tree never seen before often
falls inside the gate (eq. 20) of a mapped neighbour: when the pose is uncertain
relative to that neighbour (sigma 1.5 m against a 5 m grid), the gate's ellipse
covers more than one grid cell, and nearest neighbour takes the only mapped
candidate. The gate asks "is this innovation plausible if the sighting is landmark
``j``?"; it never asks whether the sighting is likelier to be ``j`` than a landmark
that is not in the map yet.

Here both hypotheses get a likelihood in the measurement space ``[bearing, range]``
(rad, m):

- "the sighting is landmark ``j``": ``N(nu; 0, Psi_j) = exp(-d2 / 2) / (2 pi sqrt(det Psi_j))``
  (eq. 19-20, ``Psi_j`` the innovation covariance with the pose-landmark cross term);
- "the sighting is an unmapped landmark": landmarks stand with an area density
  ``rho`` (1 / m^2) in the world, and the area element of ``[bearing, range]`` at
  range ``r`` is ``r dbearing drange``, so the density in measurement space is
  ``rho r``.

A match is kept only when ``N(nu; 0, Psi_j) >= odds * rho * r`` (its log-odds
:func:`match_log_odds` at least ``log odds``). A small, well-known innovation
covariance passes easily; a wide one (the pose uncertain relative to an old
landmark) passes only where the landmarks are sparse. ``rho`` is the map's own:
``1 / s^2`` with ``s`` the median nearest-neighbour distance of the mapped planar
landmarks (:func:`map_density`; for a square grid of spacing ``s`` that is its
density; for trees scattered at random it overstates the density about 4.5x, the
cautious side), or a stated spacing.

Frames: world, m; ``[bearing, range]`` in rad and m.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.spatial import cKDTree

from lampsam.arrays import FloatArray

#: Fewer mapped planar landmarks than this: no density estimate (the test is off).
MIN_LANDMARKS = 8


def match_log_odds(d2: float, logdet_psi: float, range_m: float, density: float) -> float:
    """Log of ``N(nu; 0, Psi) / (density * range)`` for one range-bearing match (module doc).

    Args:
        d2: squared Mahalanobis distance ``nu^T Psi^-1 nu`` (eq. 20).
        logdet_psi: ``log det Psi`` of the (2, 2) ``[bearing, range]`` innovation
            covariance (rad^2 m^2).
        range_m: the sighting's range, m (> 0).
        density: landmarks per m^2 (> 0).

    Returns:
        The log-odds of "landmark j" over "an unmapped landmark"; ``-inf`` for a
        non-finite input.
    """
    if not (math.isfinite(d2) and math.isfinite(logdet_psi)) or range_m <= 0.0 or density <= 0.0:
        return -math.inf
    log_match = -0.5 * d2 - math.log(2.0 * math.pi) - 0.5 * logdet_psi
    return log_match - math.log(density * range_m)


def psi_logdet(psi: FloatArray | None) -> float:
    """``log det Psi`` of an innovation covariance; NaN when there is none (the
    landmark could not be predicted) or it is not positive definite."""
    if psi is None:
        return math.nan
    sign, logdet = np.linalg.slogdet(psi)
    return float(logdet) if sign > 0 else math.nan


def refuses(d2: float, psi: FloatArray | None, range_m: float, density: float,
            odds: float) -> bool:
    """Whether the alias test refuses a gated range-bearing pair: its log-odds
    (:func:`match_log_odds`) under ``log odds`` (``odds`` > 0). A pair without a
    usable ``Psi`` (:func:`psi_logdet` NaN) is refused."""
    return match_log_odds(d2, psi_logdet(psi), range_m, density) < math.log(odds)


def map_density(xy: FloatArray, spacing: float = 0.0) -> float:
    """Landmarks per m^2: ``1 / spacing^2``, or from the map when ``spacing`` is 0.

    Args:
        xy: (M, 2) world positions of the mapped planar landmarks, m.
        spacing: a stated spacing, m; 0: the median nearest-neighbour distance of
            ``xy`` (landmarks closer than 0.5 m to their nearest neighbour, copies of
            one tree, are skipped).

    Returns:
        The density; 0 (no test) when ``spacing`` is 0 and fewer than
        :data:`MIN_LANDMARKS` landmarks are mapped.
    """
    if spacing > 0.0:
        return 1.0 / (spacing * spacing)
    pts = np.asarray(xy, float).reshape(-1, 2)
    if len(pts) < MIN_LANDMARKS:
        return 0.0
    dist, _ = cKDTree(pts).query(pts, k=2)
    nn = dist[:, 1]
    nn = nn[nn > 0.5]
    if len(nn) < MIN_LANDMARKS // 2:
        return 0.0
    s = float(np.median(nn))
    return 1.0 / (s * s)
