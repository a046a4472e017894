"""The final solve of an online run without ids on a graph log: its association re-solved in
batch at the log's stated noise (issue 15).

An online run without ids (``lampsam slam LOG --no-ids --backend isam2``; the EKF, and the
batch backend's iSAM2 pass, when ``[reassociation] passes = 0``) decides each sighting
once. To hold on a log like Victoria Park it may need the odometry noise inflated
(``[pose2_odometry] cov_scale = 16``), and its estimate is then the optimum of a graph
with the wrong noise: on Victoria Park the known-id iSAM2 run with ``cov_scale = 16`` is
itself 2.5 m from GTSAM's LM on the file's graph. The association the run made is
still worth having. At the end of the run it is handed to the offline machinery of
:mod:`lampsam.backend.noids_offline` as one more source of an initial association (the
candidates' EKF passes are the other): :func:`~lampsam.backend.noids_offline.solve_candidate`
(re-association passes, :func:`lampsam.backend.reassociate.refine`, and the
description-length merges and splits) and
:func:`~lampsam.backend.noids_offline.final_pass`, with the odometry covariance as the
file states it (times ``[reassociation] online_final_cov_scale``, default 1).

What the online run recorded: every range-bearing sighting it matched or used to make a
landmark, with that landmark (``planar_sightings`` of the EKF and of the graph backends;
the graph backends record keyframes, mapped here to log poses). Sightings it held and
never used, or dropped between its gate and the new-landmark threshold, are not in the
association; the description length charges each as a sighting that matches nothing,
as offline.

The online picker (:func:`run_online_picker`, ``[reassociation] online_candidates``):
no single online setting holds on every log, so each candidate setting is run online and
final-solved, and the final solve with the least description length ``C`` is kept. Only
the online run sees a candidate's changes; every final solve uses the config as given,
so the ``C`` are of the same sightings under the same noise. A candidate whose online run
fails, is stopped (a stop request, or its CPU budget), records nothing, or whose final
solve fails, loses. With ``[reassociation] online_label_entropy`` (default) the picker
compares ``C`` plus the entropy of the sightings' labels, at each candidate's own
sighting noise scale (:mod:`lampsam.backend.label_entropy`): a map that splits a
landmark into copies closer than the noise pays for its guessed labels.

CPU budgets (:mod:`lampsam.backend.cpu_budget`): the first candidate's online run gets
``[reassociation] online_first_cpu_per_sighting`` s per sighting of the log (the later
ones ``online_candidate_cpu_factor`` times the least finished one's), each final solve
``final_solve_cpu_per_sighting``, both at least ``online_candidate_cpu_floor_s``. A final
solve past its budget stops at its next pass, round or stage and keeps the last
association it accepted (a valid answer; the warning, the candidate's row and
``noids_stopped_by_budget`` say so); the chosen one's left-out sightings are then not
placed.

Frames: world, m and rad; sightings ``[bearing, range]`` in the body frame.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from collections.abc import Callable, Mapping
from typing import Any

import numpy as np

from lampsam.arrays import FloatArray
from lampsam.backend.config import SlamConfig
from lampsam.backend.config_offline import ReassociationConfig, online_candidate_changes
from lampsam.backend.cpu_budget import BudgetSpent, CpuBudget, interrupt_past, sighting_budget
from lampsam.backend.graph_log import run_graph_log_backend
from lampsam.backend.held_placement import place_into
from lampsam.backend.interface import SlamBackend, SlamResult, log_pruned
from lampsam.backend.label_entropy import label_cost, profiled_cost, sighting_scale
from lampsam.backend.landmark_moves import Move
from lampsam.backend.noids_offline import (
    OfflineRun,
    answer_of,
    batch_graph_inputs,
    candidate_pruning_quiet,
    dropped_sightings,
    final_pass,
    result_of,
    solve_candidate,
)
from lampsam.backend.reassociate import (
    Sightings,
    first_sight_positions,
    sightings_from,
)
from lampsam.datasets.graph_text import GraphLog
from lampsam.errors import LampsamError
from lampsam.interrupt import stop_requested
from lampsam.observe import observing

log = logging.getLogger(__name__)


def online_association(backend: SlamBackend, result: SlamResult) -> Sightings:
    """The association an online run made, each sighting at its log pose.

    Args:
        backend: the backend after the run (EKF: ``planar_sightings`` by step; graph
            backends: by keyframe, keyframe 0 the start pose).
        result: its result (``keyframes``: (N,) True at the steps that made one).

    Returns:
        The sightings with ``k`` the log pose (step) index and ``lid`` the run's landmark
        (a copy the revisit check tied to an older landmark: the older one).
    """
    records = list(getattr(backend, "planar_sightings", []))
    s = sightings_from(records)
    if backend.name != "ekf" and len(s.k):
        step_of = np.r_[0, np.flatnonzero(result.keyframes)]
        s.k = step_of[s.k]
    # the revisit check's merges are stiff ties between two landmarks in the online graph
    # (``revisit_ties``: keyframe, copy, old); the batch graph has no tie factor, so the
    # copy's sightings go to the old landmark (chains followed)
    to = {int(c): int(o) for _, c, o in getattr(backend, "revisit_ties", [])}
    if to:
        def root(i: int) -> int:
            seen = {i}
            while i in to and to[i] not in seen:
                i = to[i]
                seen.add(i)
            return i

        s.lid = np.array([root(i) for i in s.lid.tolist()], int)
    return s


def online_landmarks(result: SlamResult, s: Sightings) -> dict[int, FloatArray]:
    """Landmark id -> (2,) position of every landmark of ``s``: the run's estimate where it
    reported one (map or provisional), else where its first sighting puts it from the
    run's poses."""
    lms = first_sight_positions(result.poses, s)
    for lm in list(result.landmarks) + list(result.provisional):
        if int(lm.id) in lms:
            lms[int(lm.id)] = np.asarray(lm.position[:2], float)
    return lms


