"""Odometry as relative ``Pose2`` increments in the logged-run format (beside wheel travel).

A logged run's odometry is either wheel travel (``odometry.csv``, ``t,d_left,d_right``:
the ceiling robot's differential drive, paper 1 eqs. 13-15) or, for any other robot,
``odometry_pose2.csv``:

    t,dx,dy,dtheta,var_x,cov_xy,cov_xtheta,var_y,cov_ytheta,var_theta

one line per odometry sample: the increment ``prev_T_body`` since the previous line
(the first line: since the start pose) in the previous sample's body frame, m and
rad, and its covariance in GTSAM's right tangent at the increment (m^2, rad^2;
docs/conventions.md). Empty or ``nan`` covariance fields mean "use the model's
default" (:class:`Pose2OdometryModel`). Absolute odometry poses (``nav_msgs/Odometry``
poses, a wheel-odometry TUM file) become increments with
:func:`pose2_odometry_from_poses`.
"""

from __future__ import annotations

import csv
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from lampsam.angles import wrap_angle
from lampsam.arrays import FloatArray
from lampsam.config_loader import check_limits, limits
from lampsam.datasets.textio import check_speed, open_text
from lampsam.errors import DatasetError
from lampsam.safe_io import atomic_path


def increments_from_poses(poses: FloatArray) -> FloatArray:
    """Absolute odometry poses -> increments (``delta_i = pose_{i-1}^-1 pose_i``).

    Args:
        poses: (N, 3) ``odom_T_body`` (x, y in m, theta in rad) in the odometry's own
            (drifting) frame.

    Returns:
        (N, 3) increments in the frame of the earlier pose; the first is zero (the
        robot is at its first pose).
    """
    p = np.asarray(poses, dtype=float).reshape(-1, 3)
    out = np.zeros_like(p)
    if len(p) > 1:
        d = p[1:, :2] - p[:-1, :2]
        c, s = np.cos(p[:-1, 2]), np.sin(p[:-1, 2])
        out[1:, 0] = c * d[:, 0] + s * d[:, 1]
        out[1:, 1] = -s * d[:, 0] + c * d[:, 1]
        out[1:, 2] = wrap_angle(p[1:, 2] - p[:-1, 2])
    return out

#: File name of Pose2-increment odometry in a run directory.
ODOMETRY_POSE2_FILE = "odometry_pose2.csv"
#: File name of absolute odometry poses (TUM, planar) in a run directory.
ODOMETRY_POSES_FILE = "odometry_poses.tum"
#: Its header.
ODOMETRY_POSE2_HEADER = ("t", "dx", "dy", "dtheta", "var_x", "cov_xy", "cov_xtheta", "var_y",
                         "cov_ytheta", "var_theta")
#: Columns of a step's sample matrix: increment (3) + row-major covariance (9).
POSE2_SAMPLE_WIDTH = 12


@dataclass(frozen=True)
class Pose2OdometryModel:
    """Noise of Pose2-increment odometry where a sample gives none, and its floor.

    A sample without a covariance gets
    ``diag(k_xy |d|, k_xy |d|, k_theta |dtheta| + k_theta_xy |d|)`` (variance growing
    with travel, as eq. 15 for wheels); every sample (with or without one) then gets
    ``diag(var_floor_xy, var_floor_xy, var_floor_theta)`` added. The floor is what
    keeps a robot at rest from giving a zero (singular) covariance: over ``N`` samples
    at rest the odometry's uncertainty grows as ``N`` times the floor (a random walk
    per sample), never to an infinitely confident factor.

    Set from a SLAM config's ``[pose2_odometry]`` table or a run's ``rig.yaml``
    ``pose2_odometry`` section (the rig's wins: it describes the robot; see
    :func:`lampsam.backend.slam.pose2_model_for`), both read by the strict loader.

    Attributes:
        k_xy: translation variance per metre travelled, m (default 1e-4: 1 cm over 1 m).
        k_theta: heading variance per radian turned, rad (default 1e-4).
        k_theta_xy: heading variance per metre travelled, rad^2/m (default 1e-5).
        var_floor_xy: translation variance added per sample, m^2 (default 1e-8).
        var_floor_theta: heading variance added per sample, rad^2 (default 1e-8).
        cov_scale: factor on the covariance a sample carries itself (a log's stated
            odometry noise), default 1. A filter linearised at drifting estimates is
            overconfident when the stated noise is the optimum's (Victoria Park: the
            EKF's revisits come back beyond the 99 % gate even with known ids); a
            variance factor > 1 keeps a revisited landmark inside the gate, which
            association without ids needs (docs/graph-backend.md, "Association without
            ids on Victoria Park").
    """

    k_xy: float = field(default=1e-4, metadata=limits(ge=0.0))
    k_theta: float = field(default=1e-4, metadata=limits(ge=0.0))
    k_theta_xy: float = field(default=1e-5, metadata=limits(ge=0.0))
    var_floor_xy: float = field(default=1e-8, metadata=limits(gt=0.0))
    var_floor_theta: float = field(default=1e-8, metadata=limits(gt=0.0))
    cov_scale: float = field(default=1.0, metadata=limits(gt=0.0))

    def __post_init__(self) -> None:
        """Validate: every constant finite and >= 0, the floors > 0 (a robot at rest
        would otherwise give a singular covariance); a FieldValueError names the key."""
        check_limits(self)
        vals = (self.k_xy, self.k_theta, self.k_theta_xy, self.var_floor_xy, self.var_floor_theta,
                self.cov_scale)
        if not all(math.isfinite(v) for v in vals):
            raise ValueError(f"Pose2OdometryModel constants must be finite, got {vals}")

    def sample_cov(self, delta: FloatArray, cov: FloatArray) -> FloatArray:
        """(3, 3) covariance of one sample: its own (or the default) plus the floor.

        Args:
            delta: (3,) the increment; cov: (3, 3) its covariance, NaN if not given.
        """
        if not np.all(np.isfinite(cov)):
            d = math.hypot(float(delta[0]), float(delta[1]))
            cov = np.diag([self.k_xy * d, self.k_xy * d,
                           self.k_theta * abs(float(delta[2])) + self.k_theta_xy * d])
        elif self.cov_scale != 1.0:
            cov = self.cov_scale * cov
        return cov + np.diag([self.var_floor_xy, self.var_floor_xy, self.var_floor_theta])


