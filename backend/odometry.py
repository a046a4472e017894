"""Odometry as the backends see it: the model's constants and checked increments.

The ceiling robot's odometry is differential-drive wheel travel ``(d_left, d_right)``
per sample (paper 1, eqs. 13-15; :mod:`lampsam.factors.motion`). Every backend (EKF,
iSAM2, batch) reads the same constants through :class:`WheelParams` and validates a
step's increments with :func:`check_wheel`.
"""

from __future__ import annotations

from typing import Protocol

import numpy as np

from lampsam.arrays import FloatArray
from lampsam.errors import EstimationError


class WheelParams(Protocol):
    """The wheel model's constants (``lampsam.datasets.logrun.OdometryModel`` is one).

    Attributes:
        wheel_base: distance between the wheels, m.
        k_r, k_l: wheel noise variances per metre of travel, m (eq. 15:
            ``var(d) = k |d|``).
    """

    @property
    def wheel_base(self) -> float: ...  # noqa: D102

    @property
    def k_r(self) -> float: ...  # noqa: D102

    @property
    def k_l(self) -> float: ...  # noqa: D102


def check_wheel(t: float, wheel: FloatArray) -> FloatArray:
    """Validate a step's wheel travels.

    Args:
        t: step time, s (for the message).
        wheel: (K, 2) ``(d_left, d_right)`` travels, m.

    Returns:
        The travels as a float (K, 2) array.

    Raises:
        EstimationError: wrong shape or NaN / inf.
    """
    arr = np.asarray(wheel, dtype=float).reshape(-1, 2)
    if not np.all(np.isfinite(arr)):
        raise EstimationError(f"t={t:.3f} s: odometry increment is NaN or inf")
    return arr
