"""The last pass of offline association without ids: single sightings, and merges with the
poses free, by description length.

The batch re-association (:mod:`lampsam.backend.reassociate`) moves a sighting only when
its landmark is beyond the gate, and keeps or drops a pass as a whole; the merges and
splits of :mod:`lampsam.backend.landmark_moves` are scored with the poses fixed. Two
kinds of error survive both (Victoria Park, docs/noids-offline.md):

- a sighting inside the gate of a neighbouring tree's landmark that its own tree's
  landmark explains better (:func:`sighting_moves`);
- a tree mapped twice where a revisit was missed: the copy and the poses that saw it
  are offset together, so the merge only pays once the poses move
  (:func:`joint_merge_candidates`, tried with LM on the whole graph).

Every move is judged by the description length of :mod:`lampsam.backend.noids_offline`,
``C = chi2 + c_new (n_landmarks + n_dropped)``, and kept only if the re-optimised graph's
``C`` fell (:func:`refine_final`). The pipeline runs it once, on the chosen candidate.

Frames: world, m and rad; sightings ``z = [bearing, range]`` in the body frame with
covariance ``R`` (2, 2); poses ``(x, y, theta)``.
"""

from __future__ import annotations

import logging

import gtsam
import numpy as np
from gtsam.symbol_shorthand import L
from scipy.spatial import cKDTree

from lampsam.arrays import FloatArray, IntArray
from lampsam.backend.landmark_moves import (
    Move,
    description_cost,
    fit_point,
    partition_cost,
    point_chi2,
    refine_by_cost,
    sighted_points,
    solve_association,
)
from lampsam.backend.reassociate import Sightings, pairs_diff_cov, read_estimate

log = logging.getLogger(__name__)


