"""Errors in a map's own frame: the map-to-world rigid transform, fitted on landmarks.

A map built by SLAM lives in the frame of its mapping run's first pose. Its landmarks
are then a few millimetres and hundredths of a degree off the world as a whole (one
common error, the map frame's offset) plus each landmark's own error. A robot that
localizes on the map tracks in the map's frame: its world-frame error cannot be
smaller than the map frame's offset, which no run can observe (a known start pose
ties the map to the world only where that run starts). Two readings of one
trajectory are therefore reported (docs/ceiling-map.md):

- world frame: poses against the truth as they are;
- map frame: poses first moved by ``truth_T_map``, the SE(2) transform that takes the
  map's landmarks onto their true positions in the least-squares sense, fitted on the
  landmarks only (never on the trajectory, which would hide the tracking's own error).

The fit is the weighted 2-D Procrustes problem (Umeyama 1991 restricted to a
rotation about ``z``): with centroids ``m_s = sum w s / sum w``, ``m_d`` likewise and
deviations ``s'``, ``d'``,
``theta = atan2(sum w (s'_x d'_y - s'_y d'_x), sum w (s'_x d'_x + s'_y d'_y))`` and
``t = m_d - R(theta) m_s``; it is exact when the points differ by a rigid motion.
Frames: ``truth_T_map`` maps map-frame coordinates ``p`` to world ``R p + t``; units
m and rad.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from lampsam.arrays import FloatArray, IntArray
from lampsam.factors.geometry import rigid_fit_2d


class AlignmentInputError(ValueError):
    """Point sets that cannot be aligned (shapes, too few pairs, non-finite values)."""


@dataclass(frozen=True)
class MapAlignment:
    """The fitted map-to-world transform and how well the landmarks agree with it.

    Attributes:
        truth_T_map: (3,) ``(x, y, theta)`` taking map-frame points to the world, m, rad.
        residual_rms_m: RMS of the landmarks' residual after the transform (their own
            errors, the map's distortion), m.
        n_pairs: landmark pairs the transform was fitted on.
        n_lamps: of which lamps.
    """

    truth_T_map: FloatArray
    residual_rms_m: float
    n_pairs: int
    n_lamps: int


def fit_se2(src: FloatArray, dst: FloatArray, weights: FloatArray | None = None) -> FloatArray:
    """Least-squares rigid 2-D transform ``T`` with ``dst ~ R(theta) src + t``.

    Args:
        src: (N, 2) points in the source (map) frame, m, N >= 2.
        dst: (N, 2) the same points in the destination (world) frame, m.
        weights: (N,) non-negative weights (default 1), at least two positive.

    Returns:
        (3,) ``(t_x, t_y, theta)``: ``dst_T_src``.

    Raises:
        AlignmentInputError: shapes differ, fewer than 2 points, non-finite values or
            weights that are negative or leave fewer than 2 points.
    """
    s = np.asarray(src, dtype=np.float64)
    d = np.asarray(dst, dtype=np.float64)
    if s.ndim != 2 or s.shape[1] != 2 or s.shape != d.shape:
        raise AlignmentInputError(f"need two (N, 2) arrays of the same shape, got {s.shape} and {d.shape}")
    w = np.ones(len(s)) if weights is None else np.asarray(weights, dtype=np.float64)
    if w.shape != (len(s),):
        raise AlignmentInputError(f"weights must have shape ({len(s)},), got {w.shape}")
    if not (np.all(np.isfinite(s)) and np.all(np.isfinite(d)) and np.all(np.isfinite(w))):
        raise AlignmentInputError("points and weights must be finite")
    if np.any(w < 0) or np.count_nonzero(w) < 2:
        raise AlignmentInputError("need at least 2 points with positive weight and no negative weight")
    return rigid_fit_2d(s, d, w)


def transform_points(T: FloatArray, xy: FloatArray) -> FloatArray:
    """(N, 2) points moved by ``T = (t_x, t_y, theta)``: ``R p + t``."""
    c, s = math.cos(float(T[2])), math.sin(float(T[2]))
    p = np.asarray(xy, dtype=np.float64)
    return np.column_stack([T[0] + c * p[:, 0] - s * p[:, 1], T[1] + s * p[:, 0] + c * p[:, 1]])


def transform_poses(T: FloatArray, poses: FloatArray) -> FloatArray:
    """(N, 3) poses ``(x, y, theta)`` composed on the left with ``T``: ``T * pose``."""
    p = np.asarray(poses, dtype=np.float64)
    out = np.empty_like(p)
    out[:, :2] = transform_points(T, p[:, :2])
    out[:, 2] = p[:, 2] + float(T[2])
    return out


def pair_with_truth(map_xy: FloatArray, map_kinds: Sequence[str], true_xy: FloatArray,
                    true_kinds: Sequence[str], max_dist: float) -> tuple[IntArray, IntArray]:
    """Mutual nearest pairs of map and true landmarks of one kind within ``max_dist``.

    A kind matches when the true kind starts with the map's (``lamp`` pairs with
    ``lamp_rect``, ``lamp_round`` ...; ``corner`` with ``corner``).

    Args:
        map_xy: (L, 2) map landmark positions, m. map_kinds: (L,) their kinds.
        true_xy: (T, 2) true landmark positions, m. true_kinds: (T,) their kinds.
        max_dist: the largest distance of a pair, m.

    Returns:
        ``(map indices (P,), true indices (P,))``.
    """
    mx = np.asarray(map_xy, dtype=np.float64).reshape(-1, 2)
    tx = np.asarray(true_xy, dtype=np.float64).reshape(-1, 2)
    out_m: list[int] = []
    out_t: list[int] = []
    for kind in sorted(set(map_kinds)):
        mi = np.array([i for i, k in enumerate(map_kinds) if k == kind], dtype=np.int64)
        ti = np.array([i for i, k in enumerate(true_kinds) if str(k).startswith(kind)], dtype=np.int64)
        if len(mi) == 0 or len(ti) == 0:
            continue
        d = np.linalg.norm(mx[mi, None, :] - tx[None, ti, :], axis=2)
        best_t = np.argmin(d, axis=1)
        best_m = np.argmin(d, axis=0)
        for a, b in enumerate(best_t):
            if best_m[b] == a and d[a, b] <= max_dist:
                out_m.append(int(mi[a]))
                out_t.append(int(ti[b]))
    return np.asarray(out_m, dtype=np.int64), np.asarray(out_t, dtype=np.int64)


def map_to_truth(map_xy: FloatArray, map_kinds: Sequence[str], true_xy: FloatArray,
                 true_kinds: Sequence[str], max_dist: float = 0.05, trim: float = 5.0,
                 rounds: int = 3) -> MapAlignment | None:
    """The map-to-world transform fitted on a map's landmarks against the truth.

    Landmarks are paired by :func:`pair_with_truth` (mutual nearest of one kind
    within ``max_dist``). The kinds are not equally precise (on the lab maps, lamps
    are 1.3 mm RMS from the truth after the frame, corners about 5 mm, and some
    frontend corners on lamp or item edges pair with a true corner centimetres
    away), so the fit is iteratively reweighted: each round weights every pair by
    ``1 / var_kind`` (the mean squared residual of its kind's kept pairs in the
    previous round; the first round is unweighted) and keeps the pairs whose
    residual is at most ``trim`` times their kind's median residual.

    Args:
        map_xy: (L, 2) map landmark positions in the map's frame, m.
        map_kinds: (L,) ``"lamp"`` or ``"corner"``.
        true_xy: (T, 2) true positions, world frame, m. true_kinds: (T,) true kinds.
        max_dist: pairing radius, m (default 5 cm: the maps' frame offsets are a few mm).
        trim: residual cut, a multiple of the kind's median residual.
        rounds: reweighting rounds after the first fit.

    Returns:
        The :class:`MapAlignment`, or None with fewer than 3 pairs.
    """
    im, it = pair_with_truth(map_xy, map_kinds, true_xy, true_kinds, max_dist)
    if len(im) < 3:
        return None
    src = np.asarray(map_xy, dtype=np.float64)[im]
    dst = np.asarray(true_xy, dtype=np.float64)[it]
    kinds = np.array([map_kinds[int(i)] for i in im])
    keep = np.ones(len(src), dtype=bool)
    w = np.ones(len(src))
    T = fit_se2(src, dst)
    for _ in range(rounds):
        r = np.linalg.norm(transform_points(T, src) - dst, axis=1)
        new_keep = np.zeros(len(src), dtype=bool)
        for kind in set(kinds.tolist()):
            of = kinds == kind
            new_keep[of] = r[of] <= trim * float(np.median(r[of & keep] if np.any(of & keep) else r[of]))
            sel = of & new_keep
            w[of] = 1.0 / max(float(np.mean(r[sel] ** 2)) if np.any(sel) else 1.0, 1e-12)
        if np.count_nonzero(new_keep) < 3:
            break
        keep = new_keep
        T = fit_se2(src[keep], dst[keep], w[keep])
    r = np.linalg.norm(transform_points(T, src[keep]) - dst[keep], axis=1)
    return MapAlignment(T, float(np.sqrt(np.mean(r**2))), int(np.count_nonzero(keep)),
                        int(np.count_nonzero(keep & (kinds == "lamp"))))
