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

Frames: world, m and rad; sightings ``[bearing, range]`` in the body frame.
"""

from __future__ import annotations

import dataclasses
import logging
import time

import numpy as np

from lampsam.arrays import FloatArray
from lampsam.backend.config import SlamConfig
from lampsam.backend.graph_log import run_graph_log_backend
from lampsam.backend.interface import SlamBackend, SlamResult
from lampsam.backend.noids_offline import (
    OfflineRun,
    dropped_sightings,
    final_pass,
    result_of,
    solve_candidate,
)
from lampsam.backend.reassociate import Sightings, first_sight_positions, sightings_from
from lampsam.datasets.graph_text import GraphLog

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


def final_solve(g: GraphLog, config: SlamConfig, online: SlamResult, s: Sightings
                ) -> OfflineRun:
    """The online association ``s`` re-solved in batch (module doc).

    Args:
        g: the log; config: the online run's config (:func:`final_config` is applied).
        online: the online run's result ((N, 3) poses at every log pose).
        s: its association (:func:`online_association`; ``s.lid`` is updated in place).

    Returns:
        The answer; its ``scale`` is the online pass's odometry variance factor relative
        to the final solve's.
    """
    cfg = final_config(config)
    q = config.pose2_odometry.cov_scale / cfg.pose2_odometry.cov_scale
    if cfg.reassociation.online_final_singletons:
        s = with_singletons(g, s)
    run = solve_candidate(g, cfg, q, online.poses, online_landmarks(online, s), s,
                          float(online.extra.get("total_cpu_s", float("nan"))))
    log.info("final solve of the online association: %d passes, %d moves, C %.1f",
             len(run.passes), len(run.moves), run.cost)
    if cfg.reassociation.final_pass:
        run = final_pass(g, cfg, run)
    return run


def run_online_final(g: GraphLog, backend: str, config: SlamConfig
                     ) -> tuple[SlamResult, SlamResult]:
    """``lampsam slam LOG --no-ids --backend B`` with ``[reassociation] online_final``: the
    online run, then :func:`final_solve` of its association.

    Returns:
        ``(final, online)``: the final solve as a result (``backend`` "batch"; ``extra``:
        :func:`lampsam.backend.noids_offline.result_of`'s keys, ``online_final`` 1,
        ``online_cpu_s``, ``online_final_cpu_s``, ``online_landmarks``, and the online
        run's own keys such as ``n_held``), and the online run's result. When the online
        run did not finish (status not ok) or recorded no sighting, or the final solve
        failed (GTSAM threw) or was interrupted (it is logged), ``final`` is ``online``
        with ``online_final`` 0.
    """
    t0, c0 = time.perf_counter(), time.process_time()
    online, be = run_graph_log_backend(g, backend, config, known_ids=False)
    # a stopped or failed run's last keyframe may hold sightings past the steps it kept:
    # its status is checked before its association is read
    if online.status != "ok" or be is None:
        online.extra["online_final"] = 0.0
        return online, online
    s = online_association(be, online)
    if not len(s.k):
        online.extra["online_final"] = 0.0
        return online, online
    c1 = time.process_time()
    try:
        best = final_solve(g, config, online, s)
    except (RuntimeError, KeyboardInterrupt) as exc:  # GTSAM's LM, or SIGINT / SIGTERM
        log.error("final solve stopped (%s: %s): the online answer is written",
                  type(exc).__name__, str(exc).strip()[:120] or "interrupted")
        online.extra["online_final"] = 0.0
        return online, online
    cfg = final_config(config)
    extra = {k: v for k, v in online.extra.items() if k not in ("total_time_s", "total_cpu_s")}
    extra.update({"online_final": 1.0, "online_cpu_s": c1 - c0,
                  "online_final_cpu_s": time.process_time() - c1,
                  "online_landmarks": float(len(online.landmarks))})
    final = result_of(g, cfg, best, extra, t0, c0)
    return final, online
