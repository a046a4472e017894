"""Frozen measurement dataclasses: what the frontend hands to the backends.

All image positions the estimators use are **normalised ceiling coordinates**
``m = (u, v)`` (docs/conventions.md): undistort the pixel to the camera ray
``(x_n, y_n, 1)``, rotate it into body axes and divide by the vertical
component, so ``u`` points robot-forward and ``v`` robot-left, per metre of
height above the camera. Raw pixels (OpenCV ``(col, row)``) are kept only for
drawing and for image-space matching.

Angles are radians. A lamp's long axis is a line, so it is defined modulo pi
and stored wrapped to ``(-pi/2, pi/2]`` (``alpha = atan2(dv, du)`` of the axis
direction in the ``(u, v)`` plane; conventions.md, "Angles").
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from lampsam.arrays import FloatArray


@dataclass(frozen=True)
class LampObservation:
    """One ceiling lamp seen in one image (paper 1, eqs. 1-7).

    Attributes:
        m: shape (2,), centroid in normalised ceiling coordinates ``(u, v)``
            (dimensionless: metres per metre of height).
        cov_m: shape (2, 2), covariance of ``m`` (same units squared).
        axis: long-axis direction ``alpha`` in the ``(u, v)`` plane, radians,
            modulo pi, wrapped to ``(-pi/2, pi/2]``; None for a point lamp
            (``ratio <= threshold``, default 1.5).
        var_axis: variance of ``axis`` (rad^2); ``inf`` when ``axis`` is None.
        ratio: ``R_ori = sigma1 / sigma2`` (paper eq. 7), >= 1.
        area_px: blob area in pixels.
        pixel: shape (2,), raw (distorted) centroid in pixels ``(col, row)``.
        landmark_id: known association (simulator truth), else None.
        touches_border: the blob touches the image border; its centroid and axis
            are biased. The detector drops such blobs by default; when kept
            (``FrontendConfig.keep_border_lamps``) the backends must not use them.
    """

    m: FloatArray
    cov_m: FloatArray
    axis: float | None
    var_axis: float
    ratio: float
    area_px: float
    pixel: FloatArray
    landmark_id: int | None = None
    touches_border: bool = False

    @property
    def oriented(self) -> bool:
        """True when the lamp has a usable long axis."""
        return self.axis is not None


@dataclass(frozen=True)
class CornerObservation:
    """One FAST corner on the ceiling (paper 1, sec. II; matched by NCC).

    Attributes:
        m: shape (2,), position in normalised ceiling coordinates ``(u, v)``.
        cov_m: shape (2, 2), covariance of ``m``.
        pixel: shape (2,), raw pixel position ``(col, row)``.
        patch: shape (P, P) float32, grey-level patch centred on ``pixel``
            (zero mean, unit norm: ready for NCC as a dot product).
        score: FAST response (OpenCV's corner strength).
        landmark_id: known association (simulator truth), else None.
    """

    m: FloatArray
    cov_m: FloatArray
    pixel: FloatArray
    patch: np.ndarray
    score: float
    landmark_id: int | None = None


@dataclass(frozen=True)
class CeilingFrame:
    """Everything the ceiling camera gave at one time.

    Attributes:
        t: time stamp, seconds (the run's clock).
        index: image index within the run.
        lamps: the lamp observations (border blobs excluded unless configured).
        corners: the corner observations.
    """

    t: float
    index: int
    lamps: tuple[LampObservation, ...] = field(default_factory=tuple)
    corners: tuple[CornerObservation, ...] = field(default_factory=tuple)


@dataclass(frozen=True)
class RangeBearingObservation:
    """A range-bearing measurement in the robot's body frame.

    Attributes:
        range: distance to the landmark, metres.
        bearing: angle from body ``x`` (forward), counter-clockwise, radians,
            wrapped to ``(-pi, pi]``.
        landmark_id: known association, else None.
        cov: (2, 2) noise covariance of ``[bearing, range]`` (rad^2, m^2; GTSAM's
            ``BearingRangeFactor2D`` order), or None for the configured default.
    """

    range: float
    bearing: float
    landmark_id: int | None = None
    cov: FloatArray | None = None


@dataclass(frozen=True)
class RangeBearingFrame:
    """All range-bearing measurements at one time.

    Attributes:
        t: time stamp, seconds.
        observations: the measurements.
    """

    t: float
    observations: tuple[RangeBearingObservation, ...] = field(default_factory=tuple)
