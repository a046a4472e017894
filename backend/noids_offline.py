"""Offline SLAM without ids on a graph log: online EKF pass, batch re-association, scale choice.

Without ids the online pass decides each sighting once. Where a log's stated odometry
noise is too small *for a filter linearised at drifting estimates* (Victoria Park: right
at the optimum, odometry chi-square per dof 0.19, yet the EKF's revisits come back far
beyond the gate), every revisit is mapped again and the run diverges; inflating the
odometry variance of the online pass (``[pose2_odometry] cov_scale``) by 16 holds there
but harms logs whose noise is stated right (docs/graph-backend.md). Offline all data is
at hand, so the factor is chosen from the data:

1. for each candidate variance factor ``q`` of ``[reassociation] scales`` the no-ids EKF
   runs the log with the odometry covariance times ``q`` and records each range-bearing
   sighting with its landmark (:func:`online_pass`);
2. the batch graph of that association, always with the log's *stated* odometry
   covariance, is optimised and re-associated
   (:func:`lampsam.backend.reassociate.refine`), then single landmarks are merged and
   split where that shortens the description length below
   (:func:`lampsam.backend.landmark_moves.refine_by_cost`, ``[reassociation] cost_moves``);
   the chosen candidate (step 3) then gets a last pass of single-sighting moves and
   merges with the poses free (:func:`final_pass`, ``[reassociation] final_pass``);
3. the candidates' answers are graphs of the same factors under the same noise and
   differ only in the association, so they are compared by one cost, a description
   length of the data (:func:`association_cost`):

   ``C = chi2 + c_new * (n_landmarks + n_dropped)``,

   ``chi2 = 2 E`` the graph's error at its optimum (odometry and sightings),
   ``c_new = chi2_2^-1(new_prob)`` the squared distance beyond which the gate makes a new
   landmark (eq. 20's threshold, :meth:`AssociationConfig.new_threshold`): a landmark is
   worth making only if it saves more chi-square than a sighting that matches nothing
   costs; ``n_dropped`` the sightings the online pass left out (between the gate and
   the new-landmark threshold), each charged as one that matches nothing. A diverged
   pass maps trees several times (each copy costs ``c_new``) and bends the trajectory
   to wrong matches (chi-square); the least ``C`` wins.

Variance-component estimation (iterating the groups' ``chi2 / dof`` to 1) cannot pick
the online factor: at the right association the stated odometry noise is too *large*
(VP: 0.19 per dof), and a diverged association's ratio says nothing about the filter's
linearisation. The per-group figures are reported (:class:`OfflineRun`) for that
diagnosis.

Frames: world, m and rad; sightings ``[bearing, range]`` in the body frame; ``q`` is a
variance factor.
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass

import gtsam
import numpy as np
from gtsam.symbol_shorthand import L, X

from lampsam.arrays import FloatArray, IntArray
from lampsam.backend.config import SlamConfig
from lampsam.backend.cpu_budget import BudgetSpent, CpuBudget, interrupt_past
from lampsam.backend.final_moves import readmit, refine_final
from lampsam.backend.graph_log import graph_log_steps
from lampsam.backend.interface import GraphSnapshot, LandmarkEstimate, LandmarkKind, SlamResult
from lampsam.backend.landmark_moves import Move, refine_by_cost, solve_association
from lampsam.backend.reassociate import (
    Pass,
    Sightings,
    first_sight_positions,
    read_estimate,
    refine,
    sightings_from,
)
from lampsam.backend.slam import drive, make_backend
from lampsam.datasets.graph_text import GraphLog
from lampsam.factors.geometry import wrap_angle

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class OfflineRun:
    """One candidate's answer.

    Attributes:
        scale: the online pass's odometry variance factor ``q``.
        poses: (N, 3) optimised poses, one per log pose.
        landmarks: landmark id -> (2,) optimised position (every landmark with a sighting).
        sightings: the final association.
        passes: the re-association passes (:class:`lampsam.backend.reassociate.Pass`).
        chi2_odometry, chi2_sightings: ``2 x error`` of each factor group at the optimum.
        dof_odometry, dof_sightings: residual dimensions of each group (3 per odometry
            factor, 2 per sighting).
        n_dropped: the log's range-bearing sightings the online pass did not record.
        cost: :func:`association_cost`.
        online_cpu_s, batch_cpu_s: process CPU of the EKF pass and of the batch passes.
        graph, values: the final association's factor graph and its optimum.
        moves: the description-length merges and splits after the passes
            (:mod:`lampsam.backend.landmark_moves`; ``[reassociation] cost_moves``).
        stopped: the stage a CPU budget stopped (:mod:`lampsam.backend.cpu_budget`;
            the answer is the last state it accepted); "" when none did.
    """

    scale: float
    poses: FloatArray
    landmarks: dict[int, FloatArray]
    sightings: Sightings
    passes: list[Pass]
    chi2_odometry: float
    chi2_sightings: float
    dof_odometry: int
    dof_sightings: int
    n_dropped: int
    cost: float
    online_cpu_s: float
    batch_cpu_s: float
    graph: gtsam.NonlinearFactorGraph
    values: gtsam.Values
    moves: list[Move] = dataclasses.field(default_factory=list)
    stopped: str = ""

    def mapped(self, min_observations: int = 2) -> dict[int, FloatArray]:
        """Landmarks with at least ``min_observations`` sightings."""
        ids, n = np.unique(self.sightings.lid, return_counts=True)
        return {int(i): self.landmarks[int(i)] for i, c in zip(ids, n, strict=True)
                if c >= min_observations}


class _CandidatePruneFilter(logging.Filter):
    """Drops the pruned-landmark warning (:func:`candidate_pruning_quiet`)."""

    def filter(self, record: logging.LogRecord) -> bool:
        return not str(record.msg).startswith("%d landmarks pruned from the map")


@contextlib.contextmanager
def candidate_pruning_quiet() -> Iterator[None]:
    """Inside: the backends' pruned-landmark warning is dropped. A candidate's online
    pass makes an intermediate map that the batch re-associates, and the warning read
    as if the final map had been pruned once per candidate."""
    backend_log = logging.getLogger("lampsam.backend")
    quiet = _CandidatePruneFilter()
    backend_log.addFilter(quiet)
    try:
        yield
    finally:
        backend_log.removeFilter(quiet)


def online_pass(g: GraphLog, config: SlamConfig, scale: float
                ) -> tuple[FloatArray, dict[int, FloatArray], Sightings]:
    """The no-ids EKF over the log with the odometry covariance times ``scale``.

    Returns:
        ``(poses (N, 3), landmark id -> (2,) position, sightings)``: every range-bearing
        sighting the EKF matched or used to make a landmark, with its landmark (the
        uncertainty pruning is off, ``association.prune_sigma`` = 1e9, so that every
        candidate keeps the same sightings and the batch decides; landmarks seen once
        stay).
    """
    cfg = dataclasses.replace(
        config,
        association=dataclasses.replace(config.association, use_known_ids=False,
                                        prune_sigma=1e9, prune_once_seen=False),
        pose2_odometry=dataclasses.replace(config.pose2_odometry,
                                           cov_scale=config.pose2_odometry.cov_scale * scale))
    be = make_backend("ekf", cfg.pose2_odometry, cfg, g.start_pose())
    with candidate_pruning_quiet():
        res = drive(be, graph_log_steps(g, False))
    s = sightings_from(list(be.planar_sightings))  # type: ignore[attr-defined]
    lms = first_sight_positions(res.poses, s)
    for lm in list(res.landmarks) + list(res.provisional):
        if int(lm.id) in lms:
            lms[int(lm.id)] = np.asarray(lm.position[:2], float)
    return res.poses, lms, s


def batch_graph_inputs(g: GraphLog, config: SlamConfig
                       ) -> tuple[gtsam.NonlinearFactor, list[tuple[FloatArray, FloatArray]]]:
    """The start prior and the ``(delta, cov)`` odometry factors, with the log's stated
    covariance (``cov_scale`` of the config applied, as the user asked) plus the model's
    floor; entry 0 unused."""
    model = config.pose2_odometry
    odo = [(np.zeros(3), np.eye(3))] + [
        (g.odometry.delta[k], model.sample_cov(g.odometry.delta[k], g.odometry.cov[k]))
        for k in range(1, len(g.pose_ids))]
    c = config.isam2
    prior = gtsam.PriorFactorPose2(X(0), gtsam.Pose2(*g.start_pose()),
                                   gtsam.noiseModel.Diagonal.Sigmas(np.array(
                                       [c.sigma_start_xy, c.sigma_start_xy, c.sigma_start_theta])))
    return prior, odo


def group_chi2(graph: gtsam.NonlinearFactorGraph, values: gtsam.Values
               ) -> tuple[float, float, int, int]:
    """``(chi2 odometry, chi2 sightings, dof odometry, dof sightings)`` at ``values``:
    ``2 x error`` of the ``BetweenFactorPose2`` and of the ``BearingRangeFactor2D``
    factors, and their residual dimensions (the prior is left out)."""
    co = cs = 0.0
    no = ns = 0
    for i in range(graph.size()):
        f = graph.at(i)
        if isinstance(f, gtsam.BetweenFactorPose2):
            co += 2.0 * f.error(values)
            no += 3
        elif isinstance(f, gtsam.BearingRangeFactor2D):
            cs += 2.0 * f.error(values)
            ns += 2
    return co, cs, no, ns


def association_cost(chi2: float, n_landmarks: int, n_dropped: int, new_cost: float) -> float:
    """Description length of an association (module doc):
    ``chi2 + new_cost * (n_landmarks + n_dropped)``."""
    return float(chi2) + float(new_cost) * (int(n_landmarks) + int(n_dropped))


#: called after each re-association pass: ``(pass number, Pass, poses, landmarks, sightings)``
PassReport = Callable[[int, Pass, FloatArray, dict[int, FloatArray], Sightings], None]


def run_candidate(g: GraphLog, config: SlamConfig, scale: float,
                  report: PassReport | None = None) -> OfflineRun:
    """One candidate: the online pass at ``scale``, then :func:`solve_candidate` (the batch
    re-association with the stated noise and the description-length moves)."""
    c0 = time.process_time()
    poses0, lms0, s = online_pass(g, config, scale)
    return solve_candidate(g, config, scale, poses0, lms0, s, time.process_time() - c0, report)


def solve_candidate(g: GraphLog, config: SlamConfig, scale: float, poses0: FloatArray,
                    lms0: dict[int, FloatArray], s: Sightings, online_cpu_s: float,
                    report: PassReport | None = None,
                    budget: CpuBudget | None = None) -> OfflineRun:
    """The batch re-association of one online association with the stated noise
    (``config.reassociation``; at least one pass) and the description-length moves.

    Args:
        g: the log; config: the batch's config (its odometry covariance is the one of
            :func:`batch_graph_inputs`).
        scale: the online pass's odometry variance factor (recorded in the answer).
        poses0: (N, 3) the online pass's pose at every log pose; lms0: landmark id ->
            (2,) its position (every landmark of ``s``); s: the online association
            (``s.k`` the log pose of each sighting; ``s.lid`` is updated in place).
        online_cpu_s: the online pass's CPU time, s (recorded).
        report: called with the online answer as pass 0, then after each accepted pass,
            then once after the moves (if any) as one more pass.
        budget: a CPU budget (:class:`lampsam.backend.cpu_budget.CpuBudget`; None:
            none) for the passes and the moves: once spent, each stops and keeps its
            last accepted state, and the answer's ``stopped`` names the stage.
    """
    c1 = time.process_time()
    prior, odo = batch_graph_inputs(g, config)
    rc = config.reassociation
    if rc.passes <= 0:
        rc = dataclasses.replace(rc, passes=1)
    if report is not None:
        report(0, Pass(len(lms0), 0, 0, 0, float("nan")), poses0, lms0, s)
    hook = None if report is None else (
        lambda i, p, ps, lm: report(i, p, ps, lm, s))  # s.lid is updated in place
    graph, values, passes = refine(prior, odo, s, poses0, lms0, config.association.gate(2),
                                   config.association.new_threshold(2), rc, hook, budget)
    moves: list[Move] = []
    if rc.cost_moves and not (budget is not None and budget.spent("description-length moves")):
        graph, values, moves = refine_by_cost(prior, odo, s, graph, values,
                                              config.association.new_threshold(2),
                                              rc.merge_radius, budget=budget)
        if moves and report is not None:
            merged = sum(m.kind == "merge" for m in moves)
            report(len(passes) + 1, Pass(len(np.unique(s.lid)), merged, 0, 0,
                                         float(graph.error(values))),
                   *read_estimate(values, len(g.pose_ids), np.unique(s.lid).tolist()), s)
    out = answer_of(g, config, scale, s, passes, online_cpu_s, time.process_time() - c1, graph,
                    values, moves)
    return dataclasses.replace(out, stopped=budget.stopped) if budget and budget.stopped else out


def answer_of(g: GraphLog, config: SlamConfig, scale: float, s: Sightings, passes: list[Pass],
            online_cpu_s: float, batch_cpu_s: float, graph: gtsam.NonlinearFactorGraph,
            values: gtsam.Values, moves: list[Move]) -> OfflineRun:
    """The :class:`OfflineRun` of an association and its optimum: its poses, landmarks,
    group chi-squares, dropped count and description length ``C``."""
    poses, lms = read_estimate(values, len(g.pose_ids), np.unique(s.lid).tolist())
    co, cs, no, ns = group_chi2(graph, values)
    dropped = sum(len(x) for x in g.sightings) - len(s.k)
    cost = association_cost(co + cs, len(lms), dropped, config.association.new_threshold(2))
    return OfflineRun(scale, poses, lms, s, passes, co, cs, no, ns, dropped, cost,
                      online_cpu_s, batch_cpu_s, graph, values, moves)


def dropped_sightings(g: GraphLog, s: Sightings) -> tuple[IntArray, FloatArray, FloatArray]:
    """``(keyframe (D,), z (D, 2), R (D, 2, 2))`` of the log's range-bearing sightings
    that are not among the recorded ``s`` (matched per pose by ``[bearing, range]``)."""
    ks: list[int] = []
    zs: list[list[float]] = []
    rs: list[FloatArray] = []
    by_k: dict[int, list[FloatArray]] = {}
    for k, z in zip(s.k.tolist(), s.z, strict=True):
        by_k.setdefault(k, []).append(z)
    for k, seen in enumerate(g.sightings):
        rec = by_k.get(k, [])
        for x in seen:
            z = np.array([x.bearing, x.range])
            if any(abs(wrap_angle(float(z[0] - q[0]))) < 1e-9
                   and abs(z[1] - q[1]) < 1e-9 for q in rec):
                continue
            ks.append(k)
            zs.append([float(np.arctan2(np.sin(z[0]), np.cos(z[0]))), float(z[1])])
            rs.append(np.asarray(x.cov, float)[:2, :2])
    return (np.array(ks, int), np.array(zs, float).reshape(-1, 2),
            np.array(rs, float).reshape(-1, 2, 2))


def final_pass(g: GraphLog, config: SlamConfig, run: OfflineRun,
               report: PassReport | None = None,
               budget: CpuBudget | None = None) -> OfflineRun:
    """:func:`lampsam.backend.final_moves.refine_final` on one candidate's answer (the
    chosen one): with ``[reassociation] readmit_dropped`` the dropped sightings a
    landmark explains first (:func:`lampsam.backend.final_moves.readmit`), then single
    sightings and merges with the poses free; each kept only if ``C`` falls, so the
    chosen candidate stays the least. ``report`` is called once
    after it (as one more pass) if anything moved. A ``budget``
    (:class:`lampsam.backend.cpu_budget.CpuBudget`) spent before it or while it runs
    (:func:`lampsam.backend.cpu_budget.interrupt_past`) gives ``run`` as it is, with
    ``stopped`` set."""
    if budget is not None and budget.spent("final pass"):
        return dataclasses.replace(run, stopped=run.stopped or budget.stopped)
    try:
        with interrupt_past(budget, "final pass"):
            return _final_pass(g, config, run, report)
    except BudgetSpent:  # stopped inside: the answer before the final pass
        return dataclasses.replace(run, stopped=run.stopped or "final pass")


def _final_pass(g: GraphLog, config: SlamConfig, run: OfflineRun,
                report: PassReport | None) -> OfflineRun:
    """:func:`final_pass`'s work (``run`` is not modified)."""
    c0 = time.process_time()
    prior, odo = batch_graph_inputs(g, config)
    s = Sightings(run.sightings.k, run.sightings.z, run.sightings.r, run.sightings.lid.copy())
    graph, values = run.graph, run.values
    c_new = config.association.new_threshold(2)
    n_back = 0
    if config.reassociation.readmit_dropped:
        dk, dz, dr = dropped_sightings(g, s)
        back = readmit(run.poses, run.landmarks, s, dk, dz, dr, c_new)
        n_back = int(np.count_nonzero(back >= 0))
    if n_back:
        t = back >= 0
        s2 = Sightings(np.r_[s.k, dk[t]], np.r_[s.z, dz[t]], np.r_[s.r, dr[t]],
                       np.r_[s.lid, back[t]])
        g2, v2, _ = solve_association(prior, odo, s2, s2.lid, run.poses, run.landmarks, {},
                                      c_new)
        c2 = association_cost(2.0 * float(g2.error(v2)) - 2.0 * float(prior.error(v2)),
                              len(run.landmarks), run.n_dropped - n_back, c_new)
        log.info("no-ids final pass: %d dropped sightings taken back, C %.1f -> %.1f",
                 n_back, run.cost, c2)
        if c2 < run.cost:
            s, graph, values = s2, g2, v2
    graph, values, moves = refine_final(
        prior, odo, s, graph, values, c_new,
        config.reassociation.merge_radius, config.association.gate(2),
        config.reassociation.final_rounds)
    if not moves and len(s.k) == len(run.sightings.k):
        return run
    moves = [Move("readmit", (-1, -1), 0.0)] * (len(s.k) - len(run.sightings.k)) + moves
    out = answer_of(g, config, run.scale, s, run.passes, run.online_cpu_s,
                  run.batch_cpu_s + time.process_time() - c0, graph, values,
                  run.moves + moves)
    out = dataclasses.replace(out, stopped=run.stopped)
    if report is not None:
        report(len(run.passes) + 2, Pass(len(out.landmarks),
                                         sum(m.kind == "merge" for m in moves), 0,
                                         sum(m.kind == "sighting" for m in moves),
                                         float(graph.error(values))),
               out.poses, out.landmarks, s)
    return out


