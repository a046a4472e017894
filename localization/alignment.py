"""SVD alignment of matched 3-D points, with RANSAC over the correspondences.

Paper 2 (``seeds/global-localization-environment-map.txt``), eqs. 1-6: the map's
3-D feature points ``S_i`` (world frame) and the current Kinect frame's points
``K_i`` (body frame) matched by SIFT descriptor are aligned by

1. centroids ``mu_S = mean S_i``, ``mu_K = mean K_i`` (eq. 1);
2. deviations ``S'_i = S_i - mu_S``, ``K'_i = K_i - mu_K`` (eq. 2);
3. ``W = sum_i S'_i K'_i^T`` (eq. 3), ``W = U Sigma V^T`` (eq. 4);
4. ``R = U V^T``, ``T = mu_S - R mu_K`` (eq. 5).

Corrections (DESIGN.md section 2): when ``det(U V^T) = -1`` the product is a
reflection, not a rotation; the fix is ``R = U diag(1, 1, det(U V^T)) V^T``
(Umeyama 1991). Eq. 6 as printed averages the *signed* residual vectors, which
is identically zero at the least-squares solution (the centroids coincide), so
this module reports ``eps`` as the **RMS of the per-point residual norms**,
``eps = sqrt(mean_i |S_i - (R K_i + T)|^2)`` in metres, over the inliers.

SIFT matches include wrong ones, so :func:`ransac_align` draws minimal samples
(3 correspondences; 2 in the planar variant) with a seeded generator, scores
each hypothesis by its inlier count (residual norm below a threshold), and
refits eqs. 1-5 on the best inlier set.

The planar variant (:func:`align_planar`) estimates a yaw-only rotation about
world ``z`` and a translation. It is the right model for this robot: both point
sets are referenced to the floor (world ``z = 0`` is the floor and the body
frame's origin is on the floor, ``docs/conventions.md``), and the robot cannot
roll or pitch, so a full 3-D rotation only adds three degrees of freedom that
noise and wrong matches can use; the minimal sample also drops from 3 to 2
correspondences, which makes RANSAC need far fewer draws at a given outlier
ratio.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from lampsam.arrays import BoolArray, FloatArray
from lampsam.errors import LocalizationError

log = logging.getLogger(__name__)


class AlignmentError(LocalizationError):
    """Alignment cannot be computed (too few or malformed correspondences)."""


@dataclass(frozen=True)
class RansacConfig:
    """RANSAC over correspondences.

    Attributes:
        inlier_threshold: residual norm (m) under which a correspondence is an
            inlier of a hypothesis. Default 0.10 m (Kinect depth noise at 3 m is
            a few cm; SIFT keypoint localisation adds a few more).
        max_iterations: upper bound on the number of hypotheses. Default 500.
        confidence: stop early once the probability of having drawn an
            all-inlier sample reaches this. Default 0.999.
        min_inliers: fewer inliers than this = no alignment. Default 5.
        planar: yaw-only rotation (robot on the floor, see module docstring).
            Default True.
    """

    inlier_threshold: float = 0.10
    max_iterations: int = 500
    confidence: float = 0.999
    min_inliers: int = 5
    planar: bool = True


@dataclass(frozen=True)
class Alignment:
    """Result of aligning body-frame points ``K`` onto world-frame points ``S``.

    Attributes:
        R: (3, 3) rotation ``world_R_body``.
        t: (3,) translation ``world_t_body`` (m); ``S_i ~ R K_i + t``.
        eps: RMS residual norm over the inliers (m), eq. 6 as a norm.
        inliers: (N,) bool, the correspondences consistent with (R, t).
    """

    R: FloatArray
    t: FloatArray
    eps: float
    inliers: BoolArray

    @property
    def n_inliers(self) -> int:
        """Number of inlier correspondences."""
        return int(np.count_nonzero(self.inliers))

    def pose2(self) -> FloatArray:
        """The planar robot pose ``world_T_body = (x, y, theta)`` of this alignment.

        Returns:
            (3,) x, y (m) from ``t`` and theta (rad, in (-pi, pi]) the yaw of ``R``.
        """
        theta = float(np.arctan2(self.R[1, 0], self.R[0, 0]))
        return np.array([self.t[0], self.t[1], theta])


def _check_pairs(S: FloatArray, K: FloatArray, n_min: int) -> tuple[FloatArray, FloatArray]:
    S = np.asarray(S, dtype=float)
    K = np.asarray(K, dtype=float)
    if S.ndim != 2 or S.shape[1] != 3 or S.shape != K.shape:
        raise AlignmentError(
            f"need two (N, 3) arrays of matched points, got {S.shape} and {K.shape}"
        )
    if S.shape[0] < n_min:
        raise AlignmentError(f"need at least {n_min} correspondences, got {S.shape[0]}")
    if not (np.all(np.isfinite(S)) and np.all(np.isfinite(K))):
        raise AlignmentError("matched points contain NaN or inf")
    return S, K


def kabsch_batch(S: FloatArray, K: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Eqs. 1-5 for a batch of point sets, with the reflection fix.

    Args:
        S: (B, n, 3) world-frame points, n >= 3.
        K: (B, n, 3) body-frame points matched to ``S``.

    Returns:
        R (B, 3, 3) rotations with det +1 and t (B, 3) such that
        ``S ~ R K + t`` in the least-squares sense.
    """
    mu_S = S.mean(axis=1)  # eq. 1
    mu_K = K.mean(axis=1)
    Sp = S - mu_S[:, None, :]  # eq. 2
    Kp = K - mu_K[:, None, :]
    W = np.einsum("bni,bnj->bij", Sp, Kp)  # eq. 3: sum S' K'^T
    U, _, Vt = np.linalg.svd(W)  # eq. 4
    d = np.sign(np.linalg.det(U @ Vt))
    d[d == 0] = 1.0
    D = np.zeros_like(W)
    D[:, 0, 0] = 1.0
    D[:, 1, 1] = 1.0
    D[:, 2, 2] = d  # reflection fix: det(R) = +1
    R = U @ D @ Vt  # eq. 5
    t = mu_S - np.einsum("bij,bj->bi", R, mu_K)
    return R, t


