"""Planar geometry shared by every model: rotations, pose algebra (and angle wrapping).

``wrap_angle`` and ``wrap_axis`` are defined in :mod:`lampsam.angles` and
re-exported here for the models and their callers.

Conventions (docs/conventions.md, fixed there and followed here):

* A planar pose ``world_T_body`` is the array ``(x, y, theta)``: metres, metres,
  radians, heading counter-clockwise from world ``x``, wrapped to ``(-pi, pi]``.
* Jacobians "w.r.t. the pose" are w.r.t. GTSAM's right-perturbation tangent of
  ``Pose2``: ``pose.retract(d) = ((x, y) + R(theta) (d_x, d_y), theta + d_theta)``
  (to first order; GTSAM's ``Expmap`` agrees with this to first order).
  The EKF, whose state is the plain coordinates, converts with
  :func:`coords_D_tangent`: ``z_D_coords = z_D_tangent @ tangent_D_coords(theta)``.

All functions are pure and allocate small numpy arrays; none touches GTSAM so that
the EKF can use them without building factors.
"""

from __future__ import annotations

import math

import numpy as np

from lampsam.angles import wrap_angle, wrap_axis
from lampsam.arrays import BoolArray, FloatArray
from lampsam.errors import LampsamError

__all__ = [
    "FactorError",
    "between",
    "compose",
    "coords_D_tangent",
    "mahalanobis2_2x2",
    "rot2",
    "tangent_D_coords",
    "transform_from",
    "transform_to",
    "wrap_angle",
    "wrap_axis",
]

class FactorError(LampsamError):
    """A model or factor was given unusable input (wrong shape, NaN, point below camera)."""


def rot2(theta: float) -> FloatArray:
    """Planar rotation matrix.

    Args:
        theta: rotation angle, radians, counter-clockwise.

    Returns:
        (2, 2) ``[[cos, -sin], [sin, cos]]``: maps body-frame vectors into the world
        frame when ``theta`` is the body heading.
    """
    c, s = math.cos(theta), math.sin(theta)
    return np.array([[c, -s], [s, c]])


def coords_D_tangent(theta: float) -> FloatArray:
    """Jacobian of plain pose coordinates w.r.t. GTSAM's right tangent (conventions.md).

    ``d(x, y, theta) = blockdiag(R(theta), 1) @ d_tangent``.

    Args:
        theta: pose heading, radians.

    Returns:
        (3, 3) ``blockdiag(R(theta), 1)``.
    """
    c, s = math.cos(theta), math.sin(theta)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def tangent_D_coords(theta: float) -> FloatArray:
    """Inverse of :func:`coords_D_tangent`: ``blockdiag(R(theta)^T, 1)``.

    Use it to turn a tangent Jacobian into a coordinate Jacobian (the EKF's):
    ``z_D_coords = z_D_tangent @ tangent_D_coords(theta)``.

    Args:
        theta: pose heading, radians.

    Returns:
        (3, 3) ``blockdiag(R(theta)^T, 1)``.
    """
    c, s = math.cos(theta), math.sin(theta)
    return np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]])


def compose(a_T_b: FloatArray, b_T_c: FloatArray) -> FloatArray:
    """Compose two planar poses, ``a_T_c = a_T_b * b_T_c`` (like ``Pose2.compose``).

    Args:
        a_T_b: (3,) ``(x, y, theta)`` of frame b in frame a.
        b_T_c: (3,) ``(x, y, theta)`` of frame c in frame b.

    Returns:
        (3,) ``(x, y, theta)`` of frame c in frame a, heading wrapped to ``(-pi, pi]``.
    """
    c, s = math.cos(a_T_b[2]), math.sin(a_T_b[2])
    return np.array(
        [
            a_T_b[0] + c * b_T_c[0] - s * b_T_c[1],
            a_T_b[1] + s * b_T_c[0] + c * b_T_c[1],
            wrap_angle(a_T_b[2] + b_T_c[2]),
        ]
    )


def between(a_T_b: FloatArray, a_T_c: FloatArray) -> FloatArray:
    """Relative pose ``b_T_c = a_T_b^-1 * a_T_c`` (like ``Pose2.between``).

    Args:
        a_T_b: (3,) pose of frame b in frame a.
        a_T_c: (3,) pose of frame c in frame a.

    Returns:
        (3,) pose of frame c in frame b, heading wrapped to ``(-pi, pi]``.
    """
    c, s = math.cos(a_T_b[2]), math.sin(a_T_b[2])
    dx, dy = a_T_c[0] - a_T_b[0], a_T_c[1] - a_T_b[1]
    return np.array([c * dx + s * dy, -s * dx + c * dy, wrap_angle(a_T_c[2] - a_T_b[2])])


