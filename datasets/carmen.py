"""Reader for CARMEN laser logs (the Intel Research Lab log and logs of other buildings).

Lines used (CARMEN logger format, whitespace separated; ``#`` lines are comments):

- ``FLASER n r_0 .. r_{n-1} x y theta odom_x odom_y odom_theta timestamp host logger_ts``:
  a front laser scan of ``n`` beams (metres); ``(x, y, theta)`` the laser pose in
  the world (in the ``-corrected`` logs: the SLAM-corrected pose, the pseudo ground
  truth), ``odom_*`` the robot's odometry pose.
- ``ROBOTLASER1 laser_type start_angle fov angular_resolution max_range accuracy
  remission_mode n r_0 .. r_{n-1} n_rem rem_0 .. rem_{n_rem-1} laser_x laser_y
  laser_theta robot_x robot_y robot_theta tv rv forward_safety side_safety turn_axis
  timestamp host logger_ts``: the newer front-laser message, which carries its own
  geometry (angles in rad, ranges in metres).
- ``ODOM x y theta tv rv accel timestamp host logger_ts`` (all zero in the Intel log).
- Other message types (``PARAM``, ``NEFF``, ``RAWLASER*``, ...) are ignored. A log with
  both FLASER and ROBOTLASER1 lines is read from its ROBOTLASER1 lines (they say
  their geometry; the FLASER lines of such logs repeat the same scans).

Beam angles, in the laser frame (rad, CCW from forward, first beam on the right):

- ROBOTLASER1: ``start_angle + i * angular_resolution`` as the message says.
- FLASER carries only the beam count; the log's ``PARAM laser_front_laser_fov``
  (degrees) and ``PARAM laser_front_laser_flipped`` give the geometry when present,
  else the scanner is a SICK LMS covering 180 deg from the right: ``-pi/2 + i * step``
  with ``step = pi / n`` for an even count (180 beams: 1 deg, -90..89 deg; 360: 0.5 deg) and ``step = pi / (n - 1)`` for an
  odd count (181: 1 deg and 361: 0.5 deg, both ends included)
  (:func:`flaser_beam_angles`). The 180-beam convention gives the sharpest walls on
  the Intel log (tests/test_carmen.py); reversing the beam order blurs them.

Time stamps: the scans keep the file order. Real logs of other buildings print the
time with 6 significant digits (``1.13486e+09`` on every scan) or write 0, so the
stamps cannot order the scans; :func:`~lampsam.datasets.scan_times.derive_scan_times` then takes the logger's
stamps when they increase, else spreads equal stamps evenly between distinct
values, else counts scans at a nominal rate, and the reader logs ONE warning that
says which. A scan stamped earlier than a previous one is dropped (or, with
``strict_time``, an error).

Readings at or above ``max_range`` are "no return" (80 m for FLASER, below the SICK's
81.83 m "no return" value in the Intel log; ROBOTLASER1's own ``max_range``).
The laser sits at the robot's rotation centre in the Intel log
(``robot_frontlaser_offset 0.0``).
"""

from __future__ import annotations

import gzip
import logging
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from lampsam.arrays import FloatArray
from lampsam.datasets.scan_times import NOMINAL_SCAN_RATE_HZ, derive_scan_times
from lampsam.errors import DatasetError

log = logging.getLogger(__name__)

#: Ranges at or above this are the SICK scanner's "no return" value in the Intel log, m.
INTEL_MAX_RANGE = 80.0

#: Message names of the CARMEN logger and of logs written in its format: a log's
#: records (non-comment lines) start with one of these.
CARMEN_MESSAGES = frozenset({
    "PARAM", "SYNC", "ODOM", "TRUEPOS", "FLASER", "RLASER", "LASER3", "LASER4",
    "ROBOTLASER1", "ROBOTLASER2", "RAWLASER1", "RAWLASER2", "RAWLASER3", "RAWLASER4",
    "REMISSIONFLASER", "REMISSIONRLASER", "NEFF", "SONAR", "BUMPER", "SCANMARK",
    "POSITIONLASER", "IMU", "GPSNMEA", "NMEAGGA", "NMEARMC", "ROBOTVELOCITY",
    "BASEVELOCITY", "VECTORMOVE",
})
#: Records looked at to recognise a log (:func:`sniff_carmen`).
SNIFF_RECORDS = 50


