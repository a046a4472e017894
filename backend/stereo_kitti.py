"""Stereo two-point relative pose on real KITTI images: tracking, pair selection, check.

The image processing here (corner detection, left-right matching, tracking) is
frontend work; it lives beside the stereo estimators because ``frontend/`` is
owned by others (see the report). It uses OpenCV only:
Shi-Tomasi corners (``goodFeaturesToTrack``) in the left image, pyramidal
Lucas-Kanade optical flow for left(k-1) -> left(k) tracking and for left -> right
matching on the rectified pair, each with a forward-backward check; a stereo
match must stay on the same row (rectified) and have positive disparity.

Two-point procedure (paper 3 on real data): at an anchor frame ``a`` pick two
well-separated tracked points with valid stereo; the target frame ``{O}`` is the
rig frame at ``a`` and the target points are their triangulated positions there.
At each later frame the raw two-point solver (eq. 2 inverse + Gauss-Newton on
eq. 5) gives the rig pose in ``{O}``, i.e. the planar motion ``a -> k``, compared
with KITTI's ground truth. When a point is lost, a new pair is chosen at the
last frame where the old pair was valid, and the estimates are chained.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import cv2
import numpy as np
from lampsam.arrays import BoolArray, FloatArray, ImageU8
from lampsam.backend.stereo import OK, StereoEstimatorConfig, triangulate_two_points
from lampsam.datasets.kitti import KittiStereoSequence
from lampsam.datasets.stereo_sim import StereoRig
from lampsam.factors.stereo import (
    camera_point,
    rot2,
    stereo_project,
    triangulate_point,
    two_point_measurement,
)

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class TrackConfig:
    """Corner tracking and stereo matching settings (OpenCV).

    Attributes:
        max_corners: corners detected per (re-)detection.
        quality: ``goodFeaturesToTrack`` quality level (fraction of the best).
        min_distance_px: minimum spacing of corners, px.
        redetect_below: detect new corners when fewer tracks remain.
        win_px: Lucas-Kanade window size, px; levels: pyramid levels.
        fb_max_px: forward-backward error limit, px.
        row_max_px: a stereo match may differ in row by at most this, px.
        min_disparity_px: smallest accepted disparity, px.
        border_px: drop points closer than this to the image border, px.
    """

    max_corners: int = 500
    quality: float = 0.01
    min_distance_px: float = 12.0
    redetect_below: int = 250
    win_px: int = 21
    levels: int = 4
    fb_max_px: float = 0.5
    row_max_px: float = 1.0
    min_disparity_px: float = 1.0
    border_px: float = 10.0


@dataclass(frozen=True)
class StereoTracks:
    """Tracked points over a sequence: ``M`` tracks, ``N`` frames.

    Attributes:
        u_left, u_right, v: (N, M) left/right column and row, px (0 where absent).
        seen: (N, M) bool, the track is in the left image at that frame.
        stereo: (N, M) bool, it also has a valid right match.
    """

    u_left: FloatArray
    u_right: FloatArray
    v: FloatArray
    seen: BoolArray
    stereo: BoolArray


def _lk(a: ImageU8, b: ImageU8, pts: FloatArray, cfg: TrackConfig,
        guess: FloatArray | None = None) -> tuple[FloatArray, BoolArray]:
    """Pyramidal LK ``a -> b`` with a forward-backward check: points (K, 2), ok (K,)."""
    if len(pts) == 0:
        return pts.reshape(0, 2), np.zeros(0, dtype=bool)
    p0 = pts.astype(np.float32).reshape(-1, 1, 2)
    win = (cfg.win_px, cfg.win_px)
    crit = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 30, 0.01)
    init = p0.copy() if guess is None else guess.astype(np.float32).reshape(-1, 1, 2)
    use_init = cv2.OPTFLOW_USE_INITIAL_FLOW
    p1, st1, _ = cv2.calcOpticalFlowPyrLK(a, b, p0, init, winSize=win, maxLevel=cfg.levels,
                                          criteria=crit, flags=use_init)
    p0b, st2, _ = cv2.calcOpticalFlowPyrLK(b, a, p1, p0.copy(), winSize=win,
                                           maxLevel=cfg.levels, criteria=crit, flags=use_init)
    fb = np.linalg.norm((p0b - p0).reshape(-1, 2), axis=1)
    ok = (st1.ravel() == 1) & (st2.ravel() == 1) & (fb < cfg.fb_max_px)
    return p1.reshape(-1, 2).astype(float), ok


def track_sequence(seq: KittiStereoSequence, cfg: TrackConfig | None = None) -> StereoTracks:
    """Track corners through the left images and match each to the right image.

    Args:
        seq: the KITTI sequence.
        cfg: tracking settings.

    Returns:
        The tracks (see :class:`StereoTracks`).
    """
    cfg = cfg or TrackConfig()
    n = len(seq)
    rows: list[dict[int, tuple[float, float, float, bool]]] = []
    ids = np.zeros(0, dtype=int)
    pts = np.zeros((0, 2))
    next_id = 0
    prev_left: ImageU8 | None = None
    w, h = seq.width, seq.height
    for k in range(n):
        left, right = seq.load_pair(k)
        if prev_left is not None and len(pts):
            pts, ok = _lk(prev_left, left, pts, cfg)
            inside = ((pts[:, 0] > cfg.border_px) & (pts[:, 0] < w - cfg.border_px)
                      & (pts[:, 1] > cfg.border_px) & (pts[:, 1] < h - cfg.border_px))
            keep = ok & inside
            pts, ids = pts[keep], ids[keep]
        if len(pts) < cfg.redetect_below:
            mask = np.full((h, w), 255, np.uint8)
            for p in pts:
                cv2.circle(mask, (int(p[0]), int(p[1])), int(cfg.min_distance_px), 0, -1)
            new = cv2.goodFeaturesToTrack(left, cfg.max_corners, cfg.quality,
                                          cfg.min_distance_px, mask=mask)
            if new is not None:
                new = new.reshape(-1, 2).astype(float)
                pts = np.vstack([pts, new])
                ids = np.concatenate([ids, np.arange(next_id, next_id + len(new))])
                next_id += len(new)
        # left -> right on the rectified pair; guess a 20 px disparity
        guess = pts - np.array([20.0, 0.0])
        pr, ok = _lk(left, right, pts, cfg, guess)
        disp = pts[:, 0] - pr[:, 0]
        good = ok & (np.abs(pr[:, 1] - pts[:, 1]) < cfg.row_max_px) & (disp > cfg.min_disparity_px)
        rows.append({int(i): (p[0], r[0], p[1], bool(g))
                     for i, p, r, g in zip(ids, pts, pr, good, strict=True)})
        prev_left = left
    m = next_id
    u_l, u_r, v = np.zeros((n, m)), np.zeros((n, m)), np.zeros((n, m))
    seen, stereo = np.zeros((n, m), bool), np.zeros((n, m), bool)
    for k, row in enumerate(rows):
        for i, (ul, ur, vv, g) in row.items():
            u_l[k, i], u_r[k, i], v[k, i], seen[k, i], stereo[k, i] = ul, ur, vv, True, g
    log.info("tracked %d points over %d frames", m, n)
    return StereoTracks(u_l, u_r, v, seen, stereo)


def kitti_rig(seq: KittiStereoSequence) -> StereoRig:
    """The sequence as a :class:`StereoRig` (focal length in px, pixel pitch 1)."""
    return StereoRig(baseline=seq.baseline, focal_length=seq.fx, pixel_pitch=1.0,
                     width_px=seq.width)


def paper_coords(u: FloatArray, seq: KittiStereoSequence) -> FloatArray:
    """OpenCV columns -> the paper's horizontal coordinate (px, positive left): ``cx - u``."""
    return seq.cx - np.asarray(u, dtype=float)