def select_scale(g: GraphLog, config: SlamConfig, scales: tuple[float, ...] | None = None,
                 report: Callable[[float], PassReport] | None = None
                 ) -> tuple[OfflineRun, list[OfflineRun]]:
    """Run every candidate scale (``scales``, else ``config.reassociation.scales``) and
    return ``(the least-cost run, all runs in the given order)``; with
    ``[reassociation] final_pass`` the least-cost run gets :func:`final_pass` (it can
    only lower its cost, so it stays the least; in ``runs`` it is replaced by its final
    answer). ``report(q)`` gives the pass report of candidate ``q``."""
    cand = tuple(scales if scales is not None else config.reassociation.scales) or (1.0,)
    runs = []
    for q in cand:
        r = run_candidate(g, config, q, None if report is None else report(q))
        log.info("no-ids scale %.3g: %d landmarks, chi2 odometry %.1f / %d, sightings %.1f / %d, "
                 "cost %.1f, %d passes", q, len(r.landmarks), r.chi2_odometry, r.dof_odometry,
                 r.chi2_sightings, r.dof_sightings, r.cost, len(r.passes))
        runs.append(r)
    best = min(range(len(runs)), key=lambda i: runs[i].cost)
    if config.reassociation.final_pass:
        runs[best] = final_pass(g, config, runs[best],
                                None if report is None else report(runs[best].scale))
        log.info("no-ids final pass on scale %.3g: cost %.1f", runs[best].scale,
                 runs[best].cost)
    return runs[best], runs


