"""Reader for CARMEN laser logs (the Intel Research Lab log, ``intel-corrected.log.gz``).

Lines used (CARMEN logger format, whitespace separated; ``#`` lines are comments):

- ``FLASER n r_0 .. r_{n-1} x y theta odom_x odom_y odom_theta timestamp host logger_ts``:
  a front laser scan of ``n`` beams (metres); ``(x, y, theta)`` the laser pose in
  the world (in the ``-corrected`` logs: the SLAM-corrected pose, the pseudo ground
  truth), ``odom_*`` the odometry pose (identical to the corrected pose in this log,
  so odometry must be simulated).
- ``ODOM x y theta tv rv accel timestamp host logger_ts`` (all zero in this log).
- Other message types (``PARAM``, ``NEFF``, ...) are ignored.

Beam angles: CARMEN's front laser (SICK LMS) with 180 beams covers 180 deg with
1 deg steps, from the right to the left of the robot:
``angle_i = -pi/2 + i * pi/180`` in the laser frame (CCW from forward, i = 0..179).
This was checked against the data: the scans drawn at the corrected poses with
this convention give the sharpest walls (tests/test_carmen.py), and reversing
the beam order or spreading 180 beams over 179 deg blurs them.

Readings at or above ``max_range`` (81.83 m in the Intel log) are "no return".
The laser sits at the robot's rotation centre (``robot_frontlaser_offset 0.0``).
"""

from __future__ import annotations

import gzip
import logging
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from lampsam.arrays import FloatArray
from lampsam.errors import DatasetError

log = logging.getLogger(__name__)

#: Ranges at or above this are the SICK scanner's "no return" value in the Intel log, m.
INTEL_MAX_RANGE = 80.0


@dataclass(frozen=True)
class LaserScans:
    """Planar laser scans with their poses.

    Attributes:
        t: (N,) timestamps, s, strictly increasing.
        ranges: (N, B) ranges, metres (``>= max_range`` = no return).
        angles: (B,) beam angles in the laser frame, rad, CCW from forward.
        poses: (N, 3) world pose ``(x, y, theta)`` of the laser at each scan
            (SLAM-corrected in the ``-corrected`` logs).
        odom_poses: (N, 3) odometry poses as logged.
        line: (N,) 1-based line numbers of the scans in the log.
        max_range: ranges at or above this are no return, metres.
    """

    t: FloatArray
    ranges: FloatArray
    angles: FloatArray
    poses: FloatArray
    odom_poses: FloatArray
    line: np.ndarray
    max_range: float

    def __len__(self) -> int:
        return int(self.t.shape[0])

    def subset(self, index: np.ndarray) -> LaserScans:
        """The scans selected by ``index`` (an integer or boolean array)."""
        return LaserScans(self.t[index], self.ranges[index], self.angles, self.poses[index],
                          self.odom_poses[index], self.line[index], self.max_range)


@dataclass(frozen=True)
class CarmenLog:
    """What :func:`read_carmen` returns.

    Attributes:
        path: the file read.
        scans: the FLASER scans (out-of-order ones dropped, see :func:`read_carmen`).
        odom_t: (M,) ODOM timestamps, s.
        odom_poses: (M, 3) ODOM ``(x, y, theta)``.
    """

    path: Path
    scans: LaserScans
    odom_t: FloatArray
    odom_poses: FloatArray


def carmen_beam_angles(n_beams: int, fov: float = math.pi) -> FloatArray:
    """Beam angles of a CARMEN front laser, rad, CCW from forward.

    Args:
        n_beams: number of beams (180 in the Intel log).
        fov: field of view, rad (pi for 180 beams at 1 deg).

    Returns:
        (n_beams,) ``-fov/2 + i * fov / n_beams``.
    """
    return -fov / 2 + np.arange(n_beams) * (fov / n_beams)


def _floats(tokens: list[str], path: Path, line_no: int) -> list[float]:
    """``tokens`` as floats; DatasetError naming ``path`` and ``line_no`` on a non-number."""
    try:
        values = [float(v) for v in tokens]
    except ValueError as exc:
        raise DatasetError(f"not a number in {tokens[0]!r}...: {exc}", path=path,
                           line=line_no) from exc
    if not all(math.isfinite(v) for v in values):
        raise DatasetError("non-finite value (NaN or inf)", path=path, line=line_no)
    return values


