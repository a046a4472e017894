"""Stereo two-point runs: the simulator of paper 3 and the run-directory format.

The run types (:class:`StereoRig`, :class:`StereoNoise`, :class:`StereoRun`) are
in :mod:`lampsam.datasets.stereo_types`. The simulator renders the two target
points from geometry only (pinhole cameras placed at the rig's two optical
centres); it imports no estimator code, so the truth it writes is independent
of ``lampsam.factors.stereo``.

Run directory format (all times on one clock, seconds):

``stereo_run.yaml``
    ``scenario``, ``seed``, ``rig`` (:class:`StereoRig` fields),
    ``target_t_points`` ([[x1, y1], [x2, y2]], m, target frame),
    ``noise`` (``sigma_detect_px``, ``quantise``, ``sigma_v``, ``sigma_omega``,
    ``sigma_lateral``), ``files``.
``odometry.csv``
    header ``t,v,omega``: measured forward speed (m/s) and turn rate (rad/s)
    over the step that ends at ``t`` (row 0: zeros, no motion before it).
``measurements.csv``
    header ``t,seen,xl1,xr1,xl2,xr2``: the four horizontal image coordinates (px,
    from the principal point, positive to the left: docs/stereo.md); ``seen`` is
    1 when both points are in front of both cameras and inside both images,
    else 0 and the coordinates are 0.
``groundtruth.tum``
    TUM ``t x y z qx qy qz qw``: the rig's true pose in the target frame, z = 0.
"""

from __future__ import annotations

import csv
import logging
import math
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from lampsam.arrays import BoolArray, FloatArray
from lampsam.config_loader import ConfigError, from_mapping
from lampsam.datasets.stereo_types import StereoNoise, StereoRig, StereoRun
from lampsam.datasets.tables import Trajectory
from lampsam.datasets.textio import parse_float, read_csv, read_yaml
from lampsam.datasets.tum import read_tum, write_tum
from lampsam.errors import DatasetError
from lampsam.safe_io import atomic_path, write_text_atomic

#: The run types live in :mod:`lampsam.datasets.stereo_types`; re-exported here for
#: callers that import them with the simulator.
__all__ = [
    "SCENARIOS",
    "StereoNoise",
    "StereoRig",
    "StereoRun",
    "StereoScenario",
    "read_stereo_run",
    "render_columns",
    "simulate_stereo",
    "simulate_stereo_run",
    "true_trajectory",
    "write_stereo_run",
]

log = logging.getLogger(__name__)

SCENARIOS = ("straight", "turn")
RUN_YAML = "stereo_run.yaml"
ODOMETRY_CSV = "odometry.csv"
MEASUREMENTS_CSV = "measurements.csv"
GROUNDTRUTH_TUM = "groundtruth.tum"


@dataclass(frozen=True)
class StereoScenario:
    """Geometry and timing of the two paper scenarios (target frame, m, rad, s).

    Attributes:
        dt: frame period, s.
        target_t_points: the two target points, ((x1, y1), (x2, y2)), m: a 0.6 m
            wide board facing ``-x``.
        straight_start: rig start pose for ``straight``: 8 m before the target,
            0.8 m to its side, heading at it.
        straight_speed: m/s; ``straight_end_x``: stop when x passes this, m (past
            the target, which leaves the field of view about 1.7 m before).
        turn_pose: rig position and mean heading for ``turn``.
        turn_amplitude: heading swing, rad; ``turn_period``: s; ``turn_duration``: s.
    """

    dt: float = 0.1
    target_t_points: tuple[tuple[float, float], tuple[float, float]] = ((0.0, 0.3), (0.0, -0.3))
    straight_start: tuple[float, float, float] = (-8.0, -0.8, 0.0)
    straight_speed: float = 0.5
    straight_end_x: float = 0.5
    turn_pose: tuple[float, float, float] = (-4.0, 0.2, 0.0)
    turn_amplitude: float = 0.4
    turn_period: float = 8.0
    turn_duration: float = 16.0