def run_offline(g: GraphLog, config: SlamConfig) -> SlamResult:
    """``lampsam slam LOG --no-ids --backend {ekf,batch}`` with ``[reassociation] passes``
    > 0: :func:`select_scale`, then the chosen run as a result (:func:`result_of`, whose
    ``extra`` also holds every candidate's cost, ``noids_cost_q<q>``)."""
    t0, c0 = time.perf_counter(), time.process_time()
    best, runs = select_scale(g, config)
    return result_of(g, config, best, {f"noids_cost_q{r.scale:g}": r.cost for r in runs}, t0, c0)


def result_of(g: GraphLog, config: SlamConfig, best: OfflineRun, extra: dict[str, float],
              t0: float, c0: float) -> SlamResult:
    """A batch answer as a :class:`SlamResult`.

    The landmarks' covariances are their marginals on the final graph; landmarks with
    fewer than ``association.min_observations`` sightings are ``provisional``. ``extra``
    holds the answer's factor (``noids_scale``), its passes, the group chi-squares per
    dof, the description length (``noids_cost``), the merges and splits, the dropped
    sightings, whether a CPU budget stopped it (``noids_stopped_by_budget`` 1, else 0)
    and the CPU time since ``c0`` (wall since ``t0``), then ``extra``; ``graph``
    is the answer's factor graph at its optimum (``lampsam slam --g2o``).
    """
    try:
        marg: gtsam.Marginals | None = gtsam.Marginals(best.graph, best.values)
    except RuntimeError as exc:
        log.warning("no-ids batch: no marginals (%s): landmark covariances NaN", exc)
        marg = None
    ids, counts = np.unique(best.sightings.lid, return_counts=True)
    lm_all = [LandmarkEstimate(
        int(i), LandmarkKind.POINT2, np.r_[best.landmarks[int(i)], np.nan], None,
        marg.marginalCovariance(L(int(i))) if marg is not None else np.full((2, 2), np.nan),
        int(c)) for i, c in zip(ids, counts, strict=True)]
    n_min = config.association.min_observations
    once = [x for x in lm_all if x.n_obs < n_min]
    n = len(g.pose_ids)
    seen = np.zeros(n, bool)
    seen[best.sightings.k] = True
    wall = time.perf_counter() - t0
    extra = {"noids_scale": best.scale, "reassociation_passes": float(len(best.passes)),
             "chi2_per_dof_odometry": best.chi2_odometry / max(best.dof_odometry, 1),
             "chi2_per_dof_sightings": best.chi2_sightings / max(best.dof_sightings, 1),
             "sightings_dropped": float(best.n_dropped), "noids_cost": best.cost,
             "noids_merges": float(sum(m.kind == "merge" for m in best.moves)),
             "noids_splits": float(sum(m.kind == "split" for m in best.moves)),
             "noids_sighting_moves": float(sum(m.kind == "sighting" for m in best.moves)),
             "noids_stopped_by_budget": float(bool(best.stopped)),
             **extra, "total_time_s": wall, "total_cpu_s": time.process_time() - c0}
    return SlamResult(
        backend="batch", times=g.odometry.t.copy(), poses=best.poses,
        pose_covs=np.full((n, 3, 3), np.nan),
        landmarks=[x for x in lm_all if x.n_obs >= n_min], step_times_s=np.full(n, wall / n),
        keyframes=seen, extra=extra,
        provisional=[] if config.association.prune_once_seen else once,
        n_pruned=len(once) if config.association.prune_once_seen else 0,
        pruned={"seen_too_few": len(once)} if config.association.prune_once_seen else {},
        graph=GraphSnapshot(best.graph, best.values, None))
