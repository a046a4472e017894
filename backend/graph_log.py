"""SLAM on a graph text log (iSAM ``ODOMETRY``/``LANDMARK``, g2o; e.g. GTSAM's
``victoria_park.txt``): one step per pose, each sighting with its own covariance.

Known ids take :mod:`lampsam.backend.dense_log`'s fast path; everything else goes
through the general per-step driver (:func:`lampsam.backend.slam.drive`).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Iterator

import numpy as np

from lampsam.arrays import FloatArray
from lampsam.backend.config import SlamConfig
from lampsam.backend.dense_log import run_known_ids
from lampsam.backend.interface import Frame, SlamBackend, SlamResult
from lampsam.backend.odometry import Pose2Motion
from lampsam.backend.pose_graph import closures_unused_reason
from lampsam.backend.slam import drive, make_backend
from lampsam.datasets.graph_text import GraphLog
from lampsam.datasets.odometry import Pose2OdometryModel
from lampsam.factors.geometry import wrap_angle
from lampsam.frontend.measurements import RangeBearingFrame, RangeBearingObservation
from lampsam.observe import listening

log = logging.getLogger(__name__)


def graph_log_steps(graph_log: GraphLog, known_ids: bool = True
                    ) -> Iterator[tuple[float, FloatArray, Frame | None]]:
    """One step per pose of a graph text log: its odometry sample and its sightings.

    Args:
        graph_log: the log (:func:`lampsam.datasets.graph_text.read_graph_text`).
        known_ids: keep the file's landmark ids (False: association by the backend).

    Yields:
        ``(t, samples (1, 12), frame or None)``; each sighting carries its own
        ``[bearing, range]`` covariance.
    """
    samples = graph_log.odometry.samples()
    for k, t in enumerate(graph_log.odometry.t):
        obs = tuple(RangeBearingObservation(s.range, float(wrap_angle(s.bearing)),
                                            s.landmark if known_ids else None, s.cov)
                    for s in graph_log.sightings[k])
        frame = RangeBearingFrame(float(t), obs) if obs else None
        yield float(t), samples[k : k + 1], frame


def run_graph_log(graph_log: GraphLog, backend: str = "isam2", config: SlamConfig | None = None,
                  known_ids: bool = True, odometry_model: Pose2OdometryModel | None = None,
                  start_pose: FloatArray | None = None, pose_covariances: bool = False,
                  fast: bool = True) -> SlamResult:
    """Run one backend over a graph text log, one step per pose
    (:func:`run_graph_log_backend` without the backend).

    Args:
        graph_log: the log.
        backend: ``"ekf"``, ``"isam2"`` or ``"batch"``.
        config: the SLAM config (defaults when None); keyframes are made at every
            pose with sightings (``isam2.every_frame``), as in the file's graph.
        known_ids: use the file's landmark ids; False associates by the backend's gate.
        odometry_model: floor (and default noise) of the Pose2 odometry; None:
            ``config.pose2_odometry``.
        start_pose: (3,) start pose; None: the first pose's vertex, else the origin.
        pose_covariances: the smoothers compute each step's online pose covariance
            and every keyframe's final marginal (``isam2.pose_cov_every_step``,
            ``isam2.final_covariances``). False (default): neither is computed
            (``pose_covs`` NaN; the gate still gets its marginals): what
            ``lampsam slam LOG.txt`` writes has no pose covariance, and on a log with
            a keyframe per pose they cost about 15 % of GTSAM's own iSAM2 run.
            Landmark covariances are computed either way.
        fast: with known ids, no pose covariances and no live view, iSAM2 and batch
            take the fast path (:mod:`lampsam.backend.dense_log`: the same graph and
            estimate, bit for bit, without the per-step machinery); False: always
            the general per-step path.

    Returns:
        The result; ``extra`` has ``total_time_s`` (wall) and ``total_cpu_s`` (process
        CPU time, comparable on a shared machine).
    """
    return run_graph_log_backend(graph_log, backend, config, known_ids, odometry_model,
                                 start_pose, pose_covariances, fast)[0]


def run_graph_log_backend(graph_log: GraphLog, backend: str = "isam2",
                          config: SlamConfig | None = None, known_ids: bool = True,
                          odometry_model: Pose2OdometryModel | None = None,
                          start_pose: FloatArray | None = None, pose_covariances: bool = False,
                          fast: bool = True) -> tuple[SlamResult, SlamBackend | None]:
    """:func:`run_graph_log` (same arguments) and the backend object that ran it (None on
    the known-id fast path), e.g. for its association
    (:func:`lampsam.backend.online_final.online_association`)."""
    import dataclasses

    config = config or SlamConfig()
    config = dataclasses.replace(
        config, isam2=dataclasses.replace(config.isam2, every_frame=True,
                                          pose_cov_every_step=pose_covariances,
                                          final_covariances=pose_covariances),
        association=dataclasses.replace(config.association, use_known_ids=known_ids))
    start = graph_log.start_pose() if start_pose is None else np.asarray(start_pose, float)
    model = odometry_model or config.pose2_odometry
    t0, c0 = time.perf_counter(), time.process_time()
    quick = None
    if fast and known_ids and not pose_covariances and not listening():
        quick = run_known_ids(graph_log, backend, config, Pose2Motion(model), start)
    be: SlamBackend | None = None
    if quick is not None:
        result = quick
    else:
        if graph_log.closures:
            log.warning("%s: the %d loop closures are not used by this run (%s): its poses "
                        "are the odometry and landmarks alone", graph_log.path,
                        len(graph_log.closures), closures_unused_reason(backend, config, known_ids,
                                                                        pose_covariances))
        be = make_backend(backend, model, config, start)
        result = drive(be, graph_log_steps(graph_log, known_ids))
    result.extra["loop_closures_used"] = float(len(graph_log.closures) if quick is not None else 0)
    result.extra["total_time_s"] = time.perf_counter() - t0
    result.extra["total_cpu_s"] = time.process_time() - c0
    return result, be