def _points_at(tracks: StereoTracks, k: int, seq: KittiStereoSequence,
               idx: FloatArray) -> FloatArray:
    """(len(idx), 2) triangulated rig-frame points ``(depth, left)`` of tracks at frame k."""
    xl = paper_coords(tracks.u_left[k, idx], seq)
    xr = paper_coords(tracks.u_right[k, idx], seq)
    return np.array([triangulate_point(a, b, seq.baseline, seq.fx) for a, b in zip(xl, xr,
                                                                                  strict=True)])


def select_pairs(
    tracks: StereoTracks, k: int, k_next: int, seq: KittiStereoSequence,
    depth_range: tuple[float, float] = (3.0, 25.0), max_abs_x_frac: float = 0.7,
    max_candidates: int = 80, heading_weight_m: float = 10.0, n_best: int = 5,
) -> list[tuple[int, int]]:
    """Pairs of tracks with stereo at ``k`` and ``k_next``, best-determined pose first.

    Candidates: depth within ``depth_range`` and within ``max_abs_x_frac`` of the
    half image width from the centre (they stay in view longer as the car drives
    forward); at most ``max_candidates`` of them, evenly spread over the list.
    Each pair is scored by the two-point pose covariance at the anchor,
    ``(H^T H)^-1`` from eq. 5's Jacobian, as ``var_x + var_y + (w var_theta)``
    with ``w = heading_weight_m^2``; the ``n_best`` smallest scores are returned
    (empty list: no pair). Nearly collinear pairs score badly by construction.
    """
    cand = np.nonzero(tracks.stereo[k] & tracks.stereo[k_next])[0]
    if len(cand) < 2:
        return []
    c = _points_at(tracks, k, seq, cand)
    x = paper_coords(tracks.u_left[k, cand], seq)
    good = ((c[:, 0] > depth_range[0]) & (c[:, 0] < depth_range[1])
            & (np.abs(x) < max_abs_x_frac * 0.5 * seq.width))
    cand, c = cand[good], c[good]
    if len(cand) < 2:
        return []
    if len(cand) > max_candidates:
        sel = np.linspace(0, len(cand) - 1, max_candidates).round().astype(int)
        cand, c = cand[sel], c[sel]
    # per-point information J^T J of its two coordinates w.r.t. the pose (at identity)
    info_pt = np.zeros((len(cand), 3, 3))
    for i, point in enumerate(c):
        c_cam, c_D_pose, _ = camera_point(np.zeros(3), point)
        _, x_D_c = stereo_project(c_cam, seq.baseline, seq.fx)
        jac = x_D_c @ c_D_pose
        info_pt[i] = jac.T @ jac
    info = info_pt[:, None] + info_pt[None, :]  # (M, M, 3, 3), pair information
    iu, ju = np.triu_indices(len(cand), k=1)
    pair_info = info[iu, ju]
    det = np.linalg.det(pair_info)
    ok = det > 1e-12 * np.max(np.abs(det))
    if not ok.any():
        return []
    cov = np.linalg.inv(pair_info[ok])
    score = cov[:, 0, 0] + cov[:, 1, 1] + heading_weight_m**2 * cov[:, 2, 2]
    order = np.argsort(score)[:n_best]
    return [(int(cand[iu[ok][b]]), int(cand[ju[ok][b]])) for b in order]


