"""Localize-only tracking on a saved ceiling map against SLAM from scratch (issue 20).

Usage::

    lampsam simulate lab --out LAB1 --seed 1
    lampsam slam LAB1 --backend batch --out SLAM1 --save-map MAP
    lampsam simulate lab_day2 --out DAY2 --seed 2
    python scripts/bench/bench_localize_only.py --map MAP DAY2 [DAY3 ...] [--repeats 3]

For every run the frames are made once (the frontend on the images, or
``--frames truth``) and fed to: localize-only on MAP (:class:`MapLocalizer`), and
SLAM from scratch on the same frames with the backends of ``--backends`` (default
isam2, batch, ekf). Printed per run and method: position and heading RMS against the
run's truth (no alignment, known start pose), and the CPU time (``time.process_time``,
comparable on a loaded machine) per frame: the median of the online steps that had a
frame, and the mean per frame including the final optimisation (batch LM). Timings
are medians over ``--repeats`` runs; ``x ref`` divides by the reference method's
figure (``--reference``, default isam2) measured in the same run. The frontend's
time is not included (it is the same for every method).
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
import os
import time
from typing import Any

import numpy as np

from lampsam.backend.ceiling import CeilingModel
from lampsam.backend.ceiling_map_io import read_map
from lampsam.backend.config import SlamConfig
from lampsam.backend.interface import SlamBackend
from lampsam.backend.localize_only import MapLocalizer
from lampsam.backend.slam import (
    errors_vs_truth,
    iter_steps,
    make_backend,
    make_frames,
    start_pose_of,
)
from lampsam.datasets.logrun import LoggedRun, read_run


def timed_run(backend: SlamBackend, run: LoggedRun, frames: list[Any]) -> dict[str, float]:
    """Step a backend through the run; errors and CPU times."""
    step_cpu, has_frame = [], []
    for t, wheel, frame in iter_steps(run.odometry, frames):
        c0 = time.process_time()
        backend.step(t, wheel, frame)
        step_cpu.append(time.process_time() - c0)
        has_frame.append(frame is not None)
    c0 = time.process_time()
    result = backend.finish()
    finish_cpu = time.process_time() - c0
    pos, head = errors_vs_truth(result, run.groundtruth)
    cpu = np.asarray(step_cpu)
    n_frames = max(int(np.sum(has_frame)), 1)
    return {"pos_rms_mm": 1e3 * float(np.sqrt(np.mean(pos**2))),
            "pos_max_mm": 1e3 * float(pos.max()),
            "head_rms_deg": float(np.degrees(np.sqrt(np.mean(head**2)))),
            "frame_median_ms": 1e3 * float(np.median(cpu[np.asarray(has_frame)])),
            "per_frame_ms": 1e3 * (float(cpu.sum()) + finish_cpu) / n_frames,
            "finish_s": finish_cpu,
            "landmarks": float(len(result.landmarks)),
            "status_ok": float(result.status == "ok")}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("runs", nargs="+", help="run directories (e.g. lab_day2 simulations)")
    ap.add_argument("--map", required=True, help="ceiling map folder (slam --save-map)")
    ap.add_argument("--frames", default="images", choices=("images", "truth"))
    ap.add_argument("--backends", default="isam2,batch,ekf", help="SLAM from scratch backends")
    ap.add_argument("--reference", default="isam2", help="method the ratios divide by")
    ap.add_argument("--repeats", type=int, default=3, help="runs per method (timing median)")
    args = ap.parse_args()
    logging.basicConfig(level=logging.ERROR)
    cmap = read_map(args.map)
    config = SlamConfig()
    config = dataclasses.replace(config, isam2=dataclasses.replace(config.isam2,
                                                                   final_covariances=False))
    load = os.getloadavg()
    print(f"map {args.map}: {len(cmap.by_kind('lamp'))} lamps, {len(cmap.by_kind('corner'))} "
          f"corners; frames {args.frames}; repeats {args.repeats}; load average "
          f"{load[0]:.1f} {load[1]:.1f} {load[2]:.1f} (2 cores)")
    methods = ["localize", *[b for b in args.backends.split(",") if b]]
    rows: dict[str, list[dict[str, float]]] = {m: [] for m in methods}
    for run_dir in args.runs:
        run = read_run(run_dir)
        made, _ = make_frames(run, args.frames)
        frames = list(made)
        start = start_pose_of(run)
        figures: dict[str, dict[str, float]] = {}
        for m in methods:
            reps = []
            for _ in range(args.repeats):
                if m == "localize":
                    be: SlamBackend = MapLocalizer(run.rig.odometry, config, start, cmap,
                                                   CeilingModel.from_camera(run.rig.camera))
                else:
                    be = make_backend(m, run.rig.odometry, config, start, run.rig.camera)
                reps.append(timed_run(be, run, frames))
            fig = {k: float(np.median([r[k] for r in reps])) for k in reps[0]}
            figures[m] = fig
            rows[m].append(fig)
        ref = figures.get(args.reference)
        print(f"\n{run_dir} ({len(frames)} frames)")
        print("| method | pos RMS mm | pos max mm | head RMS deg | CPU/frame median ms | "
              "x ref | CPU/frame mean incl. final ms | x ref |")
        print("|---|---:|---:|---:|---:|---:|---:|---:|")
        for m, f in figures.items():
            r1 = f["frame_median_ms"] / ref["frame_median_ms"] if ref else float("nan")
            r2 = f["per_frame_ms"] / ref["per_frame_ms"] if ref else float("nan")
            print(f"| {m} | {f['pos_rms_mm']:.1f} | {f['pos_max_mm']:.1f} | {f['head_rms_deg']:.3f} "
                  f"| {f['frame_median_ms']:.2f} | {r1:.3f} | {f['per_frame_ms']:.2f} | {r2:.3f} |")
    if len(args.runs) > 1:
        print("\nmean over runs")
        for m, fs in rows.items():
            print(f"{m}: pos RMS {np.mean([f['pos_rms_mm'] for f in fs]):.1f} mm, CPU/frame median "
                  f"{np.mean([f['frame_median_ms'] for f in fs]):.2f} ms, mean incl. final "
                  f"{np.mean([f['per_frame_ms'] for f in fs]):.2f} ms")


if __name__ == "__main__":
    main()
