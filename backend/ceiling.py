"""The upward-camera observation model as the backends use it (wraps :mod:`lampsam.factors.ceiling`).

Landmark state in EKF form (world frame, metres, radians):

- corner or point lamp: ``p = (x, y, z)``, ``z`` above the floor;
- oriented lamp: ``(x, y, z, phi)``, ``phi`` the long axis (mod pi).

Measurements: ``(u, v)`` normalised ceiling coordinates and, for an oriented lamp
seen with its axis, ``alpha = wrap_axis(phi - theta)`` (paper 1, eqs. 17-18,
Cartesian form; conventions.md). A lamp first seen without an axis stays a point
lamp (paper III.4); an oriented lamp seen without its axis updates only its
position.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from lampsam.arrays import FloatArray
from lampsam.factors.ceiling import (
    HeightPrior,
    init_point_from_observation,
    lamp_axis,
    project_point,
)
from lampsam.factors.geometry import FactorError, wrap_axis

#: Smallest usable height of a landmark above the camera, m (conventions.md).
MIN_USABLE_HEIGHT = 0.1


class CeilingModel:
    """Projection, axis and initialisation of ceiling landmarks for one rig.

    Args:
        body_t_camera: (3,) camera optical centre in the body frame, m.
        max_radius: largest ``|m|`` seen in the image (from the camera's field of
            view); landmarks predicted beyond ``1.2 * max_radius`` are not candidates
            for association.
    """

    def __init__(self, body_t_camera: FloatArray, max_radius: float) -> None:
        self.body_t_camera = np.asarray(body_t_camera, dtype=float)
        self.max_radius = float(max_radius)

    @classmethod
    def from_camera(cls, camera: Any) -> CeilingModel:
        """Build from a :class:`lampsam.datasets.logrun.CameraModel` (FoV from its corners)."""
        w, h = camera.width, camera.height
        corners = np.array([[0, 0], [w - 1, 0], [0, h - 1], [w - 1, h - 1],
                            [w / 2, 0], [0, h / 2], [w - 1, h / 2], [w / 2, h - 1]], float)
        m = camera.normalized_from_pixels(corners)
        return cls(camera.body_t_camera, float(np.max(np.linalg.norm(m, axis=1))))

    def predict(self, pose: FloatArray, state: FloatArray, with_axis: bool
                ) -> tuple[FloatArray, FloatArray, FloatArray]:
        """Predicted ``(u, v[, alpha])`` with Jacobians.

        Args:
            pose: (3,) ``world_T_body``.
            state: (3,) or (4,) landmark state.
            with_axis: include the axis row (needs a 4-state).

        Returns:
            ``(z_hat (k,), z_D_pose (k, 3) right tangent, z_D_state (k, d))``.

        Raises:
            FactorError: the landmark is not above the camera.
        """
        m, m_D_pose, m_D_point = project_point(pose, state[:3], self.body_t_camera)
        d = len(state)
        if not with_axis:
            h_l = np.zeros((2, d))
            h_l[:, :3] = m_D_point
            return m, m_D_pose, h_l
        alpha, a_D_pose, a_D_phi = lamp_axis(pose, float(state[3]))
        h_l = np.zeros((3, d))
        h_l[:2, :3] = m_D_point
        h_l[2, 3] = a_D_phi[0, 0]
        return np.array([m[0], m[1], alpha]), np.vstack([m_D_pose, a_D_pose]), h_l

    def initialize(self, pose: FloatArray, obs: Any, prior: HeightPrior
                   ) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
        """Undelayed initialisation along the viewing ray at the prior height (eqs. 24-25).

        The augmented measurement is ``(u, v[, alpha], h)`` with covariance
        ``blockdiag(R, height_sigma^2)``.

        Args:
            pose: (3,) ``world_T_body``.
            obs: a :class:`lampsam.backend.models.Obs` of kind lamp or corner.
            prior: the height prior.

        Returns:
            ``(state, state_D_pose (d, 3) right tangent, state_D_zaug (d, q), cov_zaug (q, q))``.
        """
        m = obs.z[:2]
        point, p_D_pose, p_D_m, p_D_h = init_point_from_observation(
            pose, m, prior.height_mean, self.body_t_camera)
        k = len(obs.z)
        cov = np.zeros((k + 1, k + 1))
        cov[:k, :k] = obs.R
        cov[k, k] = prior.height_sigma**2
        if obs.kind == "lamp" and obs.has_axis:
            state = np.array([*point, float(wrap_axis(float(obs.z[2]) + pose[2]))])
            g_pose = np.zeros((4, 3))
            g_pose[:3] = p_D_pose
            g_pose[3, 2] = 1.0
            g_z = np.zeros((4, 4))
            g_z[:3, :2] = p_D_m
            g_z[3, 2] = 1.0
            g_z[:3, 3] = p_D_h[:, 0]
            return state, g_pose, g_z, cov
        g_z = np.zeros((3, 3))
        g_z[:, :2] = p_D_m
        g_z[:, 2] = p_D_h[:, 0]
        return point, p_D_pose, g_z, cov

    def in_view(self, pose: FloatArray, state: FloatArray) -> bool:
        """True when the landmark is above the camera and predicted inside the image."""
        try:
            m, _, _ = project_point(pose, state[:3], self.body_t_camera)
        except FactorError:
            return False
        if state[2] - self.body_t_camera[2] < MIN_USABLE_HEIGHT:
            return False
        return math.hypot(m[0], m[1]) < 1.2 * self.max_radius

    def world_position(self, state: FloatArray) -> FloatArray:
        """(3,) world position of a landmark state, m."""
        return np.asarray(state[:3], dtype=float).copy()
