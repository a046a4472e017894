"""Localize-only tracking against a saved ceiling map: the map is used, never grown.

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
:meth:`lampsam.backend.odometry.MotionModel.ekf_predict`). Association is vectorised
per kind (every observation against every map landmark predicted in view, as
:func:`lampsam.backend.association.pairwise_d2`) on the position rows ``(u, v)``. A
lamp axis then adds one scalar row, ``alpha = wrap_axis(phi - theta)`` (eq. 18,
``d alpha / d theta = -1``) with variance ``R_alpha + var(phi)``, when it is inside
its own 1-dof gate. The update with the frame's K matched observations is done in
information form: with ``W_i = (H_l,i Sigma_l,i H_l,i^T + R_i)^-1`` block by block,
``P+^-1 = P^-1 + sum H_x,i^T W_i H_x,i`` and ``x+ = x + P+ sum H_x,i^T W_i nu_i``,
which equals eqs. 21-23 for the stacked update but costs O(K) with 2 x 2 and 3 x 3
inverses instead of a (2K x 2K) one.

The map as fixed values is a pose-only EKF: the step is a handful of 3 x 3 products,
but the track inherits the map's error (its frame offset and distortion), and adding
``Sigma_l`` to every innovation independently treats repeated sightings of one map
landmark as independent. :attr:`LocalizeConfig.map_mode` offers the two remedies:
``"priors"`` puts the used map landmarks in the state with the map as their prior
(a localize-only EKF-SLAM that never adds a landmark; the run's known start then pulls
part of the map's error out), ``"consider"`` keeps the same joint covariance but never
moves the map (a Schmidt / consider filter: consistent, not more accurate). Their
cost is one EKF update over ``3 + 3 L`` states per frame (``L`` the map landmarks
used, a few dozen). Accuracy and cost of the three: docs/ceiling-map.md.

With a version-2 map and :attr:`LocalizeConfig.frame_offset`, the map frame's offset
``g = (dx, dy, dtheta)`` (:mod:`lampsam.backend.map_frame`) joins the state after the
pose with the map's ``S`` as its prior: landmark ``l`` is at ``p_l + C_l g`` with its
conditional covariance ``D_l``, and ``d h / d g = H_l C_l``.

With the map as priors, a used lamp that the run's sightings contradict (a chi-square test of
its correction against its map prior) is released: its prior is widened and it is reported
(:mod:`lampsam.backend.map_release`, :attr:`LocalizeConfig.release`).

Corner patches are stored in the map but used for association only when
:attr:`LocalizeConfig.corner_ncc` is set: the frontend's patches are not rotation
invariant, so a corner seen on another day at another heading would fail the NCC.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import time
from dataclasses import dataclass

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
    StepHistory,
    check_step_time,
)
from lampsam.backend.localize_config import LocalizeConfig
from lampsam.backend.map_frame import MapFrame, shift_only
from lampsam.backend.map_release import UNSEEN_RADIUS, Released, ReleaseTracker
from lampsam.backend.models import Obs, observations_from_frame
from lampsam.backend.odometry import OdometryConstants, motion_model
from lampsam.factors.geometry import tangent_D_coords, wrap_angle, wrap_axis

log = logging.getLogger(__name__)


class _KindArrays:
    """The map's landmarks of one kind as arrays (for vectorised prediction).

    With a map frame (``frame``), ``cov_p`` and ``var_phi`` are the conditional
    covariances ``D_l`` and ``gains`` (M, 4, 3) the ``C_l``; otherwise the marginals
    and None.
    """

    def __init__(self, lms: list[MapLandmark], scale: float, frame: MapFrame | None) -> None:
        self.lms = lms
        self.ids = [lm.id for lm in lms]
        self.points = np.array([lm.position for lm in lms], float).reshape(-1, 3)
        covs = [lm.cov if frame is None or lm.id not in frame.gains
                else frame.conditional(lm.id, lm.cov) for lm in lms]
        # unknown marginals (NaN): no extra noise
        self.cov_p = np.nan_to_num(scale * np.array([c[:3, :3] for c in covs],
                                                    float).reshape(-1, 3, 3))
        self.phi = np.array([np.nan if lm.phi is None else lm.phi for lm in lms], float)
        self.var_phi = np.nan_to_num(scale * np.array([c[3, 3] for c in covs], float))
        self.gains: FloatArray | None = None
        if frame is not None:
            self.gains = np.array([frame.gains.get(lm.id, np.zeros((4, 3))) for lm in lms],
                                  float).reshape(-1, 4, 3)


@dataclass
class _Matches:
    """The used observations of one kind and what the update needs of each (K rows).

    ``nu`` (K, 2) innovations, ``h_x`` (K, 2, 3 + G) Jacobians on the plain-coordinate
    pose and (G = 3 with a map frame, else 0) the frame offset ``g``,
    ``r_tot`` (K, 2, 2) ``H_l Sigma_l H_l^T + R``, ``obs`` (K,) observation indices,
    ``lm`` (K,) indices into the kind's :class:`_KindArrays`.
    """

    nu: FloatArray
    h_x: FloatArray
    r_tot: FloatArray
    obs: np.ndarray
    lm: np.ndarray
    h_l: FloatArray
    r: FloatArray


def _with_floor(lm: MapLandmark, bias_px: float, cmap: CeilingMap) -> MapLandmark:
    """``lm`` with ``(bias_px d / f_x)^2`` added to its ``x, y`` variances
    (:attr:`LocalizeConfig.corner_bias_px`)."""
    if bias_px <= 0.0:
        return lm
    cam = cmap.rig.camera
    depth = max(float(lm.position[2]) - float(cam.body_t_camera[2]), 0.0)
    cov = np.array(lm.cov, float)
    cov[0, 0] += (bias_px * depth / cam.fx) ** 2
    cov[1, 1] += (bias_px * depth / cam.fx) ** 2
    return dataclasses.replace(lm, cov=cov)


def _inv2(a: FloatArray) -> FloatArray:
    """Inverses of a stack of 2 x 2 matrices (closed form), (K, 2, 2)."""
    det = a[:, 0, 0] * a[:, 1, 1] - a[:, 0, 1] * a[:, 1, 0]
    out = np.empty_like(a)
    out[:, 0, 0] = a[:, 1, 1]
    out[:, 1, 1] = a[:, 0, 0]
    out[:, 0, 1] = -a[:, 0, 1]
    out[:, 1, 0] = -a[:, 1, 0]
    return out / det[:, None, None]


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
        corners = [_with_floor(lm, self.loc.corner_bias_px, cmap)
                   for lm in cmap.by_kind(LandmarkKind.CORNER.value)
                   if lm.n_obs >= self.loc.min_corner_obs
                   and math.sqrt(max(lm.cov[0, 0], lm.cov[1, 1])) <= self.loc.max_corner_sigma]
        frame = cmap.frame if self.loc.frame_offset else None
        if frame is not None and not self.loc.frame_turn:
            frame = shift_only(frame)
        self._kinds = {LandmarkKind.LAMP.value: _KindArrays(cmap.by_kind(LandmarkKind.LAMP.value),
                                                            self.loc.map_cov_scale, frame),
                       LandmarkKind.CORNER.value: _KindArrays(
                           corners, self.loc.map_cov_scale * self.loc.corner_cov_scale, frame)}
        # the map frame's offset g (module docstring of map_frame), states 3..5
        self._g: FloatArray | None = None if frame is None else np.zeros(3)
        self._na = 3 if frame is None else 6  # pose (+ g)
        # the joint covariance over (pose, g, landmarks of _kinds in order): with a frame
        # or map_mode priors / consider; the pose-only EKF otherwise
        self._offsets: dict[str, int] = {}
        self._pj: FloatArray | None = None
        if self.loc.map_mode != "fixed" or frame is not None:
            n = self._na
            if self.loc.map_mode != "fixed":
                for kind, arr in self._kinds.items():
                    self._offsets[kind] = n
                    n += 3 * len(arr.ids)
            self._pj = np.zeros((n, n))
            self._pj[:3, :3] = self.P
            if frame is not None:
                self._pj[3:6, 3:6] = frame.cov
            for kind, o0 in self._offsets.items():
                arr = self._kinds[kind]
                for j in range(len(arr.ids)):
                    o = o0 + 3 * j
                    self._pj[o:o + 3, o:o + 3] = arr.cov_p[j]
        #: today's sightings, the release test and the unseen lamps (map_release)
        self.tracker = ReleaseTracker({k: (a.ids, a.points, a.cov_p) for k, a in self._kinds.items()},
                                      self.loc)
        self._gate2 = config.association.gate(2)
        self._gate1 = config.association.gate(1)
        self._last_t = -math.inf
        self._t = 0.0
        self._history = StepHistory()
        self.n_used = 0
        self.n_ignored = 0
        self.n_ambiguous = 0
        #: the last step's used observations: ``(observation, map landmark, axis used)``
        #: (read by :mod:`lampsam.backend.map_smoother`)
        self.frame_matches: list[tuple[Obs, MapLandmark, bool]] = []

    # ------------------------------------------------------------------ association
    def _match(self, obs: list[Obs], kind: str, arr: _KindArrays) -> _Matches | None:
        """Gate the frame's observations of one kind against the map (module docstring)."""
        idx = np.array([i for i, o in enumerate(obs) if o.kind == kind], int)
        if len(idx) == 0 or not arr.ids:
            return None
        pose = self.x
        points = arr.points if self._g is None or arr.gains is None else (
            arr.points + arr.gains[:, :3] @ self._g)
        m, m_d_pose, m_d_pt, vis = self.ceiling.project_many(pose, points)
        keep = np.flatnonzero(vis)
        self.tracker.in_view(kind, np.asarray(vis, bool) & (np.hypot(m[:, 0], m[:, 1])
                                                             < UNSEEN_RADIUS * self.ceiling.max_radius))
        if len(keep) == 0:
            self.n_ignored += len(idx)
            self.tracker.unmatched(kind, len(idx))
            return None
        h_x = m_d_pose[keep] @ tangent_D_coords(float(pose[2]))
        h_l = m_d_pt[keep]
        p_a = self.P
        if self._g is not None and arr.gains is not None:  # d h / d g = H_l C_l
            h_x = np.concatenate([h_x, h_l @ arr.gains[keep][:, :3]], axis=2)
            assert self._pj is not None
            p_a = self._pj[:6, :6]
        s_map = h_l @ arr.cov_p[keep] @ np.transpose(h_l, (0, 2, 1))
        s = h_x @ p_a @ np.transpose(h_x, (0, 2, 1)) + s_map
        z = np.array([obs[i].z[:2] for i in idx], float)
        r = np.array([obs[i].R[:2, :2] for i in idx], float)
        d2 = pairwise_d2(z, r, m[keep], s)  # (N, M), eq. 20
        inside = d2 < self._gate2
        if self.loc.corner_ncc and kind == LandmarkKind.CORNER.value:
            for row, col in zip(*np.nonzero(inside), strict=True):
                inside[row, col] = (patch_ncc(obs[idx[row]].patch, arr.lms[keep[col]].patch)
                                    >= self.config.association.ncc_min)
        count = inside.sum(axis=1)
        self.n_ignored += int(np.sum(count == 0))
        self.tracker.unmatched(kind, int(np.sum(count == 0)))
        if self.loc.unique:
            self.n_ambiguous += int(np.sum(count > 1))
            rows = np.flatnonzero(count == 1)
        else:
            rows = np.flatnonzero(count >= 1)
        if len(rows) == 0:
            return None
        cols = np.argmin(np.where(inside[rows], d2[rows], np.inf), axis=1)
        d2_rc = d2[rows, cols]
        order = np.argsort(d2_rc, kind="stable")  # one observation per landmark, closest first
        _, first = np.unique(cols[order], return_index=True)
        sel = order[np.sort(first)]
        if kind == LandmarkKind.CORNER.value and self.loc.max_corners is not None:
            sel = sel[np.argsort(d2_rc[sel], kind="stable")[: self.loc.max_corners]]
        rows, cols = rows[sel], cols[sel]
        return _Matches(nu=z[rows] - m[keep[cols]], h_x=h_x[cols], r_tot=r[rows] + s_map[cols],
                        obs=idx[rows], lm=keep[cols], h_l=h_l[cols], r=r[rows])

    def _record(self, obs: list[Obs], mt: _Matches, arr: _KindArrays, axes: set[int]) -> None:
        """Append the matches to :attr:`frame_matches` (``axes``: lamps whose axis row is used)."""
        for i, j in zip(mt.obs, mt.lm, strict=True):
            self.frame_matches.append((obs[int(i)], arr.lms[int(j)], int(j) in axes))

    # ------------------------------------------------------------------ update
    def _axis_rows(self, obs: list[Obs], mt: _Matches, arr: _KindArrays,
                   var_theta: float) -> list[tuple[float, float, int]]:
        """The scalar axis rows of a frame's matched lamps (eq. 18's ``alpha = phi - theta`` mod pi).

        One row per matched lamp whose observation has an axis and whose map lamp has
        one: ``(nu, var, j)`` with ``nu`` the wrapped axis innovation, rad, ``var`` the
        observation's axis variance plus the map's ``var(phi)``, rad^2 (the axes are not
        states), and ``j`` the lamp's index; a row outside its own 1-dof gate
        (``var_theta``: the heading's variance, rad^2) is left out. ``d alpha / d theta
        = -1``; with a map frame the axis is ``phi + C_phi g`` (``d alpha / d g = C_phi``).
        """
        rows: list[tuple[float, float, int]] = []
        for i, j in zip(mt.obs, mt.lm, strict=True):
            o = obs[int(i)]
            if not o.has_axis or math.isnan(arr.phi[j]) or self.tracker.released[LandmarkKind.LAMP.value][j]:
                continue
            phi = arr.phi[j] if self._g is None or arr.gains is None else (
                arr.phi[j] + float(arr.gains[j, 3] @ self._g))
            nu_a = float(wrap_axis(float(o.z[2]) - (phi - self.x[2])))
            var = float(o.R[2, 2]) + float(arr.var_phi[j])
            if nu_a * nu_a / (var + var_theta) >= self._gate1:
                continue
            rows.append((nu_a, var, int(j)))
        return rows

    def _update(self, obs: list[Obs]) -> int:
        """Information-form EKF update with the frame's matched observations."""
        if self._pj is not None:
            return self._update_joint(obs)
        info = np.zeros((3, 3))
        grad = np.zeros(3)
        n = 0
        for kind, arr in self._kinds.items():
            mt = self._match(obs, kind, arr)
            if mt is None:
                continue
            self.tracker.seen[kind][mt.lm] += 1
            w = _inv2(mt.r_tot)  # (K, 2, 2)
            hw = np.transpose(mt.h_x, (0, 2, 1)) @ w  # (K, 3, 2)
            info += np.einsum("kij,kjl->il", hw, mt.h_x)
            grad += np.einsum("kij,kj->i", hw, mt.nu)
            n += len(mt.obs)
            axes: set[int] = set()
            if kind == LandmarkKind.LAMP.value:
                for nu_a, var, j in self._axis_rows(obs, mt, arr, float(self.P[2, 2])):
                    info[2, 2] += 1.0 / var
                    grad[2] += -nu_a / var  # d alpha / d theta = -1
                    axes.add(j)
            self._record(obs, mt, arr, axes)
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

    def _update_joint(self, obs: list[Obs]) -> int:
        """The stacked EKF update over pose, map frame offset and map landmarks.

        Rows: ``(u, v)`` of each matched observation, ``H = [H_x, H_l C_l, 0 .. H_l .. 0]``
        (the ``g`` block with a map frame; the landmark block with ``map_mode`` priors /
        consider), noise ``R`` (the landmark's uncertainty is in the state), or
        ``H_l D_l H_l^T + R`` when the landmarks are not states (``fixed`` with a
        frame); a lamp axis adds the scalar row of :meth:`_update` on ``theta`` (and
        ``C_phi`` on ``g``) with the map's ``var(phi)`` in its noise (the axes are not
        states). Priors: ``K = P H^T S^-1``,
        ``P+ = P - K S K^T`` (eqs. 21-23). Consider (Schmidt): the landmark rows of
        ``K`` are zero and ``P+ = P - K H P - P H^T K^T + K S K^T`` (Joseph form, exact
        for a gain that is not the optimal one), which leaves ``P_ll`` unchanged.
        """
        assert self._pj is not None
        pj = self._pj
        n = pj.shape[0]
        na = self._na
        in_state = bool(self._offsets)
        rows_h: list[FloatArray] = []
        rows_nu: list[float] = []
        rows_r: list[FloatArray] = []  # (2, 2) or (1, 1) blocks
        for kind, arr in self._kinds.items():
            mt = self._match(obs, kind, arr)
            if mt is None:
                continue
            self.tracker.seen[kind][mt.lm] += 1
            for k in range(len(mt.obs)):
                h = np.zeros((2, n))
                h[:, :mt.h_x.shape[2]] = mt.h_x[k]
                if in_state:
                    o = self._offsets[kind] + 3 * int(mt.lm[k])
                    h[:, o:o + 3] = mt.h_l[k]
                rows_h.append(h)
                rows_nu.extend(mt.nu[k])
                rows_r.append(mt.r[k] if in_state else mt.r_tot[k])
            axis_rows = (self._axis_rows(obs, mt, arr, float(pj[2, 2]))
                         if kind == LandmarkKind.LAMP.value else [])
            self._record(obs, mt, arr, {j for _, _, j in axis_rows})
            for nu_a, var, j in axis_rows:
                h = np.zeros((1, n))
                h[0, 2] = -1.0
                if self._g is not None and arr.gains is not None:
                    h[0, 3:6] = arr.gains[j, 3]
                rows_h.append(h)
                rows_nu.append(nu_a)
                rows_r.append(np.array([[var]]))
        if not rows_h:
            return 0
        hm = np.vstack(rows_h)
        m = hm.shape[0]
        r = np.zeros((m, m))
        at = 0
        for blk in rows_r:
            b = blk.shape[0]
            r[at:at + b, at:at + b] = blk
            at += b
        pht = pj @ hm.T
        s = hm @ pht + r
        try:
            gain = np.linalg.solve(s, pht.T).T  # K = P H^T S^-1
        except np.linalg.LinAlgError:
            log.warning("innovation covariance not invertible: update skipped")
            return 0
        if self.loc.map_mode == "consider":
            gain[na:] = 0.0
            kph = gain @ pht.T  # K H P
            pj = pj - kph - kph.T + gain @ s @ gain.T
        else:
            pj = pj - gain @ s @ gain.T
        dx = gain @ np.asarray(rows_nu, float)
        self._pj = 0.5 * (pj + pj.T)
        self.x = self.x + dx[:3]
        self.x[2] = wrap_angle(float(self.x[2]))
        self.P = self._pj[:3, :3].copy()
        if self._g is not None:
            self._g = self._g + dx[3:6]
        for kind, o in self._offsets.items():
            arr = self._kinds[kind]
            k = len(arr.ids)
            if k == 0:
                continue
            arr.points = arr.points + dx[o:o + 3 * k].reshape(k, 3)
            idx = o + 3 * np.arange(k)[:, None] + np.arange(3)[None, :]
            arr.cov_p = self._pj[idx[:, :, None], idx[:, None, :]]
        if self.loc.release and self.loc.map_mode == "priors":
            self.tracker.check(self._t, {k: a.points for k, a in self._kinds.items()},
                               {k: a.cov_p for k, a in self._kinds.items()}, self._pj,
                               self._offsets)
        return sum(1 for h in rows_h if h.shape[0] == 2)

    # ------------------------------------------------------------------ release
    @property
    def releases(self) -> list[Released]:
        """The landmarks released so far (:class:`lampsam.backend.map_release.ReleaseTracker`)."""
        return self.tracker.releases

    @property
    def release_blocked(self) -> int:
        """Frames in which some landmarks failed the test but too many to release one."""
        return self.tracker.blocked

    @property
    def lamps_unmatched(self) -> int:
        """Lamp sightings of no map lamp (one missing from the map, or moved out of its gate)."""
        return self.tracker.lamps_unmatched

    def release_report(self) -> list[dict[str, object]]:
        """:meth:`lampsam.backend.map_release.ReleaseTracker.release_report` on the current
        landmark estimates."""
        return self.tracker.release_report({k: a.points for k, a in self._kinds.items()})

    def unseen_report(self) -> list[dict[str, object]]:
        """:meth:`lampsam.backend.map_release.ReleaseTracker.unseen_report`."""
        return self.tracker.unseen_report()

    def released_ids(self) -> set[int]:
        """Ids of the released map landmarks."""
        return {r.id for r in self.releases}

    # ------------------------------------------------------------------ interface
    def step(self, t: float, wheel: FloatArray, frame: Frame | None) -> StepEstimate:
        """See :meth:`SlamBackend.step`; ``n_new`` is always 0 (the map is not grown)."""
        t0 = time.perf_counter()
        self._last_t = check_step_time(t, self._last_t)
        self._t = t
        u = self.motion.check(t, wheel)
        if len(u):
            pose, f, q = self.motion.ekf_predict(self.x, u)
            self.P = f @ self.P @ f.T + q + self.loc.var_floor * np.eye(3)
            self.x = np.asarray(pose, float)
            if self._pj is not None:  # eq. 13's F on the pose rows, landmarks static
                self._pj[:3, :3] = self.P
                self._pj[:3, 3:] = f @ self._pj[:3, 3:]
                self._pj[3:, :3] = self._pj[:3, 3:].T
        n_used = 0
        self.frame_matches = []
        if frame is not None:
            obs = observations_from_frame(frame, self.config.features, self.config.noise)
            obs = [o for o in obs if o.kind != LandmarkKind.POINT2]
            if obs:
                n_used = self._update(obs)
                self.n_used += n_used
        dt = time.perf_counter() - t0
        self._history.add(t, self.x.copy(), self.P.copy(), dt, n_used > 0)
        return StepEstimate(t, self.x.copy(), self.P.copy(), n_used > 0, n_used, 0, dt)

    def finish(self, status: str = "ok") -> SlamResult:
        """The tracked poses; ``landmarks`` is the map, unchanged."""
        lms = [LandmarkEstimate(lm.id, LandmarkKind(lm.kind), lm.position.copy(), lm.phi,
                                lm.state_cov(), lm.n_obs) for lm in self.cmap.landmarks]
        return self._history.result(
            self.name, lms, status,
            extra={"observations_used": float(self.n_used),
                   "observations_ignored": float(self.n_ignored),
                   "observations_ambiguous": float(self.n_ambiguous),
                   "map_landmarks": float(len(self.cmap.landmarks)),
                   "lamp_sightings_unmatched": float(self.lamps_unmatched),
                   "map_lamps_unseen": float(len(self.unseen_report())),
                   **({} if not (self.loc.release and self._offsets) else {
                       "map_landmarks_released": float(len(self.releases)),
                       "release_blocked_frames": float(self.release_blocked)}),
                   **({} if self._g is None else {
                       "map_frame_dx_m": float(self._g[0]), "map_frame_dy_m": float(self._g[1]),
                       "map_frame_dtheta_rad": float(self._g[2])})},
        )