def sighting_moves(poses: FloatArray, k: IntArray, z: FloatArray, r: FloatArray, lid: IntArray,
                   lms: dict[int, FloatArray], new_cost: float, gate: float
                   ) -> tuple[IntArray, dict[int, FloatArray], list[Move]]:
    """One round of single-sighting moves that each lower the description length.

    The re-association passes move a sighting only when its landmark is beyond the gate
    (:func:`lampsam.backend.reassociate.reassociate`), and a pass is kept or dropped as a
    whole, so a sighting inside the gate of a neighbouring tree's landmark stays there
    even when its own tree's landmark explains it better. Here every sighting with
    another landmark inside its gate (squared Mahalanobis distance ``d2 < gate`` with
    its stated ``R``, at the optimised pose) closer than its own, or with its own
    landmark beyond the gate, is scored on its own: moving it from landmark ``a`` to
    ``b`` changes the description length by

        ``dC = chi2(a without it) - chi2(a) + chi2(b with it) - chi2(b) - c_new [a emptied]
        + P(n_a - 1, n_b + 1) - P(n_a, n_b)``,

    each ``chi2`` the landmark's sightings at their best point with the poses fixed
    (:func:`fit_point`: an upper bound of the re-optimised graph's, module doc), ``P``
    the description of the two landmarks' labels
    (:func:`lampsam.backend.landmark_moves.partition_cost`); ``b`` must not already be
    sighted at the sighting's keyframe (mutual exclusion). A sighting beyond the gate
    of its own landmark may also start a new landmark (``+ c_new + P(n_a - 1, 1)``, its
    own chi-square 0). Without ``P`` the moves split a landmark one sighting per
    round, the split's price unpaid (measured on a seeded 400-pose simulated log:
    landmarks drained into copies of their own tree). Moves with ``dC < 0`` are
    applied best first, each landmark in at most one move per round.

    Args:
        poses: (K, 3) keyframe poses at the current optimum.
        k: (S,) keyframe of each sighting; z: (S, 2) ``[bearing, range]``; r: (S, 2, 2)
            noise; lid: (S,) landmark of each sighting.
        lms: landmark id -> (2,) position at the optimum, world, m.
        new_cost: ``c_new``; gate: squared-distance gate (2 dof).

    Returns:
        ``(new lid (S,), positions of the changed and new landmarks, the moves)``; a move
        is ``Move("sighting", (from, to), gain, P change)``, new landmarks get ids above every id
        in ``lms``.
    """
    w: FloatArray = np.asarray(np.linalg.inv(r), float)
    pk = poses[k]
    rows = {int(i): np.flatnonzero(lid == i) for i in np.unique(lid)}
    ids = np.array(sorted(rows))
    if len(ids) == 0:
        return lid.copy(), {}, []
    xy = np.array([lms[int(i)] for i in ids])
    tree = cKDTree(xy)
    fits: dict[int, tuple[FloatArray, float]] = {}

    def fitted(i: int) -> tuple[FloatArray, float]:
        if i not in fits:
            fits[i] = fit_point(pk[rows[i]], z[rows[i]], w[rows[i]], lms[i], iters=5)
        return fits[i]

    pts = sighted_points(pk, z)
    own = point_chi2(pk, z, w, np.array([lms[int(i)] for i in lid.tolist()]))
    # every (sighting, other landmark within 10 m of where it puts its landmark) pair
    near = tree.query_ball_point(pts, 10.0)
    pj = np.repeat(np.arange(len(k)), [len(x) for x in near])
    pb = ids[np.concatenate([np.asarray(x, int) for x in near])] if len(pj) else pj
    index = {int(i): n for n, i in enumerate(ids)}
    # not its own landmark, nor one already sighted at its keyframe (mutual exclusion)
    span = int(ids.max()) + 1
    seen = np.asarray(k, np.int64) * span + lid
    keep_pair = (pb != lid[pj]) & ~np.isin(np.asarray(k[pj], np.int64) * span + pb, seen)
    pj, pb = pj[keep_pair], pb[keep_pair]
    d2 = point_chi2(pk[pj], z[pj], w[pj], xy[[index[int(b)] for b in pb.tolist()]]) \
        if len(pj) else np.zeros(0)
    ok = (d2 < gate) & ((d2 < own[pj]) | (own[pj] >= gate))
    targets: dict[int, list[int]] = {}
    for j, b in zip(pj[ok].tolist(), pb[ok].tolist(), strict=True):
        targets.setdefault(j, []).append(b)
    cand: list[tuple[float, int, int, int, FloatArray, FloatArray, float]] = []
    top = int(ids.max())
    new_xy = np.zeros(2)
    for j in sorted(set(targets) | set(np.flatnonzero(own >= gate).tolist())):
        a = int(lid[j])
        rest = rows[a][rows[a] != j]
        xa, ca = fitted(a)
        if len(rest):
            xa2, ca2 = fit_point(pk[rest], z[rest], w[rest], xa, iters=5)
        else:
            xa2, ca2 = xa, 0.0
        release = ca2 - ca - (new_cost if len(rest) == 0 else 0.0)
        na = len(rows[a])
        for b in targets.get(j, []):
            xb, cb = fitted(b)
            jb = np.r_[rows[b], j]
            xb2, cb2 = fit_point(pk[jb], z[jb], w[jb], xb, iters=5)
            nb = len(rows[b])
            price = partition_cost(na - 1, nb + 1) - partition_cost(na, nb)
            dc = release + cb2 - cb + price
            if dc < 0:
                cand.append((dc, j, a, b, xa2, xb2, price))
        if own[j] >= gate and len(rest):
            price = partition_cost(na - 1, 1)
            dc = release + new_cost + price
            if dc < 0:
                cand.append((dc, j, a, -1, xa2, new_xy, price))
    out = lid.copy()
    moved: dict[int, FloatArray] = {}
    moves: list[Move] = []
    busy: set[int] = set()
    for dc, j, a, b, xa2, xb2, price in sorted(cand, key=lambda c: c[0]):
        if a in busy or b in busy:
            continue
        if b < 0:
            top += 1
            b, xb2 = top, pts[j]
        out[j] = b
        busy |= {a, b}
        if np.any(out == a):
            moved[a] = xa2
        moved[b] = xb2
        moves.append(Move("sighting", (a, b), -dc, price))
    return out, moved, moves


