"""Online robust scale of the association gate's normalised innovations
(``[association] odometry_noise_adapt``; shared by the EKF and the smoothers).

A log's stated noise is often conservative or optimistic; the confirmed matches'
squared Mahalanobis distances (paper 1, eq. 20) tell by how much. This module keeps
their running median over a window and turns it into a scale of the innovation
covariance ``Psi`` (eq. 19) that the gate then uses.
"""

from __future__ import annotations

import collections
import math
from collections.abc import Mapping

import numpy as np
from scipy.special import chdtri

from lampsam.backend.association import Assignment
from lampsam.backend.config import AssociationConfig
from lampsam.backend.models import Obs


class InnovationScale:
    """Online robust scale of the normalised innovations of confirmed matches.

    A log's stated measurement noise is often conservative: on Victoria Park the
    file's bearing sigma (0.2 rad) is about 4x the scatter of the residuals at the
    optimum, so correct matches have squared Mahalanobis distances (eq. 20) near
    0.03 where a chi-square(2) variable has median 1.39, and the gate admits trees
    metres apart. If the innovation covariance ``Psi`` (eq. 19) of correct matches
    is overstated by a factor ``1/s``, their distances ``d2 = nu^T Psi^-1 nu`` are
    ``s`` times chi-square distributed; the gate then uses ``d2 / s`` (the whole
    ``Psi`` scaled by ``s``, pose and landmark parts included, since they were
    built from the same conservative noise).

    Estimator: only matches inside the gate are ever seen, so the sample is a
    chi-square truncated at the gate ``g`` (quantile ``p``). Under the scaled model
    the median of the accepted distances is ``s * chi2.ppf(p / 2, dof)``, so
    ``s_hat = median(d2 of the last `window` matches) / chi2.ppf(p / 2, dof)``,
    multiplied by ``margin`` (>= 1, conservative: a few wrong matches or a filter
    that grows inconsistent must not close the gate on the right ones) and clamped
    to ``[floor, 1]``: the gate never gets wider than the stated noise gives, nor
    narrower than ``floor`` of it. Until ``min_count`` matches are in, ``s = 1``.

    Args:
        dof: innovation dimension (2 for ``[bearing, range]``).
        gate_prob: the gate's chi-square probability ``p``.
        window: matches kept (the most recent).
        min_count: matches needed before the scale leaves 1.
        floor: the smallest scale.
        margin: factor on the estimate.
    """

    def __init__(self, dof: int = 2, gate_prob: float = 0.99, window: int = 200,
                 min_count: int = 20, floor: float = 0.05, margin: float = 2.0) -> None:
        if not (0.0 < floor <= 1.0) or margin <= 0.0 or window < 1 or min_count < 1:
            raise ValueError(f"InnovationScale: need 0 < floor <= 1, margin > 0, window, "
                             f"min_count >= 1 (got {floor}, {margin}, {window}, {min_count})")
        self.window = window
        self.min_count = min_count
        self.floor = floor
        self.margin = margin
        # chi2.ppf(p / 2, dof) through scipy.special: importing scipy.stats costs
        # ~0.5 s of CPU, once per process, and every graph backend and EKF makes one
        self._ref = float(chdtri(dof, 1.0 - gate_prob / 2.0))
        self._d2: collections.deque[float] = collections.deque(maxlen=window)
        self.scale = 1.0
        self.n_seen = 0

    def add(self, d2: float) -> float:
        """Add the (unscaled) squared distance of one confirmed match; the new scale."""
        if math.isfinite(d2) and d2 >= 0.0:
            self._d2.append(float(d2))
            self.n_seen += 1
            if len(self._d2) >= self.min_count:
                s = self.margin * float(np.median(np.fromiter(self._d2, float))) / self._ref
                self.scale = min(1.0, max(self.floor, s))
        return self.scale


def innovation_scale(config: AssociationConfig) -> InnovationScale:
    """The range-bearing gate's :class:`InnovationScale` from ``config``.

    With ``planar_noise_adapt`` off the floor is 1, so the scale stays 1 (the
    stated noise).
    """
    return InnovationScale(2, config.gate_prob, config.planar_noise_window,
                           min(20, config.planar_noise_window),
                           config.planar_noise_floor if config.planar_noise_adapt else 1.0,
                           config.planar_noise_margin)


def learn_scale(scale: InnovationScale, observations: list[Obs], assignments: list[Assignment],
                screened: Mapping[int, Mapping[int, tuple[float, bool]]]) -> None:
    """Feed a frame's unambiguous planar matches to ``scale``.

    A match counts when its observation has no id, its distance is exact (the one
    :func:`associate` decided with, else the screen's exact one) and it is the only
    landmark below the new-landmark threshold (so a wrong match would have had to
    beat no rival: the sample is as clean as the gate can make it). The distances
    in ``screened`` are the scaled ones (``d2 / scale``); the estimator gets them
    unscaled, all at the scale the frame was gated with.
    """
    if scale.floor >= 1.0:
        return
    s = scale.scale
    todo: list[float] = []
    for a in assignments:
        i = a.obs_index
        if (a.status != "matched" or a.landmark_id is None or i not in screened
                or observations[i].kind != "point2" or len(screened[i]) != 1):
            continue
        d2, exact = screened[i].get(a.landmark_id, (math.nan, False))
        if not math.isnan(a.d2):  # the exact distance associate decided with
            d2, exact = a.d2, True
        if exact:
            todo.append(d2 * s)
    for d2 in todo:
        scale.add(d2)
