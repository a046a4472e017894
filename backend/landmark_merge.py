"""Merging duplicate planar landmarks after the fact (association without ids).

Without ids, a tree seen again after a long loop can come back beyond the gate
(eq. 20) of its own landmark and start a second one. A duplicate is not final: once
both copies have been seen a few times, the difference ``l_i - l_j`` of two
landmarks has a joint distribution in the filter, and the hypothesis "they are one
tree" is the test

    ``d2 = (l_i - l_j)^T (P_ii + P_jj - P_ij - P_ji)^-1 (l_i - l_j) < chi2.ppf(p, 2)``

(the same chi-square gate as eq. 20, on the joint marginal of the pair). A pair is
merged only when the merge is unambiguous: neither landmark has a second partner
within the (wider) ambiguity gate, and the two were never seen in the same frame
(two trees seen together are two trees: mutual exclusion). The EKF applies a merge
as the pseudo-measurement ``l_i - l_j = 0`` with a tiny variance (which moves the
robot and every correlated landmark, closing the loop) and then drops ``l_j``'s rows.

Frames: world, m.
"""

from __future__ import annotations

import collections
from collections.abc import Callable, Iterable
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from lampsam.arrays import BoolArray, FloatArray, IntArray
from lampsam.backend.covariance import LowerCovariance
from lampsam.factors.geometry import mahalanobis2_2x2

#: ``diff_cov(i, j)``: (K, 2, 2) covariances of ``l_i - l_j`` for index arrays (K,).
DiffCovFn = Callable[[IntArray, IntArray], FloatArray]


@dataclass(frozen=True)
class MergePair:
    """One merge decision: ``drop`` is the same tree as ``keep`` (the older one)."""

    keep: int
    drop: int
    d2: float


class CoVisibility:
    """Which landmarks were seen in the same frame (never the same tree).

    Attributes:
        seen_with: landmark id -> ids seen in a frame with it.
    """

    def __init__(self) -> None:
        self.seen_with: dict[int, set[int]] = collections.defaultdict(set)

    def add_frame(self, ids: Iterable[int]) -> None:
        """Record one frame's landmarks (matched and new) as mutually exclusive."""
        group = set(ids)
        if len(group) > 1:
            for i in group:
                self.seen_with[i] |= group - {i}

    def together(self, a: int, b: int) -> bool:
        """Whether ``a`` and ``b`` were ever seen in the same frame."""
        return b in self.seen_with.get(a, ())

    def merge(self, keep: int, drop: int) -> None:
        """``drop`` becomes ``keep``: its exclusions move over."""
        others = self.seen_with.pop(drop, set())
        for o in others:
            self.seen_with[o].discard(drop)
            if o != keep:
                self.seen_with[o].add(keep)
                self.seen_with[keep].add(o)


def merge_pairs(ids: IntArray, xy: FloatArray, created: IntArray, diff_cov: DiffCovFn,
                exclusive: Callable[[int, int], bool], gate: float, ambiguity: float,
                radius: float, sigma_max: FloatArray | None = None) -> list[MergePair]:
    """Unambiguous duplicate pairs among M planar landmarks.

    Args:
        ids: (M,) landmark ids; xy: (M, 2) their world positions, m.
        created: (M,) step each was created (the older one is kept; ties: smaller id).
        diff_cov: covariances of ``l_i - l_j`` (joint marginal) for index arrays into
            ``ids``.
        exclusive: ``exclusive(id_a, id_b)``: never merge (seen in the same frame).
        gate: squared Mahalanobis distance below which a pair is one tree
            (``chi2.ppf(gate_prob, 2)``).
        ambiguity: a second partner below this distance makes a landmark's merge
            ambiguous (>= ``gate``; ``chi2.ppf(new_prob, 2)``).
        radius: only pairs closer than this (m) are tested (a cheap pre-selection:
            no pair farther apart is expected inside the gate).
        sigma_max: (M,) an upper bound of each landmark's largest marginal standard
            deviation, m (None: no pre-test). A pair with ``|l_i - l_j|^2 >
            max(gate, ambiguity) (s_i + s_j)^2`` is beyond both thresholds whatever
            its cross-covariance (:func:`pair_bound_far`), so ``diff_cov`` is not
            asked for it: the same pairs come out, with fewer joint marginals.

    Returns:
        Disjoint pairs, smallest distance first.
    """
    m = len(ids)
    if m < 2:
        return []
    cand = [(i, j) for i, j in sorted(cKDTree(xy).query_pairs(radius))
            if not exclusive(int(ids[i]), int(ids[j]))]
    if not cand:
        return []
    pa = np.asarray(cand, int)
    d = xy[pa[:, 0]] - xy[pa[:, 1]]
    d2 = np.full(len(pa), np.inf)
    test = (np.ones(len(pa), bool) if sigma_max is None else
            ~pair_bound_far(d, sigma_max[pa[:, 0]], sigma_max[pa[:, 1]], max(gate, ambiguity)))
    if np.any(test):
        c = diff_cov(pa[test, 0], pa[test, 1])
        dt = d[test]
        d2t, pd = mahalanobis2_2x2(dt[:, 0], dt[:, 1], c[:, 0, 0],
                                   0.5 * (c[:, 0, 1] + c[:, 1, 0]), c[:, 1, 1])
        d2[test] = np.where(pd, d2t, np.inf)
    rivals = np.zeros(m, int)
    close = d2 < ambiguity
    np.add.at(rivals, pa[close, 0], 1)
    np.add.at(rivals, pa[close, 1], 1)
    out: list[MergePair] = []
    for k in np.argsort(d2):
        if d2[k] >= gate:
            break
        i, j = int(pa[k, 0]), int(pa[k, 1])
        if rivals[i] != 1 or rivals[j] != 1:
            continue
        older_i = (created[i], ids[i]) <= (created[j], ids[j])
        keep, drop = (i, j) if older_i else (j, i)
        out.append(MergePair(int(ids[keep]), int(ids[drop]), float(d2[k])))
    return out


