"""Where the mapping sensor was: pose sources for the map build.

``build_map`` places each frame or scan with a pose from the run's truth
(``groundtruth``) or from a SLAM trajectory (``slam:PATH``, planar TUM). The
trajectory is sampled at the frame times (:func:`planar_poses_at`), and a planar
body pose becomes a camera pose with the rig's mounting
(:func:`camera_poses_from_planar`).

Frames: ``world`` x, y on the floor, z up; ``body`` the robot's base (x forward,
y left); ``camera`` OpenCV (docs/conventions.md). Metres, radians, seconds.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from lampsam.arrays import FloatArray
from lampsam.localization.map_store import EnvMapError


def parse_pose_source(poses: str) -> tuple[str, Path | None]:
    """``"groundtruth"`` or ``"slam:PATH"`` -> (kind, path).

    Raises:
        EnvMapError: anything else.
    """
    if poses == "groundtruth":
        return "groundtruth", None
    if poses.startswith("slam:") and len(poses) > 5:
        return "slam", Path(poses[5:])
    raise EnvMapError(f"--poses must be 'groundtruth' or 'slam:PATH_TO_TUM', got {poses!r}")


def planar_poses_at(
    traj_t: FloatArray, traj_poses: FloatArray, t: FloatArray, tolerance: float, source: str
) -> FloatArray:
    """Planar poses at frame times, interpolated (x, y linear, heading unwrapped).

    Args:
        traj_t: (K,) trajectory times, s, increasing.
        traj_poses: (K, 3) ``(x, y, theta)``.
        t: (N,) frame times, s.
        tolerance: how far a frame may lie outside ``[traj_t[0], traj_t[-1]]``, s.
        source: name of the trajectory for the error message.

    Returns:
        (N, 3) poses.

    Raises:
        EnvMapError: a frame without a pose (outside the span by more than ``tolerance``).
    """
    t = np.asarray(t, float)
    outside = (t < traj_t[0] - tolerance) | (t > traj_t[-1] + tolerance)
    if np.any(outside):
        i = int(np.flatnonzero(outside)[0])
        raise EnvMapError(
            f"{source}: no pose for frame {i} at t={t[i]:.3f} s "
            f"(trajectory covers {traj_t[0]:.3f}..{traj_t[-1]:.3f} s; "
            f"{int(outside.sum())} frames without pose)"
        )
    th = np.unwrap(traj_poses[:, 2])
    out = np.column_stack(
        [
            np.interp(t, traj_t, traj_poses[:, 0]),
            np.interp(t, traj_t, traj_poses[:, 1]),
            np.interp(t, traj_t, th),
        ]
    )
    out[:, 2] = np.mod(out[:, 2] + np.pi, 2 * np.pi) - np.pi
    return out


def camera_poses_from_planar(planar: FloatArray, body_T_camera: FloatArray) -> FloatArray:  # noqa: N803
    """(N, 4, 4) ``world_T_camera = world_T_body(x, y, theta) @ body_T_camera``."""
    n = len(planar)
    T = np.tile(np.eye(4), (n, 1, 1))
    c, s = np.cos(planar[:, 2]), np.sin(planar[:, 2])
    T[:, 0, 0], T[:, 0, 1], T[:, 1, 0], T[:, 1, 1] = c, -s, s, c
    T[:, 0, 3], T[:, 1, 3] = planar[:, 0], planar[:, 1]
    return T @ body_T_camera