@dataclass(frozen=True)
class LaserScans:
    """Planar laser scans with their poses.

    Attributes:
        t: (N,) times, s, strictly increasing (derived when the log's stamps are
            coarse or zero: ``time_source``).
        ranges: (N, B) ranges, metres (``>= max_range`` = no return).
        angles: (B,) beam angles in the laser frame, rad, CCW from forward.
        poses: (N, 3) world pose ``(x, y, theta)`` of the laser at each scan
            (SLAM-corrected in the ``-corrected`` logs).
        odom_poses: (N, 3) the robot's odometry poses as logged.
        line: (N,) 1-based line numbers of the scans in the log.
        max_range: ranges at or above this are no return, metres.
        time_source: where ``t`` comes from: ``log`` (the message stamps), ``logger``
            (the logger's stamps), ``spread`` (equal stamps spread between distinct
            values) or ``rate`` (the nominal scan rate).
    """

    t: FloatArray
    ranges: FloatArray
    angles: FloatArray
    poses: FloatArray
    odom_poses: FloatArray
    line: np.ndarray
    max_range: float
    time_source: str = "log"

    def __len__(self) -> int:
        return int(self.t.shape[0])

    def subset(self, index: np.ndarray) -> LaserScans:
        """The scans selected by ``index`` (an integer or boolean array)."""
        return LaserScans(self.t[index], self.ranges[index], self.angles, self.poses[index],
                          self.odom_poses[index], self.line[index], self.max_range,
                          self.time_source)


@dataclass(frozen=True)
class CarmenLog:
    """What :func:`read_carmen` returns.

    Attributes:
        path: the file read.
        scans: the laser scans (out-of-order ones dropped, see :func:`read_carmen`).
        odom_t: (M,) ODOM time stamps as logged, s.
        odom_poses: (M, 3) ODOM ``(x, y, theta)``.
        message: the laser message read, ``FLASER`` or ``ROBOTLASER1``.
        time_note: what was done to the scans' time stamps ("" when they were used as
            logged).
    """

    path: Path
    scans: LaserScans
    odom_t: FloatArray
    odom_poses: FloatArray
    message: str = "FLASER"
    time_note: str = ""


def carmen_beam_angles(n_beams: int, fov: float = math.pi) -> FloatArray:
    """Beam angles of ``n_beams`` spread over ``fov`` from the right, last end open.

    Args:
        n_beams: number of beams (180 in the Intel log).
        fov: field of view, rad (pi for 180 beams at 1 deg).

    Returns:
        (n_beams,) ``-fov/2 + i * fov / n_beams``, rad.
    """
    return -fov / 2 + np.arange(n_beams, dtype=np.float64) * (fov / n_beams)


def flaser_beam_angles(n_beams: int, fov: float = math.pi, flipped: bool = False) -> FloatArray:
    """Beam angles of a FLASER scan of ``n_beams`` (a SICK LMS over 180 deg by default), rad.

    Args:
        n_beams: the beam count of the message.
        fov: the field of view, rad (the log's ``PARAM laser_front_laser_fov``, in
            degrees there; default pi).
        flipped: the scanner is mounted upside down (``PARAM
            laser_front_laser_flipped 1``): the first beam is on the left.

    Returns:
        (n_beams,) ``-fov/2 + i * step``: ``step = fov / n`` for an even count (180 over
        pi -> 1 deg, 360 -> 0.5 deg), ``fov / (n - 1)`` for an odd count (181 -> 1
        deg, 361 -> 0.5 deg, both ends included); reversed when ``flipped``.
    """
    if n_beams > 1 and n_beams % 2 == 1:
        a = -fov / 2 + np.arange(n_beams, dtype=np.float64) * (fov / (n_beams - 1))
    else:
        a = carmen_beam_angles(n_beams, fov)
    return a[::-1].copy() if flipped else a