def joint_merge_candidates(graph: gtsam.NonlinearFactorGraph, values: gtsam.Values,
                           k: IntArray, lid: IntArray, new_cost: float, radius: float
                           ) -> list[tuple[float, list[tuple[int, int]]]]:
    """Merges that would pay once the poses move with them.

    :func:`cost_moves` scores a merge with the poses fixed. Where a revisit was missed,
    the copies made there are offset together with the poses that saw them (Victoria
    Park: five trees mapped twice 1.5-4.4 m apart, fixed-pose rises 20-327 in
    chi-square), and no merge pays until the poses move. To first order the rise after
    re-optimising the whole graph is the squared Mahalanobis distance of the stacked
    differences ``D = (l_a - l_b, ...)`` under the landmarks' joint marginal,
    ``d2 = D^T (A P A^T)^-1 D`` (``A`` the difference operator; for one pair the pair
    test of :mod:`lampsam.backend.landmark_merge`). A block of ``m`` merges saves
    ``m c_new``, so it is worth trying when ``d2 < m c_new``; only single pairs
    (``m = 1``) are returned (blocks of pairs whose later copies were sighted over
    overlapping keyframes were measured on Victoria Park and did not pay:
    docs/noids-offline.md).

    Args:
        graph, values: the association's graph and its optimum.
        k: (S,) keyframe of each sighting; lid: (S,) landmark of each sighting.
        new_cost: ``c_new``; radius: pairs closer than this, m.

    Returns:
        ``(d2 - c_new, [(keep, drop)])`` for every pair closer than ``radius``, never
        sighted at one keyframe, with ``d2 < c_new``, most negative first; ``keep`` is
        the landmark sighted first.
    """
    rows = {int(i): np.flatnonzero(lid == i) for i in np.unique(lid)}
    ids = np.array(sorted(rows))
    if len(ids) < 2:
        return []
    xy = {int(i): np.asarray(values.atPoint2(L(int(i))), float) for i in ids}
    kset = {i: set(k[j].tolist()) for i, j in rows.items()}
    tree = cKDTree(np.array([xy[int(i)] for i in ids]))
    pairs = [(int(ids[a]), int(ids[b])) for a, b in sorted(tree.query_pairs(radius))
             if not kset[int(ids[a])] & kset[int(ids[b])]]
    if not pairs:
        return []
    try:
        marg = gtsam.Marginals(graph, values)
    except RuntimeError as exc:
        log.warning("joint merges: no marginals (%s)", exc)
        return []

    ordered = [(a, b) if (min(kset[a]), a) <= (min(kset[b]), b) else (b, a) for a, b in pairs]
    first, second = np.array(ordered, int).T
    covs = pairs_diff_cov(marg, first, second)  # joint marginals in chunks, not one per pair
    out: list[tuple[float, list[tuple[int, int]]]] = []
    for pair, c in zip(ordered, covs, strict=True):
        d = xy[pair[0]] - xy[pair[1]]
        try:
            d2 = float(d @ np.linalg.solve(0.5 * (c + c.T), d))
        except np.linalg.LinAlgError:
            continue
        if d2 < new_cost:
            out.append((d2 - new_cost, [pair]))
    return sorted(out)


