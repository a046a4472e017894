"""Batch association without ids: re-associate every sighting against the optimised map.

The online pass (iSAM2 without ids) decides each sighting once, with the estimate it
had then. At a long revisit whose drift exceeds the gate (Victoria Park, steps
3,500-4,500: trees come back 10-20 m from their estimates) the revisited trees are
mapped a second time, and the online smoother never learns they are the same trees.
Offline, with all data, the association can be revised (issue 15):

1. optimise the graph of the current association (LM, started from the last estimate);
2. **merges**: duplicates by the joint-marginal pair test
   (:func:`duplicate_merges`), and **revisit merges**: the landmarks made over a short stretch keep their shape among
   themselves even when the whole group is offset from the old map; every group of
   ``window`` consecutive new landmarks is aligned rigidly
   (:func:`lampsam.backend.constellation.align_constellation`) to the landmarks idle
   for at least ``revisit_keyframes`` keyframes around it; a unique, well-supported
   alignment (``min_inliers``, a margin over any differently-paired hypothesis,
   rotation under ``max_rotation``) relabels its inliers' sightings to the old
   landmarks;
3. **re-association**: every keyframe's sightings are matched again against the
   optimised map (squared Mahalanobis distance with the sighting's noise ``R`` at the
   optimised pose; one landmark per sighting per keyframe, best first); a sighting
   moves to a landmark inside the ``gate`` only when its current landmark is beyond
   it;
4. landmarks left without sightings vanish; the new association is optimised and
   kept only if at most half of the moved sightings are beyond the gate at the new
   optimum (else a wrong merge: the previous association stays); repeat until the association
   stops changing (or ``passes``);
5. with ``fit_noise``, a second stage of up to ``passes`` passes: the stated sighting noise
   may be too large (Victoria Park: chi-square per dimension 0.19 at the optimum), so
   that a gate built from it lets a tree 5-8 m away take another tree's sightings (the
   second tree then has no landmark of its own). At each pass the gate's noise is the
   stated one times the sightings' variance-component factor (:func:`noise_factor`);
   the re-association uses it (the pair test keeps the stated noise: with the tightened
   gate it merged fewer split copies, measured 40 duplicated trees against 24), and a sighting beyond the new-landmark
   threshold of its own landmark and outside every gate splits off to a new landmark.
   It starts only from the converged first stage (on a map still bent by a missed
   revisit the tightened gate splits true trees), and a pass is kept only if it also
   shortens the description length ``2 E + c_new n_landmarks`` under the stated noise
   (``c_new`` = ``ambiguity``, the new-landmark threshold; the criterion of
   :mod:`lampsam.backend.noids_offline`): a split must explain its sightings better by
   more than a landmark costs (on MRCLAM, whose range errors are not Gaussian, splits
   without it broke true landmarks: 15 -> 18 mapped, 0.006 -> 0.042 m).

Frames: world, m and rad; sightings ``[bearing, range]`` in the body frame.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass

import gtsam
import numpy as np
from gtsam.symbol_shorthand import L, X
from scipy.spatial import cKDTree

from lampsam.arrays import FloatArray
from lampsam.backend.config_offline import ReassociationConfig
from lampsam.backend.constellation import align_constellation
from lampsam.backend.cpu_budget import BudgetSpent, CpuBudget, interrupt_past
from lampsam.backend.landmark_merge import CoVisibility, merge_pairs
from lampsam.backend.planar_gate import predict_point2
from lampsam.backend.pose_cov import pose_array
from lampsam.factors.gtsam_factors import odometry_factor

log = logging.getLogger(__name__)

IntArray = np.ndarray


@dataclass
class Sightings:
    """Range-bearing sightings with their current landmark.

    Attributes:
        k: (S,) keyframe index of each sighting.
        z: (S, 2) ``[bearing, range]``, rad and m.
        r: (S, 2, 2) their noise.
        lid: (S,) landmark id (the association; changed in place by :func:`refine`).
    """

    k: IntArray
    z: FloatArray
    r: FloatArray
    lid: IntArray


@dataclass(frozen=True)
class Pass:
    """What one pass did: landmarks after it, landmarks merged, sightings relabelled by
    the merges and by re-association, the graph's error at its optimum, and whether
    it was kept (rejected: more than half of the moved sightings beyond the gate at the
    new optimum, so the previous association stays and the passes stop)."""

    mapped: int
    merged_landmarks: int
    moved_by_merge: int
    moved_by_reassociation: int
    error: float
    accepted: bool = True


def build_graph(prior: gtsam.NonlinearFactor, odometry: list[tuple[FloatArray, FloatArray]],
                s: Sightings) -> gtsam.NonlinearFactorGraph:
    """The factor graph of an association.

    Args:
        prior: the start pose's prior on ``X(0)``.
        odometry: ``(delta (3,), cov (3, 3))`` of the factor into ``X(k)``, for
            k = 1..K (entry 0 is ignored).
        s: the sightings (``BearingRangeFactor2D(X(k), L(lid))`` each).
    """
    graph = gtsam.NonlinearFactorGraph()
    graph.add(prior)
    for k in range(1, len(odometry)):
        delta, cov = odometry[k]
        graph.add(odometry_factor(X(k - 1), X(k), delta, cov))
    for k, z, r, lid in zip(s.k.tolist(), s.z, s.r, s.lid.tolist(), strict=True):
        graph.add(gtsam.BearingRangeFactor2D(X(k), L(lid), gtsam.Rot2(float(z[0])), float(z[1]),
                                             gtsam.noiseModel.Gaussian.Covariance(r)))
    return graph


def _values(poses: FloatArray, lms: dict[int, FloatArray]) -> gtsam.Values:
    v = gtsam.Values()
    for k, p in enumerate(poses):
        v.insert(X(k), gtsam.Pose2(*p))
    for lid, xy in lms.items():
        v.insert(L(lid), gtsam.Point2(*xy))
    return v


def read_estimate(values: gtsam.Values, n_kf: int, lids: list[int]
                  ) -> tuple[FloatArray, dict[int, FloatArray]]:
    """``(poses (n_kf, 3) of X(0..n_kf-1), landmark id -> (2,) position of L(id))`` in
    ``values``; m, rad."""
    poses = np.array([pose_array(values.atPose2(X(k))) for k in range(n_kf)])
    return poses, {lid: np.asarray(values.atPoint2(L(lid)), float) for lid in lids}


def revisit_merges(lms: dict[int, FloatArray], s: Sightings, cfg: ReassociationConfig
                   ) -> dict[int, int]:
    """Relabelling ``{new landmark: old landmark}`` from rigid constellation alignments.

    Landmarks are ordered by their first sighting; each run of ``window`` consecutive
    ones (stride half a window) is aligned to the landmarks last seen at least
    ``revisit_keyframes`` keyframes before the run's first and within ``radius``.
    An old landmark takes at most one new one; the first accepted alignment wins.
    """
    ids = sorted(lms)
    first = {lid: int(s.k[s.lid == lid].min()) for lid in ids}
    last = {lid: int(s.k[s.lid == lid].max()) for lid in ids}
    order = sorted(ids, key=lambda i: first[i])
    out: dict[int, int] = {}
    taken: set[int] = set()
    stride = max(1, cfg.window // 2)
    for start in range(0, max(1, len(order) - cfg.window + 1), stride):
        group = [i for i in order[start:start + cfg.window] if i not in out]
        if len(group) < cfg.min_inliers:
            continue
        k0 = first[group[0]]
        src = np.array([lms[i] for i in group])
        centre = src.mean(axis=0)
        old = [i for i in ids if last[i] <= k0 - cfg.revisit_keyframes and i not in taken
               and float(np.hypot(*(lms[i] - centre))) <= cfg.radius]
        if len(old) < cfg.min_inliers:
            continue
        dst = np.array([lms[i] for i in old])
        al = align_constellation(src, dst, cfg.tol, cfg.min_inliers, cfg.margin,
                                 cfg.max_rotation)
        if al is None:
            continue
        log.info("revisit at keyframe %d: %d landmarks onto old ones (rotation %.3f rad, "
                 "shift %.1f m, rms %.2f m)", k0, len(al.pairs), al.theta,
                 float(np.hypot(*al.shift)), al.rms)
        for a, b in al.pairs:
            out[group[a]] = old[b]
            taken.add(old[b])
    return out


def pair_diff_cov(marg: gtsam.Marginals, a: int, b: int) -> FloatArray:
    """(2, 2) covariance of ``l_a - l_b`` from the joint marginal of the two planar
    landmarks ``L(a)``, ``L(b)``: ``S_aa + S_bb - S_ab - S_ba``."""
    j = marg.jointMarginalCovariance([L(a), L(b)]).fullMatrix()
    out: FloatArray = j[:2, :2] + j[2:, 2:] - j[:2, 2:] - j[2:, :2]
    return out


def duplicate_merges(graph: gtsam.NonlinearFactorGraph, values: gtsam.Values,
                     lms: dict[int, FloatArray], s: Sightings, gate: float, ambiguity: float,
                     radius: float, budget: CpuBudget | None = None) -> dict[int, int]:
    """Relabelling ``{duplicate: original}`` by the joint-marginal pair test.

    :func:`lampsam.backend.landmark_merge.merge_pairs` on the optimised map: the
    covariance of ``l_i - l_j`` from the joint marginal of the pair
    (``gtsam.Marginals`` of the whole graph, built once per call), merged below ``gate``
    only when neither has a second partner below ``ambiguity`` and the two were never
    sighted at the same keyframe (mutual exclusion); the landmark sighted first is kept.
    Pairs that their single marginals already put beyond both thresholds
    (:func:`lampsam.backend.landmark_merge.pair_bound_far`) cost no joint marginal.

    Raises:
        BudgetSpent: ``budget`` ran out while the pairs' joint marginals were computed
            (checked every :data:`BUDGET_CHECK_PAIRS` pairs).
    """
    ids = np.array(sorted(lms))
    if len(ids) < 2:
        return {}
    xy = np.array([lms[i] for i in ids])
    created = np.array([int(s.k[s.lid == i].min()) for i in ids])
    covis = CoVisibility()
    order = np.argsort(s.k, kind="stable")
    ks, ls = s.k[order], s.lid[order]
    for lo, hi in zip(np.r_[0, np.flatnonzero(np.diff(ks)) + 1],
                      np.r_[np.flatnonzero(np.diff(ks)) + 1, len(ks)], strict=True):
        covis.add_frame(ls[lo:hi].tolist())
    try:
        marg = gtsam.Marginals(graph, values)
    except RuntimeError as exc:
        log.warning("re-association: no marginals (%s): no duplicate merges this pass", exc)
        return {}

    def diff_cov(ia: IntArray, ib: IntArray) -> FloatArray:
        if budget is not None:
            budget.check("duplicate merges (joint marginals)")
        return pairs_diff_cov(marg, ids[ia], ids[ib], budget)

    sigma = landmark_sigma_max(marg, ids, budget)
    pairs = merge_pairs(ids, xy, created, diff_cov, covis.together, gate, ambiguity, radius,
                        sigma)
    log.debug("duplicate merges: %d landmarks, %d pairs merged", len(ids), len(pairs))
    return {p.drop: p.keep for p in pairs}


#: how many landmark marginals between two looks at the CPU budget
BUDGET_CHECK_PAIRS = 32
#: landmarks in one joint-marginal query of :func:`pairs_diff_cov`
JOINT_CHUNK = 120


def pairs_diff_cov(marg: gtsam.Marginals, a: IntArray, b: IntArray,
                   budget: CpuBudget | None = None) -> FloatArray:
    """(K, 2, 2) covariances of ``l_a - l_b`` for the landmark id pairs ``a``, ``b``
    (K,): :func:`pair_diff_cov` of each, from one joint marginal over the landmarks of
    up to :data:`JOINT_CHUNK` of them at a time (a marginal of a Gaussian is a
    sub-block of any larger joint marginal: one Bayes-tree query instead of one per
    pair; on pillars' online map 0.08 s for 60 pairs against 3.7 s, the blocks equal
    to 5e-14 relative). ``budget`` is checked before each query."""
    out = np.empty((len(a), 2, 2))
    n = 0
    while n < len(a):
        if budget is not None and n:
            budget.check("duplicate merges (joint marginals)")
        keys: dict[int, None] = {}
        end = n
        while end < len(a) and len(keys.keys() | {int(a[end]), int(b[end])}) <= JOINT_CHUNK:
            keys[int(a[end])] = None
            keys[int(b[end])] = None
            end += 1
        if len(keys) <= 2:  # one pair
            out[n] = pair_diff_cov(marg, int(a[n]), int(b[n]))
            n += 1
            continue
        jm = marg.jointMarginalCovariance([L(i) for i in keys])
        for m in range(n, end):
            ka, kb = L(int(a[m])), L(int(b[m]))
            # the joint holds its upper blocks only: (smaller key, larger key)
            ab = jm.at(ka, kb) if ka < kb else jm.at(kb, ka).T
            out[m] = jm.at(ka, ka) + jm.at(kb, kb) - ab - ab.T
        n = end
    return out


def landmark_sigma_max(marg: gtsam.Marginals, ids: IntArray,
                       budget: CpuBudget | None = None) -> FloatArray:
    """(M,) each planar landmark's largest marginal standard deviation, m: the square
    root of the largest eigenvalue of ``marginalCovariance(L(id))`` (an upper bound
    is all :func:`lampsam.backend.landmark_merge.pair_bound_far` needs; it is inflated
    by 1e-6 relative against rounding)."""
    out = np.empty(len(ids))
    for n, i in enumerate(ids.tolist()):
        if budget is not None and n % BUDGET_CHECK_PAIRS == 0:
            budget.check("duplicate merges (landmark marginals)")
        c = np.asarray(marg.marginalCovariance(L(int(i))), float)
        out[n] = np.sqrt(max(float(np.linalg.eigvalsh(0.5 * (c + c.T))[-1]), 0.0))
    out *= 1.0 + 1e-6
    return out


def reassociate(poses: FloatArray, lms: dict[int, FloatArray], s: Sightings, gate: float,
                switch: float = float("inf"), split: float = float("inf")) -> IntArray:
    """New landmark ids of the sightings against the optimised map (see the module doc).

    Each keyframe's sightings are matched best first (smallest squared Mahalanobis
    distance ``d2`` with the sighting's ``R`` at the optimised pose, one landmark per
    sighting per keyframe). A sighting moves to another landmark inside the ``gate``
    when its own landmark is beyond the gate, or when the other is closer by more than
    ``switch`` in ``d2`` (a neighbouring tree matched inside a gate made wide by an
    overstated noise: without it such a sighting never moves); else it keeps its own.
    A sighting beyond ``split`` of its own landmark and beyond the gate of every other is
    an offender: a landmark's offenders inside the gate of a point at the offender
    farthest from it get one new landmark together (two trees merged into one landmark
    are split; later passes sort out the rest).

    Args:
        poses: (K, 3) keyframe poses; lms: landmark id -> (2,) position.
        s: the sightings; gate: squared-distance gate (2 dof).
        switch: margin in ``d2`` for leaving a landmark inside the gate (inf: never).
        split: ``d2`` beyond which a sighting unmatched elsewhere leaves its landmark
            (inf: never).

    Returns:
        (S,) landmark ids (new landmarks: ids above every id in ``lms``).
    """
    ids = np.array(sorted(lms))
    offenders: dict[int, list[int]] = {}
    pts = np.array([lms[i] for i in ids])
    tree = cKDTree(pts)
    out = s.lid.copy()
    by_k: dict[int, list[int]] = {}
    for j, k in enumerate(s.k.tolist()):
        by_k.setdefault(k, []).append(j)
    for k, rows in by_k.items():
        pose = poses[k]
        reach = float(max(s.z[j, 1] for j in rows)) + 10.0
        near = tree.query_ball_point(pose[:2], reach)
        if not near:
            continue
        cand = ids[near]
        zhat = predict_point2(pose, pts[near])
        pairs: list[tuple[float, int, int]] = []
        cur_d2: dict[int, float] = {}
        for j in rows:
            nu = s.z[j] - zhat
            nu[:, 0] = np.arctan2(np.sin(nu[:, 0]), np.cos(nu[:, 0]))
            d2 = np.einsum("mi,ij,mj->m", nu, np.linalg.inv(s.r[j]), nu)
            for m in np.flatnonzero(d2 < gate):
                pairs.append((float(d2[m]), j, int(cand[m])))
            hit = np.flatnonzero(cand == s.lid[j])
            cur_d2[j] = float(d2[hit[0]]) if len(hit) else float("inf")
        used: set[int] = set()
        done: set[int] = set()
        # sightings that may not leave their landmark reserve it first
        for j in rows:
            if cur_d2[j] < gate and not any(d + switch < cur_d2[j] for d, jj, _ in pairs
                                            if jj == j):
                used.add(int(s.lid[j]))
                done.add(j)
        for d, j, lid in sorted(pairs):
            if j in done or lid in used:
                continue
            if lid != s.lid[j] and cur_d2[j] < gate and not d + switch < cur_d2[j]:
                continue
            out[j] = lid
            used.add(lid)
            done.add(j)
        for j in rows:
            if j not in done and cur_d2[j] > split:
                offenders.setdefault(int(s.lid[j]), []).append(j)
    # each landmark with offenders: a new landmark at the offender seen farthest from it,
    # taking the offenders inside its gate (the rest wait for the next pass)
    top = int(ids.max())
    for own, js in offenders.items():
        pts_j = np.array([_sighted_point(poses[s.k[j]], s.z[j]) for j in js])
        seed = pts_j[int(np.argmax(np.hypot(*(pts_j - lms[own]).T)))]
        top += 1
        for j in js:
            if sighting_d2(poses, {0: seed}, Sightings(s.k[j:j + 1], s.z[j:j + 1],
                                                         s.r[j:j + 1], np.zeros(1, int)))[0] < gate:
                out[j] = top
    return out


def _sighted_point(pose: FloatArray, z: FloatArray) -> FloatArray:
    """(2,) where the sighting ``z = [bearing, range]`` from ``pose`` (3,) puts its landmark."""
    a = pose[2] + z[0]
    return pose[:2] + z[1] * np.array([np.cos(a), np.sin(a)])


def sighting_d2(poses: FloatArray, lms: dict[int, FloatArray], s: Sightings) -> FloatArray:
    """(S,) squared Mahalanobis distance of each sighting from its landmark's prediction."""
    out = np.empty(len(s.k))
    for j, (k, lid) in enumerate(zip(s.k.tolist(), s.lid.tolist(), strict=True)):
        nu = s.z[j] - predict_point2(poses[k], lms[lid])[0]
        nu[0] = np.arctan2(np.sin(nu[0]), np.cos(nu[0]))
        out[j] = float(nu @ np.linalg.solve(s.r[j], nu))
    return out