#: ``PARAM`` names of the front laser's geometry that the FLASER angles follow.
FOV_PARAM = "laser_front_laser_fov"
FLIPPED_PARAM = "laser_front_laser_flipped"


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


def _count(tok: list[str], i: int, what: str, path: Path, line_no: int) -> int:
    """The non-negative integer ``tok[i]`` (a beam or remission count)."""
    try:
        n = int(tok[i])
    except (IndexError, ValueError) as exc:
        raise DatasetError(f"{tok[0]} line without a {what}", path=path, line=line_no) from exc
    if n < 0:
        raise DatasetError(f"{tok[0]} {what} {n} is negative", path=path, line=line_no)
    return n


def _logger_stamp(tok: list[str], i: int) -> float:
    """The logger time stamp ``tok[i]`` when present and a finite number, else NaN."""
    try:
        v = float(tok[i])
    except (IndexError, ValueError):
        return math.nan
    return v if math.isfinite(v) else math.nan


@dataclass
class _Scan:
    """One laser message as read: geometry key, ranges, poses, stamps, line."""

    geometry: tuple[float, float, int]  # (start_angle, step, n) in rad; step NaN for FLASER
    ranges: list[float]
    pose: list[float]
    odom: list[float]
    t: float
    logger_t: float
    line: int
    max_range: float


def _parse_flaser(tok: list[str], path: Path, line_no: int) -> _Scan:
    """A ``FLASER`` line (module docstring)."""
    n = _count(tok, 1, "beam count", path, line_no)
    if len(tok) < 2 + n + 7 or n <= 0:
        raise DatasetError(f"FLASER with {n} beams needs {2 + n + 7} fields, got {len(tok)}",
                           path=path, line=line_no)
    values = _floats(tok[2:2 + n + 7], path, line_no)
    return _Scan((-math.pi / 2, math.nan, n), values[:n], values[n:n + 3], values[n + 3:n + 6],
                 values[n + 6], _logger_stamp(tok, 2 + n + 8), line_no, math.nan)


def _parse_robotlaser(tok: list[str], path: Path, line_no: int) -> _Scan:
    """A ``ROBOTLASER1`` line (module docstring)."""
    n = _count(tok, 8, "beam count", path, line_no)
    if n <= 0:
        raise DatasetError(f"ROBOTLASER1 with {n} beams", path=path, line=line_no)
    n_rem = _count(tok, 9 + n, "remission count", path, line_no)
    k = 10 + n + n_rem  # first field after the remissions: laser_x
    if len(tok) < k + 12:
        raise DatasetError(
            f"ROBOTLASER1 with {n} beams and {n_rem} remissions needs {k + 12} fields, "
            f"got {len(tok)}", path=path, line=line_no)
    head = _floats(tok[2:8], path, line_no)  # start, fov, resolution, max_range, accuracy, mode
    ranges = _floats(tok[9:9 + n], path, line_no)
    tail = _floats(tok[k:k + 12], path, line_no)  # 6 pose, 5 motion fields, timestamp
    start, _fov, step, max_range = head[0], head[1], head[2], head[3]
    if not step > 0:
        raise DatasetError(f"ROBOTLASER1 angular resolution {step} is not positive",
                           path=path, line=line_no)
    return _Scan((start, step, n), ranges, tail[0:3], tail[3:6], tail[11],
                 _logger_stamp(tok, k + 13), line_no, max_range)


def _parse_odom(tok: list[str], path: Path, line_no: int) -> list[float]:
    """An ``ODOM`` line: ``[x, y, theta, timestamp]``."""
    if len(tok) < 8:
        raise DatasetError(f"ODOM needs at least 8 fields, got {len(tok)}", path=path,
                           line=line_no)
    values = _floats(tok[1:8], path, line_no)
    return [*values[:3], values[6]]


