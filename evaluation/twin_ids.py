"""Twin file ids: one tree under two ids in a graph log, and the reference with them merged.

A graph log's file ids may name one tree twice: Victoria Park's file has four pairs of
ids whose known-id positions are 0.1-1.4 m apart and that are never sighted at one pose
(:func:`twin_map`). A map made without ids merges such a pair, so its distance from
GTSAM's LM on the file's ids mixes the association's errors with the twins' split. This
module gives the other reference (GTSAM's LM on the file's graph with each twin group
under one id: :func:`merged_log`, :func:`lm_reference`) and, per twin pair, the evidence
for "one tree" (:func:`twin_tests`): the chi-square the merge costs with the poses free,
at the stated noise and at the noise the residuals show, and whether the pair is one
trunk seen from two sides (ranges measured to the trunk's surface put each id's point on
the side its observers stand: one centre and a radius fitted to both ids' sightings).

Scoring only: the file's ids are read here, never by the no-ids pipeline.
Frames: world, m and rad; sightings ``[bearing, range]`` in the body frame.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import gtsam
import numpy as np
from gtsam.symbol_shorthand import L, X
from scipy.optimize import least_squares
from scipy.stats import chi2 as chi2_dist

from lampsam.arrays import FloatArray
from lampsam.backend.config import SlamConfig
from lampsam.datasets.graph_text import GraphLog

#: File ids closer than this (m) in the known-id map and never sighted together are one tree.
TWIN_RADIUS_M = 1.5


def twin_map(g: GraphLog, landmarks: dict[int, FloatArray],
             radius: float = TWIN_RADIUS_M) -> dict[int, int]:
    """File id -> the smallest file id of its twin group.

    Twins: ids whose known-id positions (``landmarks``: id -> (2,) world, m) are within
    ``radius`` m and that are never sighted at one pose (one tree under two file ids:
    Victoria Park has four such pairs, 0.1-1.4 m apart). Ids sighted together stay apart
    (cityTrees has six pairs 0.05 m apart, always sighted together). Groups are closed
    transitively (union-find)."""
    together = {(a, b) for ss in g.sightings for a in (x.landmark for x in ss)
                for b in (x.landmark for x in ss) if a != b}
    ids = sorted(landmarks)
    parent = {i: i for i in ids}

    def root(i: int) -> int:
        while parent[i] != i:
            i = parent[i]
        return i

    xy = np.array([landmarks[i] for i in ids]).reshape(-1, 2)
    for ia, a in enumerate(ids):
        near = np.flatnonzero(np.hypot(*(xy - xy[ia]).T) < radius)
        for ib in near.tolist():
            b = ids[ib]
            if a < b and (a, b) not in together:
                ra, rb = root(a), root(b)
                parent[max(ra, rb)] = min(ra, rb)
    return {i: root(i) for i in ids}


def twin_groups(twins: dict[int, int]) -> list[list[int]]:
    """The groups of two or more ids of a :func:`twin_map`, each sorted, by first id."""
    groups: dict[int, list[int]] = {}
    for i, r in twins.items():
        groups.setdefault(r, []).append(i)
    return sorted(sorted(v) for v in groups.values() if len(v) > 1)


def merged_log(g: GraphLog, twins: dict[int, int]) -> GraphLog:
    """``g`` with each sighting's file id replaced by its twin group's (:func:`twin_map`):
    the file's graph as "one tree under two ids" reads it."""
    if all(k == v for k, v in twins.items()):
        return g
    return dataclasses.replace(g, sightings=[
        [dataclasses.replace(x, landmark=twins.get(x.landmark, x.landmark)) for x in ss]
        for ss in g.sightings])


def file_graph(g: GraphLog, config: SlamConfig) -> gtsam.NonlinearFactorGraph:
    """The log's graph in GTSAM with its file ids: the start prior (``[isam2]``
    ``sigma_start_xy`` / ``sigma_start_theta``), odometry and bearing-range factors at the
    file's stated covariances; poses ``X(k)`` (log order), landmarks ``L(file id)``."""
    graph = gtsam.NonlinearFactorGraph()
    c = config.isam2
    graph.add(gtsam.PriorFactorPose2(X(0), gtsam.Pose2(*g.start_pose()),
                                     gtsam.noiseModel.Diagonal.Sigmas(np.array(
                                         [c.sigma_start_xy, c.sigma_start_xy,
                                          c.sigma_start_theta]))))
    for k in range(1, len(g.pose_ids)):
        graph.add(gtsam.BetweenFactorPose2(X(k - 1), X(k), gtsam.Pose2(*g.odometry.delta[k]),
                                           gtsam.noiseModel.Gaussian.Covariance(
                                               g.odometry.cov[k])))
    for k, ss in enumerate(g.sightings):
        for s in ss:
            graph.add(gtsam.BearingRangeFactor2D(X(k), L(s.landmark), gtsam.Rot2(s.bearing),
                                                 s.range,
                                                 gtsam.noiseModel.Gaussian.Covariance(s.cov)))
    return graph


