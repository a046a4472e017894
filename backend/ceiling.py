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
from typing import TYPE_CHECKING, Any

import numpy as np

from lampsam.arrays import FloatArray
from lampsam.factors.ceiling import (
    HeightPrior,
    init_point_from_observation,
    lamp_axis,
    project_point,
)
from lampsam.factors.geometry import FactorError, mahalanobis2_2x2, wrap_axis

if TYPE_CHECKING:  # models.py imports this module: the record type for annotations only
    from lampsam.backend.models import Obs

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
        r = np.linalg.norm(camera.normalized_from_pixels(corners), axis=1)
        # NaN: a (fisheye) border pixel sees at or beyond the horizon; no bound on |m|
        return cls(camera.body_t_camera, math.inf if np.isnan(r).any() else float(np.max(r)))

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

    def initialize(self, pose: FloatArray, obs: Obs, prior: HeightPrior
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

    def project_many(self, pose: FloatArray, points: FloatArray
                     ) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
        """Vectorised :func:`lampsam.factors.ceiling.project_point` for M landmarks at once.

        Same model (paper 1, eqs. 17-18, Cartesian): ``m = (R^T (p_xy - t) - o_xy) / h``,
        ``h = p_z - z_cam``; used to pre-select and gate candidates without a Python
        call per landmark.

        Args:
            pose: (3,) ``world_T_body``.
            points: (M, 3) world points, m (extra columns, e.g. a lamp axis, ignored).

        Returns:
            ``(m (M, 2), m_D_pose (M, 2, 3) right tangent, m_D_point (M, 2, 3),
            visible (M,) bool)``; ``visible`` is False for points less than
            :data:`MIN_USABLE_HEIGHT` above the camera or predicted beyond
            ``1.2 * max_radius`` (their other entries are finite but meaningless).
        """
        pts = np.asarray(points, dtype=float).reshape(-1, points.shape[-1] if len(points) else 3)
        n = len(pts)
        o = self.body_t_camera
        h = pts[:, 2] - o[2] if n else np.zeros(0)
        ok_h = h >= MIN_USABLE_HEIGHT
        inv_h = 1.0 / np.where(ok_h, h, 1.0)
        c, s = math.cos(pose[2]), math.sin(pose[2])
        dx, dy = pts[:, 0] - pose[0], pts[:, 1] - pose[1]
        qx, qy = c * dx + s * dy, -s * dx + c * dy
        m = np.stack([(qx - o[0]) * inv_h, (qy - o[1]) * inv_h], axis=1)
        m_D_pose = np.zeros((n, 2, 3))
        m_D_pose[:, 0, 0] = -inv_h
        m_D_pose[:, 1, 1] = -inv_h
        m_D_pose[:, 0, 2] = qy * inv_h
        m_D_pose[:, 1, 2] = -qx * inv_h
        m_D_point = np.empty((n, 2, 3))
        m_D_point[:, 0, 0] = c * inv_h
        m_D_point[:, 0, 1] = s * inv_h
        m_D_point[:, 0, 2] = -m[:, 0] * inv_h
        m_D_point[:, 1, 0] = -s * inv_h
        m_D_point[:, 1, 1] = c * inv_h
        m_D_point[:, 1, 2] = -m[:, 1] * inv_h
        visible = ok_h & (np.hypot(m[:, 0], m[:, 1]) < 1.2 * self.max_radius)
        return m, m_D_pose, m_D_point, visible

    def in_view_many(self, pose: FloatArray, points: FloatArray) -> FloatArray:
        """(M,) bool: :meth:`in_view` for M landmark states at once (``points`` (M, >=3))."""
        if len(points) == 0:
            return np.zeros(0, dtype=bool)
        return self.project_many(pose, points)[3]

    def triangulate(self, poses: FloatArray, ms: FloatArray, covs: FloatArray
                    ) -> tuple[FloatArray, FloatArray]:
        """Corner position from two or more sights (delayed initialisation).

        Eq. 17-18 is linear in ``(p_x, p_y, h)`` for known poses:
        ``R_k^T p_xy - h m_k = R_k^T t_k + o_xy``; weighted least squares over the
        sights (weights ``cov_m^-1 / h^2`` evaluated at the unweighted solution, the
        pose uncertainty ignored) gives the point and its covariance.

        Args:
            poses: (K, 3) ``world_T_body`` of the sights.
            ms: (K, 2) normalised ceiling coordinates.
            covs: (K, 2, 2) their covariances.

        Returns:
            ``(point (3,) world, cov (3, 3) over (x, y, z))``; the covariance is
            infinite-like (``1e6 I``) when the sights have no parallax.
        """
        poses = np.asarray(poses, float)
        ms = np.asarray(ms, float)
        o = self.body_t_camera
        c, s = np.cos(poses[:, 2]), np.sin(poses[:, 2])
        rows = np.zeros((len(poses), 2, 3))  # per sight: [R_k^T | -m_k]
        rows[:, 0, 0], rows[:, 0, 1], rows[:, 1, 0], rows[:, 1, 1] = c, s, -s, c
        rows[:, :, 2] = -ms
        rhs = rows[:, :, :2] @ poses[:, :2, None]
        rhs = rhs[:, :, 0] + o[:2]
        sol, *_ = np.linalg.lstsq(rows.reshape(-1, 3), rhs.reshape(-1), rcond=None)
        h = max(float(sol[2]), MIN_USABLE_HEIGHT)
        w = np.linalg.inv(np.asarray(covs, float)) / h**2
        info = np.einsum("kai,kab,kbj->ij", rows, w, rows)
        try:
            cov_s = np.linalg.inv(info)
        except np.linalg.LinAlgError:
            cov_s = 1e6 * np.eye(3)
        if not np.all(np.isfinite(cov_s)) or np.min(np.linalg.eigvalsh(cov_s)) < 0:
            cov_s = 1e6 * np.eye(3)
        point = np.array([sol[0], sol[1], sol[2] + o[2]])
        return point.astype(float), np.asarray(cov_s, dtype=np.float64)

    def reprojection_chi2(self, poses: FloatArray, point: FloatArray, ms: FloatArray,
                          covs: FloatArray) -> float:
        """Sum over sights of ``r^T C^-1 r``, ``r = m - project(pose, point)`` (eqs. 17-18).

        The consistency test of a triangulated point with its sights, vectorised over
        the sights (the same model as :meth:`project_many`, one point from K poses).

        Args:
            poses: (K, 3) ``world_T_body``; point: (3,) world, m, at least
                :data:`MIN_USABLE_HEIGHT` above the camera.
            ms: (K, 2) measured normalised coordinates; covs: (K, 2, 2) their covariances.

        Returns:
            The chi-square (2K degrees of freedom before the 3 of the point); ``inf``
            when a covariance is not positive definite.
        """
        poses = np.asarray(poses, float)
        o = self.body_t_camera
        inv_h = 1.0 / (float(point[2]) - o[2])
        c, s = np.cos(poses[:, 2]), np.sin(poses[:, 2])
        dx, dy = point[0] - poses[:, 0], point[1] - poses[:, 1]
        r0 = ms[:, 0] - ((c * dx + s * dy) - o[0]) * inv_h
        r1 = ms[:, 1] - ((-s * dx + c * dy) - o[1]) * inv_h
        a, b, d = covs[:, 0, 0], 0.5 * (covs[:, 0, 1] + covs[:, 1, 0]), covs[:, 1, 1]
        d2, pd = mahalanobis2_2x2(r0, r1, a, b, d)
        return float(np.sum(d2)) if np.all(pd) else math.inf

    def world_position(self, state: FloatArray) -> FloatArray:
        """(3,) world position of a landmark state, m."""
        return np.asarray(state[:3], dtype=float).copy()