def with_singletons(g: GraphLog, s: Sightings) -> Sightings:
    """``s`` plus every sighting of the log it lacks (held and never used, or dropped),
    each as a landmark of its own (ids above every id of ``s``): under the description
    length a singleton costs what a dropped sighting does (``c_new``), and the
    description-length merges then decide where it belongs."""
    dk, dz, dr = dropped_sightings(g, s)
    if not len(dk):
        return s
    start = int(s.lid.max()) + 1 if len(s.lid) else 0
    return Sightings(np.r_[s.k, dk], np.r_[s.z, dz], np.r_[s.r, dr],
                     np.r_[s.lid, start + np.arange(len(dk))])


def final_config(config: SlamConfig) -> SlamConfig:
    """The final solve's config: odometry covariance as stated times
    ``online_final_cov_scale``, ``online_final_passes`` re-association passes."""
    rc = config.reassociation
    return dataclasses.replace(
        config,
        pose2_odometry=dataclasses.replace(config.pose2_odometry,
                                           cov_scale=rc.online_final_cov_scale),
        reassociation=dataclasses.replace(rc, passes=rc.online_final_passes))


def final_solve(g: GraphLog, config: SlamConfig, online: SlamResult, s: Sightings,
                place: bool = True, budget: CpuBudget | None = None) -> OfflineRun:
    """The online association ``s`` re-solved in batch (module doc), then, with
    ``[reassociation] online_final_held_mixture`` and ``place``, the sightings it left
    out placed (:func:`place_left_out`).

    Args:
        g: the log; config: the online run's config (:func:`final_config` is applied).
        online: the online run's result ((N, 3) poses at every log pose).
        s: its association (:func:`online_association`; ``s.lid`` is updated in place).
        place: False for the picker's candidates: the placement lowers ``C`` by
            different amounts in different candidates and would sway the pick (MRCLAM:
            ``cov_scale=1/16``, 0.342 m against the defaults' 0.005), so the picker
            places the left-out sightings of the chosen candidate only
            (:func:`place_chosen`).
        budget: a CPU budget (:mod:`lampsam.backend.cpu_budget`; None: none) for every
            stage; a spent one stops the stage under way at its next pass or round and
            skips the later stages (the answer's ``stopped`` names where).

    Returns:
        The answer; its ``scale`` is the online pass's odometry variance factor relative
        to the final solve's.
    """
    cfg = final_config(config)
    q = config.pose2_odometry.cov_scale / cfg.pose2_odometry.cov_scale
    if cfg.reassociation.online_final_singletons:
        s = with_singletons(g, s)
    run = solve_candidate(g, cfg, q, online.poses, online_landmarks(online, s), s,
                          float(online.extra.get("total_cpu_s", float("nan"))), budget=budget)
    log.info("final solve of the online association: %d passes, %d moves, C %.1f",
             len(run.passes), len(run.moves), run.cost)
    if cfg.reassociation.final_pass:
        run = final_pass(g, cfg, run, budget=budget)
    if place and cfg.reassociation.online_final_held_mixture:
        if budget is not None and budget.spent("placement of the left-out sightings"):
            return dataclasses.replace(run, stopped=run.stopped or budget.stopped)
        run = place_left_out(g, cfg, run)
    return run


