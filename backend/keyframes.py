"""Keyframe policy of the factor-graph backends.

A frame with observations becomes a keyframe (a pose variable ``X(k)`` with its
observations' factors) when it is the first one, when the robot has moved
``keyframe_distance`` or turned ``keyframe_angle`` since the last keyframe, or always
with ``every_frame``. The smoothers use no other frame's observations; between
keyframes the pose is the last keyframe's estimate composed with the odometry
(:mod:`lampsam.backend.pose_cov`). Fewer keyframes keep iSAM2's updates small; the
measured trade-off of the defaults is in docs/graph-backend.md.

Whether a frame is *read* at all is decided from the odometry alone, before its
observations are made (:func:`keyframe_observations`): a lazy frame
(:class:`lampsam.backend.pipelined.LazyFrame`) between keyframes never has its
image processed. :class:`KeyframeMirror` makes the same decision outside the
backend, from the same odometry and the same two functions, for a process that
feeds a backend in another one (``--online decoupled``).
"""

from __future__ import annotations

import math

import gtsam
import numpy as np

from lampsam.arrays import FloatArray
from lampsam.backend.config import Isam2Config, SlamConfig
from lampsam.backend.interface import Frame
from lampsam.backend.models import Obs, observations_from_frame
from lampsam.backend.odometry import MotionModel
from lampsam.backend.pose_cov import compose_cov, pose_array

#: Variance floor used for the per-step odometry composition (the factor's own floor
#: is added once per keyframe).
STEP_FLOOR = 1e-14

#: ``(delta, cov)`` of the first samples since a keyframe with the odometry factor's floor.
FirstRelative = tuple[FloatArray, FloatArray]

#: What :func:`advance_odometry` returns: ``(delta, cov, first_rel)``.
Advanced = tuple[FloatArray, FloatArray, FirstRelative | None]


def is_keyframe(k: int, delta: FloatArray, config: Isam2Config) -> bool:
    """Whether a frame with observations becomes keyframe ``k + 1``.

    The first frame is always a keyframe: seen from the known start pose, it anchors
    the map's heading, which nothing later can observe.

    Args:
        k: index of the last keyframe (0: only the start pose so far).
        delta: (3,) odometry ``(x, y, theta)`` since keyframe ``k``, in its body frame,
            m and rad.
        config: ``every_frame``, ``keyframe_distance`` (m), ``keyframe_angle`` (rad).
    """
    if config.every_frame or k == 0:
        return True
    return bool(math.hypot(float(delta[0]), float(delta[1])) >= config.keyframe_distance
                or abs(float(delta[2])) >= config.keyframe_angle)


def keyframe_observations(frame: Frame | None, k: int, delta: FloatArray,
                          config: SlamConfig) -> list[Obs] | None:
    """The observations a smoother takes from a frame: None when it does not read it.

    The frame is read (a lazy frame's image processed) only when a frame with
    observations would become keyframe ``k + 1`` (:func:`is_keyframe`); it becomes
    one when the list is not empty.

    Args:
        frame: the step's frame, or None.
        k: index of the last keyframe.
        delta: (3,) odometry since keyframe ``k`` (its body frame), m and rad.
        config: keyframe policy (``isam2``), ``features`` and ``noise``.

    Returns:
        None (no frame, or not due), else the frame's observations (maybe empty).
    """
    if frame is None or not is_keyframe(k, delta, config.isam2):
        return None
    return observations_from_frame(frame, config.features, config.noise)


def advance_odometry(motion: MotionModel, u: FloatArray, delta: FloatArray, cov: FloatArray,
                     first: bool, floor_var: float
                     ) -> tuple[FloatArray, FloatArray, FirstRelative | None, FloatArray]:
    """The odometry since the last keyframe after one more step's samples.

    Args:
        motion: the odometry model.
        u: (K, width) the step's samples (K >= 1).
        delta: (3,) odometry since the keyframe before the step, m and rad.
        cov: (3, 3) its right-tangent covariance.
        first: no samples since the keyframe before these (``delta`` is the identity).
        floor_var: the odometry factor's variance floor (``Isam2Config.odometry_floor_var``).

    Returns:
        ``(delta, cov, first_rel, d)``: ``first_rel`` is the samples' own
        ``(delta, cov)`` with ``floor_var`` when ``first`` (the odometry factor's, if no
        samples follow before the next keyframe), else None; ``d`` (3,) is the samples'
        own composed motion (``motion.relative``'s mean, which the floor does not
        change: the tracker's odometry chain). The covariance carries
        :data:`STEP_FLOOR` per step.
    """
    if not first:
        d, c = motion.relative(u, STEP_FLOOR)
        return (pose_array(gtsam.Pose2(*delta).compose(gtsam.Pose2(*d))),
                compose_cov(d, cov, c), None, d)
    d, c_kf = motion.relative(u, floor_var)
    # composed with the identity (zero covariance) since the keyframe
    return (pose_array(gtsam.Pose2(*d)), c_kf + (STEP_FLOOR - floor_var) * np.eye(3),
            (d, c_kf), d)


class KeyframeMirror:
    """Which frames a graph backend will read, decided outside it (``--online decoupled``).

    Keeps the backend's keyframe counter and odometry since the last keyframe from
    the same steps, with the same functions (:func:`advance_odometry`,
    :func:`keyframe_observations`), so :meth:`reads` says for each step what
    :meth:`lampsam.backend.graph.GraphSlam.step` will do with its frame: read it or
    not. The counter advances only when a read frame had observations (as the
    backend's). A frame it does not read can be left unmade: the backend's result
    is the same bit for bit.

    Args:
        motion: the odometry model (the backend's).
        config: the backend's SLAM config.
    """

    def __init__(self, motion: MotionModel, config: SlamConfig) -> None:
        self.motion = motion
        self.config = config
        self.k = 0
        self.delta = np.zeros(3)
        self.cov = np.zeros((3, 3))
        self.since = False  # samples since the last keyframe
        self.n_read = 0
        #: the last step's :func:`advance_odometry` result (None: the step had no
        #: samples), the one the backend computes from the same state: a backend in
        #: another process can take it instead of composing the samples again
        #: (:meth:`lampsam.backend.graph.GraphSlam.give_odometry`)
        self.advanced: Advanced | None = None
        #: (3,) the last step's own composed motion (``advance_odometry``'s ``d``; None:
        #: no samples), the increment of the tracker's odometry chain
        self.step_motion: FloatArray | None = None

    def reads(self, u: FloatArray, frame: Frame | None) -> bool:
        """Whether the backend reads this step's frame (reading it here, if so).

        Args:
            u: (K, width) the step's checked samples (``motion.check``).
            frame: the step's frame, or None.
        """
        self.advanced = self.step_motion = None
        if len(u):
            delta, cov, first_rel, self.step_motion = advance_odometry(
                self.motion, u, self.delta, self.cov, not self.since,
                self.config.isam2.odometry_floor_var)
            self.advanced = (delta, cov, first_rel)
            self.delta, self.cov = delta, cov
            self.since = True
        obs = keyframe_observations(frame, self.k, self.delta, self.config)
        if obs is None:
            return False
        self.n_read += 1
        if obs:
            self.k += 1
            self.delta = np.zeros(3)
            self.cov = np.zeros((3, 3))
            self.since = False
        return True
