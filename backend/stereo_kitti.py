"""Stereo two-point relative pose on real KITTI images: pair selection and check.

The tracks come from the frontend, :func:`lampsam.frontend.stereo_tracking.track_sequence`
(Shi-Tomasi corners, Lucas-Kanade tracking and left-right matching); this module
is the estimation half. Pair selection stays here because its score is the
two-point pose covariance from the eq. 5 Jacobians of :mod:`lampsam.factors.stereo`,
which the frontend may not import.

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
from dataclasses import dataclass

import numpy as np

from lampsam.angles import wrap_angle
from lampsam.arrays import BoolArray, FloatArray, IntArray
from lampsam.backend.stereo import OK, StereoEstimatorConfig, triangulate_two_points
from lampsam.datasets.kitti import KittiStereoSequence
from lampsam.datasets.stereo_types import StereoRig
from lampsam.factors.geometry import between, compose
from lampsam.factors.stereo import (
    camera_point,
    stereo_project,
    triangulate_point,
    two_point_measurement,
)
from lampsam.frontend.stereo_tracking import (
    StereoTracks,
    TrackConfig,
    paper_coords,
    track_sequence,
)

#: ``track_sequence``, ``TrackConfig``, ``StereoTracks`` and ``paper_coords`` are
#: re-exported for the callers that imported them from here before the move.
__all__ = [
    "KittiTwoPointResult",
    "StereoTracks",
    "TrackConfig",
    "kitti_rig",
    "paper_coords",
    "select_pairs",
    "track_sequence",
    "two_point_on_kitti",
]

log = logging.getLogger(__name__)


def kitti_rig(seq: KittiStereoSequence) -> StereoRig:
    """The sequence's rig (:meth:`KittiStereoSequence.stereo_rig`)."""
    return seq.stereo_rig()


def _points_at(tracks: StereoTracks, k: int, seq: KittiStereoSequence,
               idx: IntArray) -> FloatArray:
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
    anchor: IntArray
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
        assert pose is not None  # a usable pair was found above
        est[k] = compose(est[a], pose)
        anchor[k] = a
        last_ok = k
        rel_err[k] = pose - between(truth[a], truth[k])
        rel_err[k, 2] = wrap_angle(rel_err[k, 2])
        scored[k] = True
    residuals = []
    for k in range(1, n):
        both = np.nonzero(tracks.stereo[k - 1] & tracks.stereo[k])[0]
        if len(both) == 0:
            continue
        c_prev = _points_at(tracks, k - 1, seq, both)
        motion = between(truth[k - 1], truth[k])
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
