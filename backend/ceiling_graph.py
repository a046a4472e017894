"""Ceiling landmarks in the factor graphs (lamps and corners), via :mod:`lampsam.factors.gtsam_factors`.

Variables: ``L(j)`` a world ``Point3`` for every lamp, ``C(j)`` one for every corner
(:func:`point_key`; landmark ids are unique across kinds, so ``j`` is the id either way);
``A(j)`` a ``Pose2`` for the long axis of an oriented lamp (its angle is the axis; its
translation carries no information and is held by a prior). Lamps and corners have
their own symbol characters so that iSAM2 can relinearise lamps on a tighter threshold
than corners (:data:`CEILING_SYMBOLS`, ``[isam2] lamp_relinearize_threshold``; GTSAM's
threshold map is per character). Factors:

- position: :func:`~lampsam.factors.gtsam_factors.projection_factor` (GTSAM's built-in
  ``PlanarProjectionFactor2``: C++, no Python callback inside the optimiser);
- axis: :func:`~lampsam.factors.axis_factors.lamp_axis_between_factor`, GTSAM's
  built-in ``BetweenFactorPose2`` with zero precision on ``x, y``, plus one
  :func:`~lampsam.factors.axis_factors.axis_anchor_prior` per lamp. It replaced one
  ``CustomFactor`` per keyframe (:func:`~lampsam.factors.axis_factors.lamp_axis_frame_factor`):
  each Python callback from inside an optimiser copies the whole ``Values``, so its
  cost grows with the run (measured: docs/graph-backend.md);
- the 0-5 m height prior on every point:
  :func:`~lampsam.factors.gtsam_factors.height_prior_factor`.

Corners use the Cartesian ``Point3`` with the built-in projection rather than the
inverse-depth ``CustomFactor`` that :mod:`lampsam.factors` also offers: the smoother
relinearises, a corner enters the graph only after two sights (so it is never
initialised from one ray alone), and the built-in avoids a Python call per factor
from inside iSAM2 (DESIGN sec. 6), which the online timing target needs.

The EKF-form state (:mod:`lampsam.backend.ceiling`) is ``(x, y, z)`` or
``(x, y, z, phi)``; its covariance for gating is ``blockdiag(cov(L), var(A))``
(the point-axis cross term, small, is neglected).
"""

from __future__ import annotations

from collections.abc import Container

import gtsam
import numpy as np
from gtsam.symbol_shorthand import A, C, L, X

from lampsam.arrays import FloatArray
from lampsam.backend.ceiling import CeilingModel
from lampsam.backend.config import IsamSymbol, SlamConfig
from lampsam.backend.handlers import (
    FactorSink,
    GraphLandmark,
    MarginalSource,
    PoseSource,
    ValueSink,
    ValueSource,
)
from lampsam.backend.interface import LandmarkKind
from lampsam.backend.models import Obs
from lampsam.errors import EstimationError
from lampsam.factors.axis_factors import (
    AxisObservation,
    axis_anchor_prior,
    lamp_axis_between_factor,
)
from lampsam.factors.geometry import wrap_axis
from lampsam.factors.gtsam_factors import height_prior_factor, projection_factor

#: The ceiling graph's variable characters -> (tangent dimension, is a lamp's): the
#: per-character relinearisation thresholds of :meth:`~lampsam.backend.config.Isam2Config.to_gtsam`
#: (GTSAM's map must name every character in the graph, each with its dimension).
CEILING_SYMBOLS: dict[str, IsamSymbol] = {
    "x": IsamSymbol(3, lamp=False),  # keyframe poses, Pose2
    "l": IsamSymbol(3, lamp=True),  # lamp positions, Point3
    "a": IsamSymbol(3, lamp=True),  # lamp axes, Pose2
    "c": IsamSymbol(3, lamp=False),  # corner positions, Point3
}


_CORNER = str(LandmarkKind.CORNER)  # a plain str: comparing with it skips the enum's lookup


def point_key(kind: str, lid: int) -> int:
    """The graph key of a ceiling landmark's position: ``C(lid)`` for a corner, else ``L(lid)``."""
    return C(lid) if kind == _CORNER else L(lid)  # type: ignore[no-any-return]


def find_point_key(lid: int, keys: Container[int]) -> int | None:
    """The position key of landmark ``lid`` (``L`` or ``C``) that is in ``keys``, or None.

    For readers that know a landmark's id but not its kind (ids are unique across kinds,
    so at most one of the two is in a graph).
    """
    for key in (int(L(lid)), int(C(lid))):
        if key in keys:
            return key
    return None


