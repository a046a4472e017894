"""Localize-only smoothing: the run's poses and the used map landmarks in one factor graph.

:class:`MapSmoother` runs the localize-only filter (:class:`lampsam.backend.localize_only.MapLocalizer`)
for association and for the online estimate, and builds a factor graph of the whole run
beside it; :meth:`MapSmoother.finish` solves the graph (hindsight: both the map's and the
new run's information for every pose). No landmark is added: only map landmarks the
filter matched become variables.

Variables (``gtsam.symbol_shorthand``): ``X(k)`` the pose before step ``k`` (``X(0)`` the
start, ``X(k + 1)`` after step ``k``), ``Pose2``; ``L(id)`` a used map landmark's world
position, ``Point3`` (m, ``z`` above the floor); ``A(id)`` a used lamp axis, a ``Pose2``
whose angle is ``phi`` (rad) and whose translation is held by
:func:`lampsam.factors.axis_factors.axis_anchor_prior`; ``G`` (``g0``) the map frame's
offset ``g = (dx, dy, dtheta)`` (m, m, rad; a turn about the frame's ``center``, then a
shift), ``Vector3``.

Factors:

- start: ``PriorFactorPose2`` on ``X(0)`` (the known start, or the global localizer's
  answer, with the filter's start covariance moved to the right tangent);
- odometry: ``BetweenFactorPose2(X(k), X(k+1))`` of step ``k``'s wheel samples (paper 1,
  eqs. 13-15 composed, :meth:`lampsam.backend.odometry.MotionModel.relative`, plus
  ``Isam2Config.odometry_floor_var``);
- sightings: the built-in ``PlanarProjectionFactor2`` on ``(X(k+1), L(id))`` (eqs. 17-18),
  and for a lamp whose axis row the filter used,
  :func:`lampsam.factors.axis_factors.lamp_axis_between_factor` on ``(X(k+1), A(id))``;
- the map: with a frame model (a version-2 map, :mod:`lampsam.backend.map_frame`) and
  :attr:`MapSmootherConfig.frame`, the rank-3 model (or its shift-only reduction,
  :func:`shift_only`, the default: :attr:`MapSmootherConfig.frame_turn`) ``l = m + C g + r``: ``g ~ N(0, S)``
  (``PriorFactorVector`` on ``G``) and per used landmark one linear factor
  ``(l - m) + e_phi (phi - phi_m) - C g ~ N(0, D)`` over ``(L, A, G)`` (rows ``x, y, z``
  and, for a lamp with an axis, ``phi``; ``D = Sigma_ll - C S C^T``, the landmark's
  residual independent of the others), a ``LinearContainerFactor`` (exact: ``L`` and
  ``G`` are vector spaces and ``A``'s angle chart is additive). Without a frame model,
  an independent prior ``N(m, Sigma_ll)`` per used landmark (its marginal), the
  ``phi`` prior on ``A``'s angle. The map is the prior; the run is the likelihood.
  The ties (or priors) of the landmarks the filter released
  (:mod:`lampsam.backend.map_release`) are widened by ``release_sigma^2`` before the solve.

The frame model is sparse (``3 + 3 L`` variables tied through one 3-vector), so the
map's common error costs three variables, not a dense ``3 L x 3 L`` prior. Its value is
that repeated sightings of the map across the whole run, tied to the world by the known
start and the odometry, can move the map's frame; the filter sees only the start.

Solved with Levenberg-Marquardt once at :meth:`MapSmoother.finish` from the filter's poses and the
map (the default: the filter already gives the online estimate), or with iSAM2
(:attr:`MapSmootherConfig.update_every` > 0: an update every that many steps, whose
current pose is then the online estimate of those steps). The result's pose
covariances are the filter's (causal); the final frame estimate and its covariance are
in ``extra`` (``map_frame_*``). Accuracy and cost: docs/ceiling-map.md.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, field

import gtsam
import numpy as np
from gtsam.symbol_shorthand import A, L, X

from lampsam.arrays import FloatArray
from lampsam.backend.ceiling import CeilingModel
from lampsam.backend.ceiling_map_io import CeilingMap, MapLandmark
from lampsam.backend.config import SlamConfig
from lampsam.backend.interface import Frame, SlamBackend, SlamResult, StepEstimate
from lampsam.backend.localize_only import LocalizeConfig, MapLocalizer
from lampsam.backend.map_frame import D_FLOOR, shift_only
from lampsam.backend.map_release import release_cov
from lampsam.backend.models import Obs
from lampsam.backend.odometry import OdometryConstants, motion_model
from lampsam.config_loader import check_limits, limits
from lampsam.errors import EstimationError
from lampsam.factors.axis_factors import axis_anchor_prior, lamp_axis_between_factor
from lampsam.factors.geometry import tangent_D_coords, wrap_angle
from lampsam.factors.gtsam_factors import (
    noise_model,
    pose_array,
    projection_factor,
    sqrt_information,
)

log = logging.getLogger(__name__)

#: key of the map frame's offset ``g``
G = gtsam.symbol("g", 0)


@dataclass(frozen=True)
class MapSmootherConfig:
    """Localize-only smoothing.

    Attributes:
        frame: use the map's frame model when it has one (default True); False, or a
            version-1 or merged map: each used landmark's marginal as an independent prior.
        frame_turn: also estimate the frame's turn ``dtheta``; default False: the
            shift-only model of :func:`shift_only` (the turn's part of each landmark's
            error goes into its independent residual). One run with a known start does not
            observe the turn: on lab its posterior sigma stays 59 of the prior's 61 mdeg and
            its estimate follows the frontend's lamp bias (docs/ceiling-map.md).
        update_every: 0 (default): one Levenberg-Marquardt solve at :meth:`MapSmoother.finish`;
            n > 0: an iSAM2 update every n steps (and at the end), the online estimate of
            those steps being iSAM2's.
        max_iterations: Levenberg-Marquardt iterations at most (default 20).
        final_updates: extra iSAM2 updates at the end (relinearisation; default 2).
    """

    frame: bool = True
    frame_turn: bool = False
    update_every: int = field(default=0, metadata=limits(ge=0))
    max_iterations: int = field(default=20, metadata=limits(ge=1))
    final_updates: int = field(default=2, metadata=limits(ge=0))

    def __post_init__(self) -> None:
        """Check the declared ranges (:class:`FieldValueError` naming the key)."""
        check_limits(self)


def map_tie_factor(lm: MapLandmark, gain: FloatArray, d_cov: FloatArray, with_axis: bool,
                   center: FloatArray) -> gtsam.LinearContainerFactor:
    """The frame model's factor of one landmark: ``(l - m) + e_phi (phi - phi_m) - C g ~ N(0, D)``.

    Args:
        lm: the map landmark (``m``: its saved position and axis).
        gain: (4, 3) ``C_l`` (rows ``x, y, z, phi``).
        d_cov: (4, 4) ``D_l``, m^2, m rad, rad^2.
        with_axis: include the ``phi`` row and the ``A(id)`` variable.
        center: (2,) the frame's rotation centre (the ``A`` anchor's translation), m.

    Returns:
        A ``LinearContainerFactor`` linearised at ``L = m``, ``A = (center, phi_m)``,
        ``G = 0`` (where its residual is 0).
    """
    rows = [0, 1, 2, 3] if with_axis else [0, 1, 2]
    k = len(rows)
    cov = np.asarray(d_cov, float)[np.ix_(rows, rows)] + D_FLOOR * np.eye(k)
    j_l = np.zeros((k, 3))
    j_l[:3, :3] = np.eye(3)
    j_g = -np.asarray(gain, float)[rows]
    lin = gtsam.Values()
    lin.insert(L(lm.id), np.asarray(lm.position, float))
    lin.insert(G, np.zeros(3))
    w = sqrt_information(cov)
    model = gtsam.noiseModel.Unit.Create(k)
    if with_axis:
        assert lm.phi is not None
        j_a = np.zeros((k, 3))
        j_a[3, 2] = 1.0
        lin.insert(A(lm.id), gtsam.Pose2(float(center[0]), float(center[1]), float(lm.phi)))
        jf = gtsam.JacobianFactor(L(lm.id), w @ j_l, A(lm.id), w @ j_a, G, w @ j_g, np.zeros(k),
                                  model)
    else:
        jf = gtsam.JacobianFactor(L(lm.id), w @ j_l, G, w @ j_g, np.zeros(k), model)
    return gtsam.LinearContainerFactor(jf, lin)


class MapSmoother(SlamBackend):
    """Localize-only filter online, factor-graph smoother in hindsight (module docstring).

    Args:
        odometry: the odometry model's constants.
        config: the SLAM config (association gate, features, noise, ``isam2`` floors).
        start_pose: (3,) start pose ``world_T_body``.
        cmap: the ceiling map.
        ceiling: the run's ceiling observation model.
        loc: the filter's settings.
        start_cov: (3, 3) covariance of ``start_pose`` (plain coordinates); None: ``loc``'s.
        smooth: the smoother's settings.
    """

    name = "localize-smooth"

    def __init__(self, odometry: OdometryConstants, config: SlamConfig, start_pose: FloatArray,
                 cmap: CeilingMap, ceiling: CeilingModel, loc: LocalizeConfig | None = None,
                 start_cov: FloatArray | None = None,
                 smooth: MapSmootherConfig | None = None) -> None:
        self.filter = MapLocalizer(odometry, config, start_pose, cmap, ceiling, loc, start_cov)
        self.smooth = smooth or MapSmootherConfig()
        self.config = config
        self.cmap = cmap
        self.motion = motion_model(odometry)
        self.body_t_camera = np.asarray(ceiling.body_t_camera, float)
        self.frame = cmap.frame if self.smooth.frame else None
        if self.frame is not None and not self.smooth.frame_turn:
            self.frame = shift_only(self.frame)
        self.graph = gtsam.NonlinearFactorGraph()
        self.values = gtsam.Values()
        self._new_graph = gtsam.NonlinearFactorGraph()
        self._new_values = gtsam.Values()
        self._isam: gtsam.ISAM2 | None = None
        if self.smooth.update_every > 0:
            params = gtsam.ISAM2Params()
            params.setRelinearizeThreshold(config.isam2.relinearize_threshold)
            params.relinearizeSkip = 1
            self._isam = gtsam.ISAM2(params)
        self._landmarks: set[int] = set()
        #: landmark id -> (graph index of its map tie or prior, the landmark, axis row in it)
        self._ties: dict[int, tuple[int, MapLandmark, bool]] = {}
        self._axes: set[int] = set()
        self._online: list[FloatArray] = []
        self._k = 0
        pose0 = np.asarray(start_pose, float).reshape(3)
        p0 = self.filter.P
        t = tangent_D_coords(float(pose0[2]))
        self._add_value(X(0), gtsam.Pose2(*pose0))
        self._add_factor(gtsam.PriorFactorPose2(X(0), gtsam.Pose2(*pose0),
                                                noise_model(t @ p0 @ t.T)))
        if self.frame is not None:
            self._add_value(G, np.zeros(3))
            self._add_factor(gtsam.PriorFactorVector(G, np.zeros(3), noise_model(self.frame.cov)))

    # ------------------------------------------------------------------ graph
    def _add_value(self, key: int, value: gtsam.Pose2 | FloatArray) -> None:
        for vals in (self.values, self._new_values):
            if isinstance(value, gtsam.Pose2):
                vals.insert(key, value)
            else:
                vals.insert(key, np.asarray(value, float))

    def _add_factor(self, factor: gtsam.NonlinearFactor) -> None:
        self.graph.add(factor)
        self._new_graph.add(factor)

    def _landmark(self, lm: MapLandmark, with_axis: bool) -> None:
        """Insert ``L(id)`` (and ``A(id)``) with the map's tie, once."""
        if lm.id not in self._landmarks:
            self._landmarks.add(lm.id)
            self._add_value(L(lm.id), np.asarray(lm.position, float))
            if self.frame is None or lm.id not in self.frame.gains:
                self._ties[lm.id] = (self.graph.size(), lm, False)
                self._add_factor(_point_prior(lm, np.zeros((3, 3))))
        if not with_axis or lm.id in self._axes or lm.phi is None:
            return
        self._axes.add(lm.id)
        center = np.zeros(2) if self.frame is None else self.frame.center
        self._add_value(A(lm.id), gtsam.Pose2(float(center[0]), float(center[1]), float(lm.phi)))
        self._add_factor(axis_anchor_prior(A(lm.id), center, float(lm.phi)))
        if self.frame is None or lm.id not in self.frame.gains:
            var = float(lm.cov[3, 3]) + D_FLOOR
            self._add_factor(gtsam.PriorFactorPose2(
                A(lm.id), gtsam.Pose2(float(center[0]), float(center[1]), float(lm.phi)),
                gtsam.noiseModel.Diagonal.Precisions(np.array([0.0, 0.0, 1.0 / var]))))
        # with a frame model the phi row is in the landmark's tie (added below)

    def _tie(self, lm: MapLandmark, with_axis: bool) -> None:
        """The frame model's factor of ``lm`` (:func:`map_tie_factor`), at its first use."""
        assert self.frame is not None
        self._ties[lm.id] = (self.graph.size(), lm, with_axis)
        self._add_factor(map_tie_factor(lm, self.frame.gains[lm.id],
                                        self.frame.conditional(lm.id, lm.cov), with_axis,
                                        self.frame.center))

    def _add_sightings(self, key: int, pose: FloatArray,
                       matches: list[tuple[Obs, MapLandmark, bool]]) -> None:
        """Factors of one step's matched observations on pose ``key``."""
        for o, lm, axis in matches:
            with_axis = axis and lm.phi is not None and o.has_axis
            new_l = lm.id not in self._landmarks
            new_a = with_axis and lm.id not in self._axes
            self._landmark(lm, with_axis)
            if self.frame is not None and lm.id in self.frame.gains and (new_l or new_a):
                if new_a and not new_l:
                    # the landmark was tied without its axis: tie the axis alone (phi row)
                    self._tie_axis(lm)
                else:
                    self._tie(lm, with_axis)
            self._add_factor(projection_factor(key, L(lm.id), o.z[:2], o.R[:2, :2],
                                               self.body_t_camera))
            if with_axis:
                assert lm.phi is not None
                sigma = math.sqrt(float(o.R[2, 2]))
                self._add_factor(lamp_axis_between_factor(
                    key, A(lm.id), float(o.z[2]), sigma, wrap_angle(float(lm.phi) - pose[2])))

    def _tie_axis(self, lm: MapLandmark) -> None:
        """The ``phi`` row of the frame model for a lamp tied earlier without its axis:
        ``phi - phi_m - C_phi g ~ N(0, D_phiphi)`` (its correlation with the landmark's
        position rows, small, is dropped)."""
        assert self.frame is not None and lm.phi is not None
        d = self.frame.conditional(lm.id, lm.cov)
        model = gtsam.noiseModel.Unit.Create(1)
        w = 1.0 / math.sqrt(d[3, 3] + D_FLOOR)
        j_a = np.array([[0.0, 0.0, w]])
        j_g = -w * self.frame.gains[lm.id][3:4]
        lin = gtsam.Values()
        c = self.frame.center
        lin.insert(A(lm.id), gtsam.Pose2(float(c[0]), float(c[1]), float(lm.phi)))
        lin.insert(G, np.zeros(3))
        jf = gtsam.JacobianFactor(A(lm.id), j_a, G, j_g, np.zeros(1), model)
        self._add_factor(gtsam.LinearContainerFactor(jf, lin))

    def _isam_update(self) -> None:
        assert self._isam is not None
        self._isam.update(self._new_graph, self._new_values)
        self._new_graph = gtsam.NonlinearFactorGraph()
        self._new_values = gtsam.Values()

    # ------------------------------------------------------------------ interface
    def step(self, t: float, wheel: FloatArray, frame: Frame | None) -> StepEstimate:
        """The filter's step (its estimate is the online one), and the step's factors."""
        t0 = time.perf_counter()
        est = self.filter.step(t, wheel, frame)
        u = self.motion.check(t, wheel)
        k = self._k
        self._k += 1
        if len(u):
            delta, cov = self.motion.relative(u, self.config.isam2.odometry_floor_var)
        else:
            delta, cov = np.zeros(3), self.config.isam2.odometry_floor_var * np.eye(3)
        self._add_value(X(k + 1), gtsam.Pose2(*est.pose))
        self._add_factor(gtsam.BetweenFactorPose2(X(k), X(k + 1), gtsam.Pose2(*delta),
                                                  noise_model(cov)))
        self._add_sightings(X(k + 1), est.pose, self.filter.frame_matches)
        pose = est.pose
        if self._isam is not None and (k + 1) % self.smooth.update_every == 0:
            self._isam_update()
            p2 = self._isam.calculateEstimatePose2(X(k + 1))
            pose = np.array([p2.x(), p2.y(), p2.theta()])
        self._online.append(pose)
        return StepEstimate(t, pose, est.cov, est.keyframe, est.n_matched, 0,
                            time.perf_counter() - t0)

    def solve(self) -> gtsam.Values:
        """The graph's solution (module docstring)."""
        if self._isam is not None:
            self._isam_update()
            for _ in range(self.smooth.final_updates):
                self._isam.update()
            return self._isam.calculateEstimate()
        params = gtsam.LevenbergMarquardtParams()
        params.setMaxIterations(self.smooth.max_iterations)
        try:
            values = gtsam.LevenbergMarquardtOptimizer(self.graph, self.values, params).optimize()
        except RuntimeError as exc:
            raise EstimationError(f"localize-only smoother: {exc}") from None
        return values

    def _apply_releases(self) -> None:
        """Widen the map ties of the landmarks the filter released
        (:attr:`lampsam.backend.localize_only.LocalizeConfig.release`): their ``x, y, z``
        rows get :func:`lampsam.backend.map_release.release_cov` added, as in the filter,
        for the whole run (the hindsight solve does not know when a lamp moved). Only
        for the Levenberg-Marquardt solve (the iSAM2 engine already holds the factors)."""
        released = self.filter.released_ids() & set(self._ties)
        if not released:
            return
        if self._isam is not None:
            log.warning("%d released map landmarks are not released in the iSAM2 smoother",
                        len(released))
            return
        add = np.zeros((4, 4))
        add[:3, :3] = release_cov(self.filter.loc.release_sigma)
        for lid in sorted(released):
            index, lm, with_axis = self._ties[lid]
            factor: gtsam.NonlinearFactor
            if self.frame is not None and lid in self.frame.gains:
                factor = map_tie_factor(lm, self.frame.gains[lid],
                                        self.frame.conditional(lid, lm.cov) + add, with_axis,
                                        self.frame.center)
            else:
                factor = _point_prior(lm, add[:3, :3])
            self.graph.replace(index, factor)

    def finish(self, status: str = "ok") -> SlamResult:
        """The smoothed poses (one per step); covariances and ``extra`` counts are the
        filter's, plus the frame estimate ``map_frame_*`` (m, rad) with its sigmas."""
        res = self.filter.finish(status)
        self._apply_releases()
        values = self.solve()
        poses = np.array([pose_array(values.atPose2(X(k + 1))) for k in range(self._k)]).reshape(-1, 3)
        res.poses = poses
        res.backend = self.name
        res.extra["smoother_landmarks"] = float(len(self._landmarks))
        res.extra["smoother_factors"] = float(self.graph.size())
        if self.frame is not None:
            g = values.atVector(G)
            res.extra.update({"map_frame_dx_m": float(g[0]), "map_frame_dy_m": float(g[1]),
                              "map_frame_dtheta_rad": float(g[2])})
            try:
                cov = gtsam.Marginals(self.graph, values).marginalCovariance(G)
                res.extra.update({"map_frame_sigma_dx_m": math.sqrt(cov[0, 0]),
                                  "map_frame_sigma_dy_m": math.sqrt(cov[1, 1]),
                                  "map_frame_sigma_dtheta_rad": math.sqrt(cov[2, 2])})
            except RuntimeError as exc:
                log.warning("map frame covariance unavailable: %s", exc)
        self.online_poses = np.asarray(self._online, float).reshape(-1, 3)
        return res


def _point_prior(lm: MapLandmark, extra: FloatArray) -> gtsam.PriorFactorPoint3:
    """A map landmark's independent position prior ``N(m, Sigma_ll + extra)`` (m, m^2)."""
    cov = np.asarray(lm.cov, float)[:3, :3] + np.asarray(extra, float) + D_FLOOR * np.eye(3)
    return gtsam.PriorFactorPoint3(L(lm.id), np.asarray(lm.position, float), noise_model(cov))


def frame_to_rigid(g: FloatArray, center: FloatArray) -> FloatArray:
    """``g = (dx, dy, dtheta)`` (a turn about ``center``, then a shift) as the SE(2)
    transform ``(x, y, theta)`` it applies to the map: ``p' = R p + t`` with
    ``t = center - R center + (dx, dy)``."""
    c, s = math.cos(float(g[2])), math.sin(float(g[2]))
    cx, cy = float(center[0]), float(center[1])
    return np.array([cx - (c * cx - s * cy) + float(g[0]), cy - (s * cx + c * cy) + float(g[1]),
                     float(g[2])])


__all__ = ["MapSmoother", "MapSmootherConfig", "frame_to_rigid", "map_tie_factor", "shift_only"]