def place_chosen(g: GraphLog, config: SlamConfig, c: Candidate) -> None:
    """With ``[reassociation] online_final_held_mixture``: the chosen candidate's final
    solve with the sightings it left out placed (:func:`place_left_out`, kept only if
    ``C`` fell); ``c.solve`` and ``c.final`` are replaced in place (``c.cost`` and the
    picker's costs stay those of the pick). ``c.final.extra`` gets
    ``noids_held_placed`` (0 when nothing was placed)."""
    if not config.reassociation.online_final_held_mixture or c.solve is None or c.final is None:
        return
    c0 = time.process_time()
    cfg = final_config(config)
    placed = place_left_out(g, cfg, c.solve)
    n = len(placed.sightings.k) - len(c.solve.sightings.k)  # placed ones are appended
    if placed is not c.solve:
        old = c.final.extra
        new = result_of(g, cfg, placed, {}, time.perf_counter(), c0)
        cpu = time.process_time() - c0
        new.extra = {**old, **{k: v for k, v in new.extra.items()
                               if k not in ("total_time_s", "total_cpu_s")},
                     "total_cpu_s": float(old.get("total_cpu_s", 0.0)) + cpu,
                     "online_final_cpu_s": float(old.get("online_final_cpu_s", 0.0)) + cpu}
        c.solve, c.final = placed, new
    c.final.extra["noids_held_placed"] = float(n)


def place_left_out(g: GraphLog, cfg: SlamConfig, run: OfflineRun) -> OfflineRun:
    """The final answer with the sightings it left out placed by max-mixture factors
    (:func:`lampsam.backend.held_placement.place_into`; with
    ``online_final_held_new_landmarks`` new landmarks joined inside the association
    gate, of the sightings no landmark explains with ``online_final_held_new_unexplained``,
    then with ``online_final_held_new_merge`` the final pass's merges and single moves,
    :func:`lampsam.backend.noids_offline.final_pass`, so that a tree mapped twice is
    merged back), kept only if the description length ``C`` fell; if GTSAM fails on the
    mixture graph, ``run`` as it is (logged). With ``online_final_held_residual_scale``
    the candidates' threshold and the "none" cost are ``c_new`` times the sightings'
    chi-square per dof at ``run``'s optimum (at most 1): the choice is made at the noise
    the residuals show, the factors keep the stated noise.

    Args:
        g: the log; cfg: the final solve's config (:func:`final_config`); run: its answer.
    """
    c0 = time.process_time()
    prior, odo = batch_graph_inputs(g, cfg)
    dk, dz, dr = dropped_sightings(g, run.sightings)
    s = Sightings(run.sightings.k, run.sightings.z, run.sightings.r, run.sightings.lid.copy())
    c_new = cfg.association.new_threshold(2)
    rc = cfg.reassociation
    gate = cfg.association.gate(2) if rc.online_final_held_new_landmarks else None
    if rc.online_final_held_residual_scale:  # choose at the noise the residuals show
        f = min(1.0, run.chi2_sightings / max(run.dof_sightings, 1))
        c_new, gate = c_new * f, None if gate is None else gate * f
        log.info("placing the left-out sightings at the sightings' residual variance "
                 "factor %.3f (threshold %.1f)", f, c_new)
    try:
        placed = place_into(prior, odo, s, run.graph, run.values, dk, dz, dr, c_new, gate,
                            rc.online_final_held_new_unexplained)
    except RuntimeError as exc:  # GTSAM's LM on the mixture graph: keep the answer
        log.warning("placing the left-out sightings failed (%s): the final solve without "
                    "them is kept", str(exc).strip()[:120])
        return run
    if placed is None:
        return run
    s2, graph, values, n = placed
    out = answer_of(g, cfg, run.scale, s2, run.passes, run.online_cpu_s,
                    run.batch_cpu_s + time.process_time() - c0, graph, values,
                    run.moves + [Move("held", (-1, -1), 0.0)] * n)
    log.info("held sightings placed by max-mixture: %d of %d, C %.1f -> %.1f", n, len(dk),
             run.cost, out.cost)
    if gate is not None and rc.online_final_held_new_merge:
        out = final_pass(g, cfg, out)
        log.info("final pass after the placement: C %.1f", out.cost)
    return out if out.cost < run.cost else run


