"""Observation models as the backends see them: one record type, one predict/init API.

Every backend turns frontend observations into :class:`Obs` records (measurement
vector ``z`` and its noise ``R``) and asks this module for the predicted
measurement and its Jacobians, which come from the pure models in
:mod:`lampsam.factors` (the EKF and the factor graphs share them: DESIGN sec. 4).

Landmark kinds and their EKF state (world frame):

- ``point2``: planar range-bearing landmark ``(x, y)``, m; ``z = [bearing, range]``
  (GTSAM's ``BearingRangeFactor2D`` order, :func:`lampsam.factors.range_bearing.range_bearing`).
- ``lamp``: ceiling lamp ``(x, y, z)`` or, when oriented, ``(x, y, z, phi)``;
  ``z = (u, v)`` or ``(u, v, alpha)`` (normalised ceiling coordinates, axis angle).
- ``corner``: ceiling corner ``(x, y, z)``; ``z = (u, v)``.

Pose Jacobians are w.r.t. GTSAM's right tangent (conventions.md); the EKF converts
them with :func:`lampsam.factors.geometry.tangent_D_coords`.
"""

from __future__ import annotations

import dataclasses
import logging
import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from lampsam.arrays import FloatArray
from lampsam.backend.config import AssociationConfig, MeasurementNoiseConfig
from lampsam.backend.interface import LandmarkEstimate, LandmarkKind
from lampsam.factors.geometry import coords_D_tangent, wrap_angle, wrap_axis
from lampsam.factors.range_bearing import range_bearing
from lampsam.frontend.measurements import CeilingFrame, RangeBearingFrame

if TYPE_CHECKING:  # ceiling.py takes Obs records: import its type for annotations only
    from lampsam.backend.ceiling import CeilingModel

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Obs:
    """One observation in backend form.

    Attributes:
        kind: ``"point2"``, ``"lamp"`` or ``"corner"``.
        z: (k,) measurement vector (see module docstring).
        R: (k, k) measurement noise covariance.
        landmark_id: known association, or None.
        has_axis: a lamp observation with a usable axis (``z`` has 3 entries).
        patch: corner image patch for NCC (zero mean, unit norm), or None.
    """

    kind: LandmarkKind
    z: FloatArray
    R: FloatArray
    landmark_id: int | None = None
    has_axis: bool = False
    patch: np.ndarray | None = None


def observations_from_frame(
    frame: CeilingFrame | RangeBearingFrame,
    features: tuple[str, ...],
    noise: MeasurementNoiseConfig,
) -> list[Obs]:
    """Convert a frontend frame into :class:`Obs` records.

    Lamps touching the image border are skipped (biased centroid, frontend docs);
    ``features`` selects ``"lamps"`` and/or ``"corners"`` (range-bearing frames
    ignore it).

    Args:
        frame: the frame.
        features: subset of ``("lamps", "corners")``.
        noise: default noise of range-bearing observations (an observation's own
            ``cov`` replaces it) and the lamp-axis variance floor.

    Returns:
        The observations, in frame order.
    """
    out: list[Obs] = []
    if isinstance(frame, RangeBearingFrame):
        r = np.diag([noise.sigma_bearing**2, noise.sigma_range**2])
        for o in frame.observations:
            if not (math.isfinite(o.range) and math.isfinite(o.bearing)) or o.range <= 0:
                continue
            r_o = r if o.cov is None else np.asarray(o.cov, float)
            out.append(Obs(LandmarkKind.POINT2, np.array([o.bearing, o.range]), r_o,
                           o.landmark_id))
        return out
    if "lamps" in features:
        for lamp in frame.lamps:
            if lamp.touches_border:
                continue
            if lamp.axis is not None and math.isfinite(lamp.var_axis):
                cov = np.zeros((3, 3))
                cov[:2, :2] = lamp.cov_m
                cov[2, 2] = max(lamp.var_axis, noise.var_axis_min)
                z = np.array([lamp.m[0], lamp.m[1], lamp.axis])
                out.append(Obs(LandmarkKind.LAMP, z, cov, lamp.landmark_id, has_axis=True))
            else:
                out.append(Obs(LandmarkKind.LAMP, np.asarray(lamp.m, float), np.asarray(lamp.cov_m, float),
                               lamp.landmark_id))
    if "corners" in features:
        for c in frame.corners:
            out.append(Obs(LandmarkKind.CORNER, np.asarray(c.m, float), np.asarray(c.cov_m, float),
                           c.landmark_id, patch=c.patch))
    return out


def for_landmark(obs: Obs, state_dim: int) -> Obs:
    """The part of ``obs`` that a landmark with a ``state_dim`` state can predict.

    A lamp first seen without a usable axis has a position-only state ``(x, y, z)``;
    when a later frame does measure its axis, that observation updates the position
    only (paper 1, III.4, the converse case), so the axis row is dropped here rather
    than the state being resized. Everything else is returned unchanged.

    Args:
        obs: the observation.
        state_dim: length of the landmark's state (3: no axis, 4: with axis).
    """
    if obs.kind == "lamp" and obs.has_axis and state_dim < 4:
        return dataclasses.replace(obs, z=obs.z[:2].copy(), R=obs.R[:2, :2].copy(), has_axis=False)
    return obs