@dataclass(frozen=True, eq=False)
class Pose2OdometryLog:
    """Odometry as relative Pose2 increments (see module docstring).

    Attributes:
        t: (N,) time stamps, s, strictly increasing.
        delta: (N, 3) increments ``(dx, dy, dtheta)`` since the previous sample, in its
            body frame, m and rad.
        cov: (N, 3, 3) right-tangent covariances, m^2 / rad^2; NaN = model default.
    """

    t: FloatArray
    delta: FloatArray
    cov: FloatArray

    def __post_init__(self) -> None:
        """Check shapes: (N,), (N, 3), (N, 3, 3)."""
        n = len(self.t)
        if np.shape(self.delta) != (n, 3) or np.shape(self.cov) != (n, 3, 3):
            raise ValueError(f"Pose2OdometryLog: t {np.shape(self.t)}, delta "
                             f"{np.shape(self.delta)}, cov {np.shape(self.cov)} disagree")

    def __len__(self) -> int:
        """Number of samples."""
        return int(len(self.t))

    def samples(self) -> FloatArray:
        """(N, 12) rows ``[dx, dy, dtheta, cov row-major]`` (what a backend step takes)."""
        return np.hstack([self.delta, self.cov.reshape(-1, 9)])


def pose2_odometry_from_poses(t: FloatArray, poses: FloatArray,
                              cov: FloatArray | None = None) -> Pose2OdometryLog:
    """Absolute odometry poses -> a :class:`Pose2OdometryLog` of increments.

    Args:
        t: (N,) time stamps, s.
        poses: (N, 3) ``odom_T_body`` in the odometry's own frame, m and rad.
        cov: optional (N, 3, 3) right-tangent covariance of each increment (e.g. a
            twist covariance times dt^2); None: the model's default.

    Returns:
        The increments; the first is zero (the run starts at the first pose).
    """
    t = np.asarray(t, float)
    c = np.full((len(t), 3, 3), np.nan) if cov is None else np.asarray(cov, float)
    return Pose2OdometryLog(t=t, delta=increments_from_poses(poses), cov=c)


def read_pose2_odometry(path: str | Path) -> Pose2OdometryLog:
    """Read ``odometry_pose2.csv`` (header and units: module docstring).

    Raises:
        DatasetError: missing file, wrong header, a malformed or non-finite field
            (covariance fields may be empty or ``nan``), time not increasing, or an
            increment faster than ``textio.MAX_SPEED`` (100 m/s);
            the message names the file and line.
    """
    path = Path(path)
    rows: list[list[float]] = []
    lines: list[int] = []
    with open_text(path) as fh:
        reader = csv.reader(fh)
        header = next(reader, None)
        if header is None or tuple(h.strip() for h in header) != ODOMETRY_POSE2_HEADER:
            raise DatasetError(f"header must be {','.join(ODOMETRY_POSE2_HEADER)}", path, 1)
        for line, row in enumerate(reader, start=2):
            if not row or all(not f.strip() for f in row):
                continue
            if len(row) != len(ODOMETRY_POSE2_HEADER):
                raise DatasetError(f"expected {len(ODOMETRY_POSE2_HEADER)} fields, got {len(row)}",
                                   path, line)
            vals: list[float] = []
            for col, text in zip(ODOMETRY_POSE2_HEADER, row, strict=True):
                text = text.strip()
                if not text and col.startswith(("var", "cov")):
                    vals.append(math.nan)
                    continue
                try:
                    v = float(text)
                except ValueError:
                    raise DatasetError(f"column {col!r}: not a number: {text!r}", path,
                                       line) from None
                if not math.isfinite(v) and not col.startswith(("var", "cov")):
                    raise DatasetError(f"column {col!r}: not finite: {text!r}", path, line)
                vals.append(v)
            if rows and vals[0] <= rows[-1][0]:
                raise DatasetError(f"time {vals[0]} does not increase (previous {rows[-1][0]})",
                                   path, line)
            rows.append(vals)
            lines.append(line)
    if not rows:
        raise DatasetError("no odometry samples", path)
    a = np.array(rows)
    check_speed(a[:, 0], np.hypot(a[:, 1], a[:, 2]), lines, path, "dx/dy")
    i = [4, 5, 6, 5, 7, 8, 6, 8, 9]  # symmetric 3x3 from the upper triangle
    return Pose2OdometryLog(t=a[:, 0], delta=a[:, 1:4], cov=a[:, i].reshape(-1, 3, 3))


def write_pose2_odometry(path: str | Path, odometry: Pose2OdometryLog) -> None:
    """Write ``odometry_pose2.csv`` (time to 1 us; NaN covariances as empty fields)."""
    path = Path(path)
    with atomic_path(path) as tmp, tmp.open("w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(ODOMETRY_POSE2_HEADER)
        for t, d, c in zip(odometry.t, odometry.delta, odometry.cov, strict=True):
            cv = [c[0, 0], c[0, 1], c[0, 2], c[1, 1], c[1, 2], c[2, 2]]
            w.writerow([f"{t:.6f}", *(repr(float(x)) for x in d),
                        *("" if not math.isfinite(x) else repr(float(x)) for x in cv)])