@dataclass(frozen=True)
class Reference:
    """GTSAM's LM optimum of a log's graph.

    Attributes:
        poses: (N, 3) poses; landmarks: file id -> (2,) position, world, m.
        chi2: ``2 x error`` of the whole graph at the optimum; dof: residual dimensions
            less the variables' (3 per pose, 2 per landmark).
        chi2_sightings, dof_sightings: the bearing-range factors' ``2 x error`` and
            residual dimensions (2 per sighting).
    """

    poses: FloatArray
    landmarks: dict[int, FloatArray]
    chi2: float
    dof: int
    chi2_sightings: float
    dof_sightings: int


def lm_reference(g: GraphLog, config: SlamConfig, start: gtsam.Values) -> Reference:
    """GTSAM's LM on :func:`file_graph` of ``g`` from ``start`` (every ``X(k)`` and each
    file id's ``L``; extra keys are ignored)."""
    graph = file_graph(g, config)
    keys = graph.keyVector()
    init = gtsam.Values()
    for key in keys:
        if start.exists(key):
            if gtsam.Symbol(key).chr() == ord("x"):
                init.insert(key, start.atPose2(key))
            else:
                init.insert(key, start.atPoint2(key))
    v = gtsam.LevenbergMarquardtOptimizer(graph, init, gtsam.LevenbergMarquardtParams()).optimize()
    n = len(g.pose_ids)
    poses = np.array([[p.x(), p.y(), p.theta()] for p in (v.atPose2(X(k)) for k in range(n))])
    ids = sorted({x.landmark for ss in g.sightings for x in ss})
    lms = {i: np.asarray(v.atPoint2(L(i)), float) for i in ids}
    n_sight = sum(len(ss) for ss in g.sightings)
    cs = 2.0 * sum(graph.at(i).error(v) for i in range(graph.size())
                   if isinstance(graph.at(i), gtsam.BearingRangeFactor2D))
    dims = 3 + 3 * (n - 1) + 2 * n_sight
    return Reference(poses, lms, 2.0 * graph.error(v), dims - 3 * n - 2 * len(ids), cs,
                     2 * n_sight)


def merged_start(ref: Reference, twins: dict[int, int]) -> gtsam.Values:
    """Values for :func:`lm_reference` of :func:`merged_log` from the file-id optimum
    ``ref``: the poses, and each twin group at the mean of its ids' positions."""
    v = gtsam.Values()
    for k, p in enumerate(ref.poses):
        v.insert(X(k), gtsam.Pose2(*p))
    groups: dict[int, list[FloatArray]] = {}
    for i, xy in ref.landmarks.items():
        groups.setdefault(twins.get(i, i), []).append(xy)
    for r, pts in groups.items():
        v.insert(L(r), gtsam.Point2(*np.mean(pts, axis=0)))
    return v


@dataclass(frozen=True)
class TwinTest:
    """The evidence on one twin pair (:func:`twin_tests`).

    Attributes:
        ids: the two file ids; n: (2,) their sightings; separation_m: their distance at
            the file-id optimum.
        chi2_merge: the rise of the whole graph's ``2 x error`` when the two are one
            landmark, poses and landmarks free (LM from the file-id optimum); 2 dof.
        p_stated: its chi-square tail probability at the stated noise (2 dof).
        scale: the sightings' chi-square per dof at the file-id optimum (the noise the
            residuals show, as a variance factor on the stated ``R``).
        p_scaled: the tail probability of ``chi2_merge / scale``.
        view_angle_deg: the angle between the two ids' mean viewing directions (the
            unit vectors from each id's point to the poses that sight it).
        radius_m: the trunk radius of one centre fitted to both ids' sightings with the
            range to its surface (``|c - p| - r``), poses fixed at the file-id optimum.
        chi2_two, chi2_one, chi2_trunk: the pair's sightings' chi-square at the stated
            noise, poses fixed, with two points (4 parameters), one point (2) and one
            trunk (centre and radius, 3).
    """

    ids: tuple[int, int]
    n: tuple[int, int]
    separation_m: float
    chi2_merge: float
    p_stated: float
    scale: float
    p_scaled: float
    view_angle_deg: float
    radius_m: float
    chi2_two: float
    chi2_one: float
    chi2_trunk: float


