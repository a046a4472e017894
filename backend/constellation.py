"""Revisit detection by constellation: a 2-D rigid alignment of recent landmarks to the map.

At a revisit whose drift exceeds the filter's covariance, the trees seen again are
mapped a second time (beyond every gate of eq. 20), but among themselves the new
copies keep their shape: a few landmarks made over a short window are related to the
old map by one rigid motion (rotation ``theta``, shift ``t``). Here every pair of
recent landmarks is paired with every old pair of about the same length (within
``tol``), each such correspondence gives a rigid motion (both orientations), and the
motion is scored by its inliers: recent landmarks that land within ``tol`` of a
distinct old landmark (one-to-one, nearest first). This is RANSAC with every minimal
sample enumerated (deterministic). The answer is accepted only with at least
``min_inliers`` inliers and when no hypothesis that pairs the landmarks differently
comes within ``margin`` inliers of it (a unique answer; a rival shares fewer than
half of its pairs with the best), and the motion is refined by
least squares on the inliers (Arun et al. 1987).

Frames: world, m and rad.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from lampsam.arrays import FloatArray
from lampsam.factors.geometry import rigid_fit_2d


@dataclass(frozen=True)
class Alignment:
    """A rigid motion taking recent landmarks onto old ones.

    Attributes:
        theta: rotation, rad; shift: (2,) translation, m (``dst ~ R(theta) src + shift``).
        pairs: (src index, dst index) of the inliers.
        runner_up: inliers of the best hypothesis pairing the landmarks differently.
        rms: RMS residual of the inliers after the least-squares fit, m.
    """

    theta: float
    shift: FloatArray
    pairs: tuple[tuple[int, int], ...]
    runner_up: int
    rms: float


def _inliers(moved: FloatArray, tree: cKDTree, tol: float) -> list[tuple[int, int]]:
    """One-to-one (src, dst) pairs within ``tol``, nearest first."""
    dist, idx = tree.query(moved, distance_upper_bound=tol)
    order = np.argsort(dist)
    used: set[int] = set()
    out: list[tuple[int, int]] = []
    for i in order:
        if not np.isfinite(dist[i]) or int(idx[i]) in used:
            continue
        used.add(int(idx[i]))
        out.append((int(i), int(idx[i])))
    return out


def rank_hypotheses(src: FloatArray, dst: FloatArray, tol: float,
                    max_rotation: float = math.pi) -> list[tuple[int, frozenset[tuple[int, int]],
                                                                 list[tuple[int, int]]]]:
    """Every distinct pairing with 3+ inliers, most inliers first (see the module doc).

    Args: as :func:`align_constellation`.

    Returns:
        ``(n inliers, pairs as a set, pairs nearest first)`` per hypothesis.
    """
    src = np.asarray(src, float).reshape(-1, 2)
    dst = np.asarray(dst, float).reshape(-1, 2)
    if len(src) < 2 or len(dst) < 2:
        return []
    tree = cKDTree(dst)
    ii, jj = np.triu_indices(len(dst), 1)
    dlen = np.linalg.norm(dst[jj] - dst[ii], axis=1)
    order = np.argsort(dlen)
    dlen, ii, jj = dlen[order], ii[order], jj[order]
    hyps: list[tuple[int, frozenset[tuple[int, int]], list[tuple[int, int]]]] = []
    seen: set[frozenset[tuple[int, int]]] = set()
    for a, b in zip(*np.triu_indices(len(src), 1), strict=True):
        v = src[b] - src[a]
        length = float(np.hypot(*v))
        if length < tol:
            continue  # too short to fix a rotation
        lo, hi = np.searchsorted(dlen, [length - tol, length + tol])
        for c, d in zip(ii[lo:hi], jj[lo:hi], strict=True):
            for p, q in ((c, d), (d, c)):
                w = dst[q] - dst[p]
                theta = math.atan2(v[0] * w[1] - v[1] * w[0], v[0] * w[0] + v[1] * w[1])
                if abs(theta) > max_rotation:
                    continue
                cth, sth = math.cos(theta), math.sin(theta)
                rot = np.array([[cth, -sth], [sth, cth]])
                shift = dst[p] - rot @ src[a]
                pairs = _inliers(src @ rot.T + shift, tree, tol)
                key = frozenset(pairs)
                if len(pairs) >= 3 and key not in seen:
                    seen.add(key)
                    hyps.append((len(pairs), key, pairs))
    hyps.sort(key=lambda h: -h[0])
    return hyps


def best_apart(hyps: Iterable[tuple[int, frozenset[tuple[int, int]], list[tuple[int, int]]]],
               key: frozenset[tuple[int, int]]) -> int:
    """Inliers of the best hypothesis that pairs most of its landmarks differently
    from ``key`` (shares fewer than half of its pairs with it); 0 without any."""
    return max((n for n, k, _ in hyps if 2 * len(k & key) < len(k)), default=0)


def best_and_rival(hyps: list[tuple[int, frozenset[tuple[int, int]], list[tuple[int, int]]]]
                   ) -> tuple[int, int]:
    """Inliers of the best hypothesis and of its best rival (:func:`best_apart`);
    ``(0, 0)`` without any."""
    if not hyps:
        return 0, 0
    n_best, key_best, _ = hyps[0]
    return n_best, best_apart(hyps[1:], key_best)


def align_constellation(src: FloatArray, dst: FloatArray, tol: float, min_inliers: int,
                        margin: int = 2, max_rotation: float = math.pi) -> Alignment | None:
    """The unique rigid motion taking most of ``src`` onto ``dst`` (see the module doc).

    Args:
        src: (N, 2) recent landmarks (their shape is trusted); dst: (M, 2) old landmarks.
        tol: inlier distance and pair-length tolerance, m (the map's non-rigidity).
        min_inliers: inliers needed (>= 3: two points always fit).
        margin: the best must beat every differently-paired hypothesis by this many.
        max_rotation: hypotheses rotating more than this (rad) are skipped (the
            heading drift the caller can believe).

    Returns:
        The alignment, or None (too few inliers, or not unique).
    """
    src = np.asarray(src, float).reshape(-1, 2)
    dst = np.asarray(dst, float).reshape(-1, 2)
    hyps = rank_hypotheses(src, dst, tol, max_rotation)
    n_best, runner = best_and_rival(hyps)
    if not hyps or n_best < min_inliers or n_best - runner < margin:
        return None
    pairs_best = hyps[0][2]
    s_idx = np.array([p[0] for p in pairs_best])
    d_idx = np.array([p[1] for p in pairs_best])
    fit = rigid_fit_2d(src[s_idx], dst[d_idx])
    theta, shift = float(fit[2]), fit[:2]
    c, s = math.cos(theta), math.sin(theta)
    res = src[s_idx] @ np.array([[c, -s], [s, c]]).T + shift - dst[d_idx]
    rms = float(np.sqrt(np.mean(np.sum(res * res, axis=1))))
    return Alignment(theta, shift, tuple(sorted(pairs_best)), runner, rms)
