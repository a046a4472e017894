"""Benchmark: the online ceiling pipeline with the frontend in turn vs overlapped.

Usage::

    python scripts/bench/bench_pipeline.py --run RUN [--backend isam2]
        [--modes sequential,process,decoupled] [--paces none,4] [--max-frames N] [--depth 8]

with ``RUN`` from ``lampsam simulate lab --seed 3 --out RUN`` (2,601 frames, 173 s).

For every replay pace and mode, in one process, one after the other: image
load + frontend (:func:`lampsam.backend.pipelined.frame_source`) feeding the
backend's online steps (:func:`lampsam.backend.slam.iter_steps`, the final
optimisation not counted), as ``lampsam slam --frontend MODE`` runs them.

* ``sequential``: the frontend runs in the estimator's thread when a frame is
  due (today's default);
* ``thread`` / ``process``: a worker makes up to ``--depth`` frames ahead.
* ``decoupled``: the frontend in a worker process as ``process``, the backend in a
  second worker process, and this process giving every frame's pose at once from
  the backend's newest estimate plus odometry (:mod:`lampsam.backend.tracking`:
  tracking vs mapping). Its latency is frame arrival -> tracked pose; it also
  prints the keyframe latency (step handed to the backend -> its estimate back),
  how many steps the tracked pose's anchor was behind, the wall clock until the
  backend finished the last step (its x real time is the throughput) and the
  tracked poses' largest difference from the backend's own online poses. On a loaded
  machine the worker's wall-clock latencies reflect the load, so the keyframe
  latency is also replayed from the worker's CPU time per step as if it had a core of
  its own, steps arriving at 1x, 4x and 8x real time
  (:func:`~lampsam.backend.tracking.replay_latency`).

Paces: ``none`` replays as fast as possible (throughput: x real time by wall
clock; a frame "arrives" when its image starts to be read, so a worker that runs
ahead adds queue wait to the latency); a number replays at that multiple of real
time (image ``i`` arrives at ``start + (t_i - t_0) / pace``; what a robot's camera
does at 1). Printed per row: wall-clock x real time of the online run, process
CPU of the estimator's process and of the worker (a process worker's CPU is its
own; together they are the machine's work), latency from a frame's arrival to
its pose estimate (median / p95 / max, ms), start-up (call to first frame), and
the largest pose difference to the sequential row's online poses (0 when the
frames are the same). Ratios: each row's wall clock and latency against the
sequential row of the same pace, measured in this run.

Overlap needs a second core: the worker process's CPU is spent on the other
core, so wall clock falls towards the larger stage while the CPU summed over
both processes rises (pickling the frames). On a loaded machine both figures
are inflated; the load average is printed.
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
import os
import time
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from lampsam.backend.config import SlamConfig
from lampsam.backend.pipelined import MODES, FrameTimes, frame_source
from lampsam.backend.slam import iter_steps, make_backend, start_pose_of
from lampsam.backend.tracking import replay_latency, run_decoupled
from lampsam.datasets.logrun import LoggedRun, read_run
from lampsam.datasets.tables import OdometryLog


def _cut(run: LoggedRun, max_frames: int | None) -> LoggedRun:
    """The run's first ``max_frames`` images and the odometry up to the last one."""
    if max_frames is None or run.images is None or max_frames >= len(run.images):
        return run
    im = run.images
    images = dataclasses.replace(im, t=im.t[:max_frames], files=im.files[:max_frames])
    odo = run.odometry
    if not isinstance(odo, OdometryLog):
        raise SystemExit("--max-frames needs wheel odometry (a simulated ceiling run)")
    keep = odo.t <= images.t[-1]
    odometry = dataclasses.replace(odo, t=odo.t[keep], d_left=odo.d_left[keep],
                                   d_right=odo.d_right[keep])
    return dataclasses.replace(run, images=images, odometry=odometry)


#: Paces (x real time) at which the decoupled row's keyframe latency is replayed from
#: the backend's measured CPU per step (:func:`replay_latency`).
REPLAY_PACES = (1.0, 4.0, 8.0)


