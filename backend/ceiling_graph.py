"""Ceiling landmarks in the factor graphs (lamps and corners), via :mod:`lampsam.factors.gtsam_factors`.

Variables: ``L(j)`` a world ``Point3`` for every lamp and corner; ``A(j)`` a ``Rot2``
for the long axis of an oriented lamp. Factors:

- position: :func:`~lampsam.factors.gtsam_factors.projection_factor` (GTSAM's built-in
  ``PlanarProjectionFactor2``: C++, no Python callback inside the optimiser);
- axis: :func:`~lampsam.factors.gtsam_factors.lamp_axis_frame_factor`, one
  ``CustomFactor`` per keyframe for all its lamp axes (a Python callback from inside
  iSAM2 copies the whole ``Values``, so fewer, larger custom factors are cheaper);
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

from typing import Any

import gtsam
import numpy as np
from gtsam.symbol_shorthand import A, L, X

from lampsam.arrays import FloatArray
from lampsam.backend.ceiling import CeilingModel
from lampsam.backend.config import SlamConfig
from lampsam.factors.geometry import wrap_axis
from lampsam.factors.gtsam_factors import (
    AxisObservation,
    height_prior_factor,
    lamp_axis_frame_factor,
    projection_factor,
)


class CeilingHandler:
    """Graph handler for ``lamp`` and ``corner`` landmarks (see module docstring).

    Args:
        model: the rig's ceiling model (camera offset).
    """

    def __init__(self, model: CeilingModel) -> None:
        self.model = model
        self._axis: dict[int, list[AxisObservation]] = {}

    @staticmethod
    def _oriented(lm: Any) -> bool:
        return bool(lm.kind == "lamp" and len(lm.state) == 4)

    def insert(self, lm: Any, values: Any) -> None:
        """Insert ``L(j)`` (and ``A(j)``) with the landmark's current estimate."""
        values.insert(L(lm.id), np.asarray(lm.state[:3], float))
        if self._oriented(lm):
            values.insert(A(lm.id), gtsam.Rot2(float(lm.state[3])))

    def priors(self, lm: Any, graph: Any, pose_of: Any, config: SlamConfig) -> None:
        """The height prior on ``L(j)`` (eqs. 24-25's 0-5 m range)."""
        graph.add(height_prior_factor(L(lm.id), lm.state[:2], self.model.body_t_camera,
                                      config.association.height_prior()))

    def factors(self, lm: Any, k: int, obs: Any, robust: float | None
                ) -> list[gtsam.NonlinearFactor]:
        """Projection factor; an axis observation is buffered for :meth:`flush`."""
        if self._oriented(lm) and obs.has_axis:
            self._axis.setdefault(k, []).append(
                AxisObservation(A(lm.id), float(obs.z[2]), float(np.sqrt(obs.R[2, 2]))))
        return [projection_factor(X(k), L(lm.id), obs.z[:2], obs.R[:2, :2],
                                  self.model.body_t_camera, robust)]

    def flush(self, robust: float | None) -> list[gtsam.NonlinearFactor]:
        """One axis factor per keyframe for the buffered axis observations."""
        out: list[gtsam.NonlinearFactor] = []
        for k, items in self._axis.items():
            groups: list[list[AxisObservation]] = [[]]
            for item in items:  # a lamp seen twice in one frame goes to a second factor
                g = next((g for g in groups if all(o.axis_key != item.axis_key for o in g)), None)
                if g is None:
                    g = []
                    groups.append(g)
                g.append(item)
            out.extend(lamp_axis_frame_factor(X(k), g, robust) for g in groups if g)
        self._axis = {}
        return out

    def read(self, lm: Any, get: Any) -> FloatArray:
        """EKF-form state from an estimate source ``get(key, kind)``."""
        p = np.asarray(get(L(lm.id), "point3"), float)
        if self._oriented(lm):
            phi = float(wrap_axis(get(A(lm.id), "rot2").theta()))
            return np.array([*p, phi])
        return p

    def marginal(self, lm: Any, marginal_of: Any) -> FloatArray:
        """``blockdiag(cov(L), var(A))`` from a marginal-covariance source."""
        c = np.asarray(marginal_of(L(lm.id)))
        if not self._oriented(lm):
            return c
        out = np.zeros((4, 4))
        out[:3, :3] = c
        out[3, 3] = float(np.asarray(marginal_of(A(lm.id)))[0, 0])
        return out

    def keys(self, lm: Any) -> list[int]:
        """Graph keys of the landmark."""
        return [L(lm.id), A(lm.id)] if self._oriented(lm) else [L(lm.id)]
