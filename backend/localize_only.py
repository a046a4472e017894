"""Localize-only tracking against a saved ceiling map: the map is used, never grown (issue 20).

:class:`MapLocalizer` is a :class:`lampsam.backend.interface.SlamBackend` whose state
is the robot pose alone, ``x = (x, y, theta)`` with covariance ``P`` (3 x 3, plain
coordinates, world frame of the map). The map's landmarks are fixed values whose
uncertainty enters every innovation as extra noise: for an observation ``z`` of map
landmark ``l`` with state covariance ``Sigma_l`` (from ``landmarks.csv``),

    nu  = z - h(x, l)                                   (paper 1, eqs. 17-18)
    Psi = H_x P H_x^T + H_l Sigma_l H_l^T + R           (eq. 19 without the pose-map term)

and the observation is associated when ``nu^T Psi^-1 nu`` is under the chi-square gate
of :class:`lampsam.backend.config.AssociationConfig` (eq. 20, the SLAM backends'
gate). Only observations with exactly one map landmark inside the gate are used
(a repeated ceiling pattern, such as a tile grid, never picks the nearest of two),
one observation per landmark (the smaller distance wins). Observations of nothing
in the map are ignored: no landmark is ever added, moved or removed.

Prediction is the wheel model of the SLAM EKF (eqs. 13-15,
:meth:`lampsam.backend.odometry.MotionModel.ekf_predict`). The update with the
frame's K matched observations is done in information form: with
``W_i = (H_l,i Sigma_l,i H_l,i^T + R_i)^-1`` block by block,
``P+^-1 = P^-1 + sum H_x,i^T W_i H_x,i`` and ``x+ = x + P+ sum H_x,i^T W_i nu_i``,
which equals eqs. 21-23 for the stacked update but costs O(K) with 3 x 3 inverses
instead of a (2K x 2K) one.

Why a pose-only EKF rather than a fixed-lag iSAM2 over poses: with the map fixed,
the pose posterior given the past is all an online tracker needs, the EKF step is
a handful of 3 x 3 products (the smoothers' cost is one GTSAM update and a pose
marginal per keyframe), and measured on lab (docs/ceiling-map.md) its error is
already below the from-scratch smoothers'.

Corner patches are stored in the map but used for association only when
:attr:`LocalizeConfig.corner_ncc` is set: the frontend's patches are not rotation
invariant, so a corner seen on another day at another heading would fail the NCC.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, field

import numpy as np

from lampsam.arrays import FloatArray
from lampsam.backend.association import pairwise_d2, patch_ncc
from lampsam.backend.ceiling import CeilingModel
from lampsam.backend.ceiling_map_io import CeilingMap, MapLandmark
from lampsam.backend.config import SlamConfig
from lampsam.backend.interface import (
    Frame,
    LandmarkEstimate,
    LandmarkKind,
    SlamBackend,
    SlamResult,
    StepEstimate,
)
from lampsam.backend.models import Obs, for_landmark, observations_from_frame, residual
from lampsam.backend.odometry import OdometryConstants, motion_model
from lampsam.config_loader import check_limits, limits
from lampsam.errors import EstimationError
from lampsam.factors.geometry import FactorError, tangent_D_coords, wrap_angle

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class LocalizeConfig:
    """Localize-only tracking.

    Attributes:
        sigma_start_xy: standard deviation of the start position, m (default 0.02),
            used when the start has no covariance of its own (a known start pose or
            ``--start``; ``--start-from`` takes the global localizer's covariance).
        sigma_start_theta: of the start heading, rad (default 0.01, 0.6 deg).
        var_floor: additive floor on the pose process covariance per step, m^2 and
            rad^2 (default 1e-10).
        map_cov_scale: factor on the map's landmark covariances (default 1).
        unique: use an observation only when exactly one map landmark is inside its
            gate (default True).
        corner_ncc: also require ``association.ncc_min`` NCC between a corner's patch
            and the map's (default False: patches are not rotation invariant).
        max_corners: at most this many corner observations per frame, the smallest
            Mahalanobis distances first (default None: all).
    """

    sigma_start_xy: float = field(default=0.02, metadata=limits(gt=0.0))
    sigma_start_theta: float = field(default=0.01, metadata=limits(gt=0.0))
    var_floor: float = field(default=1e-10, metadata=limits(ge=0.0))
    map_cov_scale: float = field(default=1.0, metadata=limits(ge=0.0))
    unique: bool = True
    corner_ncc: bool = False
    max_corners: int | None = field(default=None, metadata=limits(ge=0))

    def __post_init__(self) -> None:
        """Check the declared ranges (:class:`FieldValueError` naming the key)."""
        check_limits(self)


class _KindArrays:
    """The map's landmarks of one kind as arrays (for vectorised prediction)."""

    def __init__(self, lms: list[MapLandmark], scale: float) -> None:
        self.lms = lms
        self.ids = [lm.id for lm in lms]
        self.points = np.array([lm.position for lm in lms], float).reshape(-1, 3)
        self.cov_p = scale * np.array([lm.cov[:3, :3] for lm in lms], float).reshape(-1, 3, 3)
        self.cov_p = np.nan_to_num(self.cov_p)  # unknown marginals: no extra noise


def _h_x(m_d_pose: FloatArray, theta: float) -> FloatArray:
    """(…, 2, 3) right-tangent projection Jacobians -> plain-coordinate ones."""
    return m_d_pose @ tangent_D_coords(theta)


class MapLocalizer(SlamBackend):
    """Pose-only EKF against a fixed ceiling map (see module docstring).

    Args:
        odometry: the odometry model's constants.
        config: the SLAM config (association gate, features, measurement noise).
        start_pose: (3,) start pose ``world_T_body`` in the map's frame.
        cmap: the ceiling map.
        ceiling: the run's ceiling observation model.
        loc: localize-only settings.
        start_cov: (3, 3) covariance of ``start_pose``; None: from ``loc``.
    """

    name = "localize"

    def __init__(self, odometry: OdometryConstants, config: SlamConfig, start_pose: FloatArray,
                 cmap: CeilingMap, ceiling: CeilingModel, loc: LocalizeConfig | None = None,
                 start_cov: FloatArray | None = None) -> None:
        self.motion = motion_model(odometry)
        self.config = config
        self.loc = loc or LocalizeConfig()
        self.ceiling = ceiling
        self.cmap = cmap
        self.x = np.asarray(start_pose, float).reshape(3).copy()
        self.P = (np.diag([self.loc.sigma_start_xy**2, self.loc.sigma_start_xy**2,
                           self.loc.sigma_start_theta**2]) if start_cov is None
                  else np.asarray(start_cov, float).reshape(3, 3).copy())
        self._by_id = {lm.id: lm for lm in cmap.landmarks}
        self._kinds = {k: _KindArrays(cmap.by_kind(k), self.loc.map_cov_scale)
                       for k in (LandmarkKind.LAMP.value, LandmarkKind.CORNER.value)}
        self._last_t = -math.inf
        self._times: list[float] = []
        self._poses: list[FloatArray] = []
        self._covs: list[FloatArray] = []
        self._step_times: list[float] = []
        self._used: list[bool] = []
        self.n_used = 0
        self.n_ignored = 0
        self.n_ambiguous = 0

    # ------------------------------------------------------------------ association
    def _candidates(self, obs: list[Obs]) -> list[tuple[float, int, MapLandmark]]:
        """Gated (d2, obs index, landmark) pairs of the frame, one per used observation."""
        pose = self.x
        pairs: list[tuple[float, int, MapLandmark]] = []
        for kind, arr in self._kinds.items():
            idx = [i for i, o in enumerate(obs) if o.kind == kind]
            if not idx or not arr.ids:
                continue
            m, m_d_pose, m_d_pt, vis = self.ceiling.project_many(pose, arr.points)
            keep = np.flatnonzero(vis)
            if len(keep) == 0:
                self.n_ignored += len(idx)
                continue
            h_x = _h_x(m_d_pose[keep], float(pose[2]))
            h_l = m_d_pt[keep]
            s = (h_x @ self.P @ np.transpose(h_x, (0, 2, 1))
                 + h_l @ arr.cov_p[keep] @ np.transpose(h_l, (0, 2, 1)))
            z = np.array([obs[i].z[:2] for i in idx], float)
            r = np.array([obs[i].R[:2, :2] for i in idx], float)
            d2 = pairwise_d2(z, r, m[keep], s)
            gate = self.config.association.gate(2)
            for row, i in enumerate(idx):
                inside = np.flatnonzero(d2[row] < gate)
                if self.loc.corner_ncc and kind == LandmarkKind.CORNER.value:
                    inside = np.array([j for j in inside
                                       if patch_ncc(obs[i].patch, arr.lms[keep[j]].patch)
                                       >= self.config.association.ncc_min], int)
                if len(inside) == 0:
                    self.n_ignored += 1
                    continue
                if len(inside) > 1 and self.loc.unique:
                    self.n_ambiguous += 1
                    continue
                j = int(inside[np.argmin(d2[row, inside])])
                pairs.append((float(d2[row, j]), i, arr.lms[keep[j]]))
        # one observation per landmark, the closest first
        pairs.sort(key=lambda p: p[0])
        used_lm: set[int] = set()
        out: list[tuple[float, int, MapLandmark]] = []
        n_corners = 0
        for d2_ij, i, lm in pairs:
            if lm.id in used_lm:
                continue
            if lm.kind == LandmarkKind.CORNER.value:
                if self.loc.max_corners is not None and n_corners >= self.loc.max_corners:
                    continue
                n_corners += 1
            used_lm.add(lm.id)
            out.append((d2_ij, i, lm))
        return out

    # ------------------------------------------------------------------ update
    def _update(self, obs: list[Obs], pairs: list[tuple[float, int, MapLandmark]]) -> int:
        """Information-form EKF update with the matched observations (module docstring)."""
        pose = self.x
        t_d_c = tangent_D_coords(float(pose[2]))
        info = np.zeros((3, 3))
        grad = np.zeros(3)
        n = 0
        for _, i, lm in pairs:
            o = for_landmark(obs[i], 4 if lm.phi is not None else 3)
            state = lm.state()
            try:
                z_hat, z_d_pose, z_d_l = self.ceiling.predict(pose, state, o.has_axis)
            except FactorError:
                continue
            h_x = z_d_pose @ t_d_c
            cov_l = self.loc.map_cov_scale * np.nan_to_num(lm.state_cov())
            r_tot = z_d_l @ cov_l @ z_d_l.T + o.R
            nu = residual(o, z_hat)
            if o.has_axis:  # the full gate, now that the axis row is known
                psi = h_x @ self.P @ h_x.T + r_tot
                try:
                    if float(nu @ np.linalg.solve(psi, nu)) >= self.config.association.gate(3):
                        o = for_landmark(o, 3)
                        h_x, nu, r_tot = h_x[:2], nu[:2], r_tot[:2, :2]
                except np.linalg.LinAlgError:
                    continue
            try:
                w = np.linalg.inv(r_tot)
            except np.linalg.LinAlgError:
                continue
            info += h_x.T @ w @ h_x
            grad += h_x.T @ w @ nu
            n += 1
        if n == 0:
            return 0
        try:
            p_new = np.linalg.inv(np.linalg.inv(self.P) + info)
        except np.linalg.LinAlgError:
            log.warning("pose information not invertible: update skipped")
            return 0
        self.x = self.x + p_new @ grad
        self.x[2] = wrap_angle(float(self.x[2]))
        self.P = 0.5 * (p_new + p_new.T)
        return n

    # ------------------------------------------------------------------ interface
    def step(self, t: float, wheel: FloatArray, frame: Frame | None) -> StepEstimate:
        """See :meth:`SlamBackend.step`; ``n_new`` is always 0 (the map is not grown)."""
        t0 = time.perf_counter()
        if t < self._last_t:
            raise EstimationError(f"t={t:.3f} s: time goes backwards (previous {self._last_t:.3f})")
        self._last_t = t
        u = self.motion.check(t, wheel)
        if len(u):
            pose, f, q = self.motion.ekf_predict(self.x, u)
            self.P = f @ self.P @ f.T + q + self.loc.var_floor * np.eye(3)
            self.x = np.asarray(pose, float)
        n_used = 0
        if frame is not None:
            obs = observations_from_frame(frame, self.config.features, self.config.noise)
            obs = [o for o in obs if o.kind != LandmarkKind.POINT2]
            if obs:
                pairs = self._candidates(obs)
                n_used = self._update(obs, pairs)
                self.n_used += n_used
        dt = time.perf_counter() - t0
        self._times.append(t)
        self._poses.append(self.x.copy())
        self._covs.append(self.P.copy())
        self._step_times.append(dt)
        self._used.append(n_used > 0)
        return StepEstimate(t, self.x.copy(), self.P.copy(), n_used > 0, n_used, 0, dt)

    def finish(self, status: str = "ok") -> SlamResult:
        """The tracked poses; ``landmarks`` is the map, unchanged."""
        lms = [LandmarkEstimate(lm.id, LandmarkKind(lm.kind), lm.position.copy(), lm.phi,
                                lm.state_cov(), lm.n_obs) for lm in self.cmap.landmarks]
        return SlamResult(
            backend=self.name,
            times=np.asarray(self._times, float),
            poses=np.asarray(self._poses, float).reshape(-1, 3),
            pose_covs=np.asarray(self._covs, float).reshape(-1, 3, 3),
            landmarks=lms,
            step_times_s=np.asarray(self._step_times, float),
            keyframes=np.asarray(self._used, bool),
            status=status,
            extra={"observations_used": float(self.n_used),
                   "observations_ignored": float(self.n_ignored),
                   "observations_ambiguous": float(self.n_ambiguous),
                   "map_landmarks": float(len(self.cmap.landmarks))},
        )