#: Laser messages lampsam does not read, and why (for the "no scans" error).
UNREAD_LASERS = {
    "RAWLASER1": "no pose", "RAWLASER2": "no pose", "RAWLASER3": "no pose",
    "RAWLASER4": "no pose", "RLASER": "the rear laser", "ROBOTLASER2": "the rear laser",
    "LASER3": "no pose", "LASER4": "no pose", "REMISSIONFLASER": "not read",
}


def _found(others: dict[str, int], odom_t: list[float]) -> str:
    """What a log without FLASER/ROBOTLASER1 scans holds instead, for its error."""
    parts = [f"{n} {name} ({UNREAD_LASERS[name]})" for name, n in others.items()
             if name in UNREAD_LASERS]
    if odom_t:
        parts.append(f"{len(odom_t)} ODOM")
    if not parts:
        return ""
    hint = ""
    if any(name.startswith(("RAWLASER", "LASER")) for name in others):
        hint = ("; raw laser messages carry no pose: write the scans as FLASER lines at "
                "corrected poses (a scan matcher's output) to build a map from them")
    return f"; found {', '.join(parts)}{hint}"


def _flaser_geometry(params: dict[str, tuple[str, int]], path: Path) -> tuple[float, bool]:
    """``(fov, flipped)`` of the FLASER scans from the log's PARAM lines (default pi, False).

    Raises:
        DatasetError: a value that is not a number, or a field of view outside (0, 360] deg.
    """
    fov = math.pi
    flipped = False
    if FOV_PARAM in params:
        text, line = params[FOV_PARAM]
        try:
            deg = float(text)
        except ValueError as exc:
            raise DatasetError(f"PARAM {FOV_PARAM} {text!r} is not a number", path=path,
                               line=line) from exc
        if not 0.0 < deg <= 360.0:
            raise DatasetError(f"PARAM {FOV_PARAM} {deg:g} deg is outside (0, 360]", path=path,
                               line=line)
        fov = math.radians(deg)
    if FLIPPED_PARAM in params:
        text, line = params[FLIPPED_PARAM]
        try:
            flipped = float(text) != 0.0
        except ValueError as exc:
            raise DatasetError(f"PARAM {FLIPPED_PARAM} {text!r} is not a number", path=path,
                               line=line) from exc
    return fov, flipped


def _choose_message(flaser: list[_Scan], robot: list[_Scan], path: Path) -> tuple[str, list[_Scan]]:
    """ROBOTLASER1 scans when the log has any, else FLASER scans."""
    if robot:
        if flaser:
            log.info("%s: %d ROBOTLASER1 and %d FLASER lines: reading ROBOTLASER1", path,
                     len(robot), len(flaser))
        return "ROBOTLASER1", robot
    return "FLASER", flaser


def _check_geometry(scans: list[_Scan], message: str, path: Path) -> tuple[float, float, int]:
    """The one beam geometry of all scans; DatasetError at the first scan that differs."""
    first = scans[0].geometry
    for s in scans[1:]:
        g = s.geometry
        if g[2] != first[2]:
            raise DatasetError(f"{message} beam count {g[2]} differs from earlier {first[2]}",
                               path=path, line=s.line)
        if message == "ROBOTLASER1" and not np.allclose(g[:2], first[:2], atol=1e-9):
            raise DatasetError(
                f"ROBOTLASER1 start angle/resolution {g[0]:.6g}/{g[1]:.6g} rad differ from "
                f"earlier {first[0]:.6g}/{first[1]:.6g}", path=path, line=s.line)
    return first