def candidate_config(config: SlamConfig, spec: str) -> SlamConfig:
    """``config`` with one ``[reassociation] online_candidates`` entry's changes
    (:func:`lampsam.backend.config_offline.online_candidate_changes`): the association
    options it names on, and the online pass's odometry ``cov_scale`` if it sets one."""
    assoc, cov = online_candidate_changes(spec)
    cfg = dataclasses.replace(config, association=dataclasses.replace(config.association,
                                                                      **assoc))
    if cov is not None:
        cfg = dataclasses.replace(cfg, pose2_odometry=dataclasses.replace(
            cfg.pose2_odometry, cov_scale=cov))
    return cfg


@dataclasses.dataclass
class Candidate:
    """One online setting's run and final solve (:func:`run_online_picker`).

    Attributes:
        name: the ``online_candidates`` entry (``"as given"`` without a list).
        status: ``"ok"`` (final solve done), ``"online <status>"`` (the online run failed
            or was stopped), ``"no sightings recorded"``, ``"final solve failed: ..."``,
            or ``"not run (stop requested)"``; any but ``"ok"`` loses.
        cost: the final solve's description length ``C`` (NaN without one).
        final: the final solve as a result (None without one); online: the online run.
        cpu_s: process CPU of the online run and the final solve, s.
        solve: the final solve's :class:`~lampsam.backend.noids_offline.OfflineRun`
            (its association; None without one).
        label_cost: twice the entropy of its sightings' labels
            (:func:`label_entropy_costs`; NaN without it or without a final solve).
        picker_cost: with ``[reassociation] online_label_entropy``, what the picker
            compares: ``C`` at the candidate's own sighting noise scale plus
            ``label_cost`` (:func:`label_entropy_costs`); NaN without it.

    A final solve stopped by its CPU budget (``[reassociation]
    final_solve_cpu_per_sighting``) is still ``"ok"``: its answer is the last state it
    accepted, a valid association with its ``C``; ``solve.stopped`` (``row()``'s
    ``stopped_by_budget``) names the stage it stopped in.
    """

    name: str
    status: str
    cost: float = float("nan")
    final: SlamResult | None = None
    online: SlamResult | None = None
    cpu_s: float = 0.0
    solve: OfflineRun | None = None
    label_cost: float = float("nan")
    picker_cost: float = float("nan")

    def score(self) -> float:
        """What :func:`pick` compares: ``picker_cost`` where set, else ``cost``."""
        return self.picker_cost if np.isfinite(self.picker_cost) else self.cost

    def row(self) -> dict[str, object]:
        """The candidate's entry in ``summary.json`` (``online_picker.candidates``)."""
        on = self.online.extra if self.online is not None else {}
        return {"name": self.name, "status": self.status,
                "C": None if not np.isfinite(self.cost) else round(float(self.cost), 3),
                "picker_cost": (None if not np.isfinite(self.picker_cost)
                                else round(float(self.picker_cost), 3)),
                "landmarks": None if self.final is None else len(self.final.landmarks),
                "landmarks_online": None if self.online is None else len(self.online.landmarks),
                "held": int(on.get("n_held", 0)), "held_unused": int(on.get("n_held_unused", 0)),
                "sightings_dropped": (None if self.final is None else
                                      int(self.final.extra["sightings_dropped"])),
                "cpu_s": round(self.cpu_s, 3),
                "stopped_by_budget": (self.solve.stopped or None) if self.solve is not None
                else None}


