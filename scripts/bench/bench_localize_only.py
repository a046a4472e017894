"""Localize-only tracking on a saved ceiling map against SLAM from scratch.

Usage::

    lampsam simulate lab --out LAB1 --seed 1
    lampsam slam LAB1 --backend batch --out SLAM1 --save-map MAP
    lampsam simulate lab_day2 --out DAY2 --seed 2
    python scripts/bench/bench_localize_only.py --map MAP DAY2 [DAY3 ...] [--repeats 3]

``--map`` may be given more than once (maps of separate drives, merged by
:func:`lampsam.backend.map_merge.merge_maps`). For every run the frames are made once
(the frontend on the images, or ``--frames truth``) and fed to: localize-only on MAP
(:class:`MapLocalizer`, ``localize``: the map fixed; ``localize-priors`` and
``localize-consider``: ``LocalizeConfig.map_mode``; with a version-2 map also
``localize-frame`` and ``localize-priors-frame``: the map frame's offset state,
``LocalizeConfig.frame_offset``), and
SLAM from scratch on the same frames with the backends of ``--backends`` (default
isam2, batch, ekf). Printed per run and method: position and heading RMS against the
run's truth (no alignment, known start pose), and the CPU time (``time.process_time``,
comparable on a loaded machine) per frame: the median of the online steps that had a
frame, and the mean per frame including the final optimisation (batch LM). Timings
are medians over ``--repeats`` runs; ``x ref`` divides by the reference method's
figure (``--reference``, default isam2) measured in the same run. The frontend's
time is not included (it is the same for every method).

The map lives in the mapping run's frame, a few millimetres and hundredths of a
degree off the truth's; localize-only tracks in the map's frame. ``in map frame``
is its error after moving the poses by the rigid transform from the map's frame to
the truth's, fitted on the lamps (:func:`map_to_truth`): what is left is the
tracking's own error.
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
import math
import os
import time
from typing import Any

import numpy as np

from lampsam.arrays import FloatArray
from lampsam.backend.ceiling import CeilingModel
from lampsam.backend.ceiling_map_io import CeilingMap, read_map
from lampsam.backend.config import SlamConfig
from lampsam.backend.interface import SlamBackend
from lampsam.backend.localize_only import LocalizeConfig, MapLocalizer
from lampsam.backend.map_merge import merge_maps
from lampsam.backend.slam import (
    errors_vs_truth,
    iter_steps,
    make_backend,
    make_frames,
    start_pose_of,
)
from lampsam.datasets.logrun import LoggedRun, read_run


def map_to_truth(cmap: CeilingMap, run: LoggedRun) -> tuple[FloatArray, float, int] | None:
    """The rigid 2-D transform taking the map's frame to the truth's, fitted on the lamps.

    Each map lamp is paired with the nearest true lamp (within 0.1 m); the fit is the
    least-squares rotation and translation (Kabsch). Returns ``((3,) x, y, theta of
    truth_T_map, the residual lamp RMS in m, lamps used)`` or None without truth.
    """
    if run.landmarks is None:
        return None
    is_lamp = np.array([t.startswith("lamp") for t in run.landmarks.types])
    truth = run.landmarks.xyz[is_lamp, :2]
    pairs = []
    for lm in cmap.by_kind("lamp"):
        d = np.linalg.norm(truth - lm.position[:2], axis=1)
        if len(d) and d.min() < 0.1:
            pairs.append((lm.position[:2], truth[int(np.argmin(d))]))
    if len(pairs) < 2:
        return None
    a = np.array([p for p, _ in pairs])
    b = np.array([q for _, q in pairs])
    ca, cb = a.mean(0), b.mean(0)
    u, _, vt = np.linalg.svd((a - ca).T @ (b - cb))
    rot = (u @ vt).T
    if np.linalg.det(rot) < 0:
        return None
    t = cb - rot @ ca
    res = (rot @ a.T).T + t - b
    theta = float(np.arctan2(rot[1, 0], rot[0, 0]))
    return np.array([t[0], t[1], theta]), float(np.sqrt(np.mean(np.sum(res**2, 1)))), len(pairs)


def in_truth_frame(poses: FloatArray, truth_t_map: FloatArray) -> FloatArray:
    """Map-frame poses (N, 3) expressed in the truth's frame."""
    c, s = math.cos(truth_t_map[2]), math.sin(truth_t_map[2])
    out = np.empty_like(poses)
    out[:, 0] = truth_t_map[0] + c * poses[:, 0] - s * poses[:, 1]
    out[:, 1] = truth_t_map[1] + s * poses[:, 0] + c * poses[:, 1]
    out[:, 2] = poses[:, 2] + truth_t_map[2]
    return out


def timed_run(backend: SlamBackend, run: LoggedRun, frames: list[Any],
              truth_t_map: FloatArray | None = None) -> dict[str, float]:
    """Step a backend through the run; errors and CPU times (``truth_t_map``: also the
    error after taking the poses from the map's frame to the truth's)."""
    step_cpu, has_frame = [], []
    for t, wheel, frame in iter_steps(run.odometry, frames):
        c0 = time.process_time()
        backend.step(t, wheel, frame)
        step_cpu.append(time.process_time() - c0)
        has_frame.append(frame is not None)
    c0 = time.process_time()
    result = backend.finish()
    finish_cpu = time.process_time() - c0
    truth = run.groundtruth
    if truth is None:
        raise SystemExit(f"{run.path}: no groundtruth.tum: nothing to measure the error against")
    pos, head = errors_vs_truth(result, truth)
    in_map = float("nan")
    if truth_t_map is not None:
        moved = dataclasses.replace(result, poses=in_truth_frame(result.poses, truth_t_map))
        pos_m, _ = errors_vs_truth(moved, truth)
        in_map = 1e3 * float(np.sqrt(np.mean(pos_m**2)))
    cpu = np.asarray(step_cpu)
    n_frames = max(int(np.sum(has_frame)), 1)
    return {"pos_rms_mm": 1e3 * float(np.sqrt(np.mean(pos**2))),
            "pos_max_mm": 1e3 * float(pos.max()),
            "pos_rms_map_frame_mm": in_map,
            "head_rms_deg": float(np.degrees(np.sqrt(np.mean(head**2)))),
            "frame_median_ms": 1e3 * float(np.median(cpu[np.asarray(has_frame)])),
            "per_frame_ms": 1e3 * (float(cpu.sum()) + finish_cpu) / n_frames,
            "finish_s": finish_cpu,
            "landmarks": float(len(result.landmarks)),
            "status_ok": float(result.status == "ok")}


