"""Benchmark: the online ceiling pipeline with the frontend in turn vs overlapped.

Usage::

    python scripts/bench/bench_pipeline.py --run RUN [--backend isam2]
        [--modes sequential,process,decoupled,decoupled-process] [--paces none,4]
        [--repeats 3] [--max-lag 15] [--max-frames N] [--depth 8] [--catch-up 1,8]

with ``RUN`` from ``lampsam simulate lab --seed 3 --out RUN`` (2,601 frames, 173 s).

For every replay pace and mode, in one process, one after the other: image
load + frontend (:func:`lampsam.backend.pipelined.frame_source`) feeding the
backend's online steps (:func:`lampsam.backend.slam.iter_steps`, the final
optimisation not counted), as ``lampsam slam --frontend MODE`` runs them.

* ``sequential``: the frontend runs in the estimator's thread when a frame is
  due (today's default);
* ``thread`` / ``process``: a worker makes up to ``--depth`` frames ahead.
* ``decoupled``: as ``lampsam slam --online decoupled`` runs it
  (:mod:`lampsam.backend.tracking`: tracking vs mapping): the frontend and the
  tracking in this process, the backend in a worker process, every frame's pose
  given at once from the backend's newest estimate plus odometry, with
  ``--max-lag`` steps of back-pressure (default 15, as the CLI; -1 never waits, as
  a robot's camera). ``decoupled-process``: the frontend in a third process too.
  Its latency is frame arrival -> tracked pose. Also printed: the CPU of each part
  of both processes (frontend, tracking, queue pickling; the backend's steps, taking
  them from the inbox, the rest, and apart its final optimisation, which runs after
  the timed steps), the worker's idle time, its stalls and the tracker's
  back-pressure waits (wall; a stall: the worker neither computing nor waiting for
  steps, i.e. waiting for a core while other processes load the machine), the bound
  two free cores would give (data duration / the busiest process's CPU until the
  last step, independent of the other sessions' load), the CPU per frame of
  the tracking thread (image load + frontend + tracking, p95), the keyframe latency
  (step handed over -> its estimate back), how many steps the tracked pose's anchor
  was behind, and the tracked poses' largest difference from the backend's own. On
  a loaded machine the worker's wall-clock latencies reflect the load, so the
  keyframe latency is also replayed from the worker's CPU time per step as if it
  had a core of its own, steps arriving at 1x, 4x and 8x real time
  (:func:`~lampsam.backend.tracking.replay_latency`).

``--catch-up 1,8``: each decoupled mode once per ``[online] catch_up`` value (keyframes
per iSAM2 update at most while the worker is behind; 1 = off), labelled ``cu=N``.
Every row also gives the accuracy against the run's ground truth: the position RMS
of the final trajectory (the decoupled rows run the backend's final step in the
worker, after the timed steps) and of the online poses (decoupled: the tracked
poses, ``tracked.tum``), and for catch-up how many of the worker's iSAM2 updates took
more than one keyframe.

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

from lampsam.backend.config import OnlineConfig, SlamConfig
from lampsam.backend.online_run import DEFAULT_MAX_LAG, online_figures
from lampsam.backend.pipelined import MODES, FrameTimes, frame_source
from lampsam.backend.slam import iter_steps, make_backend, start_pose_of
from lampsam.backend.tracking import replay_latency, run_decoupled
from lampsam.datasets.logrun import LoggedRun, read_run
from lampsam.datasets.tables import OdometryLog
from lampsam.evaluation.metrics import interpolate_poses, pose_errors


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


#: The decoupled rows: the frontend in this process (as the CLI), or in a worker too.
DECOUPLED = ("decoupled", "decoupled-process")

#: Paces (x real time) at which the decoupled row's keyframe latency is replayed from
#: the backend's measured CPU per step (:func:`replay_latency`).
REPLAY_PACES = (1.0, 4.0, 8.0)


def rms_mm(run: LoggedRun, t: np.ndarray, poses: np.ndarray) -> float:
    """Position RMS (mm) of ``poses`` at times ``t`` against the run's ground truth."""
    truth = interpolate_poses(np.asarray(t, float), run.groundtruth.t, run.groundtruth.poses)
    err, _ = pose_errors(np.asarray(poses, float).reshape(-1, 3), truth)
    return float(1e3 * np.sqrt(np.mean(err**2)))