# --------------------------------------------------------------------------- simulation
def true_trajectory(scenario: str, cfg: StereoScenario) -> tuple[FloatArray, FloatArray]:
    """The true rig poses of a scenario.

    Args:
        scenario: ``"straight"`` (drive toward and past the target) or ``"turn"``
            (turn in place, heading swinging sinusoidally).
        cfg: the scenario geometry.

    Returns:
        ``t`` (N,) s and ``poses`` (N, 3) ``(x, y, theta)`` in the target frame.
    """
    if scenario == "straight":
        x0, y0, th0 = cfg.straight_start
        n = int(math.floor((cfg.straight_end_x - x0) / (cfg.straight_speed * cfg.dt))) + 1
        t = np.arange(n) * cfg.dt
        s = cfg.straight_speed * t
        poses = np.column_stack(
            [x0 + s * math.cos(th0), y0 + s * math.sin(th0), np.full(n, th0)]
        )
    elif scenario == "turn":
        x0, y0, th0 = cfg.turn_pose
        n = int(round(cfg.turn_duration / cfg.dt)) + 1
        t = np.arange(n) * cfg.dt
        theta = th0 + cfg.turn_amplitude * np.sin(2.0 * np.pi * t / cfg.turn_period)
        poses = np.column_stack([np.full(n, x0), np.full(n, y0), theta])
    else:
        raise DatasetError(f"unknown scenario {scenario!r}; choose one of {SCENARIOS}")
    return np.asarray(t, dtype=np.float64), np.asarray(poses, dtype=np.float64)


def render_columns(
    pose: FloatArray, target_t_points: FloatArray, rig: StereoRig
) -> tuple[FloatArray, BoolArray]:
    """Exact image columns of the two points in both cameras (pinhole, OpenCV columns).

    Each camera is a pinhole at ``rig centre +- (B/2) * left axis`` looking along
    the rig's heading; image right is the rig's ``-y`` (right-hand side).

    Args:
        pose: (3,) rig pose in the target frame.
        target_t_points: (2, 2) target points, m.
        rig: the stereo rig.

    Returns:
        ``u`` (2, 2) columns, px, ``u[j] = (u_left, u_right)`` of point j, and
        ``ok`` (2,) bool: both in front of and inside both images.
    """
    x, y, th = pose
    forward = np.array([math.cos(th), math.sin(th)])
    left = np.array([-math.sin(th), math.cos(th)])
    centres = [np.array([x, y]) + 0.5 * rig.baseline * left,
               np.array([x, y]) - 0.5 * rig.baseline * left]
    u = np.zeros((2, 2))
    ok = np.ones(2, dtype=bool)
    for j, point in enumerate(np.asarray(target_t_points, dtype=float)):
        for i, centre in enumerate(centres):
            rel = point - centre
            depth = float(rel @ forward)
            right = -float(rel @ left)
            if depth <= 1e-6:
                ok[j] = False
                continue
            u[j, i] = rig.cu_px + rig.f_px * right / depth
            if not (-0.5 <= u[j, i] <= rig.width_px - 0.5):
                ok[j] = False
    return u, ok


def simulate_stereo(
    scenario: str,
    rng: np.random.Generator,
    rig: StereoRig | None = None,
    noise: StereoNoise | None = None,
    cfg: StereoScenario | None = None,
    seed: int = -1,
) -> StereoRun:
    """Simulate one run of a paper scenario (in memory).

    Measurement noise: Gaussian detection noise, then rounding of the column to
    a whole pixel (quantisation, variance 1/12 px^2). Odometry: true speed and
    turn rate over each step plus white Gaussian noise.

    Args:
        scenario: ``"straight"`` or ``"turn"``.
        rng: the random generator (seeded by the caller).
        rig, noise, cfg: parameters (defaults when None).
        seed: recorded in the run for reference.

    Returns:
        The run, with ``truth``.
    """
    rig = rig or StereoRig()
    noise = noise or StereoNoise()
    cfg = cfg or StereoScenario()
    t, poses = true_trajectory(scenario, cfg)
    points = np.asarray(cfg.target_t_points, dtype=float)
    n = len(t)
    v = np.zeros(n)
    omega = np.zeros(n)
    for k in range(1, n):
        dt = t[k] - t[k - 1]
        d = poses[k, :2] - poses[k - 1, :2]
        th = poses[k - 1, 2]
        v_true = (d[0] * math.cos(th) + d[1] * math.sin(th)) / dt
        dth = math.atan2(math.sin(poses[k, 2] - th), math.cos(poses[k, 2] - th))
        v[k] = v_true + rng.normal(0.0, noise.sigma_v)
        omega[k] = dth / dt + rng.normal(0.0, noise.sigma_omega)
    z = np.zeros((n, 4))
    seen = np.zeros(n, dtype=bool)
    for k in range(n):
        u, ok = render_columns(poses[k], points, rig)
        u_noisy = u + rng.normal(0.0, noise.sigma_detect_px, size=u.shape)
        if noise.quantise:
            u_noisy = np.round(u_noisy)
        if ok.all():
            seen[k] = True
            z[k] = (rig.cu_px - u_noisy).reshape(4)  # paper coordinate: positive left
    log.info("simulated %s: %d frames, %d with both points seen", scenario, n, int(seen.sum()))
    return StereoRun(None, rig, noise, points, t, v, omega, z, seen, poses, scenario, seed)


