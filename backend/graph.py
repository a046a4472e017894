"""Factor-graph backends: iSAM2 (online) and batch Levenberg-Marquardt (offline).

Both build the same graph (DESIGN sec. 4; paper 1's models in a smoother):

- keyframe poses ``X(k)`` (``Pose2``), a prior on the known start pose;
- odometry ``BetweenFactorPose2`` between consecutive keyframes, its covariance the
  odometry model's noise composed over the samples between them
  (:mod:`lampsam.backend.odometry`: wheel travel, eqs. 13-15, or Pose2 increments)
  plus ``Isam2Config.odometry_floor_var``;
- measurement factors built by a per-kind landmark handler
  (:class:`lampsam.backend.handlers.LandmarkHandler`: planar range-bearing with
  GTSAM's built-in ``BearingRangeFactor2D``; lamps and corners with
  :class:`lampsam.backend.ceiling_graph.CeilingHandler`).

The work is split by job over :class:`lampsam.backend.graph_state.GraphState`:
keyframe policy (:mod:`~lampsam.backend.keyframes`), gating
(:mod:`~lampsam.backend.gating`), landmark lifecycle
(:mod:`~lampsam.backend.landmarks`), iSAM2 updates and recovery
(:mod:`~lampsam.backend.isam2_update`), pose-covariance algebra
(:mod:`~lampsam.backend.pose_cov`). This module makes keyframes, steps and the
final result.

Between keyframes the current pose is the last keyframe estimate composed with the
odometry since then, covariance propagated to first order
(``Sigma = Ad(delta^-1) Sigma_k Ad(delta^-1)^T + Sigma_delta`` in the right tangent).
Each keyframe gives factors to at most ``AssociationConfig.max_corner_updates``
corners already in the graph, those with the longest tracks first
(:func:`~lampsam.backend.association.corner_budget`): iSAM2 puts every newly
observed variable in the root clique, so the update and the pose marginal grow with
the cube of their number, and a frame carries 50-150 corners. Corner factors carry
a Huber loss by default (``Isam2Config.corner_huber_k``): they are associated by
gate + NCC without ids.

The batch backend runs the same online pass (``init = "isam2"``) or a pure odometry
pass (``init = "odometry"``: running estimate = dead reckoning, gating then without
cross-covariance: meant for known association) and then one LM over the whole
graph, with Huber noise if configured; if LM fails (a trial step throwing), the
iSAM2 estimate is kept, with a warning. In the final result every step's pose is its
keyframe's final estimate composed with the odometry conditioned on both
neighbouring keyframes (:func:`~lampsam.backend.pose_cov.odometry_bridge`).
"""

from __future__ import annotations

import logging
import time

import gtsam
import numpy as np
from gtsam.symbol_shorthand import X

from lampsam.arrays import FloatArray
from lampsam.backend.alias_gate import map_density
from lampsam.backend.association import Assignment, associate, corner_budget
from lampsam.backend.ceiling import CeilingModel
from lampsam.backend.ceiling_graph import point_key
from lampsam.backend.config import SlamConfig
from lampsam.backend.config_offline import BatchConfig
from lampsam.backend.handlers import (
    GraphLandmark,
    LandmarkHandler,
    MarginalSource,
    value_of_kind,
)
from lampsam.backend.held_sightings import held_candidates
from lampsam.backend.innovation_scale import learn_scale
from lampsam.backend.interface import (
    Frame,
    GraphSnapshot,
    LandmarkEstimate,
    SlamResult,
    StepEstimate,
    check_step_time,
)
from lampsam.backend.isam2_update import Isam2Updates
from lampsam.backend.joint_gating import JointGating
from lampsam.backend.keyframes import STEP_FLOOR as STEP_FLOOR
from lampsam.backend.keyframes import Advanced, advance_odometry, keyframe_observations
from lampsam.backend.landmarks import LandmarkLifecycle
from lampsam.backend.models import (
    Obs,
    landmark_estimate,
)
from lampsam.backend.odometry import OdometryConstants
from lampsam.backend.odometry_scale import feed_scale
from lampsam.backend.pose_cov import compose_cov, odometry_bridge, pose_array, tangent_to_coords_cov
from lampsam.backend.revisit_merge import RevisitMerge
from lampsam.errors import EstimationError
from lampsam.factors.gtsam_factors import odometry_factor

log = logging.getLogger(__name__)