def _drop_backwards(scans: list[_Scan], strict_time: bool, path: Path) -> tuple[list[_Scan], str]:
    """Scans whose stamp is not earlier than any before it, and a note on the rest.

    Raises:
        DatasetError: with ``strict_time``, at the first scan stamped earlier.
    """
    kept: list[_Scan] = []
    dropped: list[int] = []
    latest = -math.inf
    for s in scans:
        if s.t < latest:
            if strict_time:
                raise DatasetError(f"time goes backwards: {s.t} after {latest}", path=path,
                                   line=s.line)
            dropped.append(s.line)
            continue
        latest = s.t
        kept.append(s)
    if not dropped:
        return kept, ""
    shown = ", ".join(str(v) for v in dropped[:5]) + (", ..." if len(dropped) > 5 else "")
    return kept, f"dropped {len(dropped)} scans stamped earlier than a previous one (lines {shown})"


def _is_gzip(path: Path) -> bool:
    """True when the file starts with gzip's magic bytes, whatever its suffix."""
    try:
        with open(path, "rb") as fh:
            return fh.read(2) == b"\x1f\x8b"
    except OSError as exc:
        raise DatasetError(f"cannot read: {exc.strerror or exc}", path=path) from exc


def _head_records(path: Path, n: int) -> list[str]:
    """The first ``n`` records (non-blank lines not starting with ``#``) of a text file,
    gzip-compressed or not (the magic bytes decide), from its first 64 KiB.

    Raises:
        DatasetError: unreadable, or a gzip stream that does not decompress.
    """
    try:
        with (gzip.open(path, "rb") if _is_gzip(path) else open(path, "rb")) as fh:
            head = fh.read(65536)
    except (OSError, EOFError) as exc:
        raise DatasetError(f"cannot read: {getattr(exc, 'strerror', None) or exc}", path=path) from exc
    text = head.decode("utf-8", errors="replace").lstrip("\ufeff")
    records = [ln.strip() for ln in text.splitlines() if ln.strip() and not ln.lstrip().startswith("#")]
    return records[:n]


def sniff_carmen(path: str | Path) -> tuple[bool, str]:
    """Whether a file is a CARMEN log, by its content (whatever its name or suffix).

    It is when one of its first :data:`SNIFF_RECORDS` records starts with a CARMEN
    message name (:data:`CARMEN_MESSAGES`: ``PARAM``, ``ODOM``, ``FLASER``,
    ``ROBOTLASER1``...); ``#`` comments and blank lines are skipped, gzip is read
    through.

    Returns:
        ``(is_carmen, found)``: ``found`` says what the file starts with, for a
        message (``"its first record is 'VERTEX_SE2 0 0 0 0'"``, ``"no records
        (empty, or comments only)"``).

    Raises:
        DatasetError: the file cannot be read.
    """
    path = Path(path)
    records = _head_records(path, SNIFF_RECORDS)
    if not records:
        return False, "no records (empty, or comments only)"
    is_carmen = any(r.split()[0] in CARMEN_MESSAGES for r in records)
    first = records[0] if len(records[0]) <= 60 else records[0][:57] + "..."
    return is_carmen, f"its first record is {first!r}"