def decoupled_row(run: LoggedRun, backend: str, pace: float | None, depth: int,
                  frontend: str, max_lag: int | None, catch_up: int = 1) -> dict[str, Any]:
    """One online run with tracking decoupled from mapping, as ``lampsam slam --online
    decoupled`` runs it (:func:`run_decoupled`; the final optimisation not run): the
    frontend in this process (``frontend`` "sequential") or a worker, the backend in a
    worker process."""
    assert run.images is not None
    times = FrameTimes()
    w0, c0, th0 = time.perf_counter(), time.process_time(), time.thread_time()
    source = frame_source(run.images, run.rig.camera, mode=frontend,  # type: ignore[arg-type]
                          depth=depth, pace=pace, times=times)
    config = SlamConfig(online=OnlineConfig(catch_up=catch_up))
    tm = run_decoupled(iter_steps(run.odometry, source), backend, run.rig.odometry, config,
                       start_pose_of(run), run.rig.camera, max_lag=max_lag, finish=True)
    cpu, thread_cpu = time.process_time() - c0, time.thread_time() - th0
    duration = float(run.odometry.t[-1] - run.odometry.t[0])
    figs = online_figures(tm, np.asarray(times.arrival, float), duration, w0, cpu)
    fr = np.asarray(tm.framed, bool)
    out, ready = np.asarray(tm.out)[fr], np.asarray(times.ready[:int(fr.sum())])
    track = 1e3 * (out - ready)  # frame made -> its tracked pose (wall)
    step_thread_cpu = 1e3 * np.diff(np.concatenate([[th0], tm.cpu_out]))  # make + track a step
    kf = np.asarray(tm.keyframe, bool)
    step_cpu = np.asarray(tm.step_cpu)
    replay = {f"replay_{p:g}x_kf_p95_ms": float(np.percentile(
        1e3 * replay_latency(np.asarray(tm.t), step_cpu, p)[kf], 95)) for p in REPLAY_PACES}
    poses = np.asarray(tm.pose)
    diff = poses - np.asarray(tm.backend_pose)
    diff[:, 2] = np.angle(np.exp(1j * diff[:, 2]))
    frontend_cpu = times.worker_cpu_s
    in_thread = frontend == "sequential"
    main_cpu = cpu
    worker_cpu = tm.worker_cpu_s + (0.0 if in_thread else frontend_cpu)
    # the backend worker's online CPU: its final optimisation (after the timed steps) apart
    online_cpu = figs["online_backend_online_cpu_s"]
    bound = max(main_cpu, online_cpu, 0.0 if in_thread else frontend_cpu)
    final = tm.result
    mode = "decoupled" if in_thread else f"decoupled-{frontend}"
    return {"mode": mode if catch_up == 1 else f"{mode} cu={catch_up}",
            "rms_final_mm": rms_mm(run, final.times, final.poses) if final is not None
            else float("nan"),
            "rms_online_mm": rms_mm(run, np.asarray(tm.t), poses),
            "catch_up_updates": figs["online_catch_up_updates"],
            "catch_up_keyframes": figs["online_catch_up_keyframes"],
            "kf_per_update_max": figs["online_keyframes_per_update_max"],
            "pace": "max" if pace is None else f"{pace:g}x",
            "frames": int(fr.sum()), "startup_s": figs["online_worker_startup_s"],
            "online_wall_s": figs["online_wall_s"], "x_rt_wall": figs["online_x_real_time"],
            "cpu_main_s": main_cpu, "cpu_worker_s": worker_cpu,
            "cpu_total_s": main_cpu + worker_cpu, "x_rt_cpu_main": duration / main_cpu,
            "frontend_cpu_s": frontend_cpu,
            "tracking_cpu_s": thread_cpu - (frontend_cpu if in_thread else 0.0),
            "other_threads_cpu_s": cpu - thread_cpu,
            "backend_steps_cpu_s": figs["online_backend_step_cpu_s"],
            "backend_online_cpu_s": online_cpu,
            "backend_rest_cpu_s": online_cpu - figs["online_backend_step_cpu_s"],
            "backend_inbox_cpu_s": figs["online_backend_inbox_cpu_s"],
            "backend_finish_cpu_s": figs["online_backend_finish_cpu_s"],
            "backend_idle_s": figs["online_backend_idle_s"],
            "backend_stalled_s": figs["online_backend_stalled_s"],
            "lag_wait_s": figs["online_lag_wait_s"],
            "x_rt_2core_bound": duration / bound,
            "lat_med_ms": figs["online_tracked_latency_ms_median"],
            "lat_p95_ms": figs["online_tracked_latency_ms_p95"],
            "lat_max_ms": figs["online_tracked_latency_ms_max"],
            "track_p95_ms": float(np.percentile(track, 95)),
            "frame_cpu_p95_ms": float(np.percentile(step_thread_cpu[fr], 95)),
            "kf_lat_med_ms": figs["online_keyframe_latency_ms_median"],
            "kf_lat_p95_ms": figs["online_keyframe_latency_ms_p95"],
            "lag_p95_steps": figs["online_anchor_lag_p95_steps"],
            "tracked_vs_backend_max": float(np.nanmax(np.abs(diff))), "_poses": poses,
            "backend_cpu_x_rt": duration / float(np.nansum(step_cpu)),
            "kf_cpu_p95_ms": float(np.percentile(1e3 * step_cpu[kf], 95)), **replay}


