"""Corner tracking and left-right matching on rectified stereo sequences (KITTI).

The image-processing half of the KITTI two-point check (paper 3 on real data);
the estimation half, pair selection and the two-point solver, is
:mod:`lampsam.backend.stereo_kitti`. OpenCV only:

* Shi-Tomasi corners (``cv2.goodFeaturesToTrack``) in the left image, detected
  again (away from the surviving tracks) whenever fewer than
  ``TrackConfig.redetect_below`` remain.
* Pyramidal Lucas-Kanade optical flow for left(k-1) -> left(k) tracking and for
  left -> right matching on the rectified pair, each with a forward-backward
  check (``fb_max_px``).
* A stereo match must stay on the same row (``row_max_px``, the pair is
  rectified) and have positive disparity (``min_disparity_px``).

Image coordinates: OpenCV columns ``u`` / rows ``v`` in pixels. The paper's
horizontal coordinate (positive to the left, eq. 2) is ``x = cx - u``
(:func:`paper_coords`; docs/stereo.md and :mod:`lampsam.factors.stereo`).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import cv2
import numpy as np

from lampsam.arrays import BoolArray, FloatArray, ImageU8
from lampsam.datasets.kitti import KittiStereoSequence

log = logging.getLogger(__name__)

#: Initial left -> right disparity guess for the Lucas-Kanade search, px.
DISPARITY_GUESS_PX = 20.0


@dataclass(frozen=True)
class TrackConfig:
    """Corner tracking and stereo matching settings (OpenCV).

    Attributes:
        max_corners: corners detected per (re-)detection (default 500).
        quality: ``goodFeaturesToTrack`` quality level, fraction of the best
            corner's response (default 0.01).
        min_distance_px: minimum spacing of corners, px (default 12).
        redetect_below: detect new corners when fewer tracks remain (default 250).
        win_px: Lucas-Kanade window size, px (default 21).
        levels: Lucas-Kanade pyramid levels (default 4).
        fb_max_px: forward-backward error limit, px (default 0.5).
        row_max_px: a stereo match may differ in row by at most this, px (default 1).
        min_disparity_px: smallest accepted disparity, px (default 1).
        border_px: drop points closer than this to the image border, px (default 10).
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
        u_left: (N, M) left-image column, px (0 where absent).
        u_right: (N, M) right-image column of the stereo match, px (0 where absent).
        v: (N, M) row, px (0 where absent).
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
    """Pyramidal LK ``a -> b`` with a forward-backward check.

    Args:
        a, b: (H, W) uint8 images.
        pts: (K, 2) ``(u, v)`` points in ``a``, px.
        cfg: window, pyramid and forward-backward limit.
        guess: (K, 2) initial positions in ``b``, px (default: ``pts``).

    Returns:
        ``(K, 2)`` tracked positions in ``b`` (px) and ``(K,)`` bool validity.
    """
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
        seq: the rectified KITTI sequence (images loaded one pair at a time).
        cfg: tracking settings (default :class:`TrackConfig`).

    Returns:
        The tracks (see :class:`StereoTracks`); track ``i`` is column ``i``.
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
                new_pts = new.reshape(-1, 2).astype(float)
                pts = np.vstack([pts, new_pts])
                ids = np.concatenate([ids, np.arange(next_id, next_id + len(new_pts))])
                next_id += len(new_pts)
        # left -> right on the rectified pair, starting from a typical disparity
        guess = pts - np.array([DISPARITY_GUESS_PX, 0.0])
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


def paper_coords(u: FloatArray, seq: KittiStereoSequence) -> FloatArray:
    """OpenCV columns -> the paper's horizontal coordinate ``x = cx - u``.

    Args:
        u: (...) columns, px.
        seq: gives the principal point ``cx``, px.

    Returns:
        (...) horizontal coordinates, px, positive to the left (eq. 2).
    """
    return seq.cx - np.asarray(u, dtype=float)
