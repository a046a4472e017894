"""How a landmark kind lives in the factor graph: the handler protocol and its record.

The smoothers (:mod:`lampsam.backend.graph`) keep one :class:`GraphLandmark` per
landmark and leave everything kind-specific (which variables, which factors, how
to read the EKF-form state back) to a :class:`LandmarkHandler`:

- :class:`Point2Handler`: planar range-bearing, ``L(j)`` a ``Point2`` with GTSAM's
  built-in ``BearingRangeFactor2D`` (DESIGN sec. 4);
- :class:`lampsam.backend.ceiling_graph.CeilingHandler`: lamps and corners.

The EKF-form state of each kind is described in :mod:`lampsam.backend.models`.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Literal, Protocol, TypeAlias

import gtsam
import numpy as np
from gtsam.symbol_shorthand import L, X

from lampsam.arrays import FloatArray
from lampsam.backend.config import SlamConfig
from lampsam.backend.interface import LandmarkKind
from lampsam.backend.models import Obs
from lampsam.errors import EstimationError
from lampsam.factors.gtsam_factors import check_cov, noise_model

#: How a graph value is read: ``Point2``/``Point3``/``Vector`` as arrays, or a ``Pose2``.
ValueKind: TypeAlias = Literal["point2", "point3", "vector", "pose2"]

#: A value in a GTSAM ``Values`` as Python sees it.
GraphValue: TypeAlias = gtsam.Pose2 | FloatArray

#: ``get(key, kind)`` -> the current estimate of a graph variable.
ValueSource: TypeAlias = Callable[[int, ValueKind], GraphValue]

#: ``marginal_of(key)`` -> (d, d) marginal covariance of a graph variable (tangent).
MarginalSource: TypeAlias = Callable[[int], FloatArray]

#: ``pose_of(k)`` -> (3,) current estimate of keyframe ``k``, world frame.
PoseSource: TypeAlias = Callable[[int], FloatArray]


@dataclass
class GraphLandmark:
    """A landmark known to a graph backend.

    Attributes:
        id: landmark id (``L(id)`` in the graph; the known id when association is known).
        kind: the landmark kind.
        in_graph: its variables are in the graph (else pending: gated, not yet added).
        n_obs: observations associated with it.
        state: (d,) EKF-form estimate, world frame (refreshed from iSAM2 when gating).
        cov: (d, d) first-sight covariance (eq. 25 marginal, or a triangulation's).
        pending: ``(keyframe, observation)`` pairs not yet in the graph.
        patch: corner image patch for NCC, or None.
        oriented: a lamp with an axis in its state.
        last_kf: last keyframe that observed it.
        cov_rel: (3, 3) position covariance relative to the pose of ``last_kf``, or None.
        sights: first sights of a lamp (triangulated to tighten its gate).
        first_kf: keyframe of its first sighting.
    """

    id: int
    kind: LandmarkKind
    in_graph: bool
    n_obs: int
    state: FloatArray
    cov: FloatArray
    pending: list[tuple[int, Obs]] = field(default_factory=list)
    patch: np.ndarray | None = None
    oriented: bool = False
    last_kf: int = 0
    cov_rel: FloatArray | None = None
    sights: list[tuple[int, Obs]] = field(default_factory=list)
    first_kf: int = 0


class ValueSink(Protocol):
    """Where a handler inserts new variables (``gtsam.Values`` is one)."""

    def insert(self, key: int, value: GraphValue) -> None:
        """Insert a new variable with its initial value."""


class FactorSink(Protocol):
    """Where a handler adds prior factors (``gtsam.NonlinearFactorGraph`` is one)."""

    def add(self, factor: gtsam.NonlinearFactor) -> None:
        """Add a factor."""


class LandmarkHandler(Protocol):
    """What the smoothers need of a landmark kind in the graph."""

    def insert(self, lm: GraphLandmark, values: ValueSink) -> None:
        """Insert the landmark's variable(s) with its current estimate."""

    def priors(self, lm: GraphLandmark, graph: FactorSink, pose_of: PoseSource,
               config: SlamConfig) -> None:
        """Add the priors a newly inserted landmark needs (e.g. the height prior)."""

    def factors(self, lm: GraphLandmark, k: int, obs: Obs, robust: float | None
                ) -> list[gtsam.NonlinearFactor]:
        """Factors of one observation of ``lm`` from keyframe ``k`` (Huber if ``robust``)."""

    def flush(self, robust: float | None, pose_of: PoseSource) -> list[gtsam.NonlinearFactor]:
        """Factors buffered during a keyframe, given once its observations are in."""

    def read(self, lm: GraphLandmark, get: ValueSource) -> FloatArray:
        """(d,) EKF-form state from an estimate source."""

    def marginal(self, lm: GraphLandmark, marginal_of: MarginalSource) -> FloatArray:
        """(d, d) covariance of the EKF-form state from a marginal source."""

    def state_index(self, lm: GraphLandmark) -> list[int]:
        """Rows of the EKF-form state in the stacked tangent of :meth:`keys`."""

    def keys(self, lm: GraphLandmark) -> list[int]:
        """Graph keys of the landmark, in state order."""


#: Distinct noise models a :class:`Point2Handler` keeps (cleared when full).
NOISE_CACHE_SIZE = 4096


class Point2Handler:
    """Planar range-bearing landmarks: ``Point2`` + GTSAM's ``BearingRangeFactor2D``.

    One noise model per distinct ``(covariance, robust)``, validated once
    (:func:`lampsam.factors.gtsam_factors.check_cov`) and shared by the factors
    that carry it (GTSAM's noise models are immutable): a log with one global
    range-bearing noise builds one, not one per sighting.
    """

    def __init__(self) -> None:
        self._noise: dict[tuple[bytes, float | None], gtsam.noiseModel.Base] = {}

    def noise(self, cov: FloatArray, robust: float | None) -> gtsam.noiseModel.Base:
        """The (cached) noise model of a (2, 2) ``[bearing, range]`` covariance.

        Raises:
            FactorError: a covariance that is not finite, (2, 2) and positive definite.
        """
        arr = np.asarray(cov, dtype=float)
        key = (arr.tobytes(), robust)
        model = self._noise.get(key)
        if model is None or arr.shape != (2, 2):
            model = noise_model(check_cov(arr, 2, "range-bearing"), robust)
            if len(self._noise) >= NOISE_CACHE_SIZE:
                self._noise.clear()
            self._noise[key] = model
        return model

    def insert(self, lm: GraphLandmark, values: ValueSink) -> None:
        """Insert ``L(id)`` at the landmark's current ``(x, y)``."""
        values.insert(L(lm.id), np.asarray(lm.state[:2], float))

    def priors(self, lm: GraphLandmark, graph: FactorSink, pose_of: PoseSource,
               config: SlamConfig) -> None:
        """No prior: one range-bearing sight determines a planar landmark."""

    def factors(self, lm: GraphLandmark, k: int, obs: Obs, robust: float | None
                ) -> list[gtsam.NonlinearFactor]:
        """``BearingRangeFactor2D(X(k), L(id))``, GTSAM's built-in factor (as
        :func:`lampsam.factors.gtsam_factors.bearing_range_factor` builds it without a
        sensor offset), with the cached noise model of ``obs.R``."""
        z0, z1 = obs.z.tolist()
        return [gtsam.BearingRangeFactor2D(X(k), L(lm.id), gtsam.Rot2(z0), z1,
                                           self.noise(obs.R, robust))]

    def flush(self, robust: float | None, pose_of: PoseSource) -> list[gtsam.NonlinearFactor]:
        """Nothing is buffered."""
        return []

    def read(self, lm: GraphLandmark, get: ValueSource) -> FloatArray:
        """``(x, y)`` of ``L(id)``, m."""
        return np.asarray(get(L(lm.id), "point2"), float)

    def marginal(self, lm: GraphLandmark, marginal_of: MarginalSource) -> FloatArray:
        """(2, 2) marginal of ``L(id)``, m^2."""
        return np.asarray(marginal_of(L(lm.id)))

    def state_index(self, lm: GraphLandmark) -> list[int]:
        """Both rows of the ``Point2`` tangent."""
        return [0, 1]

    def keys(self, lm: GraphLandmark) -> list[int]:
        """``[L(id)]``."""
        return [L(lm.id)]


def value_of_kind(values: gtsam.Values, key: int, kind: ValueKind) -> GraphValue:
    """The value of ``key`` read as ``kind``.

    Raises:
        EstimationError: an unknown kind.
    """
    if kind == "point2":
        return np.asarray(values.atPoint2(key), float)
    if kind == "point3":
        return np.asarray(values.atPoint3(key), float)
    if kind == "vector":
        return np.asarray(values.atVector(key), float)
    if kind == "pose2":
        return values.atPose2(key)
    raise EstimationError(f"unknown graph value kind {kind!r}")


def value_at(values: gtsam.Values, key: int) -> GraphValue:
    """The value of ``key`` in its own type (``Pose2`` for ``x``/``a`` keys, else an array).

    Raises:
        EstimationError: the value is none of ``Point3``, ``Point2``, ``Vector``.
    """
    ch = chr(gtsam.Symbol(key).chr())
    if ch in ("x", "a"):
        return values.atPose2(key)
    for getter in (values.atPoint3, values.atPoint2, values.atVector):
        try:
            return np.asarray(getter(key), float)
        except RuntimeError:
            continue
    raise EstimationError(f"cannot read graph value {gtsam.DefaultKeyFormatter(key)}")
