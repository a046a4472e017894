"""Benchmark and accuracy tables of the three SLAM backends, against their targets.

Usage::

    python scripts/bench/bench_backends.py --lab RUN_DIR [--frames images|truth] [--repeats 3]
    python scripts/bench/bench_backends.py --mrclam [--duration S]

``--lab``: a simulated run (``lampsam simulate lab --out RUN_DIR``). Frames are made
once (the frontend on the images, or the simulator's truth projections) and fed to
every backend with features lamps+corners, corners only and lamps only. Printed:
position/heading error (no alignment, known start) and timings: per-frame median /
p95 of the online step, iSAM2 update median / p95 per keyframe, the batch LM time
and the whole batch run time, and the online run and the whole pipeline (the frontend's
time for the frames included) as multiples of real time (data duration / compute
time). Timings are medians over ``--repeats`` runs; the ratio column divides by the
EKF's per-frame median measured in the same run (reference).

``--mrclam``: MRCLAM ds0 with known association and with the gate alone, the three
backends and dead reckoning, errors against Vicon.
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
import os
import time
from pathlib import Path
from typing import Any

import numpy as np

from lampsam.backend.config import SlamConfig
from lampsam.backend.ekf import EkfSlam
from lampsam.backend.slam import (
    drive,
    errors_vs_truth,
    iter_steps,
    make_backend,
    make_frames,
    start_pose_of,
)
from lampsam.datasets.logrun import LoggedRun, read_run
from lampsam.evaluation.slam_report import markdown_table

BACKENDS = ("ekf", "isam2", "batch")
FEATURES = {"lamps+corners": ("lamps", "corners"), "corners": ("corners",), "lamps": ("lamps",)}


def _errors(result: Any, run: LoggedRun) -> dict[str, float]:
    pos, head = errors_vs_truth(result, run.groundtruth)
    return {"pos_rms_m": float(np.sqrt(np.mean(pos**2))), "pos_max_m": float(pos.max()),
            "head_rms_deg": float(np.degrees(np.sqrt(np.mean(head**2)))),
            "head_max_deg": float(np.degrees(np.abs(head).max()))}


def one_run(name: str, run: LoggedRun, frames: list[Any], config: SlamConfig,
            ceiling: bool) -> dict[str, Any]:
    """Run one backend on prepared frames; errors and timings."""
    t0 = time.perf_counter()
    c0 = time.process_time()
    be = make_backend(name, run.rig.odometry, config, start_pose_of(run),
                      run.rig.camera if ceiling else None)
    res = drive(be, iter_steps(run.odometry, frames))
    total = time.perf_counter() - t0
    cpu = time.process_time() - c0
    frame_ms = res.step_times_s[res.keyframes] * 1e3 if res.keyframes.any() else np.zeros(1)
    row: dict[str, Any] = {"backend": name, "status": res.status, **_errors(res, run),
                           "landmarks": len(res.landmarks), "keyframes": int(res.keyframes.sum()),
                           "frame_median_ms": float(np.median(frame_ms)),
                           "frame_p95_ms": float(np.percentile(frame_ms, 95)),
                           "total_s": total, "cpu_s": cpu, "final_s": res.final_time_s}
    upd = getattr(be, "update_times", None)
    if upd:
        row["update_median_ms"] = float(np.median(upd) * 1e3)
        row["update_p95_ms"] = float(np.percentile(upd, 95) * 1e3)
        est = getattr(be, "estimate_times", [])
        row["estimate_median_ms"] = float(np.median(est) * 1e3) if est else float("nan")
    return row


def median_rows(rows: list[dict[str, Any]]) -> dict[str, Any]:
    """Median of the numeric fields of repeated runs (errors are identical across repeats)."""
    out = dict(rows[0])
    for k, v in rows[0].items():
        if isinstance(v, float):
            out[k] = float(np.median([r[k] for r in rows]))
    return out


def bench_lab(run_dir: Path, source: str, repeats: int, max_frames: int | None,
              backends: tuple[str, ...] = BACKENDS, features: tuple[str, ...] = tuple(FEATURES)
              ) -> None:
    run = read_run(run_dir)
    t0 = time.perf_counter()
    frames, ceiling = make_frames(run, source)
    frames = list(frames)[:max_frames]
    if max_frames is not None:  # cut the odometry at the last frame too
        odo = run.odometry
        keep = odo.t <= frames[-1].t
        run = dataclasses.replace(run, odometry=dataclasses.replace(
            odo, t=odo.t[keep], d_left=odo.d_left[keep], d_right=odo.d_right[keep]))
    frontend_s = time.perf_counter() - t0
    duration = float(run.odometry.t[-1] - run.odometry.t[0])
    print(f"lab run {run_dir}: {len(frames)} frames from {source} in {frontend_s:.1f} s "
          f"({duration:.1f} s of data)")
    base = SlamConfig()
    table = []
    for label, feats in FEATURES.items():
        if label not in features:
            continue
        cfg = dataclasses.replace(base, features=feats)
        for name in backends:
            reps = repeats if label == features[0] else 1
            row = median_rows([one_run(name, run, frames, cfg, ceiling) for _ in range(reps)])
            row["features"] = label
            table.append(row)
            print(f"  {label:14s} {name:6s} pos RMS {row['pos_rms_m']:.4f} m  "
                  f"({row['status']}, {row['total_s']:.1f} s)", flush=True)
    dr = drive(EkfSlam(run.rig.odometry, base, start_pose_of(run)), iter_steps(run.odometry, []))
    table.append({"features": "none (dead reckoning)", "backend": "-", **_errors(dr, run)})
    ekf_rows = [r for r in table if r["backend"] == "ekf"]
    for r in table:
        if "frame_median_ms" in r and ekf_rows:
            r["frame_ratio_vs_ekf"] = r["frame_median_ms"] / ekf_rows[0]["frame_median_ms"]
        if "total_s" in r:
            # online = every step but the final optimisation; "x real time" = data
            # duration / compute time (backend alone, and with the frontend's time)
            online = r["total_s"] - r["final_s"]
            r["online_x_realtime"] = duration / online
            r["pipeline_x_realtime"] = duration / (online + frontend_s)
    print(markdown_table(table, ["features", "backend", "pos_rms_m", "pos_max_m", "head_rms_deg",
                                 "landmarks", "keyframes"]))
    print()
    print(f"timings (median of {repeats} runs for lamps+corners; wall clock, machine shared):")
    print(markdown_table([r for r in table if r.get("features") == features[0]],
                         ["backend", "frame_median_ms", "frame_p95_ms", "frame_ratio_vs_ekf",
                          "update_median_ms", "update_p95_ms", "estimate_median_ms", "final_s",
                          "total_s", "cpu_s", "online_x_realtime", "pipeline_x_realtime"]))
    print(f"x real time = {duration:.1f} s of data / compute time: online = the backend's "
          f"steps (no final optimisation); pipeline = online + the frontend on every frame "
          f"({frontend_s:.1f} s); targets: pipeline >= 10x, iSAM2 frame p95 <= 15 ms; "
          f"load average now {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores")


def bench_mrclam(duration: float | None) -> None:
    from lampsam.datasets.mrclam import mrclam_run
    from lampsam.datasets.paths import shared_dataset

    root = shared_dataset("mrclam_ds0")
    if root is None:
        raise SystemExit("mrclam_ds0 not found (set LAMPSAM_DATA)")
    table = []
    for known in (True, False):
        run = mrclam_run(root, known_ids=known, duration=duration)
        frames, _ = make_frames(run, "rangebearing")
        cfg = SlamConfig()
        for name in BACKENDS:
            row = one_run(name, run, frames, cfg, False)
            row["association"] = "known ids" if known else "gate only"
            table.append(row)
            print(f"  {row['association']:9s} {name:6s} pos RMS {row['pos_rms_m']:.3f} m "
                  f"({row['status']}, {row['total_s']:.1f} s)", flush=True)
    dr = drive(EkfSlam(run.rig.odometry, SlamConfig(), start_pose_of(run)),
               iter_steps(run.odometry, []))
    table.append({"association": "-", "backend": "dead reckoning", **_errors(dr, run)})
    print(markdown_table(table, ["association", "backend", "pos_rms_m", "pos_max_m", "head_rms_deg",
                                 "head_max_deg", "landmarks", "keyframes", "update_median_ms",
                                 "update_p95_ms", "total_s"]))


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--lab", type=Path, default=None, help="simulated lab run directory")
    p.add_argument("--frames", choices=("images", "truth"), default="images")
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--max-frames", type=int, default=None, help="lab: first frames only")
    p.add_argument("--backends", default=",".join(BACKENDS), help="lab: comma-separated subset")
    p.add_argument("--features", default=",".join(FEATURES),
                   help="lab: comma-separated subset of " + ", ".join(FEATURES))
    p.add_argument("--mrclam", action="store_true")
    p.add_argument("--duration", type=float, default=None, help="MRCLAM: first seconds only")
    args = p.parse_args()
    logging.basicConfig(level=logging.WARNING)
    print(f"OPENBLAS_NUM_THREADS={os.environ.get('OPENBLAS_NUM_THREADS', 'unset')}")
    if args.lab is not None:
        bench_lab(args.lab, args.frames, args.repeats, args.max_frames,
                  tuple(args.backends.split(",")), tuple(args.features.split(",")))
    if args.mrclam:
        bench_mrclam(args.duration)
    if args.lab is None and not args.mrclam:
        p.error("give --lab RUN_DIR and/or --mrclam")


if __name__ == "__main__":
    main()