def pair_bound_far(d: FloatArray, s_i: FloatArray, s_j: FloatArray, threshold: float
                   ) -> BoolArray:
    """(K,) True where a pair is surely beyond ``threshold`` in squared Mahalanobis
    distance, from its (K, 2) difference ``d`` (m) and upper bounds ``s_i``, ``s_j`` (K,)
    of each landmark's largest marginal standard deviation (m).

    For any unit direction ``u``, ``u^T Cov(l_i - l_j) u = v_i + v_j - 2 c_ij`` with
    ``|c_ij| <= sqrt(v_i v_j)`` (Cauchy-Schwarz), so the largest eigenvalue of the
    difference's covariance is at most ``(s_i + s_j)^2`` and ``d2 >= |d|^2 / (s_i +
    s_j)^2``. The test uses a margin of 1e-9 relative, so rounding never drops a pair
    that is at the threshold.
    """
    bound = (np.asarray(s_i, float) + np.asarray(s_j, float)) ** 2 * threshold
    out: BoolArray = np.einsum("ki,ki->k", d, d) > bound * (1.0 + 1e-9)
    return out


def lower_diff_cov(cov: LowerCovariance, offsets: IntArray) -> DiffCovFn:
    """:data:`DiffCovFn` of landmarks at state ``offsets`` (2 rows each) of an EKF covariance."""
    rows = np.asarray(offsets, int)[:, None] + np.arange(2)[None, :]

    def diff(i: IntArray, j: IntArray) -> FloatArray:
        ri, rj = rows[i], rows[j]
        pii = cov.take(ri[:, :, None], ri[:, None, :])
        pjj = cov.take(rj[:, :, None], rj[:, None, :])
        pij = cov.take(ri[:, :, None], rj[:, None, :])
        out: FloatArray = pii + pjj - pij - np.swapaxes(pij, 1, 2)
        return out

    return diff


def equality_update(x: FloatArray, cov: LowerCovariance, oi: int, oj: int,
                    var: float = 1e-6) -> float:
    """EKF update with the pseudo-measurement ``l_i - l_j = 0`` (2 rows), in place.

    ``H = [.. I (at oi) .. -I (at oj) ..]``, ``S = H P H^T + var I``,
    ``x += P H^T S^-1 (0 - (l_i - l_j))``, ``P -= P H^T S^-1 H P`` (eqs. 21-23 with a
    linear measurement). Afterwards ``l_i`` and ``l_j`` agree to ``sqrt(var)`` and the
    caller drops ``l_j``'s rows.

    Args:
        x: (n,) state (a view into the filter's, modified).
        cov: the filter's covariance (modified).
        oi, oj: state offsets of the two landmarks.
        var: pseudo-measurement variance, m^2.

    Returns:
        The squared Mahalanobis distance of the pair before the update.
    """
    ph = cov.columns(oi, 2) - cov.columns(oj, 2)  # (n, 2) = P H^T
    s = ph[oi : oi + 2] - ph[oj : oj + 2] + var * np.eye(2)
    s = 0.5 * (s + s.T)
    nu = -(x[oi : oi + 2] - x[oj : oj + 2])
    chol = np.linalg.cholesky(s)
    w = np.linalg.solve(chol, ph.T).T  # (n, 2): W W^T = P H^T S^-1 H P
    x += ph @ np.linalg.solve(s, nu)
    cov.downdate(w)
    return float(nu @ np.linalg.solve(s, nu))


def ekf_merge_once(x: FloatArray, cov: LowerCovariance, ids: IntArray, offsets: IntArray,
                   created: IntArray, covis: CoVisibility, gate: float, ambiguity: float,
                   radius: float) -> MergePair | None:
    """Find the best unambiguous duplicate pair of an EKF map and fuse it (in place).

    One pair per call: the update moves every correlated state, so the other pairs'
    distances are stale afterwards. The caller drops ``drop``'s rows and merges its
    book-keeping.

    Args:
        x: (n,) state view; cov: its covariance.
        ids, offsets, created: (M,) the candidate planar landmarks (ids, state
            offsets, creation steps).
        covis: mutual exclusion (landmarks seen in one frame).
        gate, ambiguity, radius: as :func:`merge_pairs`.

    Returns:
        The merged pair, or None.
    """
    offsets = np.asarray(offsets, int)
    xy = x[offsets[:, None] + np.arange(2)[None, :]]
    pairs = merge_pairs(np.asarray(ids, int), xy, np.asarray(created, int),
                        lower_diff_cov(cov, offsets), covis.together, gate, ambiguity, radius)
    if not pairs:
        return None
    best = pairs[0]
    where = {int(i): int(o) for i, o in zip(ids, offsets, strict=True)}
    equality_update(x, cov, where[best.keep], where[best.drop])
    covis.merge(best.keep, best.drop)
    return best
