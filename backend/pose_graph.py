"""Loop closures of a graph text log as factors, and the batch start on a graph with them.

A log read by :func:`lampsam.datasets.graph_text.read_graph_text` keeps every pose-pose
edge that is not the odometry chain as a :class:`~lampsam.datasets.graph_text.PoseEdge`
(``i_T_j`` between two steps). The smoothers' known-id path
(:mod:`lampsam.backend.dense_log`) makes every pose a keyframe when a log has closures
and adds each closure as a ``BetweenFactorPose2`` with the file's covariance (GTSAM's
reading of the same line) at the step of its later pose: iSAM2 gets it in that step's
update, batch LM sees the whole graph.

Batch LM on a graph with loop closures starts (``[graph] batch_init``, :class:`~lampsam.
backend.config_graph.PoseGraphConfig`) from the online iSAM2 pass (default: ``[batch]
init``), from the chain's dead reckoning, or from GTSAM's LAGO (``gtsam.lago.initialize``:
the headings from a linear least-squares over the cycles of the graph, then the positions
given those headings; Carlone et al., IJRR 2014). iSAM2 on such a log factorizes by QR
(``[graph] isam2_factorization``). docs/log-format.md gives the figures behind both
defaults.
"""

from __future__ import annotations

import logging

import gtsam
import numpy as np
from gtsam.symbol_shorthand import L, X

from lampsam.arrays import FloatArray
from lampsam.backend.config import SlamConfig
from lampsam.backend.config_graph import PoseGraphConfig
from lampsam.backend.interface import SlamResult
from lampsam.backend.models import init_point2
from lampsam.datasets.graph_text import GraphLog, PoseEdge
from lampsam.factors.gtsam_factors import check_cov, robust_wrap

log = logging.getLogger(__name__)


def closure_noise(cov: FloatArray, config: PoseGraphConfig) -> gtsam.noiseModel.Base:
    """The noise model of one loop closure: its (3, 3) covariance, wrapped in the
    ``[graph] closure_kernel`` (Huber or Cauchy at ``closure_kernel_k`` sigmas) if any."""
    gauss = gtsam.noiseModel.Gaussian.Covariance(check_cov(cov, 3, "loop closure"))
    if config.closure_kernel == "none":
        return gauss
    return robust_wrap(gauss, config.closure_kernel_k, config.closure_kernel)


def closures_by_step(g: GraphLog) -> dict[int, list[PoseEdge]]:
    """The log's loop closures keyed by the step of their later pose (file order kept)."""
    out: dict[int, list[PoseEdge]] = {}
    for e in g.closures:
        out.setdefault(max(e.i, e.j), []).append(e)
    return out


def closure_factor(e: PoseEdge, key_i: int, key_j: int, config: PoseGraphConfig
                   ) -> gtsam.BetweenFactorPose2:
    """``BetweenFactorPose2(key_i, key_j, i_T_j)`` of one closure (keys of its two poses)."""
    return gtsam.BetweenFactorPose2(key_i, key_j, gtsam.Pose2(*np.asarray(e.delta, float)),
                                    closure_noise(e.cov, config))


def _diagonal(model: gtsam.noiseModel.Base) -> gtsam.noiseModel.Diagonal:
    """A ``Diagonal`` model with the marginal sigmas of a (robust-wrapped) Gaussian one."""
    gauss = model.noise() if isinstance(model, gtsam.noiseModel.Robust) else model
    assert isinstance(gauss, gtsam.noiseModel.Gaussian)
    return gtsam.noiseModel.Diagonal.Sigmas(np.sqrt(np.diag(gauss.covariance())))


def lago_graph(graph: gtsam.NonlinearFactorGraph) -> gtsam.NonlinearFactorGraph:
    """The graph's ``PriorFactorPose2`` / ``BetweenFactorPose2`` on poses ``X(k)``, as
    GTSAM's LAGO takes them: integer keys ``k`` (with symbol keys ``lago.initialize``
    throws ``map::at``: its anchor key 99999999 must sort above every pose key) and
    diagonal noise (it refuses any other: "current version assumes diagonal noise
    model"), each edge's covariance cut to its diagonal. Only the start uses it; LM
    then runs on the full covariances."""
    out = gtsam.NonlinearFactorGraph()
    for k in range(graph.size()):
        f = graph.at(k)
        if isinstance(f, gtsam.BetweenFactorPose2):
            i, j = (gtsam.Symbol(key).index() for key in f.keys())
            out.add(gtsam.BetweenFactorPose2(i, j, f.measured(), _diagonal(f.noiseModel())))
        elif isinstance(f, gtsam.PriorFactorPose2):
            out.add(gtsam.PriorFactorPose2(gtsam.Symbol(f.keys()[0]).index(), f.prior(),
                                           _diagonal(f.noiseModel())))
    return out