def read_carmen(path: str | Path, max_range: float | None = None, strict_time: bool = False,
                scan_rate_hz: float = NOMINAL_SCAN_RATE_HZ) -> CarmenLog:
    """Read a CARMEN log (plain or ``.gz``): FLASER or ROBOTLASER1 scans, ODOM records.

    Args:
        path: the log file.
        max_range: ranges at or above this are no return, metres (default: the
            ROBOTLASER1 messages' own ``max_range``; 80 m for FLASER).
        strict_time: if True, a scan stamped earlier than a previous scan raises; if
            False (default) it is dropped (the Intel log has 4 such scans, 0.05-0.86 s
            back in time).
        scan_rate_hz: nominal scan rate, Hz, used only when the log has no usable
            time stamps (:func:`derive_scan_times`).

    Returns:
        The scans and odometry; one warning is logged when the scans' times were
        derived or scans dropped.

    Raises:
        DatasetError: missing file, malformed FLASER/ROBOTLASER1/ODOM line (wrong
            field count, not a number, NaN; a malformed LAST line without its newline,
            as a logger stopped mid-write leaves it, is skipped with the warning), beam geometry changing within the log, no
            scans, time going backwards with ``strict_time``; the message names the
            file and line.
    """
    path = Path(path)
    if path.is_dir():
        raise DatasetError("is a directory, expected a CARMEN log file", path=path)
    if not path.is_file():
        raise DatasetError("CARMEN log not found", path=path)
    opener = gzip.open if _is_gzip(path) else open
    flaser: list[_Scan] = []
    robot: list[_Scan] = []
    odom_t: list[float] = []
    odom_poses: list[list[float]] = []
    others: dict[str, int] = {}
    params: dict[str, tuple[str, int]] = {}
    # A malformed record is an error, unless it is a last line without its newline:
    # a logger stopped while writing leaves that, and it is skipped with a warning.
    cut: DatasetError | None = None
    try:
        with opener(path, "rt", encoding="utf-8-sig", errors="replace") as fh:
            for line_no, raw in enumerate(fh, start=1):
                tok = raw.split()
                if not tok or tok[0].startswith("#"):
                    continue
                try:
                    if tok[0] == "FLASER":
                        flaser.append(_parse_flaser(tok, path, line_no))
                    elif tok[0] == "ROBOTLASER1":
                        robot.append(_parse_robotlaser(tok, path, line_no))
                    elif tok[0] == "ODOM":
                        odom_rec = _parse_odom(tok, path, line_no)
                        odom_poses.append(odom_rec[:3])
                        odom_t.append(odom_rec[3])
                    elif tok[0] == "PARAM" and len(tok) >= 3 and tok[1] in (FOV_PARAM,
                                                                         FLIPPED_PARAM):
                        params[tok[1]] = (tok[2], line_no)
                    else:
                        others[tok[0]] = others.get(tok[0], 0) + 1
                except DatasetError as exc:
                    if raw.endswith("\n"):
                        raise
                    cut = exc
    except (OSError, EOFError, UnicodeDecodeError) as exc:
        raise DatasetError(f"cannot read: {exc}", path=path) from exc
    cut_note = ""
    if cut is not None:
        cut_note = (f"skipped the last line, cut off without its newline ({cut}): the log "
                    "was stopped while it was written")
    message, raw_scans = _choose_message(flaser, robot, path)
    if not raw_scans:
        raise DatasetError("no FLASER or ROBOTLASER1 scans in the log" + _found(others, odom_t),
                           path=path)
    start, step, n_beams = _check_geometry(raw_scans, message, path)
    angles = (flaser_beam_angles(n_beams, *_flaser_geometry(params, path)) if message == "FLASER"
              else start + np.arange(n_beams, dtype=np.float64) * step)
    scans, drop_note = _drop_backwards(raw_scans, strict_time, path)
    t, source, time_note = derive_scan_times(np.array([s.t for s in scans]),
                                             np.array([s.logger_t for s in scans]),
                                             scan_rate_hz)
    notes = [v for v in (cut_note, time_note, drop_note) if v]
    if notes:
        log.warning("%s: %s", path, "; ".join(notes))
    if max_range is None:
        max_range = INTEL_MAX_RANGE if message == "FLASER" else float(scans[0].max_range)
    out = LaserScans(
        t=t, ranges=np.array([s.ranges for s in scans]), angles=angles,
        poses=np.array([s.pose for s in scans]), odom_poses=np.array([s.odom for s in scans]),
        line=np.array([s.line for s in scans], dtype=np.int64), max_range=float(max_range),
        time_source=source)
    log.info("%s: %d %s scans of %d beams (%.3g..%.3g deg), %d odometry records", path,
             len(out), message, n_beams, math.degrees(angles[0]), math.degrees(angles[-1]),
             len(odom_t))
    return CarmenLog(path, out, np.array(odom_t), np.array(odom_poses).reshape(-1, 3), message,
                     "; ".join(notes))


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