def one_row(run: LoggedRun, backend: str, mode: str, pace: float | None, depth: int,
            max_lag: int | None, catch_up: int = 1) -> dict[str, Any]:
    """One online run: timings, latencies and the online poses."""
    if mode.startswith("decoupled"):
        frontend = mode.split("-", 1)[1] if "-" in mode else "sequential"
        return decoupled_row(run, backend, pace, depth, frontend, max_lag, catch_up)
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
    final = be.finish()
    n = len(done)
    lat = 1e3 * (np.asarray(done) - np.asarray(times.arrival[:n]))
    online_wall = wall_end - (times.arrival[0] if times.arrival else w0)
    duration = float(run.odometry.t[-1] - run.odometry.t[0])
    worker_cpu = times.worker_cpu_s if mode == "process" else 0.0
    return {"mode": mode, "pace": "max" if pace is None else f"{pace:g}x",
            "frames": n, "startup_s": (first or w0) - w0, "online_wall_s": online_wall,
            "x_rt_wall": duration / online_wall, "cpu_main_s": cpu, "cpu_worker_s": worker_cpu,
            "cpu_total_s": cpu + worker_cpu, "x_rt_cpu_main": duration / cpu,
            "x_rt_2core_bound": duration / max(cpu, worker_cpu),
            "frontend_cpu_s": times.worker_cpu_s,
            "lat_med_ms": float(np.median(lat)), "lat_p95_ms": float(np.percentile(lat, 95)),
            "lat_max_ms": float(lat.max()), "_poses": np.array(poses),
            "rms_final_mm": rms_mm(run, final.times, final.poses),
            "rms_online_mm": rms_mm(run, final.times, np.array(poses))}