class OverBudget(LampsamError):
    """A candidate's online run went past its CPU budget
    (``[reassociation] online_candidate_cpu_factor``)."""


def _budget_watch(c0: float, budget_s: float,
                  name: str = "[reassociation] online_candidate_cpu_factor"
                  ) -> Callable[[str, Mapping[str, Any]], None]:
    """An observer (:mod:`lampsam.observe`) that raises :class:`OverBudget` at the first
    step after ``budget_s`` s of process CPU since ``c0`` (``name``: the option that set
    the budget, for the message); the run's driver then ends it as failed, keeping its
    finished steps."""

    def watch(event: str, _: Mapping[str, Any]) -> None:
        if event == "slam.step" and time.process_time() - c0 > budget_s:
            raise OverBudget(f"stopped after {budget_s:.1f} s of CPU (its budget: {name})")

    return watch


def _run_candidate(g: GraphLog, backend: str, config: SlamConfig, spec: str | None,
                   budget_s: float = float("inf"), final_budget_s: float = float("inf"),
                   budget_name: str = "[reassociation] online_candidate_cpu_factor"
                   ) -> Candidate:
    """One candidate: the online run with ``spec``'s changes (stopped past ``budget_s``
    s of CPU, ``budget_name`` the option that set it), then :func:`final_solve` of its
    association with ``config`` as given (its ``cov_scale`` replaced by the
    candidate's, which only sets the recorded ``noids_scale``), stopped past
    ``final_budget_s`` s of CPU with the last state it accepted
    (:class:`lampsam.backend.cpu_budget.CpuBudget`): every candidate's ``C`` is then the
    same sightings under the same noise and the same ``c_new``."""
    name = "as given" if spec is None else spec
    if stop_requested():
        return Candidate(name, "not run (stop requested)")
    t0, c0 = time.perf_counter(), time.process_time()
    cfg = config if spec is None else candidate_config(config, spec)
    # the online map's pruning is not the written map's
    with candidate_pruning_quiet(), observing(
            _budget_watch(c0, budget_s, budget_name) if np.isfinite(budget_s) else None):
        online, be = run_graph_log_backend(g, backend, cfg, known_ids=False)
    if online.n_pruned:
        log.info("online run (%s): %d landmarks pruned from its map", name, online.n_pruned)
    # a stopped or failed run's last keyframe may hold sightings past the steps it kept:
    # its status is checked before its association is read
    if online.status != "ok" or be is None:
        return Candidate(name, "online " + " ".join(online.status.split()), online=online,
                         cpu_s=time.process_time() - c0)
    s = online_association(be, online)
    if not len(s.k):
        return Candidate(name, "no sightings recorded", online=online,
                         cpu_s=time.process_time() - c0)
    c1 = time.process_time()
    solve_cfg = dataclasses.replace(config, pose2_odometry=cfg.pose2_odometry)
    try:
        budget = CpuBudget(final_budget_s, "[reassociation] final_solve_cpu_per_sighting",
                           c1)
        best = final_solve(g, solve_cfg, online, s, place=False, budget=budget)
    except (RuntimeError, KeyboardInterrupt) as exc:  # GTSAM's LM, or SIGINT / SIGTERM
        why = f"{type(exc).__name__}: {str(exc).strip()[:120] or 'interrupted'}"
        log.error("final solve of candidate %s stopped (%s)", name, why)
        return Candidate(name, f"final solve failed: {why}", online=online,
                         cpu_s=time.process_time() - c0)
    extra = {k: v for k, v in online.extra.items() if k not in ("total_time_s", "total_cpu_s")}
    extra.update({"online_final": 1.0, "online_cpu_s": c1 - c0,
                  "online_final_cpu_s": time.process_time() - c1,
                  "online_landmarks": float(len(online.landmarks)),
                  "online_landmarks_pruned": float(online.n_pruned)})
    final = result_of(g, final_config(solve_cfg), best, extra, t0, c0)
    return Candidate(name, "ok", best.cost, final, online, time.process_time() - c0, best)