def residual(obs: Obs, z_hat: FloatArray) -> FloatArray:
    """Innovation ``z - z_hat`` with angles wrapped (bearing to (-pi, pi], axis mod pi).

    Args:
        obs: the observation.
        z_hat: (k,) predicted measurement.

    Returns:
        (k,) innovation.
    """
    nu = obs.z - z_hat
    if obs.kind == "point2":
        nu[0] = wrap_angle(float(nu[0]))
    elif obs.kind == "lamp" and obs.has_axis:
        nu[2] = wrap_axis(float(nu[2]))
    return nu


def predict_point2(pose: FloatArray, state: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Predicted ``[bearing, range]`` of a planar landmark (factors.range_bearing).

    Args:
        pose: (3,) ``world_T_body``.
        state: (2,) landmark ``(x, y)``, m.

    Returns:
        ``(z_hat (2,), z_D_pose (2, 3) right tangent, z_D_landmark (2, 2))``.
    """
    return range_bearing(pose, state)


def init_point2(pose: FloatArray, z: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Inverse range-bearing model: landmark from one observation (eq. 24, planar).

    ``l = t + r (cos(theta + b), sin(theta + b))``.

    Args:
        pose: (3,) ``world_T_body``.
        z: (2,) ``[bearing, range]``.

    Returns:
        ``(l (2,), l_D_pose (2, 3) w.r.t. the right tangent, l_D_z (2, 2))``.
    """
    b, r = float(z[0]), float(z[1])
    a = pose[2] + b
    c, s = math.cos(a), math.sin(a)
    l = np.array([pose[0] + r * c, pose[1] + r * s])
    l_D_coords = np.array([[1.0, 0.0, -r * s], [0.0, 1.0, r * c]])
    l_D_z = np.array([[-r * s, c], [r * c, s]])
    return l, l_D_coords @ coords_D_tangent(pose[2]), l_D_z


def predict(kind: LandmarkKind | str, pose: FloatArray, state: FloatArray, obs: Obs | None,
            ceiling: CeilingModel | None = None) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Predicted measurement of one landmark and its Jacobians.

    Args:
        kind: landmark kind.
        pose: (3,) ``world_T_body``.
        state: landmark state (module docstring).
        obs: the observation being predicted (selects the lamp axis row), or None
            for the full measurement.
        ceiling: the :class:`lampsam.backend.ceiling.CeilingModel` for ceiling kinds.

    Returns:
        ``(z_hat (k,), z_D_pose (k, 3) right tangent, z_D_state (k, d))``.
    """
    if kind == "point2":
        return predict_point2(pose, state)
    if ceiling is None:
        raise ValueError(f"ceiling landmark kind {kind!r} needs a CeilingModel")
    with_axis = obs.has_axis if obs is not None else len(state) == 4
    return ceiling.predict(pose, state, with_axis=with_axis and len(state) == 4)


def initialize(pose: FloatArray, obs: Obs, assoc: AssociationConfig,
               ceiling: CeilingModel | None = None) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """Undelayed landmark initialisation from one observation (paper eqs. 24-25).

    Ceiling landmarks get the height prior (``assoc.height_prior()``) as an extra "measurement" so that the first estimate is
    the long ellipse along the viewing ray (paper Fig. 7).

    Args:
        pose: (3,) ``world_T_body``.
        obs: the observation.
        assoc: prior height of ceiling landmarks.
        ceiling: the ceiling model for lamps/corners.

    Returns:
        ``(state (d,), state_D_pose (d, 3) right tangent, state_D_zaug (d, q),
        cov_zaug (q, q))``: eq. 25's ``g``, ``grad g_R``, ``grad g_Z`` and ``P_new``.
    """
    if obs.kind == "point2":
        l, l_D_pose, l_D_z = init_point2(pose, obs.z)
        return l, l_D_pose, l_D_z, obs.R
    if ceiling is None:
        raise ValueError(f"ceiling landmark kind {obs.kind!r} needs a CeilingModel")
    return ceiling.initialize(pose, obs, assoc.height_prior())


def try_initialize(pose: FloatArray, obs: Obs, assoc: AssociationConfig,
                   ceiling: CeilingModel | None = None
                   ) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray] | None:
    """:func:`initialize`, or None (logged at debug level) when the observation cannot start
    a landmark (the EKF's augmentation and the smoothers' new landmarks skip it)."""
    try:
        return initialize(pose, obs, assoc, ceiling)
    except Exception as exc:
        log.debug("cannot initialise a landmark: %s", exc)
        return None


def landmark_estimate(lid: int, kind: str, state: FloatArray, cov: FloatArray, n_obs: int,
                      ceiling: CeilingModel | None = None) -> LandmarkEstimate:
    """A :class:`LandmarkEstimate` from a landmark state in EKF form.

    Args:
        lid: id; kind: landmark kind; state: (d,) EKF-form state; cov: (d, d).
        n_obs: observations used.
        ceiling: the ceiling model (its ``world_position`` maps a ceiling state to
            world (x, y, z)), or None.
    """
    kind = LandmarkKind(kind)
    if kind == LandmarkKind.POINT2:
        return LandmarkEstimate(lid, kind, np.array([state[0], state[1], np.nan]), None, cov, n_obs)
    position = np.asarray(state[:3], float)
    if ceiling is not None:
        position = ceiling.world_position(state)
    orient = float(wrap_axis(float(state[3]))) if len(state) == 4 else None
    return LandmarkEstimate(lid, kind, position, orient, cov, n_obs)