def _between(a: FloatArray, b: FloatArray) -> FloatArray:
    """Planar ``a^-1 b``: pose ``b`` in the frame of pose ``a``."""
    d = rot2(a[2]).T @ (b[:2] - a[:2])
    return np.array([d[0], d[1], math.remainder(b[2] - a[2], 2 * math.pi)])


def _compose(a: FloatArray, b: FloatArray) -> FloatArray:
    t = a[:2] + rot2(a[2]) @ b[:2]
    return np.array([t[0], t[1], math.remainder(a[2] + b[2], 2 * math.pi)])


@dataclass(frozen=True)
class KittiTwoPointResult:
    """The two-point relative pose on KITTI against the ground truth.

    Attributes:
        truth: (N, 3) ground-truth rig poses in the frame-0 rig frame (paper axes).
        estimate: (N, 3) chained two-point estimates (frame 0 = truth).
        anchor: (N,) anchor frame used for each frame's estimate (-1: none).
        rel_error: (N, 3) error of the estimated motion anchor -> k against the truth
            (x, y m; heading rad); zero rows where ``scored`` is False.
        scored: (N,) frames with a two-point estimate from an earlier anchor.
        n_pairs: how many point pairs were used (1 + re-selections).
        model_residual_px: (K,) predicted minus measured horizontal coordinate of
            triangulated points moved by the ground-truth motion k-1 -> k (eq. 2).
    """

    truth: FloatArray
    estimate: FloatArray
    anchor: FloatArray
    rel_error: FloatArray
    scored: BoolArray
    n_pairs: int
    model_residual_px: FloatArray