def candidate_label_cost(run: OfflineRun, s2: float = 1.0) -> float:
    """Twice the entropy of the labels of a final solve's sightings at their noise times
    ``s2`` (:func:`lampsam.backend.label_entropy.label_cost` at its optimum)."""
    s = run.sightings
    return label_cost(run.poses, s.k, s.z, s.r * s2, s.lid, run.landmarks)


def label_entropy_costs(cands: list[Candidate], new_cost: float) -> None:
    """With ``[reassociation] online_label_entropy``: each finished candidate's
    ``picker_cost`` and ``label_cost`` at its own sighting noise scale (:mod:`lampsam.backend.label_entropy`:
    ``C`` with the sightings' chi-square at that scale, plus the label entropy term);
    its final answer's ``extra`` gets ``noids_label_cost``, ``noids_picker_cost`` and
    ``noids_sighting_scale``."""
    for c in cands:
        run = c.solve
        if c.status != "ok" or run is None:
            continue
        s2 = sighting_scale(run.chi2_sightings, run.dof_sightings)
        c.label_cost = candidate_label_cost(run, s2)
        c.picker_cost = profiled_cost(run.chi2_odometry, run.chi2_sightings, run.dof_sightings,
                               len(run.landmarks), run.n_dropped, new_cost, s2, c.label_cost)
        if c.final is not None:
            c.final.extra.update({"noids_label_cost": c.label_cost,
                                  "noids_picker_cost": c.picker_cost,
                                  "noids_sighting_scale": s2})


def pick(cands: list[Candidate]) -> int:
    """Index of the candidate whose final solve has the least :meth:`Candidate.score`
    (``C``, or with ``[reassociation] online_label_entropy`` the picker cost); without
    any, the first whose online run finished, else 0."""
    ok = [i for i, c in enumerate(cands) if c.status == "ok"]
    if ok:
        return min(ok, key=lambda i: cands[i].score())
    done = [i for i, c in enumerate(cands) if c.online is not None and c.online.status == "ok"]
    return done[0] if done else 0