def _line(row: dict[str, Any]) -> str:
    """One row's figures as printed while the bench runs."""
    text = (f"  {row['pace']:>5s} {row['mode']:18s} wall {row['online_wall_s']:7.2f} s "
            f"({row['x_rt_wall']:5.1f}x real time), CPU main {row['cpu_main_s']:6.2f} s + "
            f"worker {row['cpu_worker_s']:6.2f} s, frontend {row['frontend_cpu_s']:6.2f} s; "
            f"latency median / p95 / max {row['lat_med_ms']:.1f} / {row['lat_p95_ms']:.1f} / "
            f"{row['lat_max_ms']:.0f} ms; start-up {row['startup_s']:.2f} s; "
            f"load {os.getloadavg()[0]:.1f}; position RMS final {row['rms_final_mm']:.3f} mm, "
            f"online {row['rms_online_mm']:.3f} mm")
    if row["mode"].startswith("decoupled"):
        text += (f"\n        main process CPU: frontend {row['frontend_cpu_s']:.2f} s, tracking "
                 f"{row['tracking_cpu_s']:.2f} s, other threads (queue pickling) "
                 f"{row['other_threads_cpu_s']:.2f} s; backend worker until the last step "
                 f"{row['backend_online_cpu_s']:.2f} s: steps {row['backend_steps_cpu_s']:.2f} s, "
                 f"rest {row['backend_rest_cpu_s']:.2f} s (of which taking the steps "
                 f"{row['backend_inbox_cpu_s']:.2f} s; the remainder start-up, replies); final "
                 f"optimisation {row['backend_finish_cpu_s']:.2f} s (not timed); worker idle "
                 f"{row['backend_idle_s']:.2f} s, stalled (no core: the load) "
                 f"{row['backend_stalled_s']:.2f} s, tracker waiting on back-pressure "
                 f"{row['lag_wait_s']:.2f} s (wall); bound on 2 free cores (CPU) "
                 f"{row['x_rt_2core_bound']:.1f}x real time"
                 f"\n        frame made -> tracked pose p95 {row['track_p95_ms']:.2f} ms (wall), "
                 f"CPU per frame (image load + frontend + tracking) p95 "
                 f"{row['frame_cpu_p95_ms']:.2f} ms; keyframe latency median / p95 "
                 f"{row['kf_lat_med_ms']:.1f} / {row['kf_lat_p95_ms']:.1f} ms; anchor lag p95 "
                 f"{row['lag_p95_steps']:.0f} steps; tracked vs backend poses max "
                 f"{row['tracked_vs_backend_max']:.2g}"
                 f"\n        backend steps' CPU = {row['backend_cpu_x_rt']:.1f}x real time, keyframe "
                 f"CPU p95 {row['kf_cpu_p95_ms']:.1f} ms; keyframe latency p95 replayed on a core "
                 "of its own: " + ", ".join(f"{row[f'replay_{p:g}x_kf_p95_ms']:.1f} ms at {p:g}x"
                                            for p in REPLAY_PACES)
                 + f"\n        catch-up: {row['catch_up_updates']:.0f} iSAM2 updates of more "
                 f"than one keyframe ({row['catch_up_keyframes']:.0f} keyframes), at most "
                 f"{row['kf_per_update_max']:.0f} keyframes in one")
    return text


def _median_rows(rows: list[dict[str, Any]]) -> dict[str, Any]:
    """The median of every numeric figure over repeated rows of one (pace, mode)."""
    med: dict[str, Any] = dict(rows[0])
    for k, v in rows[0].items():
        if isinstance(v, float) and not k.startswith("_"):
            med[k] = float(np.median([r[k] for r in rows]))
    med["repeats"] = len(rows)
    return med


