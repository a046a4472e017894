"""Laser global-localization trials on a CARMEN log, scored against its corrected poses.

The map is built from one half of the scans (the even-numbered ones), and each
trial localizes from a held-out (odd-numbered) scan and the held-out scans that
follow, from no prior knowledge (:func:`lampsam.localization.laser.localize_scans`).
The robot revisits its path, so the map still holds scans taken a few seconds
before and after each test scan: the usual situation of a robot localizing in a
map made earlier of the same building. Logs without raw odometry (the
``-corrected`` ones) get odometry simulated from the corrected poses plus seeded
noise (:func:`simulated_odometry`).

Success: final estimate within 30 cm and 10 deg of the corrected pose (the
paper's criterion). Beams without a return (at or beyond the log's maximum
range) and beyond the beam model's range are left out.

A stop request (SIGINT or SIGTERM: the ``localize`` command handles them at once)
during the trials ends them there: the trials finished are kept and the result's
``status`` is ``"interrupted"`` (``"ok"`` otherwise), so the command still writes them.
"""

from __future__ import annotations

import json
import logging
import math
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from lampsam.arrays import FloatArray
from lampsam.datasets.carmen import LaserScans, read_carmen
from lampsam.factors.geometry import wrap_angle
from lampsam.localization.correlative import ScorePyramid
from lampsam.localization.grid import OccupancyGrid, free_mask, grid_from_scans
from lampsam.localization.laser import (
    LaserAcceptConfig,
    LaserLocalizerConfig,
    localize_scans,
    search_pyramid,
)
from lampsam.localization.likelihood import LikelihoodFieldModel
from lampsam.localization.result import json_safe
from lampsam.localization.result import summarize as summarize_trials
from lampsam.safe_io import write_text_atomic

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class OdometryNoise:
    """Noise of simulated odometry increments (body frame).

    Attributes:
        trans: translation noise per metre (m/m), per axis. Default 0.05.
        rot: rotation noise per radian turned (rad/rad). Default 0.05.
        rot_trans: rotation noise per metre driven (rad/m). Default 0.02.
    """

    trans: float = 0.05
    rot: float = 0.05
    rot_trans: float = 0.02


@dataclass(frozen=True)
class LaserTrialsConfig:
    """The trials.

    Attributes:
        trials: start instants, evenly spread over the held-out scans. Default 50.
        updates: scans per trial (the start scan + the following held-out ones). Default 4.
        resolution: map cell size (m). Default 0.05.
        tol_pos: success bound on position (m). Default 0.30.
        tol_deg: success bound on heading (deg). Default 10.
        seed: trial ``k`` uses the generator seeded ``[seed, k]``. Default 0.
        scans: the scans the trials start from and use: ``"odd"`` (default,
            held out from a map of the even ones), ``"even"`` or ``"all"``.
        start_offset: shift of the start instants, in fractions of their
            spacing (default 0; 0.5 gives starts between those: tuning trials).
        odometry: noise of the simulated odometry.
        localizer: the filter.
        accept: the acceptance test; while it fails, a trial takes more of the
            following scans, up to ``accept.max_scans``.
    """

    trials: int = 50
    updates: int = 4
    resolution: float = 0.05
    tol_pos: float = 0.30
    tol_deg: float = 10.0
    seed: int = 0
    scans: str = "odd"
    start_offset: float = 0.0
    odometry: OdometryNoise = field(default_factory=OdometryNoise)
    localizer: LaserLocalizerConfig = field(default_factory=LaserLocalizerConfig)
    accept: LaserAcceptConfig = field(default_factory=LaserAcceptConfig)


def simulated_odometry(
    poses: FloatArray, rng: np.random.Generator, noise: OdometryNoise
) -> FloatArray:
    """Dead-reckoned odometry poses (N, 3) from true poses (N, 3) with noisy increments.

    Each body-frame increment ``(dx, dy, dtheta)`` between consecutive true poses
    gets Gaussian noise: translation ``trans |d| + 1 mm`` (per axis), rotation
    ``rot |dtheta| + rot_trans |d| + 1 mrad``; the odometry starts at the origin.
    """
    odom = np.zeros_like(poses)
    for k in range(1, len(poses)):
        c, s = math.cos(poses[k - 1, 2]), math.sin(poses[k - 1, 2])
        dxw, dyw = poses[k, :2] - poses[k - 1, :2]
        dx, dy = c * dxw + s * dyw, -s * dxw + c * dyw
        dth = float(wrap_angle(float(poses[k, 2] - poses[k - 1, 2])))
        d = math.hypot(dx, dy)
        dx += rng.normal(0.0, noise.trans * d + 1e-3)
        dy += rng.normal(0.0, noise.trans * d + 1e-3)
        dth += rng.normal(0.0, noise.rot * abs(dth) + noise.rot_trans * d + 1e-3)
        co, so = math.cos(odom[k - 1, 2]), math.sin(odom[k - 1, 2])
        odom[k] = [odom[k - 1, 0] + co * dx - so * dy, odom[k - 1, 1] + so * dx + co * dy,
                   float(wrap_angle(float(odom[k - 1, 2] + dth)))]  # fmt: skip
    return odom