def localize_config(method: str) -> LocalizeConfig:
    """``localize[-priors|-consider][-frame]`` as settings; ``-frame`` uses the map's frame
    model (version-2 maps) with the known start held as tightly as SLAM's (1 mm, 1 mrad)."""
    parts = method.split("-")[1:]
    mode = next((p for p in parts if p in ("priors", "consider")), "fixed")
    if "frame" in parts:
        return LocalizeConfig(map_mode=mode, frame_offset=True, sigma_start_xy=1e-3,  # type: ignore[arg-type]
                              sigma_start_theta=1e-3)
    return LocalizeConfig(map_mode=mode)  # type: ignore[arg-type]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("runs", nargs="+", help="run directories (e.g. lab_day2 simulations)")
    ap.add_argument("--map", required=True, action="append",
                    help="ceiling map folder (slam --save-map); repeat to merge maps")
    ap.add_argument("--frames", default="images", choices=("images", "truth"))
    ap.add_argument("--backends", default="isam2,batch,ekf", help="SLAM from scratch backends")
    ap.add_argument("--reference", default="isam2", help="method the ratios divide by")
    ap.add_argument("--repeats", type=int, default=3, help="runs per method (timing median)")
    args = ap.parse_args()
    logging.basicConfig(level=logging.ERROR)
    cmap = read_map(args.map[0])
    for more in args.map[1:]:
        cmap, counts = merge_maps(cmap, read_map(more))
        print(f"merged {more}: {counts}")
    config = SlamConfig()
    config = dataclasses.replace(config, isam2=dataclasses.replace(config.isam2,
                                                                   final_covariances=False))
    load = os.getloadavg()
    print(f"map {args.map}: {len(cmap.by_kind('lamp'))} lamps, {len(cmap.by_kind('corner'))} "
          f"corners; frames {args.frames}; repeats {args.repeats}; load average "
          f"{load[0]:.1f} {load[1]:.1f} {load[2]:.1f} (2 cores)")
    methods = ["localize", "localize-priors", "localize-consider",
               *(["localize-frame", "localize-priors-frame"] if cmap.frame is not None else []),
               *[b for b in args.backends.split(",") if b]]
    rows: dict[str, list[dict[str, float]]] = {m: [] for m in methods}
    for run_dir in args.runs:
        run = read_run(run_dir)
        made, _ = make_frames(run, args.frames)
        frames = list(made)
        start = start_pose_of(run)
        frame_fit = map_to_truth(cmap, run)
        figures: dict[str, dict[str, float]] = {}
        for m in methods:
            reps = []
            for _ in range(args.repeats):
                if m.startswith("localize"):
                    be: SlamBackend = MapLocalizer(
                        run.rig.odometry, config, start, cmap,
                        CeilingModel.from_camera(run.rig.camera), localize_config(m))
                else:
                    be = make_backend(m, run.rig.odometry, config, start, run.rig.camera)
                reps.append(timed_run(be, run, frames, frame_fit[0] if frame_fit and
                                      m.startswith("localize") else None))
            fig = {k: float(np.median([r[k] for r in reps])) for k in reps[0]}
            figures[m] = fig
            rows[m].append(fig)
        ref = figures.get(args.reference)
        print(f"\n{run_dir} ({len(frames)} frames)")
        if frame_fit is not None:
            x, y, th = frame_fit[0]
            print(f"map frame vs truth (fit on {frame_fit[2]} lamps): dx {1e3 * x:.1f} mm, dy "
                  f"{1e3 * y:.1f} mm, dtheta {math.degrees(th):.3f} deg; lamp residual "
                  f"{1e3 * frame_fit[1]:.1f} mm RMS")
        print("| method | pos RMS mm | in map frame | pos max mm | head RMS deg | "
              "CPU/frame median ms | x ref | CPU/frame mean incl. final ms | x ref |")
        print("|---|---:|---:|---:|---:|---:|---:|---:|---:|")
        for m, f in figures.items():
            r1 = f["frame_median_ms"] / ref["frame_median_ms"] if ref else float("nan")
            r2 = f["per_frame_ms"] / ref["per_frame_ms"] if ref else float("nan")
            print(f"| {m} | {f['pos_rms_mm']:.1f} | {f['pos_rms_map_frame_mm']:.1f} | {f['pos_max_mm']:.1f} | {f['head_rms_deg']:.3f} "
                  f"| {f['frame_median_ms']:.2f} | {r1:.3f} | {f['per_frame_ms']:.2f} | {r2:.3f} |")
    if len(args.runs) > 1:
        print("\nmean over runs")
        for m, fs in rows.items():
            print(f"{m}: pos RMS {np.mean([f['pos_rms_mm'] for f in fs]):.1f} mm, CPU/frame median "
                  f"{np.mean([f['frame_median_ms'] for f in fs]):.2f} ms, mean incl. final "
                  f"{np.mean([f['per_frame_ms'] for f in fs]):.2f} ms")


if __name__ == "__main__":
    main()