def decoupled_row(run: LoggedRun, backend: str, pace: float | None, depth: int
                  ) -> dict[str, Any]:
    """One online run with tracking decoupled from mapping (:func:`run_decoupled`)."""
    assert run.images is not None
    times = FrameTimes()
    w0, c0 = time.perf_counter(), time.process_time()
    source = frame_source(run.images, run.rig.camera, mode="process", depth=depth, pace=pace,
                          times=times)
    has_frame: list[bool] = []

    def steps() -> Any:
        for step in iter_steps(run.odometry, source):
            has_frame.append(step[2] is not None)
            yield step

    tm = run_decoupled(steps(), backend, run.rig.odometry, SlamConfig(), start_pose_of(run),
                       run.rig.camera)
    cpu = time.process_time() - c0
    fr = np.asarray(has_frame, bool)
    out = np.asarray(tm.out)[fr]
    n = len(out)
    lat = 1e3 * (out - np.asarray(times.arrival[:n]))
    track = 1e3 * (out - np.asarray(times.ready[:n]))
    kf = np.asarray(tm.keyframe, bool)
    kf_lat = 1e3 * (np.asarray(tm.back) - np.asarray(tm.sent))[kf]
    lag = np.arange(len(tm.anchor)) - np.asarray(tm.anchor)
    start = times.arrival[0] if times.arrival else w0
    duration = float(run.odometry.t[-1] - run.odometry.t[0])
    wall = tm.worker_done - start
    step_cpu = np.asarray(tm.step_cpu)
    replay = {f"replay_{p:g}x_kf_p95_ms": float(np.percentile(
        1e3 * replay_latency(np.asarray(tm.t), step_cpu, p)[kf], 95)) for p in REPLAY_PACES}
    poses = np.asarray(tm.pose)
    diff = poses - np.asarray(tm.backend_pose)
    diff[:, 2] = np.angle(np.exp(1j * diff[:, 2]))
    return {"mode": "decoupled", "pace": "max" if pace is None else f"{pace:g}x",
            "frames": n, "startup_s": start - w0, "online_wall_s": wall,
            "x_rt_wall": duration / wall, "cpu_main_s": cpu, "cpu_worker_s": tm.worker_cpu_s,
            "cpu_total_s": cpu + tm.worker_cpu_s + times.worker_cpu_s,
            "x_rt_cpu_main": duration / cpu, "frontend_cpu_s": times.worker_cpu_s,
            "lat_med_ms": float(np.median(lat)), "lat_p95_ms": float(np.percentile(lat, 95)),
            "lat_max_ms": float(lat.max()), "track_p95_ms": float(np.percentile(track, 95)),
            "kf_lat_med_ms": float(np.median(kf_lat)), "kf_lat_p95_ms": float(np.percentile(kf_lat, 95)),
            "lag_p95_steps": float(np.percentile(lag, 95)),
            "tracked_vs_backend_max": float(np.abs(diff).max()), "_poses": poses,
            "backend_cpu_x_rt": duration / float(step_cpu.sum()),
            "kf_cpu_p95_ms": float(np.percentile(1e3 * step_cpu[kf], 95)), **replay}


def one_row(run: LoggedRun, backend: str, mode: str, pace: float | None, depth: int
            ) -> dict[str, Any]:
    """One online run: timings, latencies and the online poses."""
    if mode == "decoupled":
        return decoupled_row(run, backend, pace, depth)
    assert run.images is not None
    be = make_backend(backend, run.rig.odometry, SlamConfig(), start_pose_of(run), run.rig.camera)
    times = FrameTimes()
    w0, c0 = time.perf_counter(), time.process_time()
    source = frame_source(run.images, run.rig.camera, mode=mode, depth=depth,  # type: ignore[arg-type]
                          pace=pace, times=times)
    done: list[float] = []
    poses = []
    first = None
    for t, wheel, frame in iter_steps(run.odometry, source):
        if first is None:
            first = time.perf_counter()
        est = be.step(t, wheel, frame)
        poses.append(np.asarray(est.pose, float))
        if frame is not None:
            done.append(time.perf_counter())
    wall_end, cpu = time.perf_counter(), time.process_time() - c0
    be.finish()
    n = len(done)
    lat = 1e3 * (np.asarray(done) - np.asarray(times.arrival[:n]))
    online_wall = wall_end - (times.arrival[0] if times.arrival else w0)
    duration = float(run.odometry.t[-1] - run.odometry.t[0])
    worker_cpu = times.worker_cpu_s if mode == "process" else 0.0
    return {"mode": mode, "pace": "max" if pace is None else f"{pace:g}x",
            "frames": n, "startup_s": (first or w0) - w0, "online_wall_s": online_wall,
            "x_rt_wall": duration / online_wall, "cpu_main_s": cpu, "cpu_worker_s": worker_cpu,
            "cpu_total_s": cpu + worker_cpu, "x_rt_cpu_main": duration / cpu,
            "frontend_cpu_s": times.worker_cpu_s,
            "lat_med_ms": float(np.median(lat)), "lat_p95_ms": float(np.percentile(lat, 95)),
            "lat_max_ms": float(lat.max()), "_poses": np.array(poses)}