def usable_scans(scans: LaserScans) -> LaserScans:
    """The scans with every no-return beam (``>= max_range``) set to NaN."""
    usable = np.where(scans.ranges >= scans.max_range, np.nan, scans.ranges)
    return LaserScans(scans.t, usable, scans.angles, scans.poses, scans.odom_poses, scans.line,
                      scans.max_range)  # fmt: skip


def holdout_split(n: int) -> tuple[np.ndarray, np.ndarray]:
    """Indices of the map scans (even) and of the held-out test scans (odd) of ``n`` scans."""
    return np.arange(0, n, 2), np.arange(1, n, 2)


def scan_selection(n: int, which: str) -> np.ndarray:
    """Indices of ``"odd"``, ``"even"`` or ``"all"`` of ``n`` scans.

    Raises:
        ValueError: another name.
    """
    if which == "odd":
        return np.arange(1, n, 2)
    if which == "even":
        return np.arange(0, n, 2)
    if which == "all":
        return np.arange(n)
    raise ValueError(f"scans must be odd, even or all, not {which!r}")


def laser_map(
    scans: LaserScans, index: np.ndarray, resolution: float, max_range: float
) -> OccupancyGrid:
    """The grid map of the scans ``index`` drawn at their (corrected) poses."""
    return grid_from_scans(scans.poses[index], scans.ranges[index], scans.angles, resolution,
                           max_range)  # fmt: skip


def run_trial(
    model: LikelihoodFieldModel, grid: OccupancyGrid, scans: LaserScans, idx: np.ndarray,
    config: LaserTrialsConfig, rng: np.random.Generator, pyramid: ScorePyramid | None = None,
) -> dict[str, object]:
    """Localize from the scans ``idx`` (consecutive held-out scans); the trial's record.

    ``compute_s`` is the trial's CPU time (``time.process_time``: comparable on a
    loaded machine), ``wall_s`` its wall-clock time.
    """
    t0, c0 = time.perf_counter(), time.process_time()
    odom = simulated_odometry(scans.poses[idx], rng, config.odometry)
    est = localize_scans(model, grid, scans.ranges[idx], scans.angles, odom, config.localizer,
                         rng, min_scans=config.updates, accept=config.accept,
                         pyramid=pyramid)  # fmt: skip
    idx = idx[: est.scans_used]
    truth = scans.poses[idx[-1]]
    e_pos = float(math.hypot(*(est.pose[:2] - truth[:2])))
    e_th = float(abs(wrap_angle(float(est.pose[2] - truth[2]))))
    return {
        "start_scan": int(idx[0]), "scans": [int(i) for i in idx],
        "t_start": float(scans.t[idx[0]]), "t_span": float(scans.t[idx[-1]] - scans.t[idx[0]]),
        "distance_driven": float(np.sum(np.hypot(*np.diff(scans.poses[idx, :2], axis=0).T))),
        "estimate": est.pose.tolist(), "truth": truth.tolist(),
        "covariance": est.covariance.tolist(),
        "error_pos": e_pos, "error_theta_deg": math.degrees(e_th),
        "success": bool(e_pos < config.tol_pos and math.degrees(e_th) < config.tol_deg),
        "status": est.status, "margin": est.margin, "score": est.score,
        "scans_used": est.scans_used,
        "competitor": None if est.competitor is None else est.competitor.tolist(),
        "compute_s": time.process_time() - c0, "wall_s": time.perf_counter() - t0,
        "robot_s": float(scans.t[idx[-1]] - scans.t[idx[0]]),
        "converged": est.converged, "spread_xy": est.spread_xy,
        "spread_theta_deg": math.degrees(est.spread_theta),
        "particles_end": est.particles, "time_s": time.perf_counter() - t0,
    }  # fmt: skip


def summarize(records: list[dict[str, object]], map_build_s: float) -> dict[str, object]:
    """Success rate, errors and times over the trials."""

    def col(key: str, rows: list[dict[str, object]]) -> FloatArray:
        return np.array([float(r[key]) for r in rows], dtype=float)  # type: ignore[arg-type]

    ok = [r for r in records if r["success"]]
    trials = [{"status": r["status"], "correct": bool(r["success"]), "compute_s": r["compute_s"],
               "robot_s": r["t_span"]} for r in records]  # fmt: skip
    return summarize_trials(trials) | {
        "within_bounds_rate": len(ok) / max(len(records), 1),
        "converged_rate": float(np.mean([bool(r["converged"]) for r in records])),
        "median_error_pos_m": _nanmedian(col("error_pos", records)),
        "median_error_theta_deg": _nanmedian(col("error_theta_deg", records)),
        "success_mean_error_pos_m": float(np.mean(col("error_pos", ok))) if ok else None,
        "success_mean_error_theta_deg": (
            float(np.mean(col("error_theta_deg", ok))) if ok else None
        ),
        "median_time_s": float(np.median(col("time_s", records))),
        "mean_time_s": float(np.mean(col("time_s", records))),
        "compute_s_median": float(np.median(col("compute_s", records))),
        "median_t_span_s": float(np.median(col("t_span", records))),
        "map_build_s": map_build_s,
    }


