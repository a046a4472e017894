"""Adapter for the UTIAS MRCLAM dataset (one robot, ``ds0_RS_*`` resampled at 50 Hz, or the
dataset as distributed: ``MRCLAM_DatasetN/Robot1_Odometry.dat`` ..., robot 1; :func:`mrclam_files`).

Files (whitespace separated, one record a line; Leung et al., IJRR 2011):

- ``ds0_RS_Control.dat``: ``t v w`` (s, m/s, rad/s) commanded/measured velocity,
  held from ``t`` to the next sample.
- ``ds0_RS_Measurement.dat``: ``t barcode range bearing`` (s, -, m, rad).
- ``ds0_RS_Groundtruth.dat``: ``t x y theta`` (Vicon, s, m, m, rad).
- ``ds0_RS_Landmark_Groundtruth.dat``: ``id x y sx sy`` (m).
- ``ds0_RS_Barcodes.dat``: ``id barcode``; ids 1-5 are the robots, 6-20 landmarks.

The adapter converts ``(v, w)`` into wheel travel with a nominal wheel base
(``ds = v dt``, ``dtheta = w dt``, ``d_right = ds + b dtheta / 2``,
``d_left = ds - b dtheta / 2``, the inverse of paper eq. 13), drops measurements
of other robots' barcodes (and of barcodes not in the landmark table), and
gives arrays that :func:`mrclam_run` turns into a :class:`~lampsam.datasets.logrun.LoggedRun`
with a range-bearing log, or :func:`write_mrclam_run` writes as a run folder.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from lampsam.arrays import FloatArray, IntArray
from lampsam.datasets.logrun import (
    LoggedRun,
    OdometryLog,
    OdometryModel,
    RangeBearingLog,
    Rig,
    Trajectory,
    write_run,
)
from lampsam.datasets.textio import open_text
from lampsam.errors import DatasetError

log = logging.getLogger(__name__)

#: iRobot Create (the MRCLAM robots) axle length, m; nominal, the data has only (v, w).
NOMINAL_WHEEL_BASE = 0.26
#: Robots' own ids in Barcodes.dat (their barcodes must not be used as landmarks).
ROBOT_IDS = (1, 2, 3, 4, 5)
#: The robot read from a folder in the dataset's own layout (``Robot1_Odometry.dat`` ...).
ORIGINAL_ROBOT = 1


@dataclass(frozen=True)
class MrclamData:
    """One MRCLAM robot's data, as arrays.

    Attributes:
        control_t: (N,) control times, s.
        v: (N,) forward speed, m/s; w: (N,) yaw rate, rad/s.
        meas_t: (M,) measurement times, s; meas_id: (M,) landmark ids (6-20);
        meas_range: (M,) m; meas_bearing: (M,) rad (robot frame, CCW from x).
        gt_t: (K,) Vicon times, s; gt_poses: (K, 3) (x, y, theta).
        landmark_ids: (L,) ids; landmark_xy: (L, 2) Vicon landmark positions, m.
        n_dropped_robot: measurements of other robots dropped.
        n_dropped_unknown: measurements of barcodes in no table dropped.
    """

    control_t: FloatArray
    v: FloatArray
    w: FloatArray
    meas_t: FloatArray
    meas_id: IntArray
    meas_range: FloatArray
    meas_bearing: FloatArray
    gt_t: FloatArray
    gt_poses: FloatArray
    landmark_ids: IntArray
    landmark_xy: FloatArray
    n_dropped_robot: int = 0
    n_dropped_unknown: int = 0


def _read_table(path: Path, ncols: int, monotonic_col: int | None = 0,
                unique_time: bool = False) -> FloatArray:
    """Read a whitespace table; every bad line raises a DatasetError naming it.

    The file's last line, when it is cut short (too few columns and no newline at the
    end: a logger stopped mid-write), is skipped with a warning naming it. With
    ``unique_time``, a time stamp repeated with different values keeps its first row,
    with one warning naming the first such line; an exact repeat is dropped silently.

    Args:
        path: the file.
        ncols: number of columns expected.
        monotonic_col: column whose values must not decrease (time), or None.
        unique_time: one row per time (odometry, ground truth; not measurements, where
            several landmarks share a time).

    Returns:
        (R, ncols) array.
    """
    rows: list[list[float]] = []
    lines: list[int] = []
    raw_lines: list[tuple[int, str]] = []
    with open_text(path) as fh:
        raw_lines = list(enumerate(fh, start=1))
    ends_cut = bool(raw_lines) and not raw_lines[-1][1].endswith("\n")
    last_data = max((n for n, r in raw_lines if r.strip() and not r.strip().startswith("#")),
                    default=0)
    last = -math.inf
    repeated: list[int] = []
    for lineno, raw in raw_lines:
        text = raw.strip()
        if not text or text.startswith("#"):
            continue
        parts = text.split()
        if len(parts) != ncols:
            if lineno == last_data and ends_cut and len(parts) < ncols:
                log.warning("%s:%d: the last line is cut short (%d of %d columns, no newline): "
                            "skipped", path, lineno, len(parts), ncols)
                continue
            raise DatasetError(f"expected {ncols} columns, got {len(parts)}", path, lineno)
        try:
            vals = [float(p) for p in parts]
        except ValueError as exc:
            raise DatasetError(f"not a number: {text!r}", path, lineno) from exc
        if not all(math.isfinite(v) for v in vals):
            raise DatasetError(f"non-finite value: {text!r}", path, lineno)
        if monotonic_col is not None:
            if vals[monotonic_col] < last:
                raise DatasetError("time goes backwards", path, lineno)
            if unique_time and vals[monotonic_col] == last:
                if vals != rows[-1]:
                    repeated.append(lineno)
                continue
            last = vals[monotonic_col]
        rows.append(vals)
        lines.append(lineno)
    if repeated:
        log.warning("%s:%d: %d time stamps repeated with different values: the first row of "
                    "each is kept", path, repeated[0], len(repeated))
    if not rows:
        raise DatasetError("no records", path)
    return np.asarray(rows, dtype=float)


def mrclam_files(root: Path, prefix: str = "ds0_RS_", robot: int = ORIGINAL_ROBOT) -> dict[str, Path]:
    """The five tables of one robot in an MRCLAM folder, in either layout.

    ``<prefix>Control.dat`` ... (the resampled ``ds0_RS_`` copy) when present, else the
    dataset's own layout (``MRCLAM_Dataset1`` ... ``9`` as distributed: ``Robot<i>_Odometry.dat``,
    ``Robot<i>_Measurement.dat``, ``Robot<i>_Groundtruth.dat``, ``Landmark_Groundtruth.dat``,
    ``Barcodes.dat``; same columns, ``#`` header lines, Unix times), robot ``robot``.

    Raises:
        DatasetError: neither layout's odometry file is in ``root`` (both named).
    """
    if (root / f"{prefix}Control.dat").exists():
        if robot != ORIGINAL_ROBOT:
            raise DatasetError(f"robot {robot} asked for, but the resampled copy "
                               f"({prefix}Control.dat ...) holds robot {ORIGINAL_ROBOT} only", root)
        return {"control": root / f"{prefix}Control.dat",
                "measurement": root / f"{prefix}Measurement.dat",
                "groundtruth": root / f"{prefix}Groundtruth.dat",
                "landmarks": root / f"{prefix}Landmark_Groundtruth.dat",
                "barcodes": root / f"{prefix}Barcodes.dat"}
    if (root / f"Robot{robot}_Odometry.dat").exists():
        log.info("%s: MRCLAM dataset layout, robot %d", root, robot)
        others = sorted(int(f.name[5:-13]) for f in root.glob("Robot*_Odometry.dat")
                        if f.name[5:-13].isdigit() and int(f.name[5:-13]) != robot)
        if others:
            log.warning("%s: robot %d is read; robots %s (Robot<i>_*.dat) are not used "
                        "(one robot a run: lampsam slam FOLDER --mrclam --robot i, or "
                        "mrclam_run(folder, robot=i))", root,
                        robot, ", ".join(map(str, others)))
        return {"control": root / f"Robot{robot}_Odometry.dat",
                "measurement": root / f"Robot{robot}_Measurement.dat",
                "groundtruth": root / f"Robot{robot}_Groundtruth.dat",
                "landmarks": root / "Landmark_Groundtruth.dat",
                "barcodes": root / "Barcodes.dat"}
    what = "folder not found" if not root.exists() else "not an MRCLAM folder"
    raise DatasetError(f"{what}: no {prefix}Control.dat (the resampled copy) and no "
                       f"Robot{robot}_Odometry.dat (MRCLAM_DatasetN as distributed)", root)


def read_mrclam(root: Path, prefix: str = "ds0_RS_", robot: int = ORIGINAL_ROBOT) -> MrclamData:
    """Read one MRCLAM robot folder.

    Args:
        root: folder holding ``<prefix>Control.dat`` etc., or ``Robot1_Odometry.dat`` etc.
        prefix: file prefix (default the 50 Hz resampled ``ds0_RS_``).
        robot: the robot read in the dataset's own layout (1-5; the other robots'
            files are named in a warning and not used).

    Returns:
        The parsed data with other robots' measurements dropped.

    Raises:
        DatasetError: a missing file, a malformed line, NaN, time going backwards.
    """
    root = Path(root)
    files = mrclam_files(root, prefix, robot)
    control = _read_table(files["control"], 3, unique_time=True)
    try:
        meas = _read_table(files["measurement"], 4)
    except DatasetError as exc:
        if "no records" in str(exc):
            raise DatasetError("no measurements (no record in the file): this robot saw no "
                               "landmark, so there is nothing to map", files["measurement"]
                               ) from None
        raise
    gt = _read_table(files["groundtruth"], 4, unique_time=True)
    lms = _read_table(files["landmarks"], 5, monotonic_col=None)
    codes = _read_table(files["barcodes"], 2, monotonic_col=None)

    barcode_to_id = {int(round(b)): int(round(i)) for i, b in codes}
    landmark_ids = np.round(lms[:, 0]).astype(np.int64)
    known = set(landmark_ids.tolist())
    ids = np.array([barcode_to_id.get(int(round(b)), -1) for b in meas[:, 1]], dtype=np.int64)
    is_robot = np.isin(ids, ROBOT_IDS)
    keep = np.isin(ids, list(known))
    n_robot = int(is_robot.sum())
    unknown = ~keep & ~is_robot
    n_unknown = int(unknown.sum())
    if n_unknown:
        codes_seen, counts = np.unique(np.round(meas[unknown, 1]).astype(np.int64),
                                       return_counts=True)
        log.warning("%s: %d of %d measurements are of barcodes in neither %s nor %s (%s): "
                    "dropped", files["measurement"], n_unknown, len(meas),
                    files["barcodes"].name, files["landmarks"].name,
                    ", ".join(f"{c}: {n}" for c, n in list(zip(codes_seen, counts, strict=True))[:8]))
    log.info(
        "%s: %d measurements, dropped %d of other robots and %d of unknown barcodes",
        root, len(meas), n_robot, n_unknown,
    )
    return MrclamData(
        control_t=control[:, 0],
        v=control[:, 1],
        w=control[:, 2],
        meas_t=meas[keep, 0],
        meas_id=ids[keep],
        meas_range=meas[keep, 2],
        meas_bearing=meas[keep, 3],
        gt_t=gt[:, 0],
        gt_poses=gt[:, 1:4],
        landmark_ids=landmark_ids,
        landmark_xy=lms[:, 1:3],
        n_dropped_robot=n_robot,
        n_dropped_unknown=n_unknown,
    )


def wheel_travel(
    control_t: FloatArray, v: FloatArray, w: FloatArray, wheel_base: float = NOMINAL_WHEEL_BASE
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Wheel travel per control interval from (v, w) (inverse of paper eq. 13).

    Sample ``i`` holds from ``control_t[i]`` to ``control_t[i + 1]``.

    Args:
        control_t: (N,) times, s; v: (N,) m/s; w: (N,) rad/s.
        wheel_base: axle length, m.

    Returns:
        ``(t, d_left, d_right)``, each (N - 1,): ``t`` is the end of each interval, s;
        travels in m.
    """
    dt = np.diff(control_t)
    ds = v[:-1] * dt
    dth = w[:-1] * dt
    return control_t[1:], ds - 0.5 * wheel_base * dth, ds + 0.5 * wheel_base * dth


