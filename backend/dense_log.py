"""Known-id fast path of the smoothers over a planar landmark log, one step per pose.

:func:`lampsam.backend.graph_log.run_graph_log` on a log whose landmark ids are known
(GTSAM/iSAM/g2o text files, MRCLAM turned into a graph log) makes the same graph
and the same estimate as :class:`lampsam.backend.graph.Isam2Slam` /
:class:`~lampsam.backend.graph.BatchSlam` stepped by
:func:`lampsam.backend.slam.drive`, without their per-step machinery (frames,
observation records, association, gating state, per-step covariance records):

1. one pass over the log's arrays (:func:`plan_log`) gives the keyframes (every pose
   with a usable sighting, ``isam2.every_frame``), each keyframe's odometry factor
   (the samples since the previous keyframe composed by the motion model, with
   ``isam2.odometry_floor_var``), the odometry of every other step from its
   keyframe (for the final bridge, :func:`~lampsam.backend.pose_cov.odometry_bridge`)
   and each keyframe's sightings, split into new and already-seen landmarks;
2. one ``ISAM2.update`` per keyframe with that keyframe's factors and new values
   (the odometry ``BetweenFactorPose2``, then the new landmarks'
   ``BearingRangeFactor2D`` in sighting order, then the re-sighted ones': the order
   the general path adds them in), new variables initialised from iSAM2's estimate
   of the previous keyframe composed with the odometry (DESIGN sec. 6); range-bearing
   noise models shared per distinct covariance;
3. the final estimate (iSAM2's, or batch LM over the whole graph from it), each
   step's pose from its keyframe's (:func:`~lampsam.backend.pose_cov.odometry_bridge`
   between keyframes) and each landmark's marginal.

A log with loop closures (:attr:`~lampsam.datasets.graph_text.GraphLog.closures`) makes
every pose a keyframe and adds each closure to the factors of its later pose's keyframe,
after that keyframe's sightings (:mod:`lampsam.backend.pose_graph`); batch then starts
from ``[graph] batch_init``.

No pose covariance is computed (``run_graph_log(pose_covariances=False)``). Anything
the fast path does not cover returns None from :func:`run_known_ids` and the caller
runs the general path, which then gives the usual result and messages: a sample
that is not finite, time going backwards, an odometry covariance that is not
positive definite, a landmark first seen twice from one pose, a Huber loss, an
iSAM2 update that throws (the general path rebuilds without the offending factors).
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, field

import gtsam
import numpy as np
from gtsam.symbol_shorthand import L, X

from lampsam.arrays import BoolArray, FloatArray, IntArray
from lampsam.backend.config import SlamConfig
from lampsam.backend.graph import STEP_FLOOR, batch_lm, final_source
from lampsam.backend.handlers import MarginalSource
from lampsam.backend.interface import GraphSnapshot, LandmarkEstimate, SlamResult, log_pruned
from lampsam.backend.models import init_point2, landmark_estimate
from lampsam.backend.odometry import Pose2Motion
from lampsam.backend.pose_cov import compose_cov, odometry_bridge
from lampsam.backend.pose_graph import closure_factor, closures_by_step, lago_start
from lampsam.datasets.graph_text import GraphLog
from lampsam.errors import LampsamError
from lampsam.factors.geometry import wrap_angle
from lampsam.factors.gtsam_factors import odometry_factor, pose_array
from lampsam.interrupt import raise_if_stopped

log = logging.getLogger(__name__)


@dataclass
class LogPlan:
    """What one pass over a log's arrays gives the keyframe loop (``K`` keyframes after
    the start pose ``X(0)``, ``N`` steps).

    Attributes:
        step_kf: (N,) keyframe index of each step (its own, or the last before it).
        is_kf: (N,) the step makes a keyframe.
        kf_step: (K,) step of keyframe ``k = 1..K`` (entry ``k - 1``).
        pred_delta: (K, 3) odometry mean from keyframe ``k - 1`` to ``k`` composed step
            by step (the new pose's initial value is the estimate of ``k - 1``
            composed with it).
        factors: (K,) each keyframe's new factors: odometry, new landmarks', re-sighted ones'.
        new_lms: (K,) each keyframe's new landmarks ``(id, [bearing, range])``.
        odo: (K + 1) the odometry factor's ``(delta, cov)`` of each keyframe (entry 0:
            the start, unused).
        step_delta, step_cov: (N, 3), (N, 3, 3) odometry from the step's keyframe to the
            step (zero at a keyframe).
        sighted: (K,) landmark ids each keyframe sights (with repeats).
    """

    step_kf: IntArray
    is_kf: BoolArray
    kf_step: list[int] = field(default_factory=list)
    pred_delta: list[FloatArray] = field(default_factory=list)
    factors: list[gtsam.NonlinearFactorGraph] = field(default_factory=list)
    new_lms: list[list[tuple[int, FloatArray]]] = field(default_factory=list)
    odo: list[tuple[FloatArray, FloatArray]] = field(default_factory=list)
    step_delta: FloatArray = field(default_factory=lambda: np.zeros((0, 3)))
    step_cov: FloatArray = field(default_factory=lambda: np.zeros((0, 3, 3)))
    sighted: list[list[int]] = field(default_factory=list)


def single_sample_relative(samples: FloatArray, sample_floor: FloatArray, floor_var: float,
                           cov_scale: float = 1.0) -> tuple[FloatArray, FloatArray, BoolArray]:
    """Each sample's own increment and covariance, as :meth:`Pose2Motion.relative` gives
    them for one sample with a scalar floor, over all rows at once.

    Args:
        samples: (N, 12) rows ``[dx, dy, dtheta, cov row-major]``.
        sample_floor: (3, 3) the model's per-sample floor (diagonal).
        floor_var: variance added to each diagonal entry (>= 0).
        cov_scale: factor on each row's own covariance
            (:attr:`~lampsam.datasets.odometry.Pose2OdometryModel.cov_scale`).

    Returns:
        ``(delta (N, 3), cov (N, 3, 3), ok (N,))``: the increment (theta wrapped),
        ``sym(cov_scale cov + sample_floor) + floor_var I``; ``ok`` False where the row's
        covariance is not finite (the model's default applies: not computed here).
    """
    d = samples[:, :3]
    c = samples[:, 3:].reshape(-1, 3, 3)
    ok: BoolArray = np.asarray(np.isfinite(c).all(axis=(1, 2)))
    delta = np.column_stack([0.0 + d[:, 0], 0.0 + d[:, 1], wrap_angle(0.0 + d[:, 2])])
    if cov_scale != 1.0:
        c = cov_scale * c
    cov = c + sample_floor
    sym = 0.5 * (cov + cov.transpose(0, 2, 1))
    idx = np.arange(3)
    sym[:, idx, idx] += floor_var
    return delta, sym, ok


def sighting_arrays(g: GraphLog, r_default: FloatArray
                    ) -> tuple[IntArray, list[int], list[float], list[float],
                               list[gtsam.noiseModel.Base]] | None:
    """Every usable sighting of a log, in order, with its shared noise model.

    A sighting with a range or bearing that is not finite, or a range <= 0, is left
    out (as :func:`lampsam.backend.models.observations_from_frame` does). Each
    covariance is checked as :func:`lampsam.factors.gtsam_factors.check_cov` checks a
    (2, 2) one (finite, Sylvester on the symmetric part), all at once, and one
    ``Gaussian.Covariance`` is made per distinct covariance (bytewise).

    Args:
        g: the log.
        r_default: (2, 2) ``[bearing, range]`` covariance of sightings without one.

    Returns:
        ``(bounds (N + 1,), landmark ids, bearings wrapped to (-pi, pi], ranges,
        noise models)``: step ``i``'s sightings are ``bounds[i]:bounds[i + 1]``; or
        None when a covariance is refused (the general path names it).
    """
    n = len(g.sightings)
    lids: list[int] = []
    bearings: list[float] = []
    ranges: list[float] = []
    covs: list[FloatArray] = []
    counts = np.zeros(n + 1, int)
    for i, ss in enumerate(g.sightings):
        for s in ss:
            if math.isfinite(s.range) and math.isfinite(s.bearing) and s.range > 0:
                lids.append(s.landmark)
                bearings.append(s.bearing)
                ranges.append(s.range)
                covs.append(r_default if s.cov is None else s.cov)
                counts[i + 1] += 1
    bounds = np.cumsum(counts)
    if not lids:
        return bounds, lids, bearings, ranges, []
    try:
        c = np.array(covs, dtype=float)
    except ValueError:
        return None
    if c.shape != (len(lids), 2, 2) or not np.isfinite(c).all():
        return None
    off = 0.5 * (c[:, 0, 1] + c[:, 1, 0])
    if not ((c[:, 0, 0] > 0.0) & (c[:, 0, 0] * c[:, 1, 1] - off * off > 0.0)).all():
        return None
    raw = np.ascontiguousarray(c).reshape(len(lids), 4)
    _, first, inverse = np.unique(raw.view(np.dtype((np.void, 32))).ravel(), return_index=True,
                                  return_inverse=True)
    models = [gtsam.noiseModel.Gaussian.Covariance(c[j]) for j in first]
    wrapped = wrap_angle(np.asarray(bearings, float)).tolist()
    return bounds, lids, wrapped, ranges, [models[j] for j in inverse.ravel().tolist()]


def plan_log(g: GraphLog, motion: Pose2Motion, config: SlamConfig) -> LogPlan | None:
    """The keyframes, factors and odometry records of a known-id log (module docstring).

    Args:
        g: the log (one odometry sample and its sightings per pose).
        motion: the Pose2 odometry model (its floor and default covariance).
        config: ``isam2.odometry_floor_var``, the default range-bearing noise.

    Returns:
        The plan, or None where the general path must run (module docstring).
    """
    od = g.odometry
    t = np.asarray(od.t, float)
    samples = od.samples()
    n = len(t)
    if n == 0 or len(g.sightings) != n or not np.isfinite(samples[:, :3]).all() or (
            n > 1 and not (np.diff(t) >= 0.0).all()):
        return None
    floor = float(config.isam2.odometry_floor_var)
    if not (math.isfinite(floor) and floor >= 0.0):
        return None
    r_default = np.diag([config.noise.sigma_bearing ** 2, config.noise.sigma_range ** 2])
    sights = sighting_arrays(g, r_default)
    if sights is None:
        return None
    bounds, lids, bearings, ranges, noises = sights
    scale = motion.model.cov_scale
    d_all, c_floor, ok = single_sample_relative(samples, motion.sample_floor, floor, scale)
    _, c_step, _ = single_sample_relative(samples, motion.sample_floor, STEP_FLOOR, scale)
    floor_to_step = (STEP_FLOOR - floor) * np.eye(3)
    plan = LogPlan(step_kf=np.zeros(n, int), is_kf=np.zeros(n, bool),
                   odo=[(np.zeros(3), np.zeros((3, 3)))],
                   step_delta=np.zeros((n, 3)), step_cov=np.zeros((n, 3, 3)))
    seen: set[int] = set()
    every_pose = bool(g.closures)  # a pose graph: every pose a variable, as GTSAM's graph
    closing = closures_by_step(g)
    k = 0
    since = 0
    first: tuple[FloatArray, FloatArray] = (np.zeros(3), np.zeros((3, 3)))
    delta = np.zeros(3)
    delta_cov: FloatArray | None = None
    for i in range(n):
        if since == 0:
            first = (d_all[i], c_floor[i]) if ok[i] else motion.relative(samples[i : i + 1], floor)
            delta = pose_array(gtsam.Pose2(*first[0]))
            delta_cov = None  # composed only for a step that is not a keyframe
        else:
            d, c = (d_all[i], c_step[i]) if ok[i] else motion.relative(samples[i : i + 1], STEP_FLOOR)
            assert delta_cov is not None
            delta_cov = compose_cov(d, delta_cov, c)
            delta = pose_array(gtsam.Pose2(*delta).compose(gtsam.Pose2(*d)))
        since += 1
        a, b = int(bounds[i]), int(bounds[i + 1])
        if a == b and not every_pose:  # no sighting: a step between keyframes
            if delta_cov is None:
                delta_cov = first[1] + floor_to_step
            plan.step_kf[i] = k
            plan.step_delta[i] = delta
            plan.step_cov[i] = delta_cov
            continue
        f_delta, f_cov = first if since == 1 else motion.relative(samples[i - since + 1 : i + 1], floor)
        k += 1
        try:
            odo = odometry_factor(X(k - 1), X(k), f_delta, f_cov)
        except LampsamError:
            return None  # a covariance the factor refuses: the general path says which
        graph = gtsam.NonlinearFactorGraph()
        graph.add(odo)
        new: list[tuple[int, FloatArray]] = []
        new_ids: set[int] = set()
        again: list[gtsam.BearingRangeFactor2D] = []
        xk = X(k)
        for j in range(a, b):
            lid = lids[j]
            f = gtsam.BearingRangeFactor2D(xk, L(lid), gtsam.Rot2(bearings[j]), ranges[j], noises[j])
            if lid not in seen:
                seen.add(lid)
                new_ids.add(lid)
                new.append((lid, np.array([bearings[j], ranges[j]])))
                graph.add(f)
            elif lid in new_ids:
                return None  # first seen twice from one pose: the general path's case
            else:
                again.append(f)
        for f_again in again:
            graph.add(f_again)
        plan.step_kf[i] = k
        for e in closing.get(i, ()):  # loop closures whose later pose is this one
            try:
                graph.add(closure_factor(e, X(int(plan.step_kf[e.i])), X(int(plan.step_kf[e.j])),
                                         config.graph))
            except LampsamError:
                return None
        plan.factors.append(graph)
        plan.new_lms.append(new)
        plan.sighted.append(lids[a:b])
        plan.kf_step.append(i)
        plan.pred_delta.append(delta)
        plan.odo.append((np.asarray(f_delta, float), np.asarray(f_cov, float)))
        plan.is_kf[i] = True
        since = 0
    return plan


def run_known_ids(g: GraphLog, backend: str, config: SlamConfig, motion: Pose2Motion,
                  start: FloatArray) -> SlamResult | None:
    """Run iSAM2 or batch over a known-id log by the fast path (module docstring).

    Args:
        g: the log.
        backend: ``"isam2"`` or ``"batch"`` (``batch.init`` ``"isam2"`` runs the same
            online pass first, ``"odometry"`` starts LM from dead reckoning).
        config: the SLAM config (``isam2``: parameters, floors, prior sigmas;
            ``batch``; ``association.min_observations`` / ``prune_once_seen``).
        motion: the Pose2 odometry model.
        start: (3,) start pose ``world_T_body``.

    Returns:
        The result as :meth:`lampsam.backend.graph.GraphSlam.finish` gives it without
        pose covariances (NaN); ``step_times_s`` is the first pass's time shared out
        equally over the steps, plus each keyframe's update at its step. None: the
        general path must run (module docstring).
    """
    if backend not in ("isam2", "batch") or (backend == "batch" and config.batch.huber_k is not None):
        return None
    start_from = config.graph.batch_init if g.closures else "backend"
    online = backend == "isam2" or (config.batch.init == "isam2" and start_from == "backend")
    t_plan = time.perf_counter()
    plan = plan_log(g, motion, config)
    if plan is None:
        return None
    t_plan = time.perf_counter() - t_plan
    cfg = config.isam2
    n = len(plan.is_kf)
    start = np.asarray(start, float)
    prior = gtsam.PriorFactorPose2(X(0), gtsam.Pose2(*start), gtsam.noiseModel.Diagonal.Sigmas(
        np.array([cfg.sigma_start_xy, cfg.sigma_start_xy, cfg.sigma_start_theta])))
    graph = gtsam.NonlinearFactorGraph()  # everything, in the general path's order
    graph.add(prior)
    initial = gtsam.Values()
    initial.insert(X(0), gtsam.Pose2(*start))
    params = cfg.to_gtsam()
    if g.closures:  # Cholesky throws "indeterminate" on pose graphs GTSAM's QR solves
        params.setFactorization(config.graph.isam2_factorization)
    isam = gtsam.ISAM2(params) if online else None
    update_times: list[float] = []
    estimate_times: list[float] = []
    step_times = np.full(n, t_plan / max(n, 1))  # the first pass, shared out over the steps
    kf_pose = start.copy()
    predicted = [start.copy()]  # each keyframe's initial value (kept if the final estimate lacks it)

    def update(new_graph: gtsam.NonlinearFactorGraph, new_values: gtsam.Values, k: int) -> bool:
        """One iSAM2 update; False if it throws (the general path recovers from that)."""
        nonlocal kf_pose
        assert isam is not None
        t0 = time.perf_counter()
        try:
            isam.update(new_graph, new_values)
            for _ in range(cfg.extra_updates):
                isam.update()
        except RuntimeError as exc:  # with loop closures, say it: the general path has none
            (log.warning if g.closures else log.debug)(
                "iSAM2 update failed at keyframe %d (%s): the general path runs", k,
                " ".join(str(exc).split())[:200])
            return False
        t1 = time.perf_counter()
        kf_pose = pose_array(isam.calculateEstimatePose2(X(k)))
        update_times.append(t1 - t0)
        estimate_times.append(time.perf_counter() - t1)
        return True

    if isam is not None:
        first = gtsam.NonlinearFactorGraph()
        first.add(prior)
        if not update(first, initial, 0):
            return None
    status = "ok"
    done = 0
    try:
        for j, factors in enumerate(plan.factors):
            raise_if_stopped()
            ts = time.perf_counter()
            k = j + 1
            pose = pose_array(gtsam.Pose2(*kf_pose).compose(gtsam.Pose2(*plan.pred_delta[j])))
            values = gtsam.Values()
            values.insert(X(k), gtsam.Pose2(*pose))
            predicted.append(pose)
            for lid, z in plan.new_lms[j]:
                values.insert(L(lid), init_point2(pose, z)[0])
            initial.insert(values)
            graph.push_back(factors)
            if isam is None:
                kf_pose = pose
            elif not update(factors, values, k):
                return None
            step_times[plan.kf_step[j]] += time.perf_counter() - ts
            done = k
    except KeyboardInterrupt as exc:  # SIGINT / SIGTERM between keyframes (lampsam.interrupt)
        status = "interrupted"
        log.warning("interrupted (%s): writing the %d keyframes finished so far",
                    exc or "KeyboardInterrupt", done)
    if backend == "batch" and start_from == "lago" and done == len(plan.factors):
        initial = lago_start(graph, initial, plan.new_lms) or initial
    return _finish(plan, g, config, backend, graph, initial, isam, predicted, done, status,
                   step_times, update_times, estimate_times)


def _finish(plan: LogPlan, g: GraphLog, config: SlamConfig, backend: str,
            graph: gtsam.NonlinearFactorGraph, initial: gtsam.Values, isam: gtsam.ISAM2 | None,
            predicted: list[FloatArray], done: int, status: str, step_times: FloatArray,
            update_times: list[float], estimate_times: list[float]) -> SlamResult:
    """The result of the first ``done`` keyframes (and the steps before the next one),
    as :meth:`lampsam.backend.graph.GraphSlam.finish` makes it."""
    n = len(plan.is_kf) if done == len(plan.factors) else plan.kf_step[done]
    n_obs: dict[int, int] = {}
    for lids in plan.sighted[:done]:
        for lid in lids:
            n_obs[lid] = n_obs.get(lid, 0) + 1
    assoc = config.association
    drop = {lid for lid, c in n_obs.items() if c < assoc.min_observations}
    pruned = {"seen_too_few": len(drop)} if drop else {}
    log_pruned(len(drop), pruned, assoc.min_observations, not assoc.prune_once_seen)
    t0 = time.perf_counter()
    marginal: MarginalSource | None
    try:
        if backend == "isam2":
            assert isam is not None
            values, marginal, fallback = isam.calculateEstimate(), isam.marginalCovariance, None
        else:
            start = isam.calculateEstimate() if isam is not None else initial
            values, marginal, fallback = batch_lm(graph, start, config.batch, isam)
    except (RuntimeError, LampsamError) as exc:  # a broken graph: keep the online poses
        log.error("final optimisation failed (%s): keeping the online estimates", exc)
        values, marginal, fallback = initial, None, None
        status = status if status.startswith("failed") else f"failed: {exc}"
    source, status = final_source(backend, status, fallback)
    final_time = time.perf_counter() - t0
    kf_pose = [pose_array(values.atPose2(X(k))) if values.exists(X(k)) else predicted[k]
               for k in range(done + 1)]
    poses = np.zeros((n, 3))
    for i in range(n):
        k = int(plan.step_kf[i])
        delta = plan.step_delta[i]
        if k < done and not plan.is_kf[i]:  # between two keyframes: condition on both
            delta, _ = odometry_bridge(delta, plan.step_cov[i], *plan.odo[k + 1],
                                       kf_pose[k], kf_pose[k + 1])
        poses[i] = pose_array(gtsam.Pose2(*kf_pose[k]).compose(gtsam.Pose2(*delta)))
    lms: list[LandmarkEstimate] = []
    provisional: list[LandmarkEstimate] = []
    for lid, count in n_obs.items():
        key = L(lid)
        if (lid in drop and assoc.prune_once_seen) or not values.exists(key):
            continue
        cov = np.full((2, 2), np.nan)
        if marginal is not None:
            try:
                cov = np.asarray(marginal(key))
            except (RuntimeError, IndexError):
                pass
        est = landmark_estimate(lid, "point2", np.asarray(values.atPoint2(key), float), cov, count)
        (provisional if lid in drop else lms).append(est)
    return SlamResult(
        backend=source, times=np.asarray(g.odometry.t[:n], float), poses=poses,
        pose_covs=np.full((n, 3, 3), np.nan), landmarks=lms, provisional=provisional,
        step_times_s=step_times[:n], keyframes=plan.is_kf[:n].copy(), status=status,
        final_time_s=final_time, n_pruned=len(drop), pruned=pruned,
        graph=GraphSnapshot(graph, values, None),
        extra={"n_recoveries": 0.0,
               "update_median_ms": float(np.median(update_times) * 1e3) if update_times else math.nan,
               "update_p95_ms": float(np.percentile(update_times, 95) * 1e3) if update_times else math.nan,
               "estimate_median_ms": float(np.median(estimate_times) * 1e3) if estimate_times
               else math.nan})