#: the gate's noise is never shrunk below this variance factor
MIN_NOISE_FACTOR = 0.05


def noise_factor(d2: FloatArray) -> float:
    """Variance factor of the sightings' stated noise from their squared distances ``d2``
    (2 dof) at the optimum: ``mean(d2) / 2``, the variance-component estimate of the
    sighting group (Helmert; chi-square per residual dimension, the landmarks' share of
    the redundancy neglected: with many sightings per landmark it is small), clamped to
    ``[MIN_NOISE_FACTOR, 1]``: the gate is only ever tightened to what the data show.
    Wrong matches raise the mean, so the estimate errs towards the stated noise."""
    if len(d2) == 0:
        return 1.0
    return float(np.clip(np.mean(d2) / 2.0, MIN_NOISE_FACTOR, 1.0))


def refine(prior: gtsam.NonlinearFactor, odometry: list[tuple[FloatArray, FloatArray]],
           s: Sightings, poses: FloatArray, lms: dict[int, FloatArray], gate: float,
           ambiguity: float, cfg: ReassociationConfig,
           report: Callable[[int, Pass, FloatArray, dict[int, FloatArray]], None] | None = None,
           budget: CpuBudget | None = None
           ) -> tuple[gtsam.NonlinearFactorGraph, gtsam.Values, list[Pass]]:
    """Iterate optimise / revisit merges / re-association (module doc); ``s.lid`` is updated.

    Args:
        prior, odometry: as :func:`build_graph`.
        s: the online pass's sightings and association.
        poses: (K, 3) keyframe poses and lms: landmark positions to start from.
        gate: squared-distance gate (2 dof) of the re-association and the merges.
        ambiguity: a second merge partner below this distance blocks a merge.
        cfg: the passes' settings.
        report: called after each pass with its :class:`Pass` and the estimate.
        budget: a CPU budget (:class:`lampsam.backend.cpu_budget.CpuBudget`): checked
            before each pass and inside the duplicate merges; once spent, the pass
            under way is dropped and the last accepted association is returned (its
            ``stopped`` names the stage).

    Returns:
        ``(graph, optimised values, passes)`` of the final association.
    """
    n_kf = len(poses)
    passes: list[Pass] = []
    graph = build_graph(prior, odometry, s)
    values = _values(poses, {i: lms[i] for i in np.unique(s.lid).tolist()})
    params = gtsam.LevenbergMarquardtParams()
    values = gtsam.LevenbergMarquardtOptimizer(graph, values, params).optimize()
    fitting = False  # second stage (cfg.fit_noise): after the stated-noise passes converge
    stage_passes = 0
    while stage_passes < cfg.passes or (cfg.fit_noise and not fitting):
        if budget is not None and budget.spent(f"re-association pass {len(passes) + 1}"):
            break
        if stage_passes >= cfg.passes:  # first stage out of passes: go on to the second
            fitting, stage_passes = True, 0
        stage_passes += 1
        live = np.unique(s.lid).tolist()
        poses, lms = read_estimate(values, n_kf, live)
        # the gate's noise: the stated R, or (second stage) shrunk to the sightings' spread
        f = noise_factor(sighting_d2(poses, lms, s)) if fitting else 1.0
        try:  # the constellation alignments have no look at the budget of their own
            with interrupt_past(budget, "revisit merges"):
                relabel = revisit_merges(lms, s, cfg)
        except BudgetSpent:  # the pass under way is dropped: the last accepted stays
            break
        if cfg.merge_radius > 0:
            try:
                dup = duplicate_merges(graph, values, lms, s, gate, ambiguity,
                                       cfg.merge_radius, budget)
            except BudgetSpent:  # the pass under way is dropped: the last accepted stays
                break
            relabel.update({a: b for a, b in dup.items()
                            if a not in relabel and b not in relabel})
        before = s.lid.copy()
        lid = np.array([relabel.get(i, i) for i in s.lid.tolist()]) if relabel else s.lid.copy()
        moved_merge = int(np.count_nonzero(lid != before))
        r_gate = s.r * f
        new = reassociate(poses, {i: lms[i] for i in np.unique(lid).tolist()},
                          Sightings(s.k, s.z, r_gate, lid), gate, cfg.switch,
                          ambiguity if fitting else float("inf"))
        moved_re = int(np.count_nonzero(new != lid))
        if moved_merge == 0 and moved_re == 0:
            if cfg.fit_noise and not fitting:
                fitting, stage_passes = True, 0
                continue
            break
        g_new = build_graph(prior, odometry, Sightings(s.k, s.z, s.r, new))
        start = {i: lms[i] for i in np.unique(new).tolist() if i in lms}
        start.update({i: p for i, p in first_sight_positions(
            poses, Sightings(s.k, s.z, s.r, new)).items() if i not in start})
        v_new = gtsam.LevenbergMarquardtOptimizer(g_new, _values(poses, start), params).optimize()
        e_new = float(g_new.error(v_new))
        # most moved sightings beyond the gate at the new optimum: a wrong merge
        # somewhere; keep the previous association and stop
        moved = np.flatnonzero(new != before)
        d2 = sighting_d2(*read_estimate(v_new, n_kf, np.unique(new).tolist()),
                         Sightings(s.k[moved], s.z[moved], r_gate[moved], new[moved]))
        accepted = float(np.mean(d2 > gate)) <= 0.5 if len(d2) else True
        if fitting:  # second stage: a pass must also shorten the description length
            n_old, n_new = len(np.unique(s.lid)), len(np.unique(new))
            accepted = accepted and (2.0 * e_new + ambiguity * n_new
                                     < 2.0 * float(graph.error(values)) + ambiguity * n_old)
        p = Pass(len(np.unique(new)), len(relabel), moved_merge, moved_re, e_new, accepted)
        passes.append(p)
        if not accepted:
            log.info("re-association pass %d rejected: %d of %d moved sightings beyond the gate",
                     len(passes), int(np.sum(d2 > gate)), len(moved))
            if cfg.fit_noise and not fitting:
                fitting, stage_passes = True, 0
                continue
            break
        s.lid, graph, values = new, g_new, v_new
        if report is not None:
            report(len(passes), p, *read_estimate(values, n_kf, np.unique(s.lid).tolist()))
    return graph, values, passes


def sightings_from(records: list[tuple[int, FloatArray, FloatArray, int]]) -> Sightings:
    """:class:`Sightings` from a backend's ``(keyframe, z, R, landmark id)`` records."""
    return Sightings(np.array([r[0] for r in records], int),
                     np.array([np.asarray(r[1], float)[:2] for r in records]).reshape(-1, 2),
                     np.array([np.asarray(r[2], float)[:2, :2] for r in records]).reshape(-1, 2, 2),
                     np.array([r[3] for r in records], int))


def first_sight_positions(poses: FloatArray, s: Sightings) -> dict[int, FloatArray]:
    """Each landmark where its first sighting puts it from ``poses`` (K, 3), m."""
    out: dict[int, FloatArray] = {}
    for j in np.argsort(s.k, kind="stable").tolist():
        lid = int(s.lid[j])
        if lid not in out:
            p = poses[int(s.k[j])]
            a = p[2] + s.z[j, 0]
            out[lid] = p[:2] + s.z[j, 1] * np.array([np.cos(a), np.sin(a)])
    return out