class GraphSlam(JointGating, RevisitMerge, LandmarkLifecycle, Isam2Updates):
    """The iSAM2 and batch backends' common pass (see module docstring).

    Args:
        odometry: the odometry model's constants (wheel or Pose2 increments).
        config: the SLAM config.
        start_pose: (3,) known start pose ``world_T_body``, m and rad.
        ceiling: the ceiling observation model (lamps/corners), or None.
        ceiling_handler: graph handler for ceiling kinds, or None.
        online: keep an iSAM2 estimate (True) or only odometry (False).
    """

    name = "graph"

    def __init__(self, odometry: OdometryConstants, config: SlamConfig, start_pose: FloatArray,
                 ceiling: CeilingModel | None = None,
                 ceiling_handler: LandmarkHandler | None = None, online: bool = True) -> None:
        super().__init__(odometry, config, start_pose, ceiling, ceiling_handler, online)
        self._distinct_handlers = list({id(h): h for h in self.handlers.values()}.values())
        #: keyframes made with ``step(update=False)`` not yet sent to iSAM2
        self.n_deferred = 0
        #: the next step's odometry advanced by the caller (:meth:`give_odometry`)
        self._given_odometry: Advanced | None = None
        #: lamps mapped since the last update: first-sight state and covariance (3,), (3, 3)
        self._first_sight: dict[int, tuple[FloatArray, FloatArray]] = {}
        self._flush()

    # ------------------------------------------------------------------ keyframe
    def _make_keyframe(self, obs: list[Obs], update: bool = True) -> tuple[int, int]:
        """Add a keyframe with its odometry factor and the frame's observations.

        ``update``: send them to iSAM2 at once (with any keyframes deferred before);
        False defers them to a later update (:meth:`step`).
        """
        pose = self.current_pose()
        cov_now: list[FloatArray] = []

        def pose_cov() -> FloatArray:
            """The pose's tangent covariance, composed when first needed (the gate, a
            new landmark's covariance, the odometry-only pass): a known-id keyframe
            that starts no landmark never reads the last keyframe's marginal."""
            if not cov_now:
                cov_now.append(self.current_cov())
            return cov_now[0]

        if len(self._wheel_since_kf) == 1 and self._first_rel is not None:
            delta, cov = self._first_rel  # one step's samples since the last keyframe
        else:
            u = (np.concatenate(self._wheel_since_kf) if self._wheel_since_kf
                 else np.zeros((0, self.motion.width)))
            delta, cov = self.motion.relative(u, self.config.isam2.odometry_floor_var)
        k = self._k + 1
        self._add_value(X(k), gtsam.Pose2(*pose))
        self._add_factor(odometry_factor(X(k - 1), X(k), delta, cov))
        self._k = k
        self._kf_poses.append(pose.copy())
        self._odo.append((np.asarray(delta, float), np.asarray(cov, float)))
        if self.odo_scale is not None:
            self.idle.propagate(gtsam.Pose2(*delta).inverse().AdjointMap(), cov)
        n_matched = n_new = 0
        if self._k_isam == k - 1:  # else iSAM2 (and X(k0)'s joint marginals) unchanged since
            self._joint_cache = {}
        if obs:
            gating = not self.config.association.use_known_ids or any(
                o.landmark_id is None for o in obs)
            cands: dict[str, list[int]] = {}
            if gating:
                gate_ctx = self._gate_context(k, pose)
                cands, screened = self._screen(obs, pose, pose_cov())
                self._prefetch_joint(gate_ctx[0], obs, screened)
                patches = {lid: self._landmarks[lid].patch for lid in cands.get("corner", ())}
                density = self._alias_density()
                assignments = associate(
                    obs, cands, lambda lid, o: self._innovation(gate_ctx, lid, o),
                    self.config.association, lambda i: i in self._landmarks, patches, screened,
                    self._same_place, density)
                if self.config.association.joint_compatibility:
                    assignments = self._joint_planar(gate_ctx, obs, assignments, screened,
                                                     density)
                learn_scale(self.noise_scale, obs, assignments, screened)
                if self.odo_scale is not None:
                    feed_scale(self.odo_scale, self.idle, obs, assignments, screened,
                               lambda lid, o: self._innovation_h(gate_ctx, lid, o))
            else:  # every id known: what associate() decides, without its gate machinery
                ids = [int(o.landmark_id) for o in obs if o.landmark_id is not None]
                assignments = [Assignment(i, lid, "matched" if lid in self._landmarks else "new")
                               for i, lid in enumerate(ids)]
            matches: list[tuple[GraphLandmark, Obs]] = []
            for a in assignments:
                o = obs[a.obs_index]
                if a.status == "matched" and a.landmark_id in self._landmarks:
                    lm = self._landmarks[a.landmark_id]
                    if lm.kind != o.kind:
                        continue
                    matches.append((lm, o))
                elif a.status == "new":
                    if o.kind == "lamp" and a.landmark_id is None and self._near_known_lamp(
                            pose, o, cands.get("lamp", ())):
                        continue
                    n_new += self._start_landmark(pose, pose_cov(), k, o, a.landmark_id)
            matches, self._entries_left = corner_budget(
                matches, self.config.association.max_corner_updates)
            for lm, o in matches:
                self._observe(lm, k, o)
                n_matched += 1
            acfg = self.config.association
            if gating and (acfg.planar_unique or acfg.revisit_check):
                held = [(obs[a.obs_index], held_candidates(screened, a.obs_index))
                        for a in assignments if a.status == "dropped"
                        and obs[a.obs_index].kind == "point2"
                        and obs[a.obs_index].landmark_id is None]
                self._hold(k, held)
                if acfg.planar_unique:
                    self._give_back(k)
                if acfg.revisit_check:
                    self._revisit_check(k, n_new, [o for o, _ in held])
        if k % 10 == 0:
            self._forget_pending(k)
        # The keyframe's own estimate: the prediction until iSAM2 updates it (_flush).
        self._kf_pose = pose
        if self.isam is None or not update:  # (deferred: the prediction's until the update)
            self._kf_cov = pose_cov()
        self._delta = np.zeros(3)
        self._delta_cov = np.zeros((3, 3))
        self._wheel_since_kf = []
        self._first_rel = None
        for handler in self._distinct_handlers:
            for f in handler.flush(self.robust, self._pose_of):
                self._add_factor(f)
        if update:
            self.update()
        else:  # catching up: the prediction stands until the next update
            self.n_deferred += 1
            self._place_deferred_lamps()
        return n_matched, n_new

    def _alias_density(self) -> float:
        """Landmarks per m^2 for ``association.alias_odds`` (0: the test is off):
        the stated ``alias_spacing``'s, else the map's
        (:func:`lampsam.backend.alias_gate.map_density` of the planar landmarks)."""
        acfg = self.config.association
        if acfg.alias_odds <= 0.0:
            return 0.0
        xy = [lm.state[:2] for lm in self._landmarks.values() if lm.kind == "point2"]
        return map_density(np.array(xy, float).reshape(-1, 2), acfg.alias_spacing)

    def _place_deferred_lamps(self) -> None:
        """Lamps mapped since the last update, moved to their sights' fused estimate.

        A lamp enters the graph at its first sight at the height prior (eq. 25,
        ``x0`` with covariance ``P0``); from its second sight its gate covariance is
        the triangulation's (:meth:`~lampsam.backend.landmarks.LandmarkLifecycle._tighten_lamp_gate`).
        Updated at once, iSAM2 moves the lamp to what prior and sights say; with the
        update deferred the state would keep the prior's height under the
        triangulation's covariance, and the parallax of the next keyframes pushes
        the lamp's sights out of its gate. So the state (and the initial value iSAM2
        will get) becomes ``x = (P0^-1 + P1^-1)^-1 (P0^-1 x0 + P1^-1 x1)`` with ``x1``,
        ``P1`` the triangulation of its sights (keyframes at their predictions; the
        first sight counted twice).
        """
        if self.ceiling is None:
            return
        for key in self._new_values.keys():
            lm = self._landmarks.get(int(gtsam.Symbol(key).index()))
            if lm is None or lm.kind != "lamp" or key != point_key(lm.kind, lm.id):
                continue
            if lm.id not in self._first_sight:
                if lm.cov_rel is not None:
                    self._first_sight[lm.id] = (lm.state[:3].copy(), np.asarray(lm.cov_rel))
                continue
            if len({k for k, _ in lm.sights}) < 2:
                continue
            x0, p0 = self._first_sight[lm.id]
            x1, p1 = self._triangulate_sights(lm.sights)[3:5]
            i0, i1 = np.linalg.inv(p0), np.linalg.inv(p1)
            point = np.linalg.solve(i0 + i1, i0 @ x0 + i1 @ x1)
            lm.state = np.concatenate([point, lm.state[3:]])
            self._new_values.update(key, point)
            self.initial.update(key, point)

    def _gate_context(self, k: int, pose: FloatArray
                      ) -> tuple[int, FloatArray, FloatArray, FloatArray]:
        """``(k0, pose, delta, cov)`` of the gate (:meth:`~lampsam.backend.gate_exact.ExactGate._innovation`).

        ``k0`` is the newest keyframe in iSAM2 (``k - 1`` unless keyframes were
        deferred), ``delta`` (x, y, theta) and ``cov`` (3, 3, right tangent) the
        odometry from ``X(k0)`` to the new keyframe's predicted ``pose``: the
        deferred keyframes' odometry factors composed with the steps' since
        (``Sigma = Ad(d^-1) Sigma_a Ad(d^-1)^T + Sigma_d`` per factor).
        """
        k0 = self._k_isam
        if k0 == k - 1:
            return k0, pose, self._delta.copy(), self._delta_cov.copy()
        d, c = gtsam.Pose2(), np.zeros((3, 3))
        for delta, cov in [*self._odo[k0 + 1:k], (self._delta, self._delta_cov)]:
            c = compose_cov(delta, c, cov)
            d = d.compose(gtsam.Pose2(*delta))
        return k0, pose, pose_array(d), c

    def update(self) -> None:
        """Send the keyframes' pending factors and values to iSAM2 (one update).

        :meth:`step` with ``update=True`` (the default) calls it at every keyframe
        and after deferred ones; a caller that deferred keyframes may call it itself.
        """
        self._flush()
        self._k_isam = self._k
        self.n_deferred = 0
        self._first_sight = {}

    # ------------------------------------------------------------------ interface
    def give_odometry(self, advanced: Advanced | None) -> None:
        """The next :meth:`step`'s odometry since the last keyframe, already advanced by
        the caller: :func:`~lampsam.backend.keyframes.advance_odometry` of the step's
        samples from this backend's state, as
        :class:`~lampsam.backend.keyframes.KeyframeMirror` computes it beside a backend in
        another process (``--online decoupled``); the step then does not compose its
        samples again. The same function of the same inputs: results bit for bit the
        same. None (a step without samples): the step composes as usual.
        """
        self._given_odometry = advanced

    def step(self, t: float, odometry: FloatArray, frame: Frame | None,
             update: bool = True) -> StepEstimate:
        """See :meth:`SlamBackend.step`. Raises EstimationError on NaN odometry or time reversal.

        ``update=False`` (catching up, :mod:`lampsam.backend.tracking`): a keyframe made
        here is associated against the prediction (the newest iSAM2 estimate plus
        odometry) and its factors wait; the next step with ``update=True`` sends every
        deferred keyframe to iSAM2 in one update. Each step's estimate is then the
        prediction until that update.
        """
        t0 = time.perf_counter()
        self._last_t = check_step_time(t, self._last_t)
        u = self.motion.check(t, odometry)
        given, self._given_odometry = self._given_odometry, None
        if len(u):
            self._delta, self._delta_cov, first_rel = given if given is not None else (
                advance_odometry(self.motion, u, self._delta, self._delta_cov,
                                 not self._wheel_since_kf,
                                 self.config.isam2.odometry_floor_var)[:3])
            if first_rel is not None:  # the first samples since the keyframe
                self._first_rel = first_rel  # the odometry factor's, if no samples follow
            self._wheel_since_kf.append(u)
        n_matched = n_new = 0
        is_kf = False
        # a frame between keyframes is not read (a lazy frame's image never processed)
        obs = keyframe_observations(frame, self._k, self._delta, self.config)
        if obs:
            n_matched, n_new = self._make_keyframe(obs, update)
            is_kf = True
        if update and self.n_deferred:
            self.update()
        pose = self.current_pose()
        if self.config.isam2.pose_cov_every_step:
            cov = tangent_to_coords_cov(pose, self.current_cov())
        else:  # not asked for: not computed
            cov = np.full((3, 3), np.nan)
        dt = time.perf_counter() - t0
        self._times.append(t)
        self._step_kf.append(self._k)
        self._step_delta.append(self._delta.copy())
        self._step_delta_cov.append(self._delta_cov.copy())
        self._step_times.append(dt)
        self._keyframes.append(is_kf)
        return StepEstimate(t, pose, cov, is_kf, n_matched, n_new, dt)

    def _final_values(self) -> tuple[gtsam.Values, MarginalSource | None, str | None]:
        """Final estimate, a marginal-covariance function, and why the estimate is the
        online smoother's instead of the final optimisation's (None when it is not)."""
        raise NotImplementedError

    def finish(self, status: str = "ok") -> SlamResult:
        """Final estimate; every step's pose = its keyframe's final estimate + odometry."""
        if self.n_deferred:  # keyframes deferred by a stop mid catch-up: finished, so sent
            try:
                self.update()
            except (RuntimeError, EstimationError) as exc:
                log.error("the deferred keyframes' update failed: %s", exc)
        pruned = set(self._prune_once_seen())
        t0 = time.perf_counter()
        try:
            values, marginal, fallback = self._final_values()
        except (RuntimeError, EstimationError) as exc:  # a broken graph: keep the online poses
            log.error("final optimisation failed (%s): keeping the online estimates", exc)
            values, marginal, fallback = self.initial, None, None
            status = status if status.startswith("failed") else f"failed: {exc}"
        source, status = final_source(self.name, status, fallback)
        final_time = time.perf_counter() - t0
        n_kf = self._k + 1
        kf_pose = np.array([pose_array(values.atPose2(X(k))) if values.exists(X(k))
                            else self._kf_poses[k] for k in range(n_kf)])
        kf_cov = np.full((n_kf, 3, 3), np.nan)
        with_cov = marginal is not None and self.config.isam2.final_covariances
        if with_cov:
            assert marginal is not None
            for k in range(n_kf):
                try:
                    kf_cov[k] = marginal(X(k))
                except (RuntimeError, IndexError):
                    continue
        n = len(self._times)
        poses = np.zeros((n, 3))
        covs = np.full((n, 3, 3), np.nan)
        for i in range(n):
            k = self._step_kf[i]
            delta, cov_delta = self._step_delta[i], self._step_delta_cov[i]
            # between two keyframes: condition the odometry on both (a keyframe's own
            # step has zero odometry and covariance, which the bridge leaves as is);
            # not between keyframes a fixed-lag smoother let go of at different updates
            # (estimates of two epochs: their relative pose need not fit the odometry)
            if k + 1 < n_kf and not self._keyframes[i] and not (
                    k in self._left_poses or k + 1 in self._left_poses):
                delta, cov_delta = odometry_bridge(delta, cov_delta, *self._odo[k + 1],
                                                   kf_pose[k], kf_pose[k + 1])
            p = pose_array(gtsam.Pose2(*kf_pose[k]).compose(gtsam.Pose2(*delta)))
            poses[i] = p
            if with_cov:
                covs[i] = tangent_to_coords_cov(p, compose_cov(delta, kf_cov[k], cov_delta))

        lms: list[LandmarkEstimate] = []
        provisional: list[LandmarkEstimate] = []
        for lm in self._landmarks.values():
            if not lm.in_graph or (lm.id in pruned and self.config.association.prune_once_seen):
                continue
            handler = self.handlers[lm.kind]
            if not all(values.exists(key) for key in handler.keys(lm)):
                continue
            state = handler.read(lm, lambda key, kind: value_of_kind(values, key, kind))
            cov = np.full((len(state), len(state)), np.nan)
            if marginal is not None:
                try:
                    cov = handler.marginal(lm, marginal)
                except (RuntimeError, IndexError):
                    pass
            est = landmark_estimate(lm.id, lm.kind, state, cov, lm.n_obs, self.ceiling)
            (provisional if lm.id in pruned else lms).append(est)
        return SlamResult(
            backend=source,
            times=np.asarray(self._times, float),
            poses=poses,
            pose_covs=covs,
            landmarks=lms,
            provisional=provisional,
            step_times_s=np.asarray(self._step_times, float),
            keyframes=np.asarray(self._keyframes, bool),
            status=status,
            final_time_s=final_time,
            n_pruned=self.n_pruned,
            pruned=dict(self.pruned),
            graph=GraphSnapshot(self.graph, values,
                                None if self.ceiling is None else self.ceiling.body_t_camera),
            extra={"n_recoveries": float(self.n_recoveries),
                   "n_jcbb": float(self.n_jcbb), "n_jcbb_changed": float(self.n_jcbb_changed),
                   "n_revisit_merges": float(self.n_revisit_merges),
                   "n_revisit_rejected": float(self.n_revisit_rejected),
                   "n_revisit_ambiguous": float(self.n_revisit_ambiguous),
                   "n_revisit_resolved": float(self.n_revisit_resolved),
                   "n_revisit_moved": float(self.n_revisit_moved),
                   "n_held": float(self.n_held),
                   "n_held_given_back": float(self.n_held_given_back),
                   # held sightings (planar_unique) that never became a factor
                   "n_held_unused": float(self.n_held - self.n_held_given_back
                                          - self.n_revisit_resolved),
                   "n_qr_rebuilds": float(self.n_refactorized),
                   "n_damped_rebuilds": float(self.n_damped),
                   "update_median_ms": float(np.median(self.update_times) * 1e3)
                   if self.update_times else float("nan"),
                   "update_p95_ms": float(np.percentile(self.update_times, 95) * 1e3)
                   if self.update_times else float("nan"),
                   "estimate_median_ms": float(np.median(self.estimate_times) * 1e3)
                   if self.estimate_times else float("nan")},
        )