def two_point_on_kitti(
    seq: KittiStereoSequence,
    tracks: StereoTracks,
    cfg: StereoEstimatorConfig | None = None,
    var_px2: float = 0.25,
    model_check_max_depth: float = 30.0,
    max_residual_px: float = 1.5,
) -> KittiTwoPointResult:
    """Run the two-point raw solver along the sequence and score it (module docstring).

    Args:
        seq: the sequence; tracks: from :func:`track_sequence`.
        cfg: solver thresholds.
        var_px2: assumed variance of a measured coordinate, px^2 (covariances only).
        model_check_max_depth: points deeper than this are left out of the
            projection-model check, m.
        max_residual_px: the four coordinates over-determine the three pose
            coordinates; a solved pose whose RMS reprojection residual exceeds this
            marks a mistracked point (status ``inconsistent``) and the pair is
            replaced (no ground truth is used for this).
    """
    cfg = cfg or StereoEstimatorConfig()
    rig = kitti_rig(seq)
    truth = seq.planar_rig_poses()
    n = len(seq)
    est = np.zeros((n, 3))
    est[0] = truth[0]
    anchor = np.full(n, -1)
    rel_err = np.zeros((n, 3))
    scored = np.zeros(n, bool)
    a, pair, target = 0, None, np.zeros((2, 2))
    last_ok = 0  # last frame with an estimate
    n_pairs = 0
    for k in range(1, n):
        pose = None
        if pair is not None and tracks.stereo[k, list(pair)].all():
            z = _z(tracks, k, pair, seq)
            pose, _, status = triangulate_two_points(z, target, rig, var_px2, cfg)
            if status == OK and _residual(pose, z, target, seq) > max_residual_px:
                status = "inconsistent"  # a mistracked point: the 4 coordinates disagree
            if status != OK:
                log.info("frame %d: pair %s gives %s; re-selecting", k, pair, status)
                pose = None
        if pose is None:
            # new pair anchored at the last frame that has an estimate: the best
            # candidate whose four coordinates at k are consistent
            a, pair = last_ok, None
            for cand_pair in select_pairs(tracks, last_ok, k, seq):
                cand_target = _points_at(tracks, a, seq, np.array(cand_pair))
                z = _z(tracks, k, cand_pair, seq)
                pose, _, status = triangulate_two_points(z, cand_target, rig, var_px2, cfg)
                if status == OK and _residual(pose, z, cand_target, seq) > max_residual_px:
                    status = "inconsistent"
                if status == OK:
                    pair, target = cand_pair, cand_target
                    break
                log.info("frame %d: candidate pair %s gives %s", k, cand_pair, status)
            if pair is None:
                log.warning("frame %d: no usable point pair from frame %d; no estimate", k, a)
                est[k] = est[last_ok]
                continue
            n_pairs += 1
        est[k] = _compose(est[a], pose)
        anchor[k] = a
        last_ok = k
        rel_err[k] = pose - _between(truth[a], truth[k])
        rel_err[k, 2] = math.remainder(rel_err[k, 2], 2 * math.pi)
        scored[k] = True
    residuals = []
    for k in range(1, n):
        both = np.nonzero(tracks.stereo[k - 1] & tracks.stereo[k])[0]
        if len(both) == 0:
            continue
        c_prev = _points_at(tracks, k - 1, seq, both)
        motion = _between(truth[k - 1], truth[k])
        meas_l = paper_coords(tracks.u_left[k, both], seq)
        meas_r = paper_coords(tracks.u_right[k, both], seq)
        for c, ml, mr in zip(c_prev, meas_l, meas_r, strict=True):
            if c[0] > model_check_max_depth:
                continue
            c_k = camera_point(motion, c)[0]
            if c_k[0] <= cfg.min_depth:
                continue
            pred, _ = stereo_project(c_k, seq.baseline, seq.fx)
            residuals.extend([pred[0] - ml, pred[1] - mr])
    return KittiTwoPointResult(truth, est, anchor, rel_err, scored, n_pairs, np.array(residuals))


def _residual(pose: FloatArray, z: FloatArray, target: FloatArray,
              seq: KittiStereoSequence) -> float:
    """RMS of ``h(pose) - z`` over the four coordinates (eq. 5), px."""
    h, _ = two_point_measurement(pose, target, seq.baseline, seq.fx)
    return float(np.sqrt(np.mean((h - z) ** 2)))


def _z(tracks: StereoTracks, k: int, pair: tuple[int, int], seq: KittiStereoSequence) -> FloatArray:
    """The four coordinates (eq. 5 order) of a pair at frame k, px, paper convention."""
    i, j = pair
    return paper_coords(np.array([tracks.u_left[k, i], tracks.u_right[k, i],
                                  tracks.u_left[k, j], tracks.u_right[k, j]]), seq)
