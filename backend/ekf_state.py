"""The EKF's state, prediction (paper 1, eqs. 13-15) and innovations (eq. 19).

State ``X = [x, y, theta, landmark_1, ..., landmark_n]`` (plain coordinates, world
frame, m and rad; landmark states in :mod:`lampsam.backend.models`), covariance ``P``.

- Covariance storage: :class:`lampsam.backend.covariance.LowerCovariance`, the lower
  triangle of a growable buffer, updated in place (no n x n copies, no periodic
  re-symmetrisation).
- Prediction (eqs. 13-15): only the robot block changes. With ``F_x`` the robot
  Jacobian and ``F_u Q F_u^T`` the wheel noise, ``P_RR <- F_x P_RR F_x^T + F_u Q F_u^T``
  and ``P_MR <- P_MR F_x^T``; the landmark block ``P_MM`` is untouched. Several odometry
  increments between two frames are composed on the 3x3 block first, so a step
  costs O(n) regardless of the odometry rate. No dense ``F P F^T``.
- Innovation (eq. 19) of one landmark, and the gate of a frame vectorised
  (:mod:`lampsam.backend.ekf_gate`).

The update is :mod:`lampsam.backend.ekf`, the map's growth and pruning
:mod:`lampsam.backend.ekf_map`.
"""

from __future__ import annotations

import collections
import math
from typing import Any

import numpy as np

from lampsam.arrays import FloatArray
from lampsam.backend.association import TentativeLandmarks
from lampsam.backend.config import SlamConfig
from lampsam.backend.covariance import LowerCovariance
from lampsam.backend.ekf_gate import Screened, screen_frame
from lampsam.backend.ekf_landmarks import Slot
from lampsam.backend.ekf_update import observability_project
from lampsam.backend.innovation_scale import innovation_scale
from lampsam.backend.interface import (
    LandmarkEstimate,
    LandmarkKind,
    SlamBackend,
    StepHistory,
)
from lampsam.backend.landmark_merge import CoVisibility
from lampsam.backend.models import Obs, for_landmark, landmark_estimate, predict, residual
from lampsam.backend.odometry import OdometryConstants, Pose2Motion, motion_model
from lampsam.backend.odometry_scale import IdleOdometry, ScaledMotion, odometry_scale
from lampsam.errors import EstimationError
from lampsam.factors.geometry import tangent_D_coords