def _nanmedian(x: FloatArray) -> float | None:
    """Median over the finite values (a trial without an estimate has NaN errors), None if none."""
    x = x[np.isfinite(x)]
    return float(np.median(x)) if x.size else None


def laser_trials(
    log_path: str | Path, config: LaserTrialsConfig = LaserTrialsConfig(),
    progress: bool = False, map_dir: str | Path | None = None,
) -> dict[str, object]:
    """Hold-out global-localization trials on a CARMEN log (see the module docstring).

    Args:
        log_path: a CARMEN log (``.log`` or ``.log.gz``) with corrected poses.
        config: the trials and the filter.
        progress: print one line per trial.
        map_dir: a map directory (``lampsam build-map``) to localize on; default:
            the grid of the log's even-numbered scans at their corrected poses.

    Returns:
        ``{"summary", "settings", "holdout", "map", "trials"}``, JSON-ready.

    Raises:
        DatasetError: unreadable log.
    """
    scans = usable_scans(read_carmen(log_path).scans)
    map_idx, _ = holdout_split(len(scans))
    test_idx = scan_selection(len(scans), config.scans)
    max_range = config.localizer.beam.max_range
    t0 = time.perf_counter()
    dist = None
    if map_dir is None:
        grid = laser_map(scans, map_idx, config.resolution, max_range)
    else:
        from lampsam.localization.map_store import load_env_map
        from lampsam.localization.map_tables import load_distance_field

        grid = load_env_map(map_dir).grid
        dist = load_distance_field(map_dir, grid)
    model = LikelihoodFieldModel(grid, config.localizer.beam, dist_cells=dist)
    pyramid = (search_pyramid(model, config.localizer)
               if config.localizer.seeding == "search" else None)  # fmt: skip
    t_map = time.perf_counter() - t0
    n_free = int(free_mask(grid).sum())
    if progress:
        print(f"map from {map_idx.size} even scans: {grid.width} x {grid.height} cells at "
              f"{grid.resolution} m, {n_free} free ({n_free * grid.resolution ** 2:.0f} "
              f"m^2), {t_map:.1f} s")  # fmt: skip
    n_use = max(config.updates, config.accept.max_scans)
    last_start = test_idx.size - n_use
    spacing = last_start / max(config.trials - 1, 1)
    starts = np.linspace(0, last_start, config.trials) + config.start_offset * spacing
    starts = np.clip(starts.round().astype(int), 0, last_start)
    records: list[dict[str, object]] = []
    try:
        for trial, s in enumerate(starts):
            idx = test_idx[s : s + n_use]
            rec = run_trial(model, grid, scans, idx, config,
                            np.random.default_rng([config.seed, trial]), pyramid)
            records.append(rec)
            _print_trial(progress, trial, idx, rec)
    except KeyboardInterrupt as exc:
        log.warning("laser trials stopped (%s) after %d of %d trials; the finished ones are kept",
                    exc or "SIGINT", len(records), len(starts))
        status = "interrupted"
    else:
        status = "ok"
    return {
        "status": status,
        "summary": summarize(records, t_map) if records else summarize_trials([]),
        "settings": asdict(config),
        "log": str(log_path),
        "holdout": (f"map {'from even-numbered scans' if map_dir is None else str(map_dir)}, "
                    f"trials on {config.scans} scans"),
        "map": {"width": grid.width, "height": grid.height, "resolution": grid.resolution,
                "origin": grid.origin.tolist(), "free_cells": n_free},
        "trials": records,
    }  # fmt: skip


def _print_trial(progress: bool, trial: int, idx: np.ndarray, rec: dict[str, object]) -> None:
    """One progress line of a finished trial (when ``progress``)."""
    if not progress:
        return
    used = idx[: len(rec["scans"])]  # type: ignore[arg-type]
    print(f"trial {trial:3d} scans {used[0]:4d}..{used[-1]:4d} ({rec['t_span']:5.1f} s, "
          f"{rec['distance_driven']:4.1f} m): error {100 * float(rec['error_pos']):7.1f} "  # type: ignore[arg-type]
          f"cm {rec['error_theta_deg']:6.1f} deg {'OK ' if rec['success'] else 'FAIL'} "
          f"{rec['status']:9s} margin {float(rec['margin']):7.1f} "  # type: ignore[arg-type]
          f"{rec['time_s']:.1f} s wall {float(rec['compute_s']):.1f} s cpu", flush=True)  # type: ignore[arg-type]  # fmt: skip


def write_json(result: dict[str, object], path: str | Path) -> Path:
    """Write the trials' result as JSON; returns the path."""
    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    write_text_atomic(out, json.dumps(json_safe(result), indent=1, allow_nan=False))
    return out
