"""Placing the sightings an online run held, in the final solve, by max-mixture factors.

An online run without ids holds the sightings it cannot tell between two landmarks
(:mod:`lampsam.backend.held_sightings`) and drops those between its gate and the
new-landmark threshold; whatever it never gives back is not in the association the
final solve (:mod:`lampsam.backend.online_final`) starts from, and the description
length charges each ``c_new``. Giving each one a landmark by a hard choice at the final
map puts some on a neighbour's tree (docs/noids-offline.md). Here each left-out sighting
enters the final graph as one max-mixture factor
(:func:`lampsam.factors.max_mixture.max_mixture_factor`, Olson & Agarwal 2012): its
error is the best of its candidate landmarks' range-bearing errors or the constant
``c_new`` of "none of them", re-chosen at every linearisation, so the poses and the
landmarks settle together with the choice (:func:`place_held`). The candidates
(:func:`mixture_candidates`) are the landmarks within the new-landmark threshold of the
sighting at the final map (stated noise, pose fixed), less those its pose already
sights. Optionally (``[reassociation] online_final_held_new_landmarks``) clusters of
left-out sightings that pay as landmarks of their own are candidates too
(:func:`new_landmarks`: the trees the online run never mapped). At the optimum the
choices become ordinary factors (each pose's choices at most one per landmark), the
association is re-solved (:func:`place_into`), and the caller keeps it only if the
description length ``C`` fell.

Frames: world, m and rad; sightings ``[bearing, range]`` in the body frame.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import gtsam
import numpy as np
from gtsam.symbol_shorthand import L, X
from scipy.spatial import cKDTree

from lampsam.arrays import FloatArray, IntArray
from lampsam.backend.landmark_moves import fit_point, point_chi2, sighted_points, solve_association
from lampsam.backend.reassociate import Sightings, read_estimate
from lampsam.factors.gtsam_factors import pose_array
from lampsam.factors.max_mixture import max_mixture_choice, max_mixture_factor

log = logging.getLogger(__name__)

#: Landmarks farther than this (m) from where a held sighting puts its tree are never
#: its candidates (a search radius only: the threshold ``d2 < c_new`` decides).
SEARCH_RADIUS_M = 10.0


@dataclass(frozen=True)
class Placement:
    """What :func:`place_held` decided.

    Attributes:
        lid: (D,) the landmark of each left-out sighting, -1 where it stays out.
        n_candidates: (D,) its candidate count (0: no factor was added).
        values: the mixture graph's optimum (poses and landmarks).
    """

    lid: IntArray
    n_candidates: IntArray
    values: gtsam.Values


def mixture_candidates(poses: FloatArray, lms: dict[int, FloatArray], s: Sightings,
                       dk: IntArray, dz: FloatArray, dr: FloatArray, threshold: float
                       ) -> list[list[int]]:
    """The candidate landmarks of each left-out sighting.

    Args:
        poses: (K, 3) optimised poses; lms: landmark id -> (2,) position, world, m.
        s: the association (a landmark ``s`` already sights at a pose is no candidate of
            that pose's left-out sightings: mutual exclusion).
        dk: (D,) pose of each left-out sighting; dz: (D, 2) ``[bearing, range]``;
            dr: (D, 2, 2) noise.
        threshold: squared Mahalanobis distance (stated ``R``, pose fixed) below which
            a landmark is a candidate (``c_new``).

    Returns:
        For each left-out sighting, its candidates' ids, nearest first.
    """
    out: list[list[int]] = [[] for _ in range(len(dk))]
    if not len(dk) or not lms:
        return out
    ids = np.array(sorted(lms))
    xy = np.array([lms[int(i)] for i in ids])
    tree = cKDTree(xy)
    pts = sighted_points(poses[dk], dz)
    w = np.linalg.inv(dr)
    seen = {(int(k), int(i)) for k, i in zip(s.k.tolist(), s.lid.tolist(), strict=True)}
    for j, near in enumerate(tree.query_ball_point(pts, SEARCH_RADIUS_M)):
        if not near:
            continue
        cand = ids[np.asarray(near, int)]
        cand = np.array([c for c in cand.tolist() if (int(dk[j]), c) not in seen], int)
        if not len(cand):
            continue
        n = len(cand)
        d2 = point_chi2(np.repeat(poses[dk[j]][None], n, 0), np.repeat(dz[j][None], n, 0),
                        np.repeat(w[j][None], n, 0), xy[np.searchsorted(ids, cand)])
        keep = np.argsort(d2)
        out[j] = [int(cand[i]) for i in keep if d2[i] < threshold]
    return out


def held_clusters(poses: FloatArray, dk: IntArray, dz: FloatArray, dr: FloatArray,
                  gate: float) -> IntArray:
    """Group left-out sightings that one unmapped point explains (poses fixed).

    Greedy, in pose order: a sighting joins the cluster whose fitted point it fits best
    (squared Mahalanobis distance ``< gate``, stated ``R``), never one that already holds
    a sighting of its pose; otherwise it starts a cluster. A joined cluster's point is
    re-fitted (:func:`lampsam.backend.landmark_moves.fit_point`).

    Args:
        poses: (K, 3) poses; dk: (D,) pose of each left-out sighting; dz: (D, 2)
            ``[bearing, range]``; dr: (D, 2, 2) noise; gate: the join threshold (2 dof).

    Returns:
        (D,) cluster index of each sighting (0, 1, ...; a cluster of one is its own).
    """
    w: FloatArray = (np.asarray(np.linalg.inv(dr), float) if len(dk)
                     else np.zeros((0, 2, 2)))
    pts = sighted_points(poses[dk], dz) if len(dk) else np.zeros((0, 2))
    out = np.full(len(dk), -1, int)
    members: list[list[int]] = []
    centre: list[FloatArray] = []
    for j in np.argsort(dk, kind="stable").tolist():
        best, best_d2 = -1, gate
        for c, m in enumerate(members):
            if float(np.hypot(*(centre[c] - pts[j]))) > SEARCH_RADIUS_M or any(
                    dk[i] == dk[j] for i in m):
                continue
            d2 = float(point_chi2(poses[dk[j]][None], dz[j][None], w[j][None], centre[c])[0])
            if d2 < best_d2:
                best, best_d2 = c, d2
        if best < 0:
            out[j] = len(members)
            members.append([j])
            centre.append(pts[j])
            continue
        out[j] = best
        m = members[best] + [j]
        members[best] = m
        centre[best], _ = fit_point(poses[dk[m]], dz[m], w[m], centre[best])
    return out


def new_landmarks(poses: FloatArray, lms: dict[int, FloatArray], s: Sightings,
                  dk: IntArray, dz: FloatArray, dr: FloatArray, new_cost: float, gate: float,
                  unexplained: bool = False) -> dict[int, FloatArray]:
    """Unmapped trees among the left-out sightings, as candidate landmarks.

    A cluster of :func:`held_clusters` with two sightings or more becomes a candidate
    landmark (ids above every id of ``lms``) when, by the description length at fixed
    poses, a landmark there pays: ``c_new + chi2`` of the cluster at its fitted point
    below the sum over its sightings of ``min(d2 to their nearest mapped candidate,
    c_new)``.

    Args:
        unexplained: cluster only the left-out sightings that no mapped landmark explains
            (none within ``new_cost`` at fixed poses, :func:`mixture_candidates`); False:
            all of them (a mapped tree's left-out sightings may then become its copy).

    Returns:
        New landmark id -> (2,) its fitted position, world, m.
    """
    cands = mixture_candidates(poses, lms, s, dk, dz, dr, new_cost)
    use = (np.array([not c for c in cands], bool) if unexplained
           else np.ones(len(dk), bool))
    cl = np.full(len(dk), -1, int)
    if use.any():
        cl[use] = held_clusters(poses, dk[use], dz[use], dr[use], gate)
    if not len(cl) or cl.max() < 0:
        return {}
    w: FloatArray = np.asarray(np.linalg.inv(dr), float)
    top = max(lms, default=-1) + 1
    out: dict[int, FloatArray] = {}
    for c in range(int(cl.max()) + 1):
        m = np.flatnonzero(cl == c)
        if len(m) < 2:
            continue
        xy, chi2 = fit_point(poses[dk[m]], dz[m], w[m], sighted_points(poses[dk[m]], dz[m]).mean(0))
        alt = 0.0
        for j in m.tolist():
            if cands[j]:
                x = lms[cands[j][0]]
                alt += min(float(point_chi2(poses[dk[j]][None], dz[j][None], w[j][None], x)[0]),
                           new_cost)
            else:
                alt += new_cost
        if new_cost + chi2 < alt:
            out[top] = xy
            top += 1
    return out


def place_held(graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, s: Sightings,
               dk: IntArray, dz: FloatArray, dr: FloatArray, new_cost: float,
               gate: float | None = None, unexplained: bool = False) -> Placement:
    """The left-out sightings placed by max-mixture factors on the final graph.

    Args:
        graph, values: the final association's graph and its optimum.
        s: the association (``s.lid``: the landmarks in ``values``).
        dk, dz, dr: the left-out sightings (:func:`mixture_candidates`).
        new_cost: ``c_new``: the candidates' threshold and the "none" component's cost.
        gate: with a value, the left-out sightings' clusters that pay as landmarks of
            their own (:func:`new_landmarks`, joined inside ``gate``) are candidates
            too; None: only the mapped landmarks.
        unexplained: with ``gate``, only the left-out sightings no mapped landmark
            explains are clustered (:func:`new_landmarks`).

    Returns:
        The :class:`Placement`: each sighting's component at the mixture graph's LM
        optimum; where two of one pose's sightings chose one landmark, the one it
        explains better keeps it and the other stays out; a new landmark chosen by
        fewer than two sightings is not kept (they stay out).
    """
    n_kf = 0
    while values.exists(X(n_kf)):
        n_kf += 1
    poses, lms = read_estimate(values, n_kf, np.unique(s.lid).tolist())
    fresh = {} if gate is None else new_landmarks(poses, lms, s, dk, dz, dr, new_cost, gate,
                                                  unexplained)
    cands = mixture_candidates(poses, {**lms, **fresh}, s, dk, dz, dr, new_cost)
    mix = gtsam.NonlinearFactorGraph(graph)
    start = gtsam.Values(values)
    for i, xy in fresh.items():
        start.insert(L(i), gtsam.Point2(*xy))
    for j, c in enumerate(cands):
        if c:
            mix.add(max_mixture_factor(X(int(dk[j])), [L(i) for i in c], dz[j], dr[j],
                                       new_cost))
    n_cand = np.array([len(c) for c in cands], int)
    if not n_cand.any():
        return Placement(np.full(len(dk), -1, int), n_cand, values)
    v = gtsam.LevenbergMarquardtOptimizer(mix, start, gtsam.LevenbergMarquardtParams()).optimize()
    lid = np.full(len(dk), -1, int)
    cost = np.full(len(dk), np.inf)
    for j, c in enumerate(cands):
        if not c:
            continue
        i, c2 = max_mixture_choice(pose_array(v.atPose2(X(int(dk[j])))),
                                   [np.asarray(v.atPoint2(L(x)), float) for x in c],
                                   dz[j], dr[j], new_cost)
        if i >= 0:
            lid[j], cost[j] = c[i], c2
    # mutual exclusion among one pose's left-out sightings: the better one keeps it
    taken: set[tuple[int, int]] = set()
    for j in np.argsort(cost).tolist():
        if lid[j] < 0:
            continue
        key = (int(dk[j]), int(lid[j]))
        if key in taken:
            lid[j] = -1
        else:
            taken.add(key)
    for i in fresh:  # a new landmark needs two sightings
        if np.count_nonzero(lid == i) < 2:
            lid[lid == i] = -1
    log.info("max-mixture placement: %d of %d left-out sightings with candidates, %d placed "
             "(%d on %d new landmarks)", int(np.count_nonzero(n_cand)), len(dk),
             int(np.count_nonzero(lid >= 0)), int(np.count_nonzero(np.isin(lid, list(fresh)))),
             len(set(lid.tolist()) & set(fresh)))
    return Placement(lid, n_cand, v)


def place_into(prior: gtsam.NonlinearFactor, odometry: list[tuple[FloatArray, FloatArray]],
               s: Sightings, graph: gtsam.NonlinearFactorGraph, values: gtsam.Values,
               dk: IntArray, dz: FloatArray, dr: FloatArray, new_cost: float,
               gate: float | None = None, unexplained: bool = False
               ) -> tuple[Sightings, gtsam.NonlinearFactorGraph, gtsam.Values, int] | None:
    """:func:`place_held`, then the association with the placed sightings as ordinary
    factors, re-solved by LM from the mixture's optimum.

    Args:
        prior, odometry: as :func:`lampsam.backend.reassociate.build_graph`.
        s, graph, values, dk, dz, dr, new_cost, gate, unexplained: as :func:`place_held`.

    Returns:
        ``(sightings with the placed ones appended, graph, optimum, number placed)``, or
        None when none was placed. The caller compares description lengths: the
        placed sightings' chi-square against ``c_new`` each saved.
    """
    p = place_held(graph, values, s, dk, dz, dr, new_cost, gate, unexplained)
    t = p.lid >= 0
    if not t.any():
        return None
    s2 = Sightings(np.r_[s.k, dk[t]], np.r_[s.z, dz[t]], np.r_[s.r, dr[t]], np.r_[s.lid, p.lid[t]])
    poses, lms = read_estimate(p.values, len(odometry), np.unique(s2.lid).tolist())
    g2, v2, _ = solve_association(prior, odometry, s2, s2.lid, poses, lms, {}, new_cost)
    return s2, g2, v2, int(np.count_nonzero(t))