def transform_from(world_T_body: FloatArray, body_t_point: FloatArray) -> FloatArray:
    """Map a body-frame planar point into the world: ``t + R(theta) p``.

    Args:
        world_T_body: (3,) pose.
        body_t_point: (2,) point in the body frame, metres.

    Returns:
        (2,) the point in the world frame, metres.
    """
    c, s = math.cos(world_T_body[2]), math.sin(world_T_body[2])
    return np.array(
        [
            world_T_body[0] + c * body_t_point[0] - s * body_t_point[1],
            world_T_body[1] + s * body_t_point[0] + c * body_t_point[1],
        ]
    )


def rigid_fit_2d(src: FloatArray, dst: FloatArray, weights: FloatArray | None = None) -> FloatArray:
    """Least-squares planar rigid transform with ``dst ~ R(theta) src + t`` (2-D Kabsch;
    Arun et al. 1987), closed form: ``theta`` from the weighted cross and dot sums of the
    centred points.

    Args:
        src: (N, 2) points in the source frame, metres, N >= 2.
        dst: (N, 2) the corresponding points in the destination frame, metres.
        weights: (N,) non-negative weights (None: all 1); at least two positive.

    Returns:
        (3,) ``(t_x, t_y, theta)``: the pose ``dst_T_src`` (m, m, rad).
    """
    s = np.asarray(src, dtype=np.float64)
    d = np.asarray(dst, dtype=np.float64)
    if weights is None:
        ms, md = s.mean(axis=0), d.mean(axis=0)
        a, b = s - ms, d - md
        cross = float(np.sum(a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]))
        dot = float(np.sum(a[:, 0] * b[:, 0] + a[:, 1] * b[:, 1]))
    else:
        w = np.asarray(weights, dtype=np.float64)
        ms, md = w @ s / w.sum(), w @ d / w.sum()
        a, b = s - ms, d - md
        cross = float(np.sum(w * (a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0])))
        dot = float(np.sum(w * (a[:, 0] * b[:, 0] + a[:, 1] * b[:, 1])))
    theta = math.atan2(cross, dot)
    c, sn = math.cos(theta), math.sin(theta)
    return np.array([md[0] - (c * ms[0] - sn * ms[1]), md[1] - (sn * ms[0] + c * ms[1]), theta])


def transform_to(world_T_body: FloatArray, world_t_point: FloatArray) -> FloatArray:
    """Map a world planar point into the body frame: ``R(theta)^T (p - t)``.

    Args:
        world_T_body: (3,) pose.
        world_t_point: (2,) point in the world frame, metres.

    Returns:
        (2,) the point in the body frame, metres.
    """
    c, s = math.cos(world_T_body[2]), math.sin(world_T_body[2])
    dx, dy = world_t_point[0] - world_T_body[0], world_t_point[1] - world_T_body[1]
    return np.array([c * dx + s * dy, -s * dx + c * dy])


def mahalanobis2_2x2(nu0: FloatArray, nu1: FloatArray, a: FloatArray, b: FloatArray,
                     d: FloatArray) -> tuple[FloatArray, BoolArray]:
    """``nu^T C^-1 nu`` for 2-vectors and 2x2 covariances given entry by entry (eq. 20).

    ``C = [[a, b], [b, d]]`` (``b`` the symmetrised off-diagonal), inverted in closed
    form; every argument broadcasts, so all pairs of N observations and M predictions
    go at once without an (N, M, 2, 2) temporary.

    Args:
        nu0, nu1: the innovation's two components.
        a, b, d: the covariance's entries, same units squared.

    Returns:
        ``(d2, pd)``: the squared distances, and where ``C`` is positive definite
        (``det > 0`` and ``a > 0``); ``d2`` is meaningless where ``pd`` is False.
    """
    det = a * d - b * b
    with np.errstate(divide="ignore", invalid="ignore"):
        d2 = (d * nu0**2 - 2.0 * b * nu0 * nu1 + a * nu1**2) / det
    return d2, (det > 0) & (a > 0)