class Isam2Slam(GraphSlam):
    """Online iSAM2 backend: one ``update()`` per keyframe."""

    name = "isam2"

    def __init__(self, odometry: OdometryConstants, config: SlamConfig, start_pose: FloatArray,
                 ceiling: CeilingModel | None = None,
                 ceiling_handler: LandmarkHandler | None = None) -> None:
        super().__init__(odometry, config, start_pose, ceiling, ceiling_handler, online=True)

    def _final_values(self) -> tuple[gtsam.Values, MarginalSource | None, str | None]:
        assert self.isam is not None
        return self.isam.calculateEstimate(), self.isam.marginalCovariance, None


class BatchSlam(GraphSlam):
    """Offline batch LM over the whole run (optionally started from iSAM2's estimate)."""

    name = "batch"

    def __init__(self, odometry: OdometryConstants, config: SlamConfig, start_pose: FloatArray,
                 ceiling: CeilingModel | None = None,
                 ceiling_handler: LandmarkHandler | None = None) -> None:
        if config.batch.init not in ("isam2", "odometry"):
            raise EstimationError(f"batch.init must be 'isam2' or 'odometry', got {config.batch.init!r}")
        super().__init__(odometry, config, start_pose, ceiling, ceiling_handler,
                         online=config.batch.init == "isam2")

    def _final_values(self) -> tuple[gtsam.Values, MarginalSource | None, str | None]:
        start = self.isam.calculateEstimate() if self.isam is not None else self.initial
        revised = self._reassociate(start) if self.isam is not None else None
        if revised is not None:  # without ids, the association revised offline
            start = revised
        return batch_lm(self.graph, start, self.config.batch, self.isam)


