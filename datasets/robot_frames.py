"""What a robot records while it turns in place and while it drives on (paper 2, sec. 4).

Plain data shared by every source of localization frames: the simulated
steerable robot (:mod:`lampsam.datasets.steerable_robot`), a logged run replayed
in order (:mod:`lampsam.localization.replay`), and the global localizer that
consumes them (:mod:`lampsam.localization.localizer`). Frames: ``odom`` is the
wheel-odometry pose ``odom_T_body`` (docs/conventions.md), points are in the
body frame (``x`` forward, ``y`` left, ``z`` up, metres).
"""

from __future__ import annotations

from dataclasses import dataclass

from lampsam.arrays import BoolArray, Float32Array, FloatArray


@dataclass(frozen=True)
class TurnFrame:
    """One Kinect frame recorded while turning in place.

    Attributes:
        t: time (s, the robot's clock).
        odom: (3,) ``odom_T_body`` from wheel odometry (m, m, rad).
        sift_points: (N, 3) SIFT keypoints with valid depth, body frame (m).
        sift_descriptors: (N, 128) float32 descriptors.
        depth_points: (P, 3) depth points, body frame (m), for the virtual scan.
    """

    t: float
    odom: FloatArray
    sift_points: FloatArray
    sift_descriptors: Float32Array
    depth_points: FloatArray


@dataclass(frozen=True)
class DriveFrame:
    """One ceiling-camera frame recorded while driving on.

    Attributes:
        t: time (s).
        odom: (3,) ``odom_T_body`` (m, m, rad).
        ceiling_m: (K, 2) observed ceiling features (lamps and corners) in
            normalised ceiling coordinates (paper 1, eqs. 17-18; conventions.md).
        ceiling_is_lamp: (K,) bool, which of them are lamps (None: unknown).
        ceiling_axis: (K,) lamps' long axes in the image (rad, mod pi, the
            frontend's ``LampObservation.axis``), NaN for none (None: unknown).
    """

    t: float
    odom: FloatArray
    ceiling_m: FloatArray
    ceiling_is_lamp: BoolArray | None = None
    ceiling_axis: FloatArray | None = None