def lago_start(graph: gtsam.NonlinearFactorGraph, initial: gtsam.Values,
               new_lms: list[list[tuple[int, FloatArray]]]) -> gtsam.Values | None:
    """The batch start from GTSAM's LAGO on the graph's poses.

    ``gtsam.lago.initialize`` on :func:`lago_graph` (the poses' prior and between
    factors; headings first, from a linear least-squares over the graph's cycles, then
    positions); each landmark is then placed from its first sighting
    (:func:`~lampsam.backend.models.init_point2`) off the LAGO pose of that keyframe.

    Args:
        graph: the whole graph (prior on ``X(0)``, odometry, closures, sightings).
        initial: the dead-reckoning values (poses ``X(k)``, landmarks ``L(id)``);
            a pose LAGO does not give keeps its value here.
        new_lms: per keyframe ``k = 1..K`` (entry ``k - 1``), its new landmarks
            ``(id, [bearing, range])``.

    Returns:
        The values over ``initial``'s keys, or None when LAGO throws (warned; the
        caller keeps its own start).
    """
    try:
        est = gtsam.lago.initialize(lago_graph(graph))
    except (RuntimeError, IndexError, ValueError) as exc:
        log.warning("LAGO failed (%s: %s): batch starts from the chain's dead reckoning",
                    type(exc).__name__, exc)
        return None
    out = gtsam.Values()
    for key in initial.keys():
        sym = gtsam.Symbol(key)
        if sym.chr() == ord("x"):
            k = sym.index()
            out.insert(key, est.atPose2(k) if est.exists(k) else initial.atPose2(key))
    for j, new in enumerate(new_lms):
        pose = out.atPose2(X(j + 1))
        p = np.array([pose.x(), pose.y(), pose.theta()])
        for lid, z in new:
            out.insert(L(lid), init_point2(p, z)[0])
    for key in initial.keys():  # a landmark not placed above (none today): its own start
        if not out.exists(key):
            out.insert(key, initial.atPoint2(key))
    return out


def closures_unused_reason(backend: str, config: SlamConfig, known_ids: bool,
                           pose_covariances: bool = False) -> str:
    """Why a run over a log with loop closures leaves them out (the known-id iSAM2 /
    batch path adds them, :mod:`lampsam.backend.dense_log`; nothing else does)."""
    if backend == "ekf":
        return ("the EKF's state holds the current pose only: closing a loop would need "
                "the past poses in its state; use --backend isam2 or batch")
    if not known_ids:
        return "association without ids runs the per-step path, which has no pose-pose factors"
    if backend == "batch" and config.batch.huber_k is not None:
        return "[batch] huber_k runs the per-step path ([graph] closure_kernel is the closures' own)"
    if pose_covariances:
        return "pose covariances run the per-step path"
    return ("the per-step path ran: an iSAM2 update threw (warned above), a live view, or "
            "a log the known-id path refuses")


def closure_summary(g: GraphLog, result: SlamResult, backend: str, config: SlamConfig,
                    known_ids: bool) -> dict[str, object]:
    """The ``summary.json`` ``input`` entries of a log's loop closures: their count,
    how many the run used (``result.extra["loop_closures_used"]``, 0 when absent), the
    odometry edges read backwards, and a ``closures_warning`` when they went unused."""
    used = int(result.extra.get("loop_closures_used", 0))
    out: dict[str, object] = {"loop_closures": len(g.closures), "loop_closures_used": used,
                              "reversed_odometry_edges": g.n_reversed}
    if g.closures and not used:
        out["closures_warning"] = (f"the {len(g.closures)} loop closures are not used: "
                                   + closures_unused_reason(backend, config, known_ids))
    return out