def main() -> None:
    """Run the rows, print the table."""
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--run", type=Path, required=True, help="a simulated lab run directory")
    p.add_argument("--backend", default="isam2", choices=("isam2", "ekf", "batch"))
    p.add_argument("--modes", default="sequential,process",
                   help="comma-separated subset of " + ",".join((*MODES, "decoupled")))
    p.add_argument("--paces", default="none",
                   help="comma-separated replay speeds, x real time ('none': as fast as possible)")
    p.add_argument("--depth", type=int, default=8, help="worker queue, frames (default 8)")
    p.add_argument("--max-frames", type=int, default=None, help="the run's first frames only")
    p.add_argument("--cv-threads", type=int, default=1, help="OpenCV threads (default 1)")
    args = p.parse_args()
    logging.basicConfig(level=logging.WARNING)
    cv2.setNumThreads(args.cv_threads)
    modes = args.modes.split(",")
    paces = [None if s == "none" else float(s) for s in args.paces.split(",")]
    run = _cut(read_run(args.run), args.max_frames)
    assert run.images is not None
    duration = float(run.odometry.t[-1] - run.odometry.t[0])
    print(f"{args.run}: {len(run.images)} frames, {duration:.1f} s of data; backend "
          f"{args.backend}; queue {args.depth}; OpenCV threads {cv2.getNumThreads()}; "
          f"{os.cpu_count()} cores; load average {os.getloadavg()[0]:.1f}", flush=True)
    rows = []
    for pace in paces:
        ref: dict[str, Any] | None = None
        for mode in modes:
            row = one_row(run, args.backend, mode, pace, args.depth)
            if mode == "sequential":
                ref = row
            if ref is not None:
                row["wall_vs_seq"] = row["online_wall_s"] / ref["online_wall_s"]
                row["lat_p95_vs_seq"] = row["lat_p95_ms"] / ref["lat_p95_ms"]
                row["cpu_total_vs_seq"] = row["cpu_total_s"] / ref["cpu_total_s"]
                same = row["_poses"].shape == ref["_poses"].shape
                row["max_pose_diff"] = (float(np.abs(row["_poses"] - ref["_poses"]).max())
                                        if same else float("nan"))
            rows.append(row)
            print(f"  {row['pace']:>5s} {mode:10s} wall {row['online_wall_s']:7.2f} s "
                  f"({row['x_rt_wall']:5.1f}x real time), CPU main {row['cpu_main_s']:6.2f} s + "
                  f"worker {row['cpu_worker_s']:6.2f} s, frontend {row['frontend_cpu_s']:6.2f} s; "
                  f"latency median / p95 / max {row['lat_med_ms']:.1f} / {row['lat_p95_ms']:.1f} / "
                  f"{row['lat_max_ms']:.0f} ms; start-up {row['startup_s']:.2f} s; "
                  f"load {os.getloadavg()[0]:.1f}", flush=True)
            if mode == "decoupled":
                print(f"        tracking (frame ready -> pose) p95 {row['track_p95_ms']:.2f} ms; "
                      f"keyframe latency median / p95 {row['kf_lat_med_ms']:.1f} / "
                      f"{row['kf_lat_p95_ms']:.1f} ms; anchor lag p95 {row['lag_p95_steps']:.0f} "
                      f"steps; tracked vs backend poses max {row['tracked_vs_backend_max']:.2g}",
                      flush=True)
                print(f"        backend steps' CPU {duration / row['backend_cpu_x_rt']:.2f} s = "
                      f"{row['backend_cpu_x_rt']:.1f}x real time, keyframe CPU p95 "
                      f"{row['kf_cpu_p95_ms']:.1f} ms; keyframe latency p95 replayed on a core of "
                      f"its own: " + ", ".join(f"{row[f'replay_{p:g}x_kf_p95_ms']:.1f} ms at {p:g}x"
                                               for p in REPLAY_PACES), flush=True)
    cols = ["pace", "mode", "x_rt_wall", "wall_vs_seq", "cpu_main_s", "cpu_worker_s",
            "cpu_total_vs_seq", "lat_med_ms", "lat_p95_ms", "lat_max_ms", "lat_p95_vs_seq",
            "startup_s", "max_pose_diff", "kf_lat_p95_ms", "lag_p95_steps"]
    print()
    print("| " + " | ".join(cols) + " |")
    print("|" + "---|" * len(cols))
    for r in rows:
        cells = [r.get(c, "") for c in cols]
        print("| " + " | ".join(f"{c:.3g}" if isinstance(c, float) else str(c)
                                for c in cells) + " |")
    print(f"x_rt_wall: data duration / online wall clock (decoupled: until the backend "
          f"finished); cpu_*: process CPU s (worker: the frontend process; decoupled: the "
          f"backend process); latency: frame arrival -> pose estimate (decoupled: the tracked "
          f"pose); load average {os.getloadavg()[0]:.1f} at the end")


if __name__ == "__main__":
    main()