class EkfState(SlamBackend):
    """State, covariance, prediction and innovations of :class:`~lampsam.backend.ekf.EkfSlam`.

    Args:
        odometry: the odometry model's constants (wheel, eq. 15, or Pose2
            increments; :func:`lampsam.backend.odometry.motion_model`).
        config: the SLAM config (association, noise, EKF part).
        start_pose: (3,) known start pose ``world_T_body``.
        ceiling: the ceiling observation model (for lamps/corners), or None for
            range-bearing runs.
    """

    def __init__(self, odometry: OdometryConstants, config: SlamConfig, start_pose: FloatArray,
                 ceiling: Any = None) -> None:
        self.motion = motion_model(odometry)
        self.config = config
        self.ceiling = ceiling
        cap = 64
        self._x = np.zeros(cap)
        self._n = 3
        self._x[:3] = np.asarray(start_pose, float)
        cfg = config.ekf
        self._cov = LowerCovariance(np.diag([cfg.sigma_start_xy**2, cfg.sigma_start_xy**2,
                                             cfg.sigma_start_theta**2]), cap)
        self._slots: dict[int, Slot] = {}
        self._prune_queue: collections.deque[int] = collections.deque()
        self._doomed: set[int] = set()
        self._next_id = 0
        self._step = 0
        self._last_t = -math.inf
        self._history = StepHistory()
        self.n_pruned = 0
        self.pruned: dict[str, int] = {}  # by reason; sums to n_pruned
        self._provisional: list[LandmarkEstimate] = []
        fej = config.ekf.first_estimate_jacobians
        # None (auto): first estimates for range-bearing runs on Pose2 odometry (the
        # landmark-graph logs), the paper's Jacobians for the wheel model (ceiling
        # runs, MRCLAM).
        auto = ceiling is None and isinstance(self.motion, Pose2Motion)
        self._fej = auto if fej is None else fej
        inv = config.ekf.right_invariant
        if inv and ceiling is not None:
            raise EstimationError("ekf.right_invariant applies to planar range-bearing runs only")
        self._invariant = bool(inv) if inv is not None else False
        oc = config.ekf.observability_constrained
        self._oc = bool(auto and self._fej) if oc is None else oc
        if self._oc:
            self._fej = True  # the first-estimates prediction and first estimates for N
        if self._invariant:
            self._fej = self._oc = False  # the invariant error keeps the rotation unobservable
        # None (auto): landmarks with a known id are kept on the same runs.
        prune_known = config.ekf.prune_known_ids
        self._prune_known = not auto if prune_known is None else prune_known
        self._pred_xy = self._x[:2].copy()  # p_{k|k-1}: the last predicted position
        self.tentative = TentativeLandmarks(config.association.planar_confirm_sightings,
                                            config.association.gate(2),
                                            cfg.tentative_max_idle, cfg.new_min_separation)
        self.noise_scale = innovation_scale(config.association)
        self.odo_scale = odometry_scale(config.association)  # learnt odometry noise, or None
        self.idle = IdleOdometry()
        if self.odo_scale is not None:
            self.motion = ScaledMotion(self.motion, self.odo_scale, self.idle)
        self.covis = CoVisibility()  # landmarks seen together (never merged)
        self.n_merged = 0
        #: range-bearing sightings without ids ``(step, z, R, landmark id)``, for a batch
        #: re-association of the run (:mod:`lampsam.backend.reassociate`)
        self.planar_sightings: list[tuple[int, FloatArray, FloatArray, int]] = []

    # ------------------------------------------------------------------ state
    @property
    def x(self) -> FloatArray:
        """(n,) the current state vector (a view)."""
        return self._x[: self._n]

    @property
    def P(self) -> FloatArray:
        """(n, n) the current covariance (a full copy: O(n^2), for checks)."""
        return self._cov.dense()

    # ------------------------------------------------------------------ eqs. 13-15
    def predict(self, wheel: FloatArray) -> None:
        """Prediction with several odometry samples (eqs. 13-15 for wheel travel).

        Args:
            wheel: (K, m) odometry samples of the motion model (wheel: (K, 2)
                ``(d_left, d_right)`` per sample, m).
        """
        if len(wheel) == 0:
            self._pred_xy = self._x[:2].copy()
            return
        pose, f_tot, q_acc = self.motion.ekf_predict(self._x[:3], wheel)
        if self._fej:
            # Both motion models' F has heading column J (p' - p) (J: +90 deg rotation);
            # first estimates take p = p_{k|k-1} instead of the updated p_{k|k}.
            shift = self._x[:2] - self._pred_xy
            f_tot = f_tot.copy()
            f_tot[0, 2] -= shift[1]
            f_tot[1, 2] += shift[0]
        self._pred_xy = pose[:2].copy()
        self._cov.transform_leading(f_tot, q_acc + self.config.ekf.var_floor * np.eye(3))
        self._x[:3] = pose

    # ------------------------------------------------------------------ prediction helpers
    def _h(self, slot: Slot, obs: Obs | None) -> tuple[FloatArray, FloatArray, FloatArray]:
        """``(z_hat (m,), H_r (m, 3), H_l (m, d))``: the predicted measurement of landmark
        ``slot`` (``d = slot.dim``) and its Jacobians in plain coordinates (robot
        ``(x, y, theta)``, landmark state), world frame.

        With ``ekf.first_estimate_jacobians`` the Jacobians are taken at the landmark's
        first estimate (the prediction ``z_hat`` at the current one); with
        ``ekf.observability_constrained`` a planar landmark's are the latest ones
        projected (:func:`lampsam.backend.ekf_update.observability_project`).
        """
        pose = self._x[:3]
        state = self._x[slot.offset : slot.offset + slot.dim]
        z_hat, z_D_pose, z_D_l = predict(slot.kind, pose, state, obs, self.ceiling)
        if self._oc and slot.first is not None and slot.kind == LandmarkKind.POINT2:
            h_r, h_l = observability_project(z_D_pose @ tangent_D_coords(pose[2]), z_D_l,
                                             pose[:2], slot.first[:2])
            return z_hat, h_r, h_l
        if self._fej and slot.first is not None:
            _, z_D_pose, z_D_l = predict(slot.kind, pose, slot.first, obs, self.ceiling)
        return z_hat, z_D_pose @ tangent_D_coords(pose[2]), z_D_l

    def _innovation(self, lid: int, obs: Obs) -> tuple[FloatArray, FloatArray] | None:
        """``(nu (m,), Psi (m, m))`` of eq. 19 for landmark ``lid`` and ``obs``, with the
        robot-landmark cross-covariance; None when the landmark is not predictable."""
        slot = self._slots[lid]
        obs = for_landmark(obs, slot.dim)
        try:
            z_hat, h_r, h_l = self._h(slot, obs)
        except Exception:  # landmark behind / at the camera: not predictable here
            return None
        o, d = slot.offset, slot.dim
        cov = self._cov
        p_rr, p_rl = cov.block(0, 3, 0, 3), cov.block(0, 3, o, o + d)
        p_ll = cov.block(o, o + d, o, o + d)
        cross = h_r @ p_rl @ h_l.T
        psi = h_r @ p_rr @ h_r.T + cross + cross.T + h_l @ p_ll @ h_l.T + obs.R
        return residual(obs, z_hat), psi

    def _innovation_h(self, lid: int, obs: Obs) -> tuple[FloatArray, FloatArray, FloatArray] | None:
        """``(nu, Psi, H_r)``: :meth:`_innovation` with the robot Jacobian (2, 3)."""
        pred = self._innovation(lid, obs)
        if pred is None:
            return None
        return pred[0], pred[1], self._h(self._slots[lid], for_landmark(obs, self._slots[lid].dim))[1]

    def _screen(self, obs: list[Obs]) -> tuple[dict[str, list[int]], Screened]:
        """Candidates per kind and the vectorised gate of the frame's observations
        (:func:`lampsam.backend.ekf_gate.screen_frame`), for :func:`associate`."""
        return screen_frame(obs, self._slots, self._doomed, self._x, self._cov, self.ceiling,
                            self.config.association, self._fej, self._oc, self.noise_scale.scale)

    def _estimate(self, s: Slot) -> LandmarkEstimate:
        """The current estimate of one landmark in the state."""
        st = self._x[s.offset : s.offset + s.dim].copy()
        cov = self._cov.block(s.offset, s.offset + s.dim, s.offset, s.offset + s.dim)
        return landmark_estimate(s.id, s.kind, st, cov, s.n_obs, self.ceiling)