# --------------------------------------------------------------------------- run format
def write_stereo_run(run: StereoRun, out: Path) -> Path:
    """Write a run directory (format in the module docstring).

    Args:
        run: the run.
        out: directory, created if needed.

    Returns:
        ``out``.

    Raises:
        DatasetError: ``out`` cannot be created (e.g. it is below a file).
    """
    out = Path(out)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise DatasetError(f"cannot create the run directory ({exc.strerror})", out) from exc
    meta = {
        "scenario": run.scenario,
        "seed": int(run.seed),
        "rig": asdict(run.rig),
        "noise": asdict(run.noise),
        "target_t_points": np.asarray(run.target_t_points, dtype=float).tolist(),
        "files": {
            "odometry": ODOMETRY_CSV,
            "measurements": MEASUREMENTS_CSV,
            "groundtruth": GROUNDTRUTH_TUM if run.truth is not None else None,
        },
    }
    write_text_atomic(out / RUN_YAML, yaml.safe_dump(meta, sort_keys=False))
    with atomic_path(out / ODOMETRY_CSV) as tmp, open(tmp, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["t", "v", "omega"])
        for k in range(len(run)):
            w.writerow([f"{run.t[k]:.6f}", f"{run.v[k]:.9g}", f"{run.omega[k]:.9g}"])
    with atomic_path(out / MEASUREMENTS_CSV) as tmp, open(tmp, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["t", "seen", "xl1", "xr1", "xl2", "xr2"])
        for k in range(len(run)):
            w.writerow([f"{run.t[k]:.6f}", int(run.seen[k])] + [f"{c:.6g}" for c in run.z[k]])
    if run.truth is not None:
        write_tum(out / GROUNDTRUTH_TUM, Trajectory(t=run.t, poses=run.truth),
                  comment="t x y z qx qy qz qw (rig pose in the target frame)")
    return out


def simulate_stereo_run(
    scenario: str, out: Path, seed: int = 0, rig: StereoRig | None = None,
    noise: StereoNoise | None = None, cfg: StereoScenario | None = None,
) -> Path:
    """Simulate a scenario with ``default_rng(seed)`` and write it to ``out``."""
    if scenario not in SCENARIOS:
        raise DatasetError(f"unknown scenario {scenario!r}; choose one of {SCENARIOS}")
    run = simulate_stereo(scenario, np.random.default_rng(seed), rig, noise, cfg, seed)
    return write_stereo_run(run, Path(out))


def _read_csv(path: Path, header: list[str]) -> FloatArray:
    """Numeric CSV with an exact header -> (N, len(header)); errors name file and line.

    Read with :func:`lampsam.datasets.textio.read_csv`: a binary or gzip file, a
    directory, a BOM and blank / ``#`` lines are handled as in every other reader, and
    the line named for a time that does not increase is the file's own line.
    """
    return _read_csv_lines(path, header)[0]


def _read_csv_lines(path: Path, header: list[str]) -> tuple[FloatArray, list[int]]:
    """:func:`_read_csv` and each row's line number in the file."""
    rows, lines = read_csv(path, header, [parse_float] * len(header))
    out = np.array(rows, dtype=float)
    bad = np.flatnonzero(np.diff(out[:, 0]) <= 0)
    if bad.size:
        k = int(bad[0]) + 1
        raise DatasetError(f"time does not increase ({out[k, 0]:g} after {out[k - 1, 0]:g})",
                           path, lines[k])
    return out, list(lines)


