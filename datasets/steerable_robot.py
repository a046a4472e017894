"""A simulated robot the global localizer can steer: turn in place, drive on, frames back.

:class:`SimulatedRobot` moves a true pose through a simulated world on request
(``turn(angle, rate)``, ``drive(distance)``), integrates noisy wheel odometry,
and records what its sensors see on the way: Kinect frames while turning
(paper 2, sec. 3: SIFT points and depth for the 360-degree virtual scan) and
ceiling-camera frames while driving (sec. 4.2: the lamps and corners for the
verification). It satisfies the localizer's ``Robot`` protocol
(:class:`lampsam.localization.robot.Robot`) structurally, without importing any
estimator code: the sensors are passed in as functions of the true pose, so the
same robot drives the Table-1 office (Kinect rendered with Open3D, features by
the caller's SIFT) and the tests' synthetic worlds (Kinect by ray casting).

Frames: poses are ``world_T_body`` / ``odom_T_body`` ``(x, y, theta)`` in m, m,
rad (docs/conventions.md); sensor points are in the body frame.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np

from lampsam.angles import wrap_angle, wrap_axis
from lampsam.arrays import BoolArray, Float32Array, FloatArray
from lampsam.datasets.robot_frames import DriveFrame, TurnFrame

#: ``kinect(pose, rng) -> (sift_points (N, 3), sift_descriptors (N, 128), depth_points (P, 3))``,
#: body frame (m), seen from the true pose ``world_T_body``.
KinectSensor = Callable[[FloatArray, np.random.Generator], tuple[FloatArray, Float32Array, FloatArray]]
#: ``ceiling(pose, rng) -> (m (K, 2), is_lamp (K,) or None, axis (K,) or None)``: the
#: ceiling features in normalised ceiling coordinates (:class:`DriveFrame`).
CeilingSensor = Callable[
    [FloatArray, np.random.Generator], tuple[FloatArray, BoolArray | None, FloatArray | None]
]
#: ``free_ahead(pose) -> metres`` free in front of the robot (obstacle avoidance).
FreeAhead = Callable[[FloatArray], float]


def compose_pose(a: FloatArray, b: FloatArray) -> FloatArray:
    """``a (+) b`` for planar poses ``(x, y, theta)`` (m, m, rad): ``b`` expressed in ``a``'s frame."""
    c, s = math.cos(a[2]), math.sin(a[2])
    return np.array(
        [a[0] + c * b[0] - s * b[1], a[1] + s * b[0] + c * b[1], wrap_angle(float(a[2] + b[2]))]
    )


@dataclass
class SimulatedRobot:
    """A differential-drive robot in a simulated world, steered by the localizer.

    Odometry: every commanded increment ``delta`` (body frame) moves the true
    pose exactly and the odometry pose by ``delta + N(0, (odom_sigma |delta|_1)^2 I)``.
    Driving: at ``speed`` forward while ``free_ahead`` exceeds ``blocked_within``,
    else turning left in place at ``avoid_rate`` (the distance counts only the
    forward motion).

    Attributes:
        kinect: the Kinect sensor (:data:`KinectSensor`).
        ceiling: the upward camera (:data:`CeilingSensor`).
        free_ahead: free distance ahead of a true pose (:data:`FreeAhead`).
        pose: (3,) the true ``world_T_body`` (m, m, rad); updated as the robot moves.
        rng: generator of the odometry and sensor noise.
        odom_sigma: odometry noise per unit of commanded motion (1 m or 1 rad). Default 0.01.
        kinect_rate: Kinect frames per second while turning (Hz). Default 3.
        ceiling_rate: ceiling frames per second while driving (Hz). Default 10.
        speed: forward speed (m/s). Default 0.4 (the paper's 400 mm/s).
        blocked_within: turn instead of driving when less than this is free ahead (m).
        avoid_rate: turning rate while blocked (rad/s). Default 0.5.
        odom: (3,) the odometry pose (starts at the origin).
        t: the robot's clock (s).
        turn_starts: the true pose at the start of every turn.
    """

    kinect: KinectSensor
    ceiling: CeilingSensor
    free_ahead: FreeAhead
    pose: FloatArray
    rng: np.random.Generator
    odom_sigma: float = 0.01
    kinect_rate: float = 3.0
    ceiling_rate: float = 10.0
    speed: float = 0.4
    blocked_within: float = 0.7
    avoid_rate: float = 0.5
    odom: FloatArray = field(default_factory=lambda: np.zeros(3))
    t: float = 0.0
    turn_starts: list[list[float]] = field(default_factory=list)

    def __post_init__(self) -> None:
        self.pose = np.asarray(self.pose, dtype=float).copy()

    def _move(self, delta: FloatArray) -> None:
        self.pose = compose_pose(self.pose, delta)
        scale = float(np.abs(delta).sum())
        self.odom = compose_pose(self.odom, delta + self.rng.normal(0, self.odom_sigma * scale, 3))

    def _kinect_frame(self) -> TurnFrame:
        pts, desc, depth = self.kinect(self.pose, self.rng)
        return TurnFrame(self.t, self.odom.copy(), pts, desc, depth)

    def turn(self, angle: float, rate: float) -> list[TurnFrame]:
        """Turn in place by ``angle`` (rad, CCW positive) at ``rate`` (rad/s).

        Returns the Kinect frames, one at the start heading and one after every
        step of ``rate / kinect_rate`` (the last step reaches at least ``|angle|``).
        """
        dt = 1.0 / self.kinect_rate
        self.turn_starts.append([float(v) for v in self.pose])
        n = int(math.ceil(abs(angle) / (rate * dt) - 1e-9))
        frames = [self._kinect_frame()]
        for _ in range(n):
            self._move(np.array([0.0, 0.0, math.copysign(rate * dt, angle)]))
            self.t += dt
            frames.append(self._kinect_frame())
        return frames

    def drive(self, distance: float) -> list[DriveFrame]:
        """Drive on for ``distance`` (m forward), avoiding obstacles; a ceiling frame per step."""
        dt = 1.0 / self.ceiling_rate
        frames: list[DriveFrame] = []
        travelled = 0.0
        while travelled < distance - 1e-9:
            if self.free_ahead(self.pose) > self.blocked_within:
                step = min(self.speed * dt, distance - travelled)
                self._move(np.array([step, 0.0, 0.0]))
                travelled += step
            else:
                self._move(np.array([0.0, 0.0, self.avoid_rate * dt]))
            self.t += dt
            m, is_lamp, axis = self.ceiling(self.pose, self.rng)
            frames.append(DriveFrame(self.t, self.odom.copy(), m, is_lamp, axis))
        return frames


