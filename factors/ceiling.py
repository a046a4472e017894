"""Upward ceiling camera: point projection, lamp axis, inverse-depth corners (paper 1).

Everything here is in **normalised ceiling coordinates** ``m = (u, v)`` (forward and
left, per metre of height; docs/conventions.md "Upward ceiling camera"), which is
the paper's polar observation (eqs. 17-18) in Cartesian form: the polar angle is
singular for a landmark overhead (``r -> 0``), ``m`` is not (DESIGN sec. 1).

Model (conventions.md "Observation model"), for a pose ``(x, y, theta)``, a camera
at ``body_t_camera = (x_off, y_off, z_cam)`` and a world point ``p``::

    c = (x, y) + R(theta) (x_off, y_off)      camera centre on the floor plane
    h = p_z - z_cam                           height of the point above the camera
    m = R(theta)^T (p_xy - c) / h

Lamp axis: ``alpha = wrap_axis(phi - theta)`` (a line, modulo pi).

Corners. Two parametrisations are offered.

* **Inverse depth** anchored at the pose of first sight (DESIGN sec. 4), the paper's
  undelayed idea made well conditioned: ``idp = (alpha_x, alpha_y, rho)`` with
  ``alpha`` the normalised point seen from the anchor and ``rho = 1 / h``; the point
  is ``p_xy = c_a + R(theta_a) alpha / rho``, ``p_z = z_cam + 1 / rho`` and, seen from
  pose ``k``, ``m = rho R_k^T (c_a - c_k) + R(theta_a - theta_k) alpha``
  (:func:`project_inverse_depth`). It is linear in ``alpha`` and ``rho`` for fixed
  poses, finite at ``rho -> 0`` (far) and for ``m -> 0`` (overhead), and the first
  sight is a plain prior ``alpha ~ m_0`` (no pose involved). Its drawback in GTSAM's
  Python wheel is that it must be a ``CustomFactor`` (three keys: pose, anchor, idp).
* **Cartesian ``Point3`` with the C++ built-in** ``gtsam.PlanarProjectionFactor2``
  (identical model, see :mod:`lampsam.factors.gtsam_factors`) plus a height prior on
  ``p_z`` (``PriorFactorPoint3`` with loose x/y sigmas). The smoother relinearises,
  so the classic argument for inverse depth in a filter (a Gaussian in depth is a
  poor fit along the ray) weighs less, and the built-in costs microseconds instead
  of a Python call. The measured comparison is in ``scripts/bench/bench_factors.py``
  and the module docstring of :mod:`lampsam.factors.gtsam_factors`.

The EKF keeps the paper's undelayed initialisation (eqs. 24-25): a Cartesian point
placed along the first viewing ray at a prior height, :func:`init_point_from_observation`,
whose Jacobians let the EKF build the full cross-covariance.

Height prior (:class:`HeightPrior`). The paper says "0-5 m" above the camera. A point
at ``h -> 0`` is at ``rho -> infinity`` and no ceiling feature seen by a floor robot
is closer than about half a metre, so the range used is ``[h_min, h_max] =
[0.5, 5.0] m``, encoded as a Gaussian whose +-2 sigma interval is that range:

* on the height (Cartesian points, EKF): mean 2.75 m, sigma 1.125 m;
* on the inverse depth ``rho`` (inverse-depth corners): mean ``1 / 2.75 = 0.364``
  1/m (the same most likely height) and sigma ``(1/h_min - mean) / 2 = 0.818`` 1/m,
  so that +2 sigma is ``h_min`` and -2 sigma is beyond infinity (``rho < 0``): the
  usual inverse-depth prior that includes far points. A Gaussian on ``rho`` rather
  than on ``h`` because the projection is linear in ``rho``: the prior combines with
  the observations without a change of variable, and it stays finite for far points.
  (A first version centred the ``rho`` prior on ``[1/h_max, 1/h_min]``, i.e. a 0.9 m
  height; corners seen with little parallax then settled 1.5 m too low: bench case 4.)

All pose Jacobians are w.r.t. GTSAM's right tangent (conventions.md); use
:func:`lampsam.factors.geometry.tangent_D_coords` to get the EKF's coordinates.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from lampsam.arrays import FloatArray
from lampsam.factors.geometry import FactorError, wrap_axis

__all__ = [
    "MIN_HEIGHT",
    "HeightPrior",
    "init_inverse_depth",
    "init_point_from_observation",
    "inverse_depth_to_point",
    "lamp_axis",
    "lamp_axis_residual",
    "project_inverse_depth",
    "project_inverse_depth_batch",
    "project_point",
]

#: Below this height above the camera (metres) a point cannot be projected:
#: :func:`project_point` raises. (conventions.md: usable only when h > 0.1 m; the
#: backends gate on that; this is the hard numerical limit.)
MIN_HEIGHT = 1e-6


@dataclass(frozen=True)
class HeightPrior:
    """The paper's 0-5 m height range of ceiling landmarks (above the camera).

    Attributes:
        h_min: lowest plausible height above the camera, metres. Default 0.5 (the
            paper's 0 m is ``rho = inf``; see the module docstring).
        h_max: highest plausible height above the camera, metres. Default 5.0.
    """

    h_min: float = 0.5
    h_max: float = 5.0

    def __post_init__(self) -> None:
        if not (0.0 < self.h_min < self.h_max and math.isfinite(self.h_max)):
            raise FactorError(
                f"HeightPrior needs 0 < h_min < h_max < inf, got {self.h_min}, {self.h_max}"
            )

    @property
    def height_mean(self) -> float:
        """Mean of the Gaussian on the height ``h``, metres: the range's centre."""
        return 0.5 * (self.h_min + self.h_max)

    @property
    def height_sigma(self) -> float:
        """Sigma of the Gaussian on ``h``, metres: a quarter of the range (+-2 sigma)."""
        return 0.25 * (self.h_max - self.h_min)

    @property
    def rho_mean(self) -> float:
        """Mean of the Gaussian on ``rho = 1/h``, 1/m: ``1 / height_mean``."""
        return 1.0 / self.height_mean

    @property
    def rho_sigma(self) -> float:
        """Sigma of the Gaussian on ``rho``, 1/m: ``rho_mean + 2 sigma = 1 / h_min``."""
        return 0.5 * (1.0 / self.h_min - self.rho_mean)


def _camera_centre(pose: FloatArray, body_t_camera: FloatArray) -> tuple[FloatArray, float, float]:
    """World position (2,) of the camera centre of ``pose`` (x, y, theta), m, and ``cos``/``sin`` of its heading."""
    c, s = math.cos(pose[2]), math.sin(pose[2])
    ox, oy = float(body_t_camera[0]), float(body_t_camera[1])
    centre = np.array([pose[0] + c * ox - s * oy, pose[1] + s * ox + c * oy])
    return centre, c, s


def project_point(
    pose: FloatArray, point: FloatArray, body_t_camera: FloatArray
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Normalised ceiling coordinates of a world point (paper 1, eqs. 17-18, Cartesian).

    ``m = (R^T (p_xy - t) - o_xy) / h`` with ``h = p_z - z_cam``. With
    ``q = R^T (p_xy - t)`` (the point in the body frame) the right perturbation gives
    ``dq = -d_xy + d_theta (q_y, -q_x)``.

    Args:
        pose: (3,) ``world_T_body = (x, y, theta)``; m, m, rad.
        point: (3,) ``world_t_point``, metres (``z`` above the floor).
        body_t_camera: (3,) camera optical centre in the body frame ``(x_off, y_off,
            z_cam)``, metres.

    Returns:
        m: (2,) normalised ceiling coordinates (forward, left), per metre of height.
        m_D_pose: (2, 3) w.r.t. the pose's right tangent.
        m_D_point: (2, 3) w.r.t. the world point.

    Raises:
        FactorError: the point is not above the camera (``h <= MIN_HEIGHT``).
    """
    h = float(point[2] - body_t_camera[2])
    if h <= MIN_HEIGHT:
        raise FactorError(f"point is not above the camera (height {h:.3g} m)")
    c, s = math.cos(pose[2]), math.sin(pose[2])
    dx, dy = point[0] - pose[0], point[1] - pose[1]
    qx, qy = c * dx + s * dy, -s * dx + c * dy
    inv_h = 1.0 / h
    m = np.array([(qx - body_t_camera[0]) * inv_h, (qy - body_t_camera[1]) * inv_h])
    m_D_pose = inv_h * np.array([[-1.0, 0.0, qy], [0.0, -1.0, -qx]])
    m_D_point = np.array(
        [[c * inv_h, s * inv_h, -m[0] * inv_h], [-s * inv_h, c * inv_h, -m[1] * inv_h]]
    )
    return m, m_D_pose, m_D_point


def lamp_axis(pose: FloatArray, phi: float) -> tuple[float, FloatArray, FloatArray]:
    """Predicted image axis of a lamp (paper 1, ``phi_i = phi - theta``), modulo pi.

    The axis is measured in the ``(u, v)`` plane (conventions.md "Angles"), which is
    the body frame's ``(x, y)``; so ``alpha = wrap_axis(phi - theta)``. Residuals must
    be wrapped with ``wrap_axis`` too (:func:`lamp_axis_residual`).

    Args:
        pose: (3,) ``(x, y, theta)``; only ``theta`` matters.
        phi: lamp long axis in the world, radians (mod pi).

    Returns:
        alpha: predicted axis in ``(-pi/2, pi/2]``, radians.
        alpha_D_pose: (1, 3) ``[[0, 0, -1]]`` (right tangent).
        alpha_D_phi: (1, 1) ``[[1]]``.
    """
    alpha = float(wrap_axis(phi - pose[2]))
    return alpha, np.array([[0.0, 0.0, -1.0]]), np.array([[1.0]])


def lamp_axis_residual(
    pose: FloatArray, phi: float, measured: float
) -> tuple[float, FloatArray, FloatArray]:
    """Axis residual ``wrap_axis(predicted - measured)`` with Jacobians.

    ``measured`` and ``measured + pi`` give the same residual: the pi ambiguity of a
    line is removed here, once.

    Args:
        pose: (3,) ``(x, y, theta)``.
        phi: lamp axis in the world, radians.
        measured: measured image axis ``alpha``, radians (any representative mod pi).

    Returns:
        residual: in ``(-pi/2, pi/2]``, radians.
        residual_D_pose: (1, 3).
        residual_D_phi: (1, 1).
    """
    alpha, a_D_pose, a_D_phi = lamp_axis(pose, phi)
    return float(wrap_axis(alpha - measured)), a_D_pose, a_D_phi


def project_inverse_depth(
    pose: FloatArray,
    anchor_pose: FloatArray,
    idp: FloatArray,
    body_t_camera: FloatArray,
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """Normalised point of an inverse-depth corner seen from ``pose`` (DESIGN sec. 4).

    ``m = R_k^T w`` with ``w = rho (c_a - c_k) + R_a alpha`` (``c`` the camera centres
    on the floor plane). Derivation of the Jacobians (right tangents, ``J = [[0, -1],
    [1, 0]]``, ``o = (x_off, y_off)``):

    * pose ``k``: ``dm = -rho d_xy + ((m_y, -m_x) - rho J o) d_theta``;
    * anchor: ``dm = rho R(theta_a - theta_k) d_xy + R(theta_a - theta_k) J (rho o +
      alpha) d_theta``;
    * idp: ``dm/d alpha = R(theta_a - theta_k)``, ``dm/d rho = R_k^T (c_a - c_k)``.

    Well defined for every ``rho`` (``rho = 0`` is a point at infinity; the function
    never divides by it). When ``pose`` is the anchor it returns ``alpha``.

    Args:
        pose: (3,) observing pose ``(x, y, theta)``.
        anchor_pose: (3,) pose of first sight.
        idp: (3,) ``(alpha_x, alpha_y, rho)``: normalised point at the anchor and
            inverse height above the camera, 1/m.
        body_t_camera: (3,) camera offset ``(x_off, y_off, z_cam)``, metres.

    Returns:
        m: (2,) normalised ceiling coordinates seen from ``pose``.
        m_D_pose: (2, 3) w.r.t. the pose's right tangent.
        m_D_anchor: (2, 3) w.r.t. the anchor's right tangent.
        m_D_idp: (2, 3) w.r.t. ``(alpha_x, alpha_y, rho)``.
    """
    ck, ckc, cks = _camera_centre(pose, body_t_camera)
    ca, _, _ = _camera_centre(anchor_pose, body_t_camera)
    rho = float(idp[2])
    alpha = np.asarray(idp[:2], dtype=float)
    dth = anchor_pose[2] - pose[2]
    cd, sd = math.cos(dth), math.sin(dth)
    r_ka = np.array([[cd, -sd], [sd, cd]])  # R_k^T R_a
    dc = ca - ck
    m_D_rho = np.array([ckc * dc[0] + cks * dc[1], -cks * dc[0] + ckc * dc[1]])
    m = rho * m_D_rho + r_ka @ alpha
    ox, oy = float(body_t_camera[0]), float(body_t_camera[1])
    m_D_pose = np.array([[-rho, 0.0, m[1] + rho * oy], [0.0, -rho, -m[0] - rho * ox]])
    v = rho * np.array([ox, oy]) + alpha
    j_v = np.array([-v[1], v[0]])
    m_D_anchor = np.column_stack([rho * r_ka, r_ka @ j_v])
    m_D_idp = np.column_stack([r_ka, m_D_rho])
    return m, m_D_pose, m_D_anchor, m_D_idp


def project_inverse_depth_batch(
    pose: FloatArray,
    anchor_poses: FloatArray,
    idps: FloatArray,
    body_t_camera: FloatArray,
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """:func:`project_inverse_depth` for K corners seen from one pose, vectorised.

    Used by the per-frame factor, where one Python call handles a whole frame.

    Args:
        pose: (3,) observing pose.
        anchor_poses: (K, 3) anchor pose of each corner.
        idps: (K, 3) ``(alpha_x, alpha_y, rho)`` of each corner.
        body_t_camera: (3,) camera offset, metres.

    Returns:
        m: (K, 2); m_D_pose: (K, 2, 3); m_D_anchor: (K, 2, 3); m_D_idp: (K, 2, 3);
        the same quantities as :func:`project_inverse_depth`, per corner.
    """
    anchors = np.asarray(anchor_poses, dtype=float).reshape(-1, 3)
    q = np.asarray(idps, dtype=float).reshape(-1, 3)
    k = anchors.shape[0]
    ox, oy = float(body_t_camera[0]), float(body_t_camera[1])
    ck, cks_ = math.cos(pose[2]), math.sin(pose[2])
    cax, cay = np.cos(anchors[:, 2]), np.sin(anchors[:, 2])
    # camera centres on the floor plane
    ckx = pose[0] + ck * ox - cks_ * oy
    cky = pose[1] + cks_ * ox + ck * oy
    cax_w = anchors[:, 0] + cax * ox - cay * oy
    cay_w = anchors[:, 1] + cay * ox + cax * oy
    dcx, dcy = cax_w - ckx, cay_w - cky
    m_rho_x = ck * dcx + cks_ * dcy
    m_rho_y = -cks_ * dcx + ck * dcy
    dth = anchors[:, 2] - pose[2]
    cd, sd = np.cos(dth), np.sin(dth)
    ax, ay, rho = q[:, 0], q[:, 1], q[:, 2]
    mx = rho * m_rho_x + cd * ax - sd * ay
    my = rho * m_rho_y + sd * ax + cd * ay
    m = np.column_stack([mx, my])
    m_D_pose = np.zeros((k, 2, 3))
    m_D_pose[:, 0, 0] = -rho
    m_D_pose[:, 1, 1] = -rho
    m_D_pose[:, 0, 2] = my + rho * oy
    m_D_pose[:, 1, 2] = -mx - rho * ox
    vx, vy = rho * ox + ax, rho * oy + ay
    m_D_anchor = np.empty((k, 2, 3))
    m_D_anchor[:, 0, 0] = rho * cd
    m_D_anchor[:, 0, 1] = -rho * sd
    m_D_anchor[:, 1, 0] = rho * sd
    m_D_anchor[:, 1, 1] = rho * cd
    m_D_anchor[:, 0, 2] = cd * -vy - sd * vx
    m_D_anchor[:, 1, 2] = sd * -vy + cd * vx
    m_D_idp = np.empty((k, 2, 3))
    m_D_idp[:, 0, 0] = cd
    m_D_idp[:, 0, 1] = -sd
    m_D_idp[:, 1, 0] = sd
    m_D_idp[:, 1, 1] = cd
    m_D_idp[:, 0, 2] = m_rho_x
    m_D_idp[:, 1, 2] = m_rho_y
    return m, m_D_pose, m_D_anchor, m_D_idp


def inverse_depth_to_point(
    anchor_pose: FloatArray, idp: FloatArray, body_t_camera: FloatArray
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """World point of an inverse-depth corner, ``p = (c_a + R_a alpha / rho, z_cam + 1/rho)``.

    Args:
        anchor_pose: (3,) pose of first sight.
        idp: (3,) ``(alpha_x, alpha_y, rho)``, ``rho > 0``.
        body_t_camera: (3,) camera offset, metres.

    Returns:
        point: (3,) ``world_t_point``, metres.
        point_D_anchor: (3, 3) w.r.t. the anchor's right tangent.
        point_D_idp: (3, 3) w.r.t. ``(alpha_x, alpha_y, rho)``.

    Raises:
        FactorError: ``rho <= 0`` (a point at or beyond infinity has no position).
    """
    rho = float(idp[2])
    if not rho > 0.0:
        raise FactorError(f"inverse depth must be > 0 to give a point, got rho={rho}")
    ca, c, s = _camera_centre(anchor_pose, body_t_camera)
    r_a = np.array([[c, -s], [s, c]])
    h = 1.0 / rho
    alpha = np.asarray(idp[:2], dtype=float)
    point = np.array([*(ca + h * (r_a @ alpha)), body_t_camera[2] + h])
    lever = np.array([body_t_camera[0], body_t_camera[1]]) + h * alpha
    point_D_anchor = np.zeros((3, 3))
    point_D_anchor[:2, :2] = r_a
    point_D_anchor[:2, 2] = r_a @ np.array([-lever[1], lever[0]])
    point_D_idp = np.zeros((3, 3))
    point_D_idp[:2, :2] = h * r_a
    point_D_idp[:2, 2] = -(h * h) * (r_a @ alpha)
    point_D_idp[2, 2] = -h * h
    return point, point_D_anchor, point_D_idp


def init_inverse_depth(m: FloatArray, prior: HeightPrior) -> FloatArray:
    """Initial inverse-depth parameters from a first sight: ``(m_x, m_y, rho_mean)``.

    Args:
        m: (2,) normalised observation at the anchor pose.
        prior: the height prior; its ``rho_mean`` is the starting inverse depth.

    Returns:
        (3,) ``(alpha_x, alpha_y, rho)``.
    """
    return np.array([float(m[0]), float(m[1]), prior.rho_mean])


def init_point_from_observation(
    pose: FloatArray,
    m: FloatArray,
    height_prior: float,
    body_t_camera: FloatArray,
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """Undelayed initialisation of a Cartesian landmark (paper 1, eqs. 24-25).

    The point on the viewing ray of ``m`` at height ``h`` above the camera:
    ``p_xy = c + R(theta) m h``, ``p_z = z_cam + h``. The EKF augments its state with
    ``p`` and its covariance with ``G_x P G_x^T + G_m R_m G_m^T + G_h var_h G_h^T``
    (and the cross term ``G_x P_x.``), which gives the long ellipse along the ray of
    the paper's Fig. 7 (use ``HeightPrior().height_mean`` / ``height_sigma``).

    Args:
        pose: (3,) ``(x, y, theta)``.
        m: (2,) normalised observation (forward, left per metre of height).
        height_prior: ``h``, the assumed height above the camera, metres (> 0).
        body_t_camera: (3,) camera offset ``(x_off, y_off, z_cam)``, metres.

    Returns:
        point: (3,) world point, metres.
        point_D_pose: (3, 3) w.r.t. the pose's right tangent.
        point_D_m: (3, 2) w.r.t. ``m``.
        point_D_height: (3, 1) w.r.t. ``h``.

    Raises:
        FactorError: ``height_prior <= 0``.
    """
    h = float(height_prior)
    if not h > 0.0:
        raise FactorError(f"height prior must be > 0, got {h}")
    centre, c, s = _camera_centre(pose, body_t_camera)
    r = np.array([[c, -s], [s, c]])
    mv = np.asarray(m, dtype=float)
    ray = r @ mv
    point = np.array([centre[0] + h * ray[0], centre[1] + h * ray[1], body_t_camera[2] + h])
    lever = np.array([body_t_camera[0], body_t_camera[1]]) + h * mv
    point_D_pose = np.zeros((3, 3))
    point_D_pose[:2, :2] = r
    point_D_pose[:2, 2] = r @ np.array([-lever[1], lever[0]])
    point_D_m = np.zeros((3, 2))
    point_D_m[:2, :] = h * r
    point_D_height = np.array([[ray[0]], [ray[1]], [1.0]])
    return point, point_D_pose, point_D_m, point_D_height