def _check_on_sensor(meas: FloatArray, lines: list[int], rig: StereoRig, path: Path) -> None:
    """Refuse a seen frame whose coordinate lies off the image (|x| > half its width).

    The coordinates are from the principal point (docs/stereo.md); a coordinate off the
    image (pixel columns 0 .. width of a target in the image's right half, another
    origin) is no measurement, and the estimators would run on it to a wrong answer.
    """
    half = rig.half_width_px()
    z = meas[:, 2:6]
    off = (meas[:, 1] > 0.5) & np.any(np.abs(z) > half + 1e-9, axis=1)
    if np.any(off):
        k = int(np.flatnonzero(off)[0])
        j = int(np.argmax(np.abs(z[k]) > half + 1e-9))
        col = ["xl1", "xr1", "xl2", "xr2"][j]
        raise DatasetError(
            f"column {col!r}: {z[k, j]:g} px lies off the "
            f"{rig.width_px}-px image ({int(off.sum())} seen frames like it): coordinates are "
            f"measured from the principal point, positive to the left, within +-{half:g} px "
            "(docs/stereo.md), not pixel columns", path, lines[k])


def _run_description(meta_path: Path) -> tuple[dict[str, Any], StereoRig, StereoNoise, FloatArray]:
    """``stereo_run.yaml``: the mapping, the rig, the noise and the (2, 2) target points.

    ``rig`` and ``noise`` are read strictly (:func:`lampsam.config_loader.from_mapping`):
    a missing table, an unknown key or a wrong type is an error naming the key.
    """
    meta = read_yaml(meta_path)
    if not isinstance(meta, dict):
        raise DatasetError("bad run description: expected a mapping with rig, noise and "
                           f"target_t_points, got {'an empty file' if meta is None else type(meta).__name__}",
                           meta_path)
    for key in ("rig", "noise", "target_t_points"):
        if key not in meta:
            raise DatasetError(f"bad run description: {key} is missing", meta_path)
    try:
        rig = from_mapping(StereoRig, meta["rig"], source=meta_path, key="rig")
        noise = from_mapping(StereoNoise, meta["noise"], source=meta_path, key="noise")
    except ConfigError as exc:
        raise DatasetError(f"bad run description: {exc.key}: {exc.problem}", meta_path) from None
    try:
        points = np.asarray(meta["target_t_points"], dtype=float)
    except (TypeError, ValueError):
        points = np.zeros(0)
    if points.shape != (2, 2) or not np.all(np.isfinite(points)):
        raise DatasetError("target_t_points must be 2 finite (x, y) pairs", meta_path)
    return meta, rig, noise, points


def read_stereo_run(path: Path) -> StereoRun:
    """Read a run directory written by :func:`write_stereo_run`.

    Raises:
        DatasetError: missing or malformed file (naming it and the line), frame
            times that differ between files, unknown keys.
    """
    path = Path(path)
    meta_path = path / RUN_YAML
    if not meta_path.is_file():
        raise DatasetError(f"not a stereo run directory (no {RUN_YAML})", meta_path)
    meta, rig, noise, points = _run_description(meta_path)
    odo = _read_csv(path / ODOMETRY_CSV, ["t", "v", "omega"])
    meas, meas_lines = _read_csv_lines(path / MEASUREMENTS_CSV,
                                       ["t", "seen", "xl1", "xr1", "xl2", "xr2"])
    _check_on_sensor(meas, meas_lines, rig, path / MEASUREMENTS_CSV)
    if len(odo) != len(meas) or not np.allclose(odo[:, 0], meas[:, 0], atol=1e-6):
        raise DatasetError(f"odometry and measurement times differ ({ODOMETRY_CSV}: {len(odo)} "
                           f"rows, {MEASUREMENTS_CSV}: {len(meas)}; every frame needs one row "
                           "in each, at the same time)", path / MEASUREMENTS_CSV)
    truth = None
    gt_path = path / GROUNDTRUTH_TUM
    if gt_path.exists():  # optional; a directory of that name is an error (read_tum)
        gt = read_tum(gt_path)
        if len(gt) != len(odo) or not np.allclose(gt.t, odo[:, 0], atol=1e-6):
            raise DatasetError("ground-truth times differ from the frames", gt_path)
        truth = gt.poses
    return StereoRun(
        path, rig, noise, points, odo[:, 0], odo[:, 1], odo[:, 2], meas[:, 2:6],
        meas[:, 1] > 0.5, truth, str(meta.get("scenario", "")), _seed(meta, meta_path),
    )


def _seed(meta: dict[str, Any], meta_path: Path) -> int:
    """The run's ``seed`` (provenance; -1 when absent), or DatasetError when not an integer."""
    seed = meta.get("seed", -1)
    if isinstance(seed, bool) or not isinstance(seed, int):
        raise DatasetError(f"bad run description: seed: must be an integer, got {seed!r}", meta_path)
    return seed