class PixelCamera(Protocol):
    """The part of the upward camera model that the ceiling sensor and the localizer's
    image-interior test (:func:`lampsam.localization.verify_drive.image_interior`) need
    (``logrun.CameraModel``)."""

    @property
    def width(self) -> int:
        """Image width (px)."""
        ...

    @property
    def height(self) -> int:
        """Image height (px)."""
        ...

    def pixels_from_normalized(self, m: FloatArray) -> FloatArray:
        """(N, 2) pixels of (N, 2) normalised ceiling coordinates."""
        ...


@dataclass(frozen=True)
class CeilingLandmarkSensor:
    """The ceiling camera seeing the true ceiling landmarks (a :data:`CeilingSensor`).

    Each landmark above the camera is projected to normalised ceiling
    coordinates ``m = (R^T (p_xy - t) - o_xy) / (p_z - z_cam)`` (paper 1,
    eqs. 17-18), kept when it falls inside the image, and perturbed by Gaussian
    noise; lamps' long axes are seen relative to the heading.

    Attributes:
        xyz: (L, 3) landmark positions, world frame (m).
        is_lamp: (L,) bool, lamps (True) or corners.
        phi: (L,) lamps' long axes in the world (rad, mod pi), NaN for none.
        body_t_camera: (3,) camera offset in the body frame and height (m).
        camera: the camera model (image size and pixel mapping).
        sigma_m: noise of ``m`` (normalised units). Default 0.005.
        sigma_axis: noise of the axes (rad). Default 2 degrees.
    """

    xyz: FloatArray
    is_lamp: BoolArray
    phi: FloatArray
    body_t_camera: FloatArray
    camera: PixelCamera
    sigma_m: float = 0.005
    sigma_axis: float = float(np.deg2rad(2.0))

    def __call__(
        self, pose: FloatArray, rng: np.random.Generator
    ) -> tuple[FloatArray, BoolArray, FloatArray]:
        """The features seen from the true pose ``(x, y, theta)``: ``(m, is_lamp, axis)``."""
        above = np.nonzero(self.xyz[:, 2] - self.body_t_camera[2] > 0.1)[0]
        c, s = math.cos(pose[2]), math.sin(pose[2])
        d = self.xyz[above, :2] - np.asarray(pose[:2], dtype=float)
        q = np.column_stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1]])
        h = self.xyz[above, 2] - self.body_t_camera[2]
        m = ((q - self.body_t_camera[:2]) / h[:, None]).reshape(-1, 2)
        px = np.asarray(self.camera.pixels_from_normalized(m)).reshape(-1, 2)
        w, hgt = self.camera.width, self.camera.height
        vis = (px[:, 0] >= 0) & (px[:, 0] < w) & (px[:, 1] >= 0) & (px[:, 1] < hgt)
        sel = above[vis]
        axis = np.asarray(wrap_axis(self.phi[sel] - pose[2]))
        axis = axis + rng.normal(0, self.sigma_axis, len(sel))
        noisy = m[vis] + rng.normal(0, self.sigma_m, (len(sel), 2))
        return noisy, self.is_lamp[sel], axis