def read_carmen(path: str | Path, max_range: float = INTEL_MAX_RANGE,
                strict_time: bool = False) -> CarmenLog:
    """Read a CARMEN log (plain or ``.gz``).

    Args:
        path: the log file.
        max_range: ranges at or above this are no return, metres.
        strict_time: if True, a scan whose timestamp is not later than the
            previous scan's raises; if False (default) it is dropped with a logged
            warning (the Intel log has 4 such scans, 0.05-0.86 s back in time).

    Returns:
        The scans and odometry.

    Raises:
        DatasetError: missing file, malformed FLASER/ODOM line (wrong field count,
            not a number, NaN), inconsistent beam count, no scans, time going
            backwards with ``strict_time``; the message names the file and line.
    """
    path = Path(path)
    if not path.is_file():
        raise DatasetError("CARMEN log not found", path=path)
    opener = gzip.open if path.suffix == ".gz" else open
    t: list[float] = []
    ranges: list[list[float]] = []
    poses: list[list[float]] = []
    odom: list[list[float]] = []
    lines: list[int] = []
    odom_t: list[float] = []
    odom_poses: list[list[float]] = []
    n_beams: int | None = None
    try:
        with opener(path, "rt", encoding="ascii", errors="replace") as fh:
            for line_no, raw in enumerate(fh, start=1):
                tok = raw.split()
                if not tok or tok[0].startswith("#"):
                    continue
                if tok[0] == "FLASER":
                    try:
                        n = int(tok[1])
                    except (IndexError, ValueError) as exc:
                        raise DatasetError("FLASER line without a beam count", path=path,
                                           line=line_no) from exc
                    if len(tok) < 2 + n + 7 or n <= 0:
                        raise DatasetError(
                            f"FLASER with {n} beams needs {2 + n + 7} fields, got {len(tok)}",
                            path=path, line=line_no)
                    if n_beams is None:
                        n_beams = n
                    elif n != n_beams:
                        raise DatasetError(f"FLASER beam count {n} differs from earlier {n_beams}",
                                           path=path, line=line_no)
                    values = _floats(tok[2:2 + n + 7], path, line_no)
                    ts = values[n + 6]
                    if t and ts <= t[-1]:
                        if strict_time:
                            raise DatasetError(f"time goes backwards: {ts} after {t[-1]}",
                                               path=path, line=line_no)
                        log.warning("%s:%d: scan time %.3f not after %.3f, scan skipped",
                                    path, line_no, ts, t[-1])
                        continue
                    ranges.append(values[:n])
                    poses.append(values[n:n + 3])
                    odom.append(values[n + 3:n + 6])
                    t.append(ts)
                    lines.append(line_no)
                elif tok[0] == "ODOM":
                    if len(tok) < 8:
                        raise DatasetError(f"ODOM needs at least 8 fields, got {len(tok)}",
                                           path=path, line=line_no)
                    values = _floats(tok[1:8], path, line_no)
                    odom_poses.append(values[:3])
                    odom_t.append(values[6])
    except (OSError, EOFError, UnicodeDecodeError) as exc:
        raise DatasetError(f"cannot read: {exc}", path=path) from exc
    if not t or n_beams is None:
        raise DatasetError("no FLASER scans in the log", path=path)
    scans = LaserScans(
        t=np.array(t), ranges=np.array(ranges), angles=carmen_beam_angles(n_beams),
        poses=np.array(poses), odom_poses=np.array(odom), line=np.array(lines, dtype=np.int64),
        max_range=float(max_range))
    log.info("%s: %d scans of %d beams, %d odometry records", path, len(t), n_beams,
             len(odom_t))
    return CarmenLog(path, scans, np.array(odom_t), np.array(odom_poses).reshape(-1, 3))


def scan_endpoints(scans: LaserScans, index: int | None = None) -> FloatArray:
    """World coordinates of the beam endpoints that returned (range < max_range).

    Args:
        scans: the scans.
        index: one scan, or None for all.

    Returns:
        (K, 2) world points, metres.
    """
    sel = slice(None) if index is None else slice(index, index + 1)
    r = scans.ranges[sel]
    p = scans.poses[sel]
    phi = p[:, 2:3] + scans.angles[None, :]
    x = p[:, 0:1] + r * np.cos(phi)
    y = p[:, 1:2] + r * np.sin(phi)
    ok = r < scans.max_range
    return np.stack([x[ok], y[ok]], axis=1)