def main() -> None:
    """Run the rows (round-robin over the modes, ``--repeats`` times), print the medians."""
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--run", type=Path, required=True, help="a simulated lab run directory")
    p.add_argument("--backend", default="isam2", choices=("isam2", "ekf", "batch"))
    p.add_argument("--modes", default="sequential,process",
                   help="comma-separated subset of " + ",".join((*MODES, *DECOUPLED)))
    p.add_argument("--paces", default="none",
                   help="comma-separated replay speeds, x real time ('none': as fast as possible)")
    p.add_argument("--depth", type=int, default=8, help="worker queue, frames (default 8)")
    p.add_argument("--max-frames", type=int, default=None, help="the run's first frames only")
    p.add_argument("--cv-threads", type=int, default=1, help="OpenCV threads (default 1)")
    p.add_argument("--repeats", type=int, default=1, help="rounds over the modes (medians)")
    p.add_argument("--catch-up", default="1",
                   help="decoupled rows: comma-separated [online] catch_up values (keyframes "
                        "per iSAM2 update at most while the worker is behind; 1 = off)")
    p.add_argument("--max-lag", type=int, default=DEFAULT_MAX_LAG,
                   help=f"decoupled rows' back-pressure, steps (default {DEFAULT_MAX_LAG}, as "
                        "`lampsam slam --online decoupled`; -1: never wait)")
    args = p.parse_args()
    logging.basicConfig(level=logging.WARNING)
    cv2.setNumThreads(args.cv_threads)
    modes = args.modes.split(",")
    bad = [m for m in modes if m not in (*MODES, *DECOUPLED)]
    if bad:
        raise SystemExit(f"unknown modes {bad}; choose from {', '.join((*MODES, *DECOUPLED))}")
    try:
        catch_ups = [int(c) for c in args.catch_up.split(",")]
    except ValueError:
        raise SystemExit(f"--catch-up: comma-separated integers >= 1, got {args.catch_up!r}") from None
    if any(c < 1 for c in catch_ups):
        raise SystemExit(f"--catch-up: values must be >= 1, got {args.catch_up!r}")
    # (mode, catch-up) rows: the catch-up values apply to the decoupled modes only
    variants = [(m, c) for m in modes for c in (catch_ups if m in DECOUPLED else [1])]
    max_lag = None if args.max_lag < 0 else args.max_lag
    paces = [None if s == "none" else float(s) for s in args.paces.split(",")]
    run = _cut(read_run(args.run), args.max_frames)
    assert run.images is not None
    duration = float(run.odometry.t[-1] - run.odometry.t[0])
    print(f"{args.run}: {len(run.images)} frames, {duration:.1f} s of data; backend "
          f"{args.backend}; queue {args.depth}; max lag {max_lag}; OpenCV threads "
          f"{cv2.getNumThreads()}; {os.cpu_count()} cores; load average "
          f"{os.getloadavg()[0]:.1f}", flush=True)
    done: dict[tuple[str, str], list[dict[str, Any]]] = {}
    for rep in range(args.repeats):
        for pace in paces:
            for mode, cu in variants:
                row = one_row(run, args.backend, mode, pace, args.depth, max_lag, cu)
                row["load"] = os.getloadavg()[0]
                done.setdefault((row["pace"], row["mode"]), []).append(row)
                print(f"[round {rep + 1}]" + _line(row), flush=True)
    rows = []
    for pace in paces:
        label = "max" if pace is None else f"{pace:g}x"
        ref = _median_rows(done[(label, "sequential")]) if "sequential" in modes else None
        for mode in dict.fromkeys(m for (pl, m) in done if pl == label):
            row = _median_rows(done[(label, mode)])
            if ref is not None:
                row["wall_vs_seq"] = row["online_wall_s"] / ref["online_wall_s"]
                row["lat_p95_vs_seq"] = row["lat_p95_ms"] / ref["lat_p95_ms"]
                row["cpu_total_vs_seq"] = row["cpu_total_s"] / ref["cpu_total_s"]
                row["cpu_main_vs_seq"] = row["cpu_main_s"] / ref["cpu_main_s"]
                same = row["_poses"].shape == ref["_poses"].shape
                row["max_pose_diff"] = (float(np.abs(row["_poses"] - ref["_poses"]).max())
                                        if same and not mode.startswith("decoupled")
                                        else float("nan"))
            rows.append(row)
    cols = ["pace", "mode", "repeats", "x_rt_wall", "wall_vs_seq", "x_rt_2core_bound",
            "cpu_main_s", "cpu_main_vs_seq", "cpu_worker_s", "cpu_total_vs_seq", "lat_med_ms",
            "lat_p95_ms", "lat_max_ms", "frame_cpu_p95_ms", "startup_s", "max_pose_diff",
            "kf_lat_p95_ms", "replay_1x_kf_p95_ms", "lag_p95_steps", "backend_online_cpu_s",
            "backend_steps_cpu_s", "backend_rest_cpu_s", "backend_idle_s", "backend_stalled_s",
            "kf_cpu_p95_ms", "catch_up_updates", "catch_up_keyframes", "rms_final_mm",
            "rms_online_mm", "load"]
    print(f"\nmedians of {args.repeats} rounds")
    print("| " + " | ".join(cols) + " |")
    print("|" + "---|" * len(cols))
    for r in rows:
        cells = [r.get(c, "") for c in cols]
        print("| " + " | ".join(f"{c:.3g}" if isinstance(c, float) else str(c)
                                for c in cells) + " |")
    print("x_rt_wall: data duration / online wall clock (decoupled: from the start, worker "
          "start-up included, until the backend finished the last step); x_rt_2core_bound: "
          "data duration / the busiest process's CPU until the last step (what two free cores "
          "would give; the backend worker's final optimisation apart); cpu_*: "
          "process CPU s (worker: the frontend process, decoupled: the backend process plus "
          "any frontend process); latency: frame arrival -> pose (decoupled: the tracked pose); "
          "frame_cpu_p95: decoupled, the main thread's CPU to load, process and track a frame; "
          f"load average {os.getloadavg()[0]:.1f} at the end")


if __name__ == "__main__":
    main()