def refine_final(prior: gtsam.NonlinearFactor, odometry: list[tuple[FloatArray, FloatArray]],
                 s: Sightings, graph: gtsam.NonlinearFactorGraph, values: gtsam.Values,
                 new_cost: float, radius: float, gate: float, rounds: int = 30
                 ) -> tuple[gtsam.NonlinearFactorGraph, gtsam.Values, list[Move]]:
    """The last pass on the chosen association: single sightings and merges with the
    poses free, each kept only if the re-optimised description length falls.

    Rounds of :func:`sighting_moves` (each followed by LM on the whole graph, kept if
    ``2 E + new_cost n_landmarks`` fell) until none pays; then the merges whose
    linearised rise with the poses free is below ``c_new``
    (:func:`joint_merge_candidates`), one at a time, smallest first, each re-optimised
    until one lowers ``C`` (a pair refused is not tried again); after an accepted one,
    :func:`refine_by_cost` (the merges it makes possible) and the sighting rounds again.
    ``s.lid`` is updated in place.

    Args:
        prior, odometry, s, graph, values, new_cost, radius: as :func:`refine_by_cost`.
        gate: squared-distance gate (2 dof) of the sighting moves.
        rounds: LM re-solves at most (sighting rounds and merges tried).

    Returns:
        ``(graph, values, accepted moves)`` of the final association.
    """
    n_kf = len(odometry)
    moves: list[Move] = []
    c_old = description_cost(graph, values, s.lid, new_cost)
    tried: set[tuple[int, int]] = set()
    n_solved = 0
    while n_solved < rounds:
        poses, lms = read_estimate(values, n_kf, np.unique(s.lid).tolist())
        new, moved, round_moves = sighting_moves(poses, s.k, s.z, s.r, s.lid, lms, new_cost,
                                                 gate)
        if round_moves:
            n_solved += 1
            g_new, v_new, c_new = solve_association(prior, odometry, s, new, poses, lms, moved, new_cost)
            log.info("sighting moves: %d, C %.1f -> %.1f", len(round_moves), c_old, c_new)
            if c_new + sum(m.partition for m in round_moves) < c_old:
                s.lid, graph, values, c_old = new, g_new, v_new, c_new
                moves.extend(round_moves)
                continue
        accepted = False
        for score, ((keep, drop),) in joint_merge_candidates(graph, values, s.k, s.lid,
                                                             new_cost, radius):
            if (keep, drop) in tried or n_solved >= rounds:
                continue
            tried.add((keep, drop))
            n_solved += 1
            new = np.where(s.lid == drop, keep, s.lid)
            g_new, v_new, c_new = solve_association(prior, odometry, s, new, poses, lms, {}, new_cost)
            log.info("merge %d <- %d with the poses free (d2 - c_new %.1f): C %.1f -> %.1f",
                     keep, drop, score, c_old, c_new)
            if c_new < c_old:
                moves.append(Move("merge", (keep, drop), c_old - c_new))
                s.lid, graph, values, c_old = new, g_new, v_new, c_new
                accepted = True
                break
        if not accepted:
            break
        graph, values, more = refine_by_cost(prior, odometry, s, graph, values, new_cost,
                                             radius)
        moves.extend(more)
        c_old = description_cost(graph, values, s.lid, new_cost)
    return graph, values, moves


def readmit(poses: FloatArray, lms: dict[int, FloatArray], s: Sightings, dk: IntArray,
            dz: FloatArray, dr: FloatArray, new_cost: float) -> IntArray:
    """Landmarks for sightings the online pass left out, where taking one back pays.

    The online pass drops a sighting that falls between its gate and the new-landmark
    threshold (neither a match nor a new landmark); the description length charges each
    dropped sighting ``c_new``. Against the optimised map a dropped sighting whose
    squared Mahalanobis distance to a landmark is ``d2 < c_new`` costs less matched
    (``d2``, to first order) than dropped. Each keyframe's dropped sightings take their
    landmarks best first, one sighting per landmark, and never a landmark the keyframe
    already sights (mutual exclusion).

    Args:
        poses: (K, 3) keyframe poses; lms: landmark id -> (2,) position, world, m.
        s: the recorded sightings and their landmarks.
        dk: (D,) keyframe of each dropped sighting; dz: (D, 2) ``[bearing, range]``;
            dr: (D, 2, 2) their noise.
        new_cost: ``c_new``.

    Returns:
        (D,) landmark id of each dropped sighting, -1 where it stays dropped.
    """
    out = np.full(len(dk), -1, int)
    if len(dk) == 0 or not lms:
        return out
    ids = np.array(sorted(lms))
    xy = np.array([lms[int(i)] for i in ids])
    tree = cKDTree(xy)
    w = np.linalg.inv(dr)
    pts = sighted_points(poses[dk], dz)
    taken = {(int(a), int(b)) for a, b in zip(s.k.tolist(), s.lid.tolist(), strict=True)}
    pairs: list[tuple[float, int, int]] = []
    for j in range(len(dk)):
        near = tree.query_ball_point(pts[j], 10.0)
        for m in near:
            d2 = float(point_chi2(poses[dk[j]][None], dz[j][None], w[j][None], xy[m])[0])
            if d2 < new_cost:
                pairs.append((d2, j, int(ids[m])))
    for _, j, b in sorted(pairs):
        if out[j] < 0 and (int(dk[j]), b) not in taken:
            out[j] = b
            taken.add((int(dk[j]), b))
    return out