def planar_batch(S: FloatArray, K: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Yaw-only version of eqs. 1-5 for a batch of point sets.

    The 2-D Procrustes problem on the ``x, y`` coordinates has the closed form
    ``yaw = atan2(sum (K'_x S'_y - K'_y S'_x), sum (K'_x S'_x + K'_y S'_y))``;
    ``t_z`` is the mean height difference.

    Args:
        S: (B, n, 3) world-frame points, n >= 2.
        K: (B, n, 3) body-frame points.

    Returns:
        R (B, 3, 3) rotations about ``z`` and t (B, 3).
    """
    mu_S = S.mean(axis=1)
    mu_K = K.mean(axis=1)
    Sp = S - mu_S[:, None, :]
    Kp = K - mu_K[:, None, :]
    sin_sum = np.sum(Kp[..., 0] * Sp[..., 1] - Kp[..., 1] * Sp[..., 0], axis=1)
    cos_sum = np.sum(Kp[..., 0] * Sp[..., 0] + Kp[..., 1] * Sp[..., 1], axis=1)
    yaw = np.arctan2(sin_sum, cos_sum)
    c, s = np.cos(yaw), np.sin(yaw)
    R = np.zeros((S.shape[0], 3, 3))
    R[:, 0, 0] = c
    R[:, 0, 1] = -s
    R[:, 1, 0] = s
    R[:, 1, 1] = c
    R[:, 2, 2] = 1.0
    t = mu_S - np.einsum("bij,bj->bi", R, mu_K)
    return R, t


def residual_norms(S: FloatArray, K: FloatArray, R: FloatArray, t: FloatArray) -> FloatArray:
    """Per-correspondence residual norms ``|S_i - (R K_i + t)|`` (m).

    Args:
        S: (N, 3) world points. K: (N, 3) body points. R: (3, 3). t: (3,).

    Returns:
        (N,) residual norms in metres.
    """
    return np.linalg.norm(S - (K @ R.T + t), axis=1)


def _fit(S: FloatArray, K: FloatArray, planar: bool) -> tuple[FloatArray, FloatArray]:
    fit = planar_batch if planar else kabsch_batch
    R, t = fit(S[None], K[None])
    return R[0], t[0]


def _align_all(S: FloatArray, K: FloatArray, planar: bool) -> Alignment:
    """:func:`align` (``planar`` False, 3 pairs or more) or :func:`align_planar` (True, 2)."""
    S, K = _check_pairs(S, K, 2 if planar else 3)
    R, t = _fit(S, K, planar)
    r = residual_norms(S, K, R, t)
    return Alignment(R, t, float(np.sqrt(np.mean(r**2))), np.ones(len(S), dtype=bool))


def align(S: FloatArray, K: FloatArray) -> Alignment:
    """Least-squares rigid alignment of all correspondences (eqs. 1-6, no RANSAC).

    Args:
        S: (N, 3) map points, world frame (m), N >= 3.
        K: (N, 3) current points, body frame (m), matched row by row to ``S``.

    Returns:
        The :class:`Alignment` with every correspondence an inlier.

    Raises:
        AlignmentError: fewer than 3 pairs, shape mismatch or non-finite input.
    """
    return _align_all(S, K, planar=False)


def align_planar(S: FloatArray, K: FloatArray) -> Alignment:
    """Least-squares yaw-only alignment of all correspondences.

    Args:
        S: (N, 3) map points, world frame (m), N >= 2.
        K: (N, 3) current points, body frame (m).

    Returns:
        The :class:`Alignment` (rotation about ``z`` only).

    Raises:
        AlignmentError: fewer than 2 pairs, shape mismatch or non-finite input.
    """
    return _align_all(S, K, planar=True)


def ransac_iterations(inlier_ratio: float, sample_size: int, confidence: float) -> int:
    """Draws needed to get one all-inlier sample with probability ``confidence``.

    Args:
        inlier_ratio: fraction of correct correspondences, in (0, 1].
        sample_size: minimal sample size (3, or 2 planar).
        confidence: in (0, 1).

    Returns:
        ``ceil(log(1 - confidence) / log(1 - inlier_ratio ** sample_size))``, at least 1.
    """
    p_good = inlier_ratio**sample_size
    if p_good >= 1.0:
        return 1
    if p_good <= 0.0:
        return np.iinfo(np.int32).max
    return max(1, int(np.ceil(np.log(1.0 - confidence) / np.log(1.0 - p_good))))


def ransac_align(
    S: FloatArray, K: FloatArray, rng: np.random.Generator, config: RansacConfig
) -> Alignment:
    """Robust alignment: RANSAC over correspondences, then refit on the inliers.

    Hypotheses are generated and scored in vectorised batches of minimal samples
    (eqs. 1-5 on 3 pairs, or the planar closed form on 2); the best (most
    inliers, ties broken by the smaller summed clipped residual) is refitted on
    its inliers, and the inlier set recomputed once more with the refit.

    Args:
        S: (N, 3) map points, world frame (m).
        K: (N, 3) current points, body frame (m), matched row by row.
        rng: seeded generator for the samples.
        config: thresholds and iteration bounds.

    Returns:
        The :class:`Alignment`; ``eps`` is the RMS residual over its inliers.

    Raises:
        AlignmentError: too few pairs, or fewer than ``config.min_inliers`` inliers.
    """
    n_min = 2 if config.planar else 3
    S, K = _check_pairs(S, K, max(n_min, config.min_inliers))
    n = S.shape[0]
    fit = planar_batch if config.planar else kabsch_batch
    thr = config.inlier_threshold
    best_count, best_cost = -1, np.inf
    best_R, best_t = np.eye(3), np.zeros(3)
    needed = config.max_iterations
    drawn = 0
    batch = 64
    while drawn < min(needed, config.max_iterations):
        b = min(batch, config.max_iterations - drawn)
        # sample without replacement inside each hypothesis
        idx = np.argsort(rng.random((b, n)), axis=1)[:, :n_min]
        R, t = fit(S[idx], K[idx])
        pred = np.einsum("bij,nj->bni", R, K) + t[:, None, :]
        r = np.linalg.norm(S[None] - pred, axis=2)  # (b, n)
        inl = r < thr
        counts = inl.sum(axis=1)
        costs = np.minimum(r, thr).sum(axis=1)
        order = np.lexsort((costs, -counts))
        k = order[0]
        if counts[k] > best_count or (counts[k] == best_count and costs[k] < best_cost):
            best_count, best_cost = int(counts[k]), float(costs[k])
            best_R, best_t = R[k], t[k]
            needed = ransac_iterations(best_count / n, n_min, config.confidence)
        drawn += b
    inliers = residual_norms(S, K, best_R, best_t) < thr
    if np.count_nonzero(inliers) < max(n_min, config.min_inliers):
        raise AlignmentError(
            f"RANSAC found {int(np.count_nonzero(inliers))} inliers of {n} "
            f"(need {config.min_inliers})"
        )
    for _ in range(2):  # refit on inliers, then re-select once
        R, t = _fit(S[inliers], K[inliers], config.planar)
        new_inliers = residual_norms(S, K, R, t) < thr
        if np.count_nonzero(new_inliers) < max(n_min, config.min_inliers):
            break
        inliers = new_inliers
    R, t = _fit(S[inliers], K[inliers], config.planar)
    r = residual_norms(S[inliers], K[inliers], R, t)
    eps = float(np.sqrt(np.mean(r**2)))
    log.debug("RANSAC: %d/%d inliers after %d draws, eps %.3f m", inliers.sum(), n, drawn, eps)
    return Alignment(R, t, eps, inliers)