def _pair_sightings(g: GraphLog, poses: FloatArray, ids: tuple[int, int]
                    ) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """``(pose (S, 3), z (S, 2) [bearing, range], sqrt information (S, 2, 2), which
    (S,) 0 or 1)`` of the sightings of ``ids``."""
    rows = [(poses[k], (x.bearing, x.range), np.linalg.cholesky(np.linalg.inv(x.cov)).T,
             ids.index(x.landmark)) for k, ss in enumerate(g.sightings) for x in ss
            if x.landmark in ids]
    return (np.array([r[0] for r in rows]), np.array([r[1] for r in rows]),
            np.array([r[2] for r in rows]), np.array([r[3] for r in rows], int))


def point_residuals(p: FloatArray, z: FloatArray, w: FloatArray, centre: FloatArray,
                    radius: FloatArray | float = 0.0) -> FloatArray:
    """(S * 2,) whitened ``[bearing, range]`` residuals of sightings ``z`` (S, 2) from
    poses ``p`` (S, 3) of points ``centre`` ((2,) or (S, 2)) whose ranges are measured to
    a circle of ``radius`` m about it; ``w`` (S, 2, 2) the sqrt information."""
    d = np.broadcast_to(centre, (len(p), 2)) - p[:, :2]
    b = np.arctan2(d[:, 1], d[:, 0]) - p[:, 2]
    e = np.column_stack([np.angle(np.exp(1j * (b - z[:, 0]))),
                         np.hypot(d[:, 0], d[:, 1]) - radius - z[:, 1]])
    return np.einsum("sij,sj->si", w, e).ravel()


def _fit(fun, x0: FloatArray) -> tuple[FloatArray, float]:  # type: ignore[no-untyped-def]
    r = least_squares(fun, x0, method="lm")
    return np.asarray(r.x, float), float(np.sum(r.fun ** 2))


def pair_models(p: FloatArray, z: FloatArray, w: FloatArray, which: FloatArray,
                xy0: tuple[FloatArray, FloatArray]) -> tuple[float, float, float, float]:
    """``(chi2_two, chi2_one, chi2_trunk, radius)`` of one pair's sightings at fixed
    poses (:class:`TwinTest`); ``xy0`` the two ids' start points."""
    a, b = which == 0, which == 1
    _, c2a = _fit(lambda x: point_residuals(p[a], z[a], w[a], x), xy0[0])
    _, c2b = _fit(lambda x: point_residuals(p[b], z[b], w[b], x), xy0[1])
    mid = 0.5 * (xy0[0] + xy0[1])
    _, c1 = _fit(lambda x: point_residuals(p, z, w, x), mid)
    xt, ct = _fit(lambda x: point_residuals(p, z, w, x[:2], x[2]), np.r_[mid, 0.0])
    return c2a + c2b, c1, ct, float(xt[2])


def _view_angle(p: FloatArray, which: FloatArray, xy: tuple[FloatArray, FloatArray]) -> float:
    u = []
    for i in (0, 1):
        d = p[which == i, :2] - xy[i]
        m = (d / np.hypot(d[:, 0], d[:, 1])[:, None]).mean(axis=0)
        u.append(m / np.hypot(*m))
    return float(np.degrees(np.arccos(np.clip(u[0] @ u[1], -1.0, 1.0))))


def twin_tests(g: GraphLog, config: SlamConfig, ref: Reference,
               twins: dict[int, int]) -> list[TwinTest]:
    """Per pair of ids in one twin group (:func:`twin_groups`), the evidence for one tree
    (:class:`TwinTest`). ``ref``: :func:`lm_reference` of ``g`` (file ids)."""
    scale = ref.chi2_sightings / max(ref.dof_sightings - 2 * len(ref.landmarks), 1)
    out: list[TwinTest] = []
    for grp in twin_groups(twins):
        for ia, a in enumerate(grp):
            for b in grp[ia + 1:]:
                pair = {b: a}
                m = lm_reference(merged_log(g, pair), config, merged_start(ref, pair))
                c2 = m.chi2 - ref.chi2
                p, z, w, which = _pair_sightings(g, ref.poses, (a, b))
                xy = (ref.landmarks[a], ref.landmarks[b])
                two, one, trunk, radius = pair_models(p, z, w, which, xy)
                out.append(TwinTest((a, b), (int(np.sum(which == 0)), int(np.sum(which == 1))),
                                    float(np.hypot(*(xy[0] - xy[1]))), c2,
                                    float(chi2_dist.sf(max(c2, 0.0), 2)), scale,
                                    float(chi2_dist.sf(max(c2, 0.0) / scale, 2)),
                                    _view_angle(p, which, xy), radius, two, one, trunk))
    return out
