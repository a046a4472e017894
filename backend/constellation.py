"""Loop closure without ids: re-found landmarks recognised by their constellation.

Without ids a revisited tree is matched by the gate (eqs. 19-20) only if the
estimate's drift is inside the innovation covariance. On long outdoor loops it is
not (Victoria Park: with known ids, the EKF's own loop-closing sightings reach
squared distances of 5-200 against the 99 % gate's 9.21), so the revisited trees are
mapped a second time. Their copies keep the shape of the originals, though: the
landmarks mapped in the last few dozen steps are placed with the small *local*
drift, and a rigid 2-D transform (the accumulated drift) maps several of them onto
old landmarks at once, within the sensor's scatter. That is geometric constellation
matching (the pairwise-distance consistency of Bailey's CCDA, 2002, searched here
RANSAC-style from pairs of correspondences): :func:`match_constellation` finds the
transform, and the backends merge each copy into its original
(:func:`lampsam.backend.constellation_merge.ekf_merge` for the EKF, an equality factor in
the smoothers), which closes the loop as a known id would.

A transform is accepted only with ``min_inliers`` copies or more, each within ``tol``
of a distinct old landmark, and with no conflicting transform (one that maps one
of the copies to a different old landmark) within ``margin`` inliers of it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from lampsam.arrays import FloatArray
from lampsam.backend.covariance import LowerCovariance


@dataclass(frozen=True)
class ConstellationMatch:
    """A rigid match of recent landmarks onto old ones.

    Attributes:
        pairs: ``(index into new, index into old)`` of the inliers, one-to-one.
        rotation: rad; translation: (2,) m: ``old ~ R(rotation) new + translation``.
        rms: RMS distance of the inliers after the transform, m.
        runner_up: inliers of the best conflicting transform (0 if none).
    """

    pairs: list[tuple[int, int]]
    rotation: float
    translation: FloatArray
    rms: float
    runner_up: int


def _rot(a: FloatArray) -> FloatArray:
    """(S, 2, 2) rotation matrices of angles (S,)."""
    c, s = np.cos(a), np.sin(a)
    return np.stack([np.stack([c, -s], -1), np.stack([s, c], -1)], -2)


def match_constellation(new: FloatArray, old: FloatArray, radius: float, tol: float,
                        min_inliers: int = 4, max_angle: float = 0.3, margin: int = 2
                        ) -> ConstellationMatch | None:
    """The rigid transform that puts the most recent landmarks onto old ones.

    Hypotheses come from every two correspondences ``(i, a), (j, b)`` with
    ``|new_i - old_a| <= radius`` (and the same for ``j, b``; ``radius`` bounds the
    drift), ``| |new_j - new_i| - |old_b - old_a| | < tol``, a baseline of at least
    ``2 tol`` and a rotation within ``max_angle``; each is scored by its inliers
    (transformed new points within ``tol`` of an old one, one-to-one, nearest first).

    Args:
        new: (n, 2) positions of recently mapped landmarks, m (world frame of the estimate).
        old: (m, 2) positions of the other landmarks, m.
        radius: largest drift searched, m.
        tol: inlier distance, m (a few times the landmarks' real scatter).
        min_inliers: inliers needed.
        max_angle: largest rotation searched, rad.
        margin: the best must have at least this many more inliers than any
            conflicting transform.

    Returns:
        The match, or None (too few inliers, ambiguous, or nothing to match).
    """
    new = np.asarray(new, float).reshape(-1, 2)
    old = np.asarray(old, float).reshape(-1, 2)
    if len(new) < min_inliers or len(old) < min_inliers:
        return None
    tree = cKDTree(old)
    cand = [np.asarray(c, int) for c in tree.query_ball_point(new, radius)]
    angles: list[FloatArray] = []
    trans: list[FloatArray] = []
    for i in range(len(new)):
        if not len(cand[i]):
            continue
        for j in range(i + 1, len(new)):
            if not len(cand[j]):
                continue
            d_new = new[j] - new[i]
            length = math.hypot(*d_new)
            if length < 2.0 * tol:
                continue
            a_pts, b_pts = old[cand[i]], old[cand[j]]
            d_old = b_pts[None, :, :] - a_pts[:, None, :]  # (ka, kb, 2)
            ok = np.abs(np.hypot(d_old[..., 0], d_old[..., 1]) - length) < tol
            ok &= cand[i][:, None] != cand[j][None, :]
            if not ok.any():
                continue
            ia, ib = np.nonzero(ok)
            ang = np.arctan2(d_old[ia, ib, 1], d_old[ia, ib, 0]) - math.atan2(d_new[1], d_new[0])
            ang = (ang + math.pi) % (2.0 * math.pi) - math.pi
            keep = np.abs(ang) <= max_angle
            if not keep.any():
                continue
            ang, ia, ib = ang[keep], ia[keep], ib[keep]
            mid_old = 0.5 * (a_pts[ia] + b_pts[ib])
            mid_new = 0.5 * (new[i] + new[j])
            t = mid_old - np.einsum("sij,j->si", _rot(ang), mid_new)
            angles.append(ang)
            trans.append(t)
    if not angles:
        return None
    ang_all = np.concatenate(angles)
    t_all = np.concatenate(trans)
    moved = np.einsum("sij,nj->sni", _rot(ang_all), new) + t_all[:, None, :]  # (S, n, 2)
    dist, idx = tree.query(moved.reshape(-1, 2), distance_upper_bound=tol)
    dist = dist.reshape(len(ang_all), len(new))
    idx = idx.reshape(len(ang_all), len(new))
    inlier = np.isfinite(dist)
    counts = inlier.sum(axis=1)
    order = np.argsort(-counts, kind="stable")
    best_s = -1
    best_pairs: list[tuple[int, int]] = []
    best_cost = math.inf
    for s in order:
        if counts[s] < min_inliers or counts[s] < len(best_pairs):
            break
        pairs = _one_to_one(dist[s], idx[s])
        cost = float(sum(dist[s, i] ** 2 for i, _ in pairs))
        if len(pairs) > len(best_pairs) or (len(pairs) == len(best_pairs) and cost < best_cost):
            best_s, best_pairs, best_cost = int(s), pairs, cost
    if best_s < 0 or len(best_pairs) < min_inliers:
        return None
    best_map = dict(best_pairs)
    runner_up = 0
    for s in order:
        if counts[s] <= runner_up:
            break
        pairs = _one_to_one(dist[s], idx[s])
        if any(best_map.get(i, a) != a for i, a in pairs) or any(
                a in best_map.values() and best_map.get(i) != a for i, a in pairs):
            runner_up = max(runner_up, len(pairs))
    if len(best_pairs) - runner_up < margin:
        return None
    return ConstellationMatch(best_pairs, float(ang_all[best_s]), t_all[best_s],
                              math.sqrt(best_cost / len(best_pairs)), runner_up)


def _one_to_one(dist: FloatArray, idx: np.ndarray) -> list[tuple[int, int]]:
    """Inlier pairs ``(new, old)`` with each old landmark used once (nearest first)."""
    used: set[int] = set()
    out: list[tuple[int, int]] = []
    for i in np.argsort(dist):
        if not np.isfinite(dist[i]):
            break
        a = int(idx[i])
        if a in used:
            continue
        used.add(a)
        out.append((int(i), a))
    return sorted(out)


def equality_gain(cov: LowerCovariance, x: FloatArray, pairs: list[tuple[int, int]],
                  var: float) -> tuple[FloatArray, FloatArray] | None:
    """EKF update with the constraints ``l_a - l_b = 0`` (a copy ``b`` merged into ``a``).

    A pseudo-measurement ``z = 0 = l_a - l_b + v``, ``v ~ N(0, var I)``, per pair, all
    stacked: ``H`` is ``+I`` in ``a``'s columns and ``-I`` in ``b``'s, so
    ``P H^T = P[:, a] - P[:, b]`` and ``Psi = H P H^T + var I`` (eqs. 19-23 with this
    ``H``). The robot and every correlated landmark move with the correction, as at
    a known-id loop closure.

    Args:
        cov: the EKF covariance ``P`` (n x n).
        x: (n,) the state.
        pairs: ``(offset of a, offset of b)`` of 2-D planar landmarks.
        var: the constraint's variance, m^2 (small: the two are one tree).

    Returns:
        ``(W (n, 2K), state step (n,))`` with ``P <- P - W W^T``, or None when ``Psi``
        is not positive definite.
    """
    k = 2 * len(pairs)
    pht = np.empty((cov.n, k))
    nu = np.empty(k)
    for p, (a, b) in enumerate(pairs):
        pht[:, 2 * p : 2 * p + 2] = cov.columns(a, 2) - cov.columns(b, 2)
        nu[2 * p : 2 * p + 2] = x[b : b + 2] - x[a : a + 2]
    psi = np.empty((k, k))
    for p, (a, b) in enumerate(pairs):
        psi[2 * p : 2 * p + 2] = (pht[a : a + 2] - pht[b : b + 2]).reshape(2, k)
    psi = 0.5 * (psi + psi.T) + var * np.eye(k)
    try:
        chol = np.linalg.cholesky(psi)
    except np.linalg.LinAlgError:
        return None
    c_inv = np.linalg.inv(chol)
    w = pht @ c_inv.T
    return w, w @ (c_inv @ nu)
