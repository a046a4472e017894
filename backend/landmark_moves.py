"""Merge and split landmarks by description length (offline association without ids).

The batch re-association (:mod:`lampsam.backend.reassociate`) decides whole passes: a
pass is kept when its association as a whole is better. Single landmarks can still be
wrong after it: a tree mapped twice (a split copy of the second stage, a revisit copy
the pair test left because of an ambiguous neighbour), or two trees under one landmark
(a tree whose sightings fall inside a neighbour's gate never gets its own landmark).
Here each landmark is judged on its own by the description length of
:mod:`lampsam.backend.noids_offline`,

    ``C = chi2 + c_new (n_landmarks + n_dropped)``,

``chi2`` the graph's ``2 E`` at its optimum, ``c_new = chi2_2^-1(new_prob)`` the price of
a landmark (eq. 20's new-landmark threshold):

- **merge** two landmarks never sighted at the same keyframe (mutual exclusion) when
  one point explains both sets of sightings at less than ``c_new`` extra chi-square;
- **split** a landmark in two when two points explain its sightings better by more
  than ``c_new`` plus the description of the partition, :func:`partition_cost`: the
  best of the ``2^n`` ways to share ``n`` sightings between two points always fits
  better than one point (for one Gaussian cluster by ~0.64 n in chi-square: 2/pi of
  the variance along the split), so without that price every landmark seen 30 times
  would split (measured on MRCLAM: 15 -> 25 landmarks, 0.003 -> 0.055 m).

A move is scored *locally*: the poses stay at the current optimum and only the moved
landmarks are re-fitted (:func:`fit_point`, Gauss-Newton on their range-bearing
sightings). The local chi-square is an upper bound of the chi-square after
re-optimising the whole graph from there (the optimiser only lowers it), so a move that
lowers ``C`` locally lowers it in the graph too. After each round of disjoint moves the
caller re-optimises the whole graph (:func:`lampsam.backend.noids_offline.run_candidate`)
and the next round starts from the new optimum, until no move pays.

Frames: world, m and rad; sightings ``z = [bearing, range]`` in the body frame with
covariance ``R`` (2, 2); poses ``(x, y, theta)``.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import gtsam
import numpy as np
from gtsam.symbol_shorthand import L, X
from scipy.spatial import cKDTree

from lampsam.arrays import FloatArray, IntArray
from lampsam.backend.cpu_budget import CpuBudget
from lampsam.backend.reassociate import Sightings, build_graph, read_estimate

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Move:
    """One accepted move: ``kind`` "merge" (``ids[1]`` joins ``ids[0]``) or "split"
    (``ids[0]`` gives sightings to the new ``ids[1]``); ``gain`` is the drop of the
    local description length (> 0); ``partition`` the split's :func:`partition_cost`
    (0 for a merge)."""

    kind: str
    ids: tuple[int, int]
    gain: float
    partition: float = 0.0


def point_residuals(poses: FloatArray, z: FloatArray, xy: FloatArray
                    ) -> tuple[FloatArray, FloatArray]:
    """Innovations of range-bearing sightings of one point and their Jacobians.

    Args:
        poses: (n, 3) the sighting poses; z: (n, 2) ``[bearing, range]``; xy: (2,) the
            point, world (or (n, 2): one point per sighting).

    Returns:
        ``(nu (n, 2) = z - h(pose, xy)`` with the bearing wrapped, ``h_D_xy (n, 2, 2))``:
        ``d bearing / d xy = (-dy, dx) / r^2``, ``d range / d xy = (dx, dy) / r``.
    """
    d = np.asarray(xy, float) - poses[:, :2]
    q = np.maximum(np.einsum("ni,ni->n", d, d), 1e-12)
    r = np.sqrt(q)
    nu = np.empty_like(z)
    nu[:, 0] = z[:, 0] - (np.arctan2(d[:, 1], d[:, 0]) - poses[:, 2])
    nu[:, 0] = (nu[:, 0] + np.pi) % (2 * np.pi) - np.pi
    nu[:, 1] = z[:, 1] - r
    jac = np.empty((len(z), 2, 2))
    jac[:, 0, 0], jac[:, 0, 1] = -d[:, 1] / q, d[:, 0] / q
    jac[:, 1, 0], jac[:, 1, 1] = d[:, 0] / r, d[:, 1] / r
    return nu, jac


def point_chi2(poses: FloatArray, z: FloatArray, w: FloatArray, xy: FloatArray) -> FloatArray:
    """(n,) squared Mahalanobis distances ``nu^T W nu`` of the sightings (``w`` (n, 2, 2)
    their information ``R^-1``) from the point ``xy`` (2,) (or (n, 2), one each)."""
    nu, _ = point_residuals(poses, z, xy)
    out: FloatArray = np.einsum("ni,nij,nj->n", nu, w, nu)
    return out


def fit_point(poses: FloatArray, z: FloatArray, w: FloatArray, xy0: FloatArray,
              iters: int = 15) -> tuple[FloatArray, float]:
    """The point that best explains its sightings, poses fixed (Gauss-Newton, a step
    halved until the chi-square does not rise).

    Args:
        poses: (n, 3); z: (n, 2) ``[bearing, range]``; w: (n, 2, 2) information
            ``R^-1``; xy0: (2,) start, world, m.
        iters: iterations at most (stops when the step is under 1e-6 m).

    Returns:
        ``(xy (2,), chi2)``: the point and ``sum nu^T W nu`` there.
    """
    xy = np.asarray(xy0, float).copy()
    chi2 = float(point_chi2(poses, z, w, xy).sum())
    for _ in range(iters):
        nu, jac = point_residuals(poses, z, xy)
        jw = np.einsum("nki,nkl->nil", jac, w)  # J^T W
        h = np.einsum("nil,nlj->ij", jw, jac)
        g = np.einsum("nil,nl->i", jw, nu)
        try:
            step = np.linalg.solve(h, g)
        except np.linalg.LinAlgError:
            break
        for _ in range(8):
            cand = xy + step
            c = float(point_chi2(poses, z, w, cand).sum())
            if c <= chi2:
                break
            step = 0.5 * step
        else:
            break
        xy, chi2 = cand, c
        if float(np.hypot(*step)) < 1e-6:
            break
    return xy, chi2


def sighted_points(poses: FloatArray, z: FloatArray) -> FloatArray:
    """(n, 2) where each sighting puts its landmark, world."""
    a = poses[:, 2] + z[:, 0]
    return poses[:, :2] + z[:, 1:2] * np.c_[np.cos(a), np.sin(a)]


def partition_cost(n0: int, n1: int) -> float:
    """Description length of sharing ``n0 + n1`` sightings between two landmarks, in
    chi-square units (``2 x`` nats, as ``chi2 = 2 x`` the negative log-likelihood):
    ``2 n H(n0 / n)``, ``H`` the binary entropy in nats (each sighting's label)."""
    n = n0 + n1
    p = np.array([n0, n1], float) / n
    p = p[p > 0]
    return float(-2.0 * n * np.sum(p * np.log(p)))


def best_split(poses: FloatArray, z: FloatArray, w: FloatArray, xy: FloatArray,
               min_side: int = 2, iters: int = 10
               ) -> tuple[float, IntArray, FloatArray, FloatArray] | None:
    """The best two-point explanation of one landmark's sightings (poses fixed).

    Two-means in the sightings' own metric: seeded at the landmark and at the point
    its worst-fitting sighting puts it (then at the sighted point farthest from the
    landmark), each sighting goes to the point it fits better, both points are
    re-fitted (:func:`fit_point`), until the assignment stops changing.

    Args:
        poses, z, w: as :func:`fit_point` (n sightings); xy: (2,) the landmark now.
        min_side: sightings each side needs.

    Returns:
        ``(chi2 of the two points, side (n,) 0/1, xy0, xy1)`` of the better seed, or
        None (fewer than ``2 min_side`` sightings, or every seed leaves a side short).
    """
    n = len(z)
    if n < 2 * min_side:
        return None
    pts = sighted_points(poses, z)
    d2 = point_chi2(poses, z, w, xy)
    seeds = [pts[int(np.argmax(d2))], pts[int(np.argmax(np.hypot(*(pts - xy).T)))]]
    best: tuple[float, IntArray, FloatArray, FloatArray] | None = None
    for seed in seeds:
        a, b = np.asarray(xy, float), seed
        side = np.full(n, -1)
        for _ in range(iters):
            new = (point_chi2(poses, z, w, b) < point_chi2(poses, z, w, a)).astype(int)
            if np.count_nonzero(new == 0) < min_side or np.count_nonzero(new == 1) < min_side:
                side = new
                break
            if np.array_equal(new, side):
                break
            side = new
            a, _ = fit_point(poses[side == 0], z[side == 0], w[side == 0], a)
            b, _ = fit_point(poses[side == 1], z[side == 1], w[side == 1], b)
        if np.count_nonzero(side == 0) < min_side or np.count_nonzero(side == 1) < min_side:
            continue
        c = float(point_chi2(poses[side == 0], z[side == 0], w[side == 0], a).sum()
                  + point_chi2(poses[side == 1], z[side == 1], w[side == 1], b).sum())
        if best is None or c < best[0]:
            best = (c, side, a, b)
    return best


def cost_moves(poses: FloatArray, k: IntArray, z: FloatArray, r: FloatArray, lid: IntArray,
               lms: dict[int, FloatArray], new_cost: float, radius: float,
               min_side: int = 2) -> tuple[IntArray, dict[int, FloatArray], list[Move]]:
    """One round of disjoint merges and splits that each lower the description length.

    Splits are scored first (each landmark's best two-point explanation must save more
    than ``new_cost`` and the partition's description), then merges among the landmarks no split touched: every pair
    closer than ``radius`` and never sighted at one keyframe, re-fitted as one point;
    it pays when the chi-square rises by less than ``new_cost``. Moves are applied best
    first, at most one within ``radius`` of another per round: the poses stay fixed, and
    one wrong landmark bends the poses around it, so that its neighbours' sightings fit
    worse and splitting them seems to pay until the graph is re-optimised.

    Args:
        poses: (K, 3) keyframe poses at the current optimum.
        k: (S,) keyframe of each sighting; z: (S, 2); r: (S, 2, 2) noise; lid: (S,)
            landmark of each sighting.
        lms: landmark id -> (2,) position at the optimum.
        new_cost: ``c_new``, the description length of one landmark.
        radius: merge candidates closer than this, m.
        min_side: sightings each side of a split needs.

    Returns:
        ``(new lid (S,), positions of the moved and new landmarks, the moves)``; new
        landmarks get ids above every id in ``lms``.
    """
    w: FloatArray = np.asarray(np.linalg.inv(r), float)
    pk = poses[k]
    rows = {int(i): np.flatnonzero(lid == i) for i in np.unique(lid)}
    chi2 = {i: float(point_chi2(pk[j], z[j], w[j], lms[i]).sum()) for i, j in rows.items()}
    cand: list[tuple[float, str, int, int, FloatArray, IntArray, FloatArray]] = []
    none_side = np.zeros(0, int)
    for i, j in rows.items():
        sp = best_split(pk[j], z[j], w[j], lms[i], min_side)
        if sp is None:
            continue
        price = new_cost + partition_cost(int(np.sum(sp[1] == 0)), int(np.sum(sp[1] == 1)))
        if chi2[i] - sp[0] > price:
            cand.append((price - (chi2[i] - sp[0]), "split", i, -1, sp[2], sp[1], sp[3]))
    ids = np.array(sorted(rows))
    xy = np.array([lms[int(i)] for i in ids])
    kset = {i: set(k[j].tolist()) for i, j in rows.items()}
    for a, b in sorted(cKDTree(xy).query_pairs(radius)):
        ia, ib = int(ids[a]), int(ids[b])
        if kset[ia] & kset[ib]:
            continue  # seen together: two trees
        j = np.r_[rows[ia], rows[ib]]
        na, nb = len(rows[ia]), len(rows[ib])
        start = (na * lms[ia] + nb * lms[ib]) / (na + nb)
        p, c = fit_point(pk[j], z[j], w[j], start)
        rise = c - chi2[ia] - chi2[ib]
        if rise < new_cost:
            cand.append((rise - new_cost, "merge", ia, ib, p, none_side, p))
    out = lid.copy()
    moved: dict[int, FloatArray] = {}
    moves: list[Move] = []
    busy: set[int] = set()
    near_moved: list[FloatArray] = []  # where this round's moves are
    top = int(ids.max()) if len(ids) else -1
    for score, kind, ia, ib, pa, side, pb in sorted(cand, key=lambda c: c[0]):
        here = lms[ia]
        if ia in busy or ib in busy or any(
                float(np.hypot(*(here - q))) < radius for q in near_moved):
            continue
        near_moved.append(here)
        if kind == "split":
            top += 1
            out[rows[ia][side == 1]] = top
            moved[ia], moved[top] = pa, pb
            busy.add(ia)
            moves.append(Move("split", (ia, top), -score, partition_cost(
                int(np.sum(side == 0)), int(np.sum(side == 1)))))
        else:
            older = (int(k[rows[ia]].min()), ia) <= (int(k[rows[ib]].min()), ib)
            keep, drop = (ia, ib) if older else (ib, ia)
            out[rows[drop]] = keep
            moved[keep] = pa
            busy |= {ia, ib}
            moves.append(Move("merge", (keep, drop), -score))
    return out, moved, moves


def description_cost(graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, lid: IntArray,
                     new_cost: float) -> float:
    """``2 E + new_cost n_landmarks`` of an association at ``values``."""
    return 2.0 * float(graph.error(values)) + new_cost * len(np.unique(lid))


def solve_association(prior: gtsam.NonlinearFactor, odometry: list[tuple[FloatArray, FloatArray]],
                      s: Sightings, new: IntArray, poses: FloatArray, lms: dict[int, FloatArray],
                      moved: dict[int, FloatArray], new_cost: float
                      ) -> tuple[gtsam.NonlinearFactorGraph, gtsam.Values, float]:
    """The graph of the association ``new``, its LM optimum from ``poses`` and the
    landmarks (``moved`` first, else ``lms``), and its ``2 E + new_cost n``."""
    g_new = build_graph(prior, odometry, Sightings(s.k, s.z, s.r, new))
    start = gtsam.Values()
    for kk in range(len(odometry)):
        start.insert(X(kk), gtsam.Pose2(*poses[kk]))
    for i in np.unique(new).tolist():
        start.insert(L(i), gtsam.Point2(*(moved[i] if i in moved else lms[i])))
    v_new = gtsam.LevenbergMarquardtOptimizer(g_new, start,
                                              gtsam.LevenbergMarquardtParams()).optimize()
    return g_new, v_new, description_cost(g_new, v_new, new, new_cost)


def refine_by_cost(prior: gtsam.NonlinearFactor, odometry: list[tuple[FloatArray, FloatArray]],
                   s: Sightings, graph: gtsam.NonlinearFactorGraph, values: gtsam.Values,
                   new_cost: float, radius: float, rounds: int = 10,
                   budget: CpuBudget | None = None
                   ) -> tuple[gtsam.NonlinearFactorGraph, gtsam.Values, list[Move]]:
    """Rounds of :func:`cost_moves`, each followed by LM on the whole graph (module doc).

    A round is kept only if ``2 E + new_cost n_landmarks`` of the re-optimised graph
    plus the partition costs of its splits is below the previous one (it is by
    construction unless LM fails); ``s.lid`` is updated in place.

    Args:
        prior, odometry: as :func:`lampsam.backend.reassociate.build_graph`.
        s: the sightings and their association; graph, values: its graph and optimum.
        new_cost: ``c_new``; radius: merge candidates closer than this, m.
        rounds: rounds at most.
        budget: a CPU budget, checked before each round; once spent, the rounds stop
            and the last accepted one is kept.

    Returns:
        ``(graph, values, accepted moves)`` of the final association.
    """
    n_kf = len(odometry)
    moves: list[Move] = []
    c_old = description_cost(graph, values, s.lid, new_cost)
    for n in range(rounds):
        if budget is not None and budget.spent(f"description-length round {n + 1}"):
            break
        poses, lms = read_estimate(values, n_kf, np.unique(s.lid).tolist())
        new, moved, round_moves = cost_moves(poses, s.k, s.z, s.r, s.lid, lms, new_cost, radius)
        if not round_moves:
            break
        g_new, v_new, c_new = solve_association(prior, odometry, s, new, poses, lms, moved, new_cost)
        log.info("description-length round: %d merges, %d splits, C %.1f -> %.1f",
                 sum(m.kind == "merge" for m in round_moves),
                 sum(m.kind == "split" for m in round_moves), c_old, c_new)
        if not c_new + sum(m.partition for m in round_moves) < c_old:
            break
        s.lid, graph, values, c_old = new, g_new, v_new, c_new
        moves.extend(round_moves)
    return graph, values, moves