class CeilingHandler:
    """Graph handler (:class:`~lampsam.backend.handlers.LandmarkHandler`) for ``lamp`` and ``corner`` landmarks (see module docstring).

    Args:
        model: the rig's ceiling model (camera offset).
    """

    def __init__(self, model: CeilingModel) -> None:
        self.model = model
        self._axis: dict[int, list[AxisObservation]] = {}
        # the angle each A(j) was inserted with: the graph's representative mod pi
        self._phi0: dict[int, float] = {}

    @staticmethod
    def _oriented(lm: GraphLandmark) -> bool:
        return bool(lm.kind == LandmarkKind.LAMP and len(lm.state) == 4)

    def insert(self, lm: GraphLandmark, values: ValueSink) -> None:
        """Insert ``L(j)`` or ``C(j)`` (and ``A(j)``) with the landmark's current estimate."""
        values.insert(point_key(lm.kind, lm.id), np.asarray(lm.state[:3], float))
        if self._oriented(lm):
            phi = float(lm.state[3])
            self._phi0[A(lm.id)] = phi
            values.insert(A(lm.id), gtsam.Pose2(float(lm.state[0]), float(lm.state[1]), phi))

    def priors(self, lm: GraphLandmark, graph: FactorSink, pose_of: PoseSource,
               config: SlamConfig) -> None:
        """The height prior on the position (eqs. 24-25's 0-5 m range); an axis's anchor."""
        graph.add(height_prior_factor(point_key(lm.kind, lm.id), lm.state[:2], self.model.body_t_camera,
                                      config.association.height_prior()))
        if self._oriented(lm):
            graph.add(axis_anchor_prior(A(lm.id), lm.state[:2], float(lm.state[3])))

    def factors(self, lm: GraphLandmark, k: int, obs: Obs, robust: float | None
                ) -> list[gtsam.NonlinearFactor]:
        """Projection factor; an axis observation is buffered for :meth:`flush`."""
        if self._oriented(lm) and obs.has_axis:
            self._axis.setdefault(k, []).append(
                AxisObservation(A(lm.id), float(obs.z[2]), float(np.sqrt(obs.R[2, 2]))))
        return [projection_factor(X(k), point_key(lm.kind, lm.id), obs.z[:2], obs.R[:2, :2],
                                  self.model.body_t_camera, robust)]

    def flush(self, robust: float | None, pose_of: PoseSource) -> list[gtsam.NonlinearFactor]:
        """The buffered axis observations as factors.

        Args:
            robust: optional Huber threshold.
            pose_of: ``pose_of(k)`` -> (3,) current estimate of keyframe ``k``; its
                heading picks each measurement's representative mod pi.
        """
        out: list[gtsam.NonlinearFactor] = []
        for k, items in self._axis.items():
            theta = float(pose_of(k)[2])
            out.extend(lamp_axis_between_factor(X(k), o.axis_key, o.alpha, o.sigma,
                                                self._phi0[o.axis_key] - theta, robust)
                       for o in items)
        self._axis = {}
        return out

    def read(self, lm: GraphLandmark, get: ValueSource) -> FloatArray:
        """EKF-form state from an estimate source ``get(key, kind)``."""
        p = np.asarray(get(point_key(lm.kind, lm.id), "point3"), float)
        if self._oriented(lm):
            axis = get(A(lm.id), "pose2")
            if not isinstance(axis, gtsam.Pose2):
                raise EstimationError(f"lamp axis A({lm.id}) is not a Pose2")
            phi = float(wrap_axis(axis.theta()))
            return np.array([*p, phi])
        return p

    def marginal(self, lm: GraphLandmark, marginal_of: MarginalSource) -> FloatArray:
        """``blockdiag(cov(L), var(A))`` from a marginal-covariance source."""
        c = np.asarray(marginal_of(point_key(lm.kind, lm.id)))
        if not self._oriented(lm):
            return c
        out = np.zeros((4, 4))
        out[:3, :3] = c
        out[3, 3] = float(np.asarray(marginal_of(A(lm.id)))[2, 2])
        return out

    def state_index(self, lm: GraphLandmark) -> list[int]:
        """Rows of the EKF-form state in the tangent of :meth:`keys` (``L``/``C``: 3, ``A``: 3)."""
        return [0, 1, 2, 5] if self._oriented(lm) else [0, 1, 2]

    def keys(self, lm: GraphLandmark) -> list[int]:
        """Graph keys of the landmark."""
        key = point_key(lm.kind, lm.id)
        return [key, int(A(lm.id))] if self._oriented(lm) else [key]