#: Wheel-noise constant used for MRCLAM, m (eq. 15: var = k |ds| per wheel). The
#: data has no wheel noise figure; 2e-3 m makes the dead-reckoning spread the same
#: order as its measured drift (about 4 m after 300 s).
MRCLAM_WHEEL_K = 2e-3


def mrclam_run(
    root: Path,
    wheel_base: float = NOMINAL_WHEEL_BASE,
    k_wheel: float = MRCLAM_WHEEL_K,
    known_ids: bool = True,
    duration: float | None = None,
    robot: int = ORIGINAL_ROBOT,
) -> LoggedRun:
    """Serve MRCLAM as an in-memory :class:`~lampsam.datasets.logrun.LoggedRun`.

    Args:
        root: the ``mrclam_ds0`` folder.
        wheel_base: nominal axle length used to convert (v, w) to wheel travel, m.
        k_wheel: eq. 15 noise constant for both wheels, m.
        known_ids: keep the landmark ids (known association); False writes -1
            (association by the gate alone).
        duration: keep only the first ``duration`` seconds (None: all).
        robot: the robot, in the dataset's own layout (:func:`read_mrclam`).

    Returns:
        A run with odometry, range-bearing measurements and Vicon ground truth (no
        images; the landmark truth is in :func:`read_mrclam`'s ``landmark_xy``, since
        the run format's landmark table has no planar type).
    """
    data = read_mrclam(root, robot=robot)
    t, d_left, d_right = wheel_travel(data.control_t, data.v, data.w, wheel_base)
    meas_keep = np.ones(len(data.meas_t), dtype=bool)
    gt_keep = np.ones(len(data.gt_t), dtype=bool)
    if duration is not None:
        t_end = data.control_t[0] + duration
        keep = t <= t_end
        t, d_left, d_right = t[keep], d_left[keep], d_right[keep]
        meas_keep = data.meas_t <= t_end
        gt_keep = data.gt_t <= t_end
    ids = data.meas_id[meas_keep] if known_ids else np.full(int(meas_keep.sum()), -1, np.int64)
    rig = Rig(odometry=OdometryModel(wheel_base=wheel_base, k_r=k_wheel, k_l=k_wheel))
    return LoggedRun(
        path=Path(root),
        rig=rig,
        odometry=OdometryLog(t=t, d_left=d_left, d_right=d_right),
        groundtruth=Trajectory(t=data.gt_t[gt_keep], poses=data.gt_poses[gt_keep]),
        range_bearing=RangeBearingLog(
            t=data.meas_t[meas_keep], landmark_id=ids,
            range=data.meas_range[meas_keep], bearing=data.meas_bearing[meas_keep],
        ),
        meta={"source": "MRCLAM ds0 (Leung et al., IJRR 2011)", "wheel_base_nominal": wheel_base},
    )


def write_mrclam_run(root: Path, out: Path, **kwargs: Any) -> Path:
    """Write MRCLAM as a run folder (``rangebearing.csv``, ``odometry.csv``, ...).

    Args:
        root: the ``mrclam_ds0`` folder.
        out: the run directory to write.
        **kwargs: passed to :func:`mrclam_run`.

    Returns:
        The run directory.
    """
    run = mrclam_run(root, **kwargs)
    return write_run(out, run.rig, run.odometry, groundtruth=run.groundtruth,
                     range_bearing=run.range_bearing, meta=run.meta)
