"""TUM trajectory files: one parser with a planar and a 3-D view, and the writer.

Format (TUM RGB-D benchmark, read and written by ``evo``): one pose per line,
``t tx ty tz qx qy qz qw``, space separated; blank lines and ``#`` comments are
skipped. ``t`` is in seconds, ``tx ty tz`` in metres, ``q`` the Hamilton unit
quaternion (scalar last) of the rotation ``world_R_body``. Time stamps must
increase strictly.

Views of the same parsed rows:

- :func:`read_tum` -> :class:`~lampsam.datasets.tables.Trajectory` of planar poses
  ``(x, y, yaw)`` (``z``, roll and pitch dropped): logged-run ground truth, SLAM
  estimates, stereo two-point runs.
- :func:`read_tum_3d` -> (K, 4, 4) transforms: RGB-D sequences.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from lampsam.angles import wrap_angle
from lampsam.arrays import FloatArray
from lampsam.datasets.tables import Trajectory
from lampsam.datasets.textio import check_coordinates, check_time, data_lines, parse_float
from lampsam.errors import DatasetError
from lampsam.safe_io import atomic_path

log = logging.getLogger(__name__)

#: A planar read warns when a pose's body z axis tilts more than this from world z, deg.
MAX_PLANAR_TILT_DEG = 20.0
#: Time stamps above this (about year 5100 in seconds) are taken for nanoseconds, s.
MAX_SECONDS_STAMP = 1e11

TUM_FIELDS = ("t", "x", "y", "z", "qx", "qy", "qz", "qw")
"""Column names of a TUM line (used in error messages)."""


@dataclass(frozen=True, eq=False)
class TumRows:
    """The parsed lines of a TUM file.

    Attributes:
        t: (K,) time stamps, s, strictly increasing.
        xyz: (K, 3) positions, m.
        quat_xyzw: (K, 4) quaternions ``(qx, qy, qz, qw)`` as written (not normalised;
            never zero).
        lines: the 1-based line number of each row (for later error messages).
    """

    t: FloatArray
    xyz: FloatArray
    quat_xyzw: FloatArray
    lines: list[int]


def read_tum_rows(path: str | Path) -> TumRows:
    """Parse a TUM file (module docstring) with errors naming file and line.

    Raises:
        DatasetError: missing file, a line without 8 fields, a non-number or non-finite
            value, a zero quaternion, no poses, a time stamp that does not increase, or
            a coordinate beyond ``textio.MAX_COORDINATE`` (1e8 m).
    """
    path = Path(path)
    rows: list[list[float]] = []
    lines: list[int] = []
    for lineno, text in data_lines(path):
        fields = text.split()
        if len(fields) != 8:
            hint = " (comma-separated? TUM is space-separated)" if "," in text else ""
            raise DatasetError(
                f"malformed line: expected 8 fields 't x y z qx qy qz qw', got {len(fields)}"
                + hint,
                path,
                lineno,
            )
        vals = [parse_float(f, path, lineno, c) for f, c in zip(fields, TUM_FIELDS, strict=True)]
        if sum(v * v for v in vals[4:]) < 1e-12:
            raise DatasetError("zero quaternion", path, lineno)
        rows.append(vals)
        lines.append(lineno)
    if not rows:
        raise DatasetError("no poses (empty trajectory)", path)
    a = np.array(rows, dtype=np.float64)
    check_time(a[:, 0], lines, path)
    check_coordinates(a[:, 1:4], lines, path, "x/y/z")
    if a[0, 0] > MAX_SECONDS_STAMP:
        log.warning("%s:%d: time stamp %.6g s is thousands of years from now: nanoseconds? "
                    "TUM time stamps are seconds (divide by 1e9)", path, lines[0], a[0, 0])
    return TumRows(t=a[:, 0].copy(), xyz=a[:, 1:4].copy(), quat_xyzw=a[:, 4:8].copy(), lines=lines)


def yaw_from_quaternions(quat_xyzw: FloatArray) -> FloatArray:
    """Yaw (rotation about ``z``, ZYX Euler) of quaternions, rad in (-pi, pi].

    Args:
        quat_xyzw: (K, 4) ``(qx, qy, qz, qw)``, any non-zero norm (normalised here:
            the formula below holds for unit quaternions only).

    Returns:
        (K,) ``atan2(2 (qw qz + qx qy), 1 - 2 (qy^2 + qz^2))``.
    """
    q = np.asarray(quat_xyzw, dtype=np.float64).reshape(-1, 4)
    q = q / np.linalg.norm(q, axis=1, keepdims=True)
    qx, qy, qz, qw = q[:, 0], q[:, 1], q[:, 2], q[:, 3]
    return np.asarray(
        wrap_angle(np.arctan2(2.0 * (qw * qz + qx * qy), 1.0 - 2.0 * (qy * qy + qz * qz)))
    )


def tilt_deg(quat_xyzw: FloatArray) -> FloatArray:
    """Angle between each rotation's body z axis and world z, deg.

    Args:
        quat_xyzw: (K, 4) ``(qx, qy, qz, qw)``, any non-zero norm.

    Returns:
        (K,) ``acos(1 - 2 (qx^2 + qy^2))`` of the unit quaternions, deg in [0, 180].
    """
    q = np.asarray(quat_xyzw, dtype=np.float64).reshape(-1, 4)
    q = q / np.linalg.norm(q, axis=1, keepdims=True)
    cos_tilt = np.clip(1.0 - 2.0 * (q[:, 0] ** 2 + q[:, 1] ** 2), -1.0, 1.0)
    return np.degrees(np.arccos(cos_tilt))


def pose_from_tum_fields(vals: list[float] | FloatArray) -> FloatArray:
    """(4, 4) transform from the seven numbers ``tx ty tz qx qy qz qw`` (quaternion normalised)."""
    from scipy.spatial.transform import Rotation

    v = np.asarray(vals, dtype=np.float64)
    T = np.eye(4)
    T[:3, :3] = Rotation.from_quat(v[3:7]).as_matrix()
    T[:3, 3] = v[:3]
    return T


def read_tum(path: str | Path) -> Trajectory:
    """Read a TUM trajectory as planar poses ``(x, y, yaw)``.

    ``theta`` is the yaw of the quaternion; ``z`` and any roll/pitch are dropped (one
    warning, naming the line, when a pose tilts over :data:`MAX_PLANAR_TILT_DEG`: a
    camera-frame trajectory read this way is wrong).

    Raises:
        DatasetError: as :func:`read_tum_rows`.
    """
    rows = read_tum_rows(path)
    tilt = tilt_deg(rows.quat_xyzw)
    over = np.flatnonzero(tilt > MAX_PLANAR_TILT_DEG)
    if len(over):
        first = int(over[0])
        log.warning(
            "%s:%d: the pose tilts %.0f deg from upright (%d of %d poses over %.0f deg): read as "
            "planar (x, y, yaw) with roll and pitch dropped, which is only right for a body "
            "frame with z up; a camera-frame trajectory (z forward, as visual SLAM writes "
            "it) must be turned into the robot's body frame first", Path(path),
            rows.lines[first], tilt[first], len(over), len(tilt),
            MAX_PLANAR_TILT_DEG)
    poses = np.column_stack([rows.xyz[:, :2], yaw_from_quaternions(rows.quat_xyzw)])
    return Trajectory(t=rows.t, poses=poses)


def read_tum_3d(path: str | Path) -> tuple[FloatArray, FloatArray]:
    """Read a TUM trajectory as full 3-D poses.

    Returns:
        ``t`` (K,) seconds and ``world_T_body`` (K, 4, 4).

    Raises:
        DatasetError: as :func:`read_tum_rows`.
    """
    rows = read_tum_rows(path)
    poses = np.stack(
        [pose_from_tum_fields(np.concatenate([p, q])) for p, q in zip(rows.xyz, rows.quat_xyzw, strict=True)]
    )
    return rows.t, poses


def write_tum(path: str | Path, trajectory: Trajectory, comment: str = "t x y z qx qy qz qw") -> None:
    """Write a planar trajectory as TUM (``z = 0``, yaw-only quaternion), readable by evo.

    Args:
        path: the file (overwritten).
        trajectory: planar poses ``(x, y, theta)`` at times ``t``.
        comment: text of the ``#`` first line.

    Times are written to 1 us, positions to 1 nm, quaternions to 12 decimals.
    """
    with atomic_path(path) as tmp, open(tmp, "w", encoding="utf-8") as fh:
        fh.write(f"# {comment}\n")
        for t, (x, y, th) in zip(trajectory.t, trajectory.poses, strict=True):
            fh.write(
                f"{t:.6f} {x:.9f} {y:.9f} 0 0 0 {math.sin(th / 2):.12f} {math.cos(th / 2):.12f}\n"
            )