def run_online_picker(g: GraphLog, backend: str, config: SlamConfig
                      ) -> tuple[SlamResult, SlamResult | None, list[Candidate], int]:
    """``lampsam slam LOG --no-ids --backend B`` with ``[reassociation] online_final``:
    each ``[reassociation] online_candidates`` entry (none: the config as given) run
    online and final-solved, the least ``C`` kept (module doc).

    Returns:
        ``(answer, online, candidates, chosen)``: the chosen candidate's final solve
        (``backend`` "batch", ``extra`` as :func:`run_online_final`'s) and its online
        run; when no candidate has a final solve, the answer is the chosen one's online
        run (``online_final`` 0; ``online`` None, or None too when no candidate ran).
    """
    rc = config.reassociation
    specs: list[str | None] = list(rc.online_candidates) or [None]
    cands: list[Candidate] = []
    n_sightings = sum(len(x) for x in g.sightings)
    first_s = sighting_budget(rc.online_first_cpu_per_sighting, n_sightings,
                              rc.online_candidate_cpu_floor_s)
    final_s = sighting_budget(rc.final_solve_cpu_per_sighting, n_sightings,
                              rc.online_candidate_cpu_floor_s)
    for spec in specs:
        budget, name = picker_budget([x.cpu_s for x in cands if x.status == "ok"], rc,
                                     first_s)
        c = _run_candidate(g, backend, config, spec, budget, final_s, name)
        log.info("online candidate %s: %s, C %.1f, %.1f s CPU", c.name, c.status, c.cost,
                 c.cpu_s)
        cands.append(c)
    if rc.online_label_entropy:
        label_entropy_costs(cands, config.association.new_threshold(2))
        log.info("online picker: costs with the label entropy %s",
                 ", ".join(f"{c.name} {c.picker_cost:.1f}" for c in cands))
    i = pick(cands)
    c = cands[i]
    lost = [x for x in cands if x.status != "ok"]
    if lost and len(cands) > 1:
        log.warning("online candidates without a final solve (they lose): %s; chosen: %s",
                    ", ".join(f"{x.name} ({x.status[:60]})" for x in lost), c.name)
    if c.final is None:
        answer = c.online
        if answer is None:  # a stop request before the first candidate ran
            answer, _ = run_graph_log_backend(g, backend, config, known_ids=False)
        answer.extra["online_final"] = 0.0
        return answer, None, cands, i
    if c.solve is not None and c.solve.stopped:
        log.warning("the chosen candidate's final solve was stopped by its CPU budget (in %s): "
                    "its left-out sightings are not placed", c.solve.stopped)
    else:
        placing = CpuBudget(final_s, "[reassociation] final_solve_cpu_per_sighting")
        try:
            with interrupt_past(placing, "placement of the left-out sightings"):
                place_chosen(g, config, c)
        except BudgetSpent:  # the chosen final solve as it was before the placement
            log.warning("the placement of the chosen candidate's left-out sightings was "
                        "stopped by its CPU budget: they are not placed")
    if len(cands) > 1:
        c.final.extra.update({"online_candidates": float(len(cands)),
                              "online_candidate_chosen": float(i),
                              "online_picker_cpu_s": float(sum(x.cpu_s for x in cands))})
    if c.final.n_pruned:
        log_pruned(c.final.n_pruned, c.final.pruned, config.association.min_observations)
    return c.final, c.online, cands, i


def picker_budget(done_cpu_s: list[float], rc: ReassociationConfig, first_s: float
                  ) -> tuple[float, str]:
    """``(budget_s, the option that set it)`` of the next candidate's online run: with
    finished candidates (``done_cpu_s``: their CPU, s), ``online_candidate_cpu_factor``
    times the least, at least ``online_candidate_cpu_floor_s``; before any finished,
    ``first_s`` (from ``online_first_cpu_per_sighting``)."""
    if done_cpu_s:
        return (max(rc.online_candidate_cpu_factor * min(done_cpu_s),
                    rc.online_candidate_cpu_floor_s),
                "[reassociation] online_candidate_cpu_factor")
    return first_s, "[reassociation] online_first_cpu_per_sighting"


def run_online_final(g: GraphLog, backend: str, config: SlamConfig
                     ) -> tuple[SlamResult, SlamResult]:
    """The online run at ``config`` as given (``online_candidates`` ignored), then
    :func:`final_solve` of its association.

    Returns:
        ``(final, online)``: the final solve as a result (``backend`` "batch"; ``extra``:
        :func:`lampsam.backend.noids_offline.result_of`'s keys, ``online_final`` 1,
        ``online_cpu_s``, ``online_final_cpu_s``, ``online_landmarks``,
        ``online_landmarks_pruned``, and the online run's own keys such as
        ``n_held``), and the online run's result. When the online run did not finish
        (status not ok) or recorded no sighting, or the final solve failed (GTSAM
        threw) or was interrupted (it is logged), ``final`` is ``online`` with
        ``online_final`` 0.
    """
    cfg = dataclasses.replace(config, reassociation=dataclasses.replace(
        config.reassociation, online_candidates=()))
    final, online, _, _ = run_online_picker(g, backend, cfg)
    return final, (final if online is None else online)
