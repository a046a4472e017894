"""Pose candidates from SIFT matches to the spatial feature map (paper 2, sec. 3).

While the robot turns in place (30 deg/s), each Kinect frame's SIFT features
(descriptors and 3-D points in the body frame) are matched to the spatial
feature map (descriptors and 3-D points in the world frame) with Lowe's ratio
test; the matched points are aligned by SVD inside RANSAC
(:mod:`lampsam.localization.alignment`, eqs. 1-6), which gives a robot pose
candidate ``world_T_body`` with a radius ``r = alpha * eps`` (eq. 7).

Candidates found earlier in the turn are carried along with the robot
(paper Fig. 8): each is composed with the odometry increment since, so that at
the end of the turn every candidate is a hypothesis of the robot's *current*
pose. Every candidate then receives the same number of particles (a tight
candidate is sampled densely): :func:`pf_candidates` gives the ``(pose, radius)``
pairs that :meth:`lampsam.localization.particle_filter.ParticleFilter.init_candidates`
samples.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass, field, replace

import cv2
import numpy as np
from numpy.typing import NDArray

from lampsam.arrays import FloatArray, IntArray
from lampsam.errors import LocalizationError
from lampsam.factors.geometry import compose
from lampsam.localization.alignment import AlignmentError, RansacConfig, ransac_align

log = logging.getLogger(__name__)


class CandidateError(LocalizationError):
    """Malformed feature input for candidate generation."""


@dataclass(frozen=True)
class CandidateConfig:
    """Candidate generation (paper 2, sec. 3).

    Attributes:
        ratio: Lowe ratio test threshold (best / second-best descriptor
            distance). Default 0.8 (Lowe 2004).
        min_matches: fewer ratio-test matches than this = no candidate. Default 6.
        alpha: radius per metre of residual, ``r = alpha * eps`` (eq. 7).
            Default 5.0 (an RMS residual of 4 cm gives a 20 cm disc).
        min_radius: lower bound on ``r`` (m), so a lucky near-zero residual still
            gets a disc the particle filter can sample. Default 0.10 m.
        max_radius: upper bound on ``r`` (m). Default 1.5 m.
        sigma_theta: heading spread given to a candidate's particles (rad).
            Default 0.1 rad (5.7 deg).
        ransac: the RANSAC settings (planar by default).
    """

    ratio: float = 0.8
    min_matches: int = 6
    alpha: float = 5.0
    min_radius: float = 0.10
    max_radius: float = 1.5
    sigma_theta: float = 0.1
    ransac: RansacConfig = field(default_factory=RansacConfig)


@dataclass(frozen=True)
class PoseCandidate:
    """One candidate of the robot pose.

    Attributes:
        pose: (3,) ``world_T_body = (x, y, theta)`` at the time of the latest
            propagation (m, m, rad).
        radius: disc radius (m), eq. 7 clipped to ``[min_radius, max_radius]``.
        eps: RMS alignment residual of the inliers (m).
        n_inliers: RANSAC inliers.
        t: time of the frame the candidate came from (s).
    """

    pose: FloatArray
    radius: float
    eps: float
    n_inliers: int
    t: float


def match_descriptors(
    query: NDArray[np.floating], train: NDArray[np.floating], ratio: float
) -> tuple[IntArray, IntArray]:
    """Match SIFT descriptors with brute force L2 and Lowe's ratio test.

    Args:
        query: (N, D) descriptors of the current frame (float32 or float64).
        train: (M, D) descriptors of the spatial feature map.
        ratio: keep a match when ``d1 < ratio * d2``.

    Returns:
        (query_idx (k,), train_idx (k,)) of the kept matches, each train index
        used at most once (the closest query wins).

    Raises:
        CandidateError: mismatched descriptor widths or non-finite values.
    """
    query = np.ascontiguousarray(query, dtype=np.float32)
    train = np.ascontiguousarray(train, dtype=np.float32)
    empty = np.zeros(0, dtype=np.int64)
    if query.ndim != 2 or train.ndim != 2 or query.shape[1] != train.shape[1]:
        raise CandidateError(f"descriptor shapes {query.shape} and {train.shape} do not match")
    if len(query) == 0 or len(train) < 2:
        return empty, empty.copy()
    if not (np.all(np.isfinite(query)) and np.all(np.isfinite(train))):
        raise CandidateError("descriptors contain NaN or inf")
    matcher = cv2.BFMatcher(cv2.NORM_L2)
    pairs = matcher.knnMatch(query, train, k=2)
    best: dict[int, tuple[float, int]] = {}
    for pair in pairs:
        if len(pair) < 2:
            continue
        m, n = pair
        if m.distance < ratio * n.distance:
            prev = best.get(m.trainIdx)
            if prev is None or m.distance < prev[0]:
                best[m.trainIdx] = (m.distance, m.queryIdx)
    if not best:
        return empty, empty.copy()
    train_idx = np.fromiter(best.keys(), dtype=np.int64)
    query_idx = np.array([best[int(k)][1] for k in train_idx], dtype=np.int64)
    return query_idx, train_idx


def candidate_from_frame(
    body_points: FloatArray,
    descriptors: NDArray[np.floating],
    map_points: FloatArray,
    map_descriptors: NDArray[np.floating],
    t: float,
    rng: np.random.Generator,
    config: CandidateConfig,
) -> PoseCandidate | None:
    """One Kinect frame -> one pose candidate, or None when it cannot be aligned.

    Args:
        body_points: (N, 3) SIFT keypoints' 3-D positions, body frame (m).
        descriptors: (N, D) their descriptors.
        map_points: (M, 3) spatial feature map points, world frame (m).
        map_descriptors: (M, D) their descriptors.
        t: frame time (s).
        rng: generator for RANSAC.
        config: thresholds.

    Returns:
        The :class:`PoseCandidate` (pose = alignment's planar pose, eq. 5; radius
        eq. 7), or None with a debug log when there are too few matches or inliers.
    """
    body_points = np.asarray(body_points, dtype=float)
    if body_points.ndim != 2 or body_points.shape[1] != 3 or len(body_points) != len(descriptors):
        raise CandidateError(
            f"frame at t={t}: body_points {body_points.shape} vs {len(descriptors)} descriptors"
        )
    qi, ti = match_descriptors(descriptors, map_descriptors, config.ratio)
    if len(qi) < config.min_matches:
        log.debug("t=%.2f: %d matches, no candidate", t, len(qi))
        return None
    try:
        a = ransac_align(
            np.asarray(map_points, dtype=float)[ti], body_points[qi], rng, config.ransac
        )
    except AlignmentError as exc:
        log.debug("t=%.2f: %s", t, exc)
        return None
    radius = float(np.clip(config.alpha * a.eps, config.min_radius, config.max_radius))
    return PoseCandidate(a.pose2(), radius, a.eps, a.n_inliers, float(t))


def propagate(candidates: Sequence[PoseCandidate], body_T_body2: FloatArray) -> list[PoseCandidate]:
    """Carry candidates along with the robot's motion (paper Fig. 8 b, d).

    Each candidate pose ``world_T_body`` becomes ``world_T_body * body_T_body2``:
    for a turn in place by ``d_theta`` this rotates the candidate's heading by
    ``d_theta`` about its own centre, as the paper describes.

    Args:
        candidates: the candidates so far.
        body_T_body2: (3,) odometry increment ``(dx, dy, dtheta)`` in the body frame.

    Returns:
        New candidates (the inputs are frozen and left unchanged).
    """
    return [replace(c, pose=compose(c.pose, body_T_body2)) for c in candidates]


class CandidateCollector:
    """Collects candidates during the turn, keeping them in the current body frame.

    Feed it the frames in time order with the odometry pose of each frame (any
    fixed odometry frame); it propagates earlier candidates by the odometry
    increment before adding a new one.

    Args:
        map_points: (M, 3) spatial feature map points, world frame (m).
        map_descriptors: (M, D) their descriptors.
        config: thresholds.
        rng: generator for RANSAC.
    """

    def __init__(
        self,
        map_points: FloatArray,
        map_descriptors: FloatArray,
        config: CandidateConfig,
        rng: np.random.Generator,
    ) -> None:
        self.map_points = np.asarray(map_points, dtype=float)
        self.map_descriptors = np.asarray(map_descriptors, dtype=np.float32)
        if self.map_points.ndim != 2 or self.map_points.shape[1] != 3:
            raise CandidateError(f"map points must be (M, 3), got {self.map_points.shape}")
        if len(self.map_points) != len(self.map_descriptors):
            raise CandidateError("map points and descriptors differ in length")
        self.config = config
        self.rng = rng
        self.candidates: list[PoseCandidate] = []
        self._last_odom: FloatArray | None = None

    def move_to(self, odom_pose: FloatArray) -> None:
        """Propagate the candidates to a new odometry pose.

        Args:
            odom_pose: (3,) ``odom_T_body`` now (m, m, rad).
        """
        odom_pose = np.asarray(odom_pose, dtype=float)
        if self._last_odom is not None:
            c, s = np.cos(self._last_odom[2]), np.sin(self._last_odom[2])
            d = odom_pose[:2] - self._last_odom[:2]
            delta = np.array(
                [c * d[0] + s * d[1], -s * d[0] + c * d[1], odom_pose[2] - self._last_odom[2]]
            )
            self.candidates = propagate(self.candidates, delta)
        self._last_odom = odom_pose

    def add_frame(
        self, t: float, odom_pose: FloatArray, body_points: FloatArray, descriptors: NDArray[np.floating]
    ) -> PoseCandidate | None:
        """Propagate to ``odom_pose``, then add this frame's candidate (if any).

        Args:
            t: frame time (s).
            odom_pose: (3,) ``odom_T_body`` at the frame.
            body_points: (N, 3) SIFT 3-D points, body frame.
            descriptors: (N, D) descriptors.

        Returns:
            The new candidate, or None.
        """
        self.move_to(odom_pose)
        cand = candidate_from_frame(
            body_points,
            descriptors,
            self.map_points,
            self.map_descriptors,
            t,
            self.rng,
            self.config,
        )
        if cand is not None:
            self.candidates.append(cand)
        return cand


def pf_candidates(candidates: Sequence[PoseCandidate]) -> list[tuple[FloatArray, float]]:
    """The ``(pose, radius)`` list the particle filter is initialised from.

    Args:
        candidates: the candidates at the end of the turn.

    Returns:
        ``[(pose (3,), radius), ...]``, one per candidate, same order.
    """
    return [(c.pose.copy(), c.radius) for c in candidates]