def final_source(name: str, status: str, fallback: str | None) -> tuple[str, str]:
    """The result's ``(source, status)`` after the final optimisation.

    ``fallback`` is :func:`batch_lm`'s reason when the estimate is the online iSAM2
    one: the result is then labelled ``isam2`` and a run that was ``ok`` says why.
    """
    if fallback is None:
        return name, status
    return "isam2", (f"final optimisation failed: {fallback}" if status == "ok" else status)


def batch_lm(graph: gtsam.NonlinearFactorGraph, start: gtsam.Values, config: BatchConfig,
             isam: gtsam.ISAM2 | None) -> tuple[gtsam.Values, MarginalSource | None, str | None]:
    """One Levenberg-Marquardt over the whole graph from ``start`` (``config.to_gtsam()``).

    Returns:
        ``(estimate, marginal-covariance function or None, reason)``: ``reason`` is
        None, or why the estimate is the online iSAM2 one (LM threw and ``isam`` is
        given: ``start`` and iSAM2's marginals are returned).

    Raises:
        EstimationError: LM threw and there is no online estimate to keep.
    """
    try:
        opt = gtsam.LevenbergMarquardtOptimizer(graph, start, config.to_gtsam())
        result = opt.optimize()
    except RuntimeError as exc:
        if isam is None:
            raise EstimationError(f"batch LM failed: {exc}") from exc
        # e.g. a trial step put a landmark below the camera: keep the online smoother's
        reason = f"batch LM: {type(exc).__name__}: {str(exc).strip()[:120]}"
        log.error("%s: the result is the online iSAM2 estimate, labelled isam2", reason)
        return start, isam.marginalCovariance, reason
    log.info("batch LM: error %.4g -> %.4g in %d iterations",
             graph.error(start), graph.error(result), opt.iterations())
    try:
        marginals = gtsam.Marginals(graph, result)
        return result, marginals.marginalCovariance, None
    except RuntimeError as exc:
        log.warning("batch marginals unavailable: %s", exc)
        return result, None, None
