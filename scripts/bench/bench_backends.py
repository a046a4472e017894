"""Benchmark and accuracy tables of the three SLAM backends, against their targets.

Usage::

    python scripts/bench/bench_backends.py --lab RUN_DIR [--frames images|truth] [--repeats 3]
    python scripts/bench/bench_backends.py --mrclam [--duration S]

``--lab``: a simulated run (``lampsam simulate lab --out RUN_DIR``). Frames are made
once (the frontend on the images, or the simulator's truth projections; each frame's
CPU time recorded) and fed to every backend with features lamps+corners, corners only
and lamps only. Printed: position/heading error (no alignment, known start), then
timings in process CPU time (``time.process_time``, which a loaded machine inflates
far less than wall clock): per step and per keyframe median / p95 / max, iSAM2
update and estimate (wall), the final optimisation and whole run, and the speed targets'
figures: the online run and the whole pipeline (the frontend on each image plus the
backend step that uses it) as multiples of real time (data duration / CPU time), the
pipeline's per-frame median / p95 / max, and each as a ratio to its target (10x real
time, 15 ms p95). Timings are medians over ``--repeats`` runs; ``kf_cpu_ratio_vs_ekf``
divides by the EKF's per-keyframe median measured in the same run (reference). The
The speed targets' measurement, one command::

    python scripts/bench/bench_backends.py --lab RUN_DIR --backends isam2,ekf \
        --features lamps+corners --repeats 3

with ``RUN_DIR`` from ``lampsam simulate lab --seed 3 --out RUN_DIR`` (2,601 frames, 173 s).
For the smoothers, the pipeline as ``lampsam slam`` runs it is also measured (lazy
frames: the frontend only on the frames the backend reads, ``pipe_lazy_x_realtime``,
``frames_read``). ``--isam2-variant KEY=VALUE[,KEY=VALUE]`` (repeatable) adds an iSAM2 row with those
``[isam2]`` settings (e.g. ``keyframe_distance=0.1``; ``bracket_gate=false`` is the exact
gate) for the first feature set, timed in the same run round-robin with the default
(one run of each per round, and its lazy pipeline), with its online CPU as a ratio to
the default iSAM2's (``cpu_vs_isam2``).

``--mrclam``: MRCLAM ds0 with known association and with the gate alone, the three
backends and dead reckoning, errors against Vicon.
"""

from __future__ import annotations

import argparse
import dataclasses
import hashlib
import logging
import os
import time
from pathlib import Path
from typing import Any

import numpy as np

from lampsam.arrays import FloatArray
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
TARGET_X_REALTIME = 10.0  # target: online at >= 10x real time
TARGET_P95_MS = 15.0  # target: p95 per frame <= 15 ms
FEATURES = {"lamps+corners": ("lamps", "corners"), "corners": ("corners",), "lamps": ("lamps",)}


def _errors(result: Any, run: LoggedRun) -> dict[str, float]:
    pos, head = errors_vs_truth(result, run.groundtruth)
    return {"pos_rms_m": float(np.sqrt(np.mean(pos**2))), "pos_max_m": float(pos.max()),
            "head_rms_deg": float(np.degrees(np.sqrt(np.mean(head**2)))),
            "head_max_deg": float(np.degrees(np.abs(head).max()))}


def one_run(name: str, run: LoggedRun, frames: list[Any], config: SlamConfig,
            ceiling: bool) -> dict[str, Any]:
    """Run one backend on prepared frames; errors and timings.

    Every step is timed in process CPU time (``time.process_time``: comparable under
    load, where wall clock is not) and in wall clock; the final optimisation apart.
    """
    t0 = time.perf_counter()
    c0 = time.process_time()
    be = make_backend(name, run.rig.odometry, config, start_pose_of(run),
                      run.rig.camera if ceiling else None)
    step_cpu = []
    for t, wheel, frame in iter_steps(run.odometry, frames):
        c = time.process_time()
        be.step(t, wheel, frame)
        step_cpu.append(time.process_time() - c)
    online_cpu = time.process_time() - c0
    res = be.finish()
    total = time.perf_counter() - t0
    cpu = time.process_time() - c0
    step_ms = np.asarray(step_cpu) * 1e3
    frame_ms = res.step_times_s[res.keyframes] * 1e3 if res.keyframes.any() else np.zeros(1)
    kf_cpu = step_ms[res.keyframes] if res.keyframes.any() else np.zeros(1)
    row: dict[str, Any] = {"backend": name, "status": res.status, **_errors(res, run),
                           "landmarks": len(res.landmarks), "keyframes": int(res.keyframes.sum()),
                           "frame_median_ms": float(np.median(frame_ms)),
                           "frame_p95_ms": float(np.percentile(frame_ms, 95)),
                           "kf_cpu_median_ms": float(np.median(kf_cpu)),
                           "kf_cpu_p95_ms": float(np.percentile(kf_cpu, 95)),
                           "kf_cpu_max_ms": float(kf_cpu.max()),
                           "step_cpu_median_ms": float(np.median(step_ms)),
                           "step_cpu_p95_ms": float(np.percentile(step_ms, 95)),
                           "step_cpu_max_ms": float(step_ms.max()),
                           "online_cpu_s": online_cpu,
                           "total_s": total, "cpu_s": cpu, "final_s": res.final_time_s,
                           "_step_cpu_ms": step_ms, "_keyframes": np.asarray(res.keyframes, bool)}
    upd = getattr(be, "update_times", None)
    if upd:
        row["update_median_ms"] = float(np.median(upd) * 1e3)
        row["update_p95_ms"] = float(np.percentile(upd, 95) * 1e3)
        est = getattr(be, "estimate_times", [])
        row["estimate_median_ms"] = float(np.median(est) * 1e3) if est else float("nan")
    # same trajectory = same decisions; pairs the gate's bracket settled without iSAM2
    row["traj_sha1"] = hashlib.sha1(np.ascontiguousarray(res.poses).tobytes()).hexdigest()[:10]
    row["bracket_settled"] = (getattr(be, "n_bracket_inside", 0)
                              + getattr(be, "n_bracket_outside", 0))
    return row


def frontend_frames(run: LoggedRun, source: str) -> tuple[list[Any], bool, FloatArray]:
    """The run's frames and each one's CPU time in ms (the frontend on an image)."""
    it, ceiling = make_frames(run, source)
    frames: list[Any] = []
    cpu: list[float] = []
    iterator = iter(it)
    while True:
        c = time.process_time()
        try:
            f = next(iterator)
        except StopIteration:
            break
        cpu.append(time.process_time() - c)
        frames.append(f)
    return frames, ceiling, np.asarray(cpu) * 1e3


def median_rows(rows: list[dict[str, Any]]) -> dict[str, Any]:
    """Median of the numeric fields of repeated runs (errors are identical across repeats);
    per-step CPU times: the element-wise median."""
    out = dict(rows[0])
    for k, v in rows[0].items():
        if isinstance(v, float):
            out[k] = float(np.median([r[k] for r in rows]))
    out["_step_cpu_ms"] = np.median([r["_step_cpu_ms"] for r in rows], axis=0)
    return out


def pipeline_figures(row: dict[str, Any], run: LoggedRun, frames: list[Any],
                     frontend_ms: FloatArray, duration: float) -> dict[str, float]:
    """The speed targets' figures for one backend row: x real time and per-frame CPU, with the frontend.

    A frame's pipeline time is its frontend time plus the backend step that consumed
    it (steps without a frame, odometry only, count for the backend alone).
    ``pipe_kf_x_realtime``: the same with the frontend run only on the frames the
    backend made keyframes of (the smoothers use no other frame's observations, and
    whether a frame becomes a keyframe is decided from the odometry before its
    observations are read, :func:`lampsam.backend.keyframes.is_keyframe`); a figure
    of what skipping the other frames' images would give, not of today's pipeline,
    which runs the frontend on every image. For the EKF (every frame) it equals
    ``pipeline_x_realtime``.
    """
    steps = list(iter_steps(run.odometry, frames))
    step_ms = row["_step_cpu_ms"]
    idx = {id(f): n for n, f in enumerate(frames)}
    per_frame = step_ms.copy()
    for n, (_, _, frame) in enumerate(steps):
        if frame is not None:
            per_frame[n] += frontend_ms[idx[id(frame)]]
    with_frame = np.array([f is not None for _, _, f in steps])
    pipe = per_frame[with_frame]
    online = row["online_cpu_s"]
    used = row["_keyframes"] if row["backend"] != "ekf" else np.ones(len(steps), bool)
    kf_frontend_ms = sum(frontend_ms[idx[id(f)]] for n, (_, _, f) in enumerate(steps)
                         if f is not None and used[n])
    return {"online_x_realtime": duration / online,
            "pipeline_x_realtime": duration / (online + frontend_ms.sum() / 1e3),
            "pipe_kf_x_realtime": duration / (online + kf_frontend_ms / 1e3),
            "pipe_frame_median_ms": float(np.median(pipe)),
            "pipe_frame_p95_ms": float(np.percentile(pipe, 95)),
            "pipe_frame_max_ms": float(pipe.max())}


def lazy_pipeline(name: str, run: LoggedRun, config: SlamConfig) -> dict[str, float]:
    """The one-process pipeline as ``lampsam slam`` runs it for a smoother, measured:
    lazy frames (:class:`lampsam.backend.pipelined.LazyFrame`), so the frontend runs
    inside the steps that read a frame, on those frames only.

    Returns:
        ``pipe_lazy_cpu_s`` (process CPU of image reads + frontend + online steps),
        ``pipe_lazy_frame_median_ms`` / ``_p95_ms`` / ``_max_ms`` (CPU of each framed
        step, its frontend included when read) and ``frames_read``.
    """
    import lampsam.backend.pipelined as pipelined

    frames, _ = make_frames(run, "images", lazy=True)
    c0 = time.process_time()
    be = make_backend(name, run.rig.odometry, config, start_pose_of(run), run.rig.camera)
    framed: list[float] = []
    read = 0
    for t, wheel, frame in iter_steps(run.odometry, frames):
        c = time.process_time()
        be.step(t, wheel, frame)
        if frame is not None:
            framed.append(time.process_time() - c)
            read += isinstance(frame, pipelined.LazyFrame) and frame.loaded
    cpu = time.process_time() - c0
    ms = np.asarray(framed) * 1e3
    return {"pipe_lazy_cpu_s": cpu, "pipe_lazy_frame_median_ms": float(np.median(ms)),
            "pipe_lazy_frame_p95_ms": float(np.percentile(ms, 95)),
            "pipe_lazy_frame_max_ms": float(ms.max()), "frames_read": float(read)}


def isam2_variant(base: SlamConfig, spec: str) -> SlamConfig:
    """``base`` with the ``[isam2]`` settings of ``spec`` (``KEY=VALUE[,KEY=VALUE]``).

    Raises:
        SystemExit: an unknown key or a value of the wrong type, naming it.
    """
    over: dict[str, Any] = {}
    for item in spec.split(","):
        key, _, value = item.partition("=")
        key = key.strip()
        default = getattr(base.isam2, key, None)
        if not value or key not in {f.name for f in dataclasses.fields(base.isam2)}:
            raise SystemExit(f"--isam2-variant {spec!r}: {key!r} is not an [isam2] setting=VALUE")
        try:
            over[key] = (value.strip().lower() in ("1", "true", "yes")) if isinstance(default, bool) \
                else type(default)(value) if default is not None else float(value)
        except ValueError:
            raise SystemExit(f"--isam2-variant {spec!r}: bad value for {key!r}") from None
    return dataclasses.replace(base, isam2=dataclasses.replace(base.isam2, **over))


def bench_lab(run_dir: Path, source: str, repeats: int, max_frames: int | None,
              backends: tuple[str, ...] = BACKENDS, features: tuple[str, ...] = tuple(FEATURES),
              variants: tuple[str, ...] = ()) -> None:
    run = read_run(run_dir)
    load0 = os.getloadavg()[0]
    frames, ceiling, frontend_ms = frontend_frames(run, source)
    frames = frames[:max_frames]
    frontend_ms = frontend_ms[:len(frames)]
    if max_frames is not None:  # cut the odometry at the last frame too
        odo = run.odometry
        keep = odo.t <= frames[-1].t
        run = dataclasses.replace(run, odometry=dataclasses.replace(
            odo, t=odo.t[keep], d_left=odo.d_left[keep], d_right=odo.d_right[keep]))
    frontend_s = float(frontend_ms.sum() / 1e3)
    duration = float(run.odometry.t[-1] - run.odometry.t[0])
    print(f"lab run {run_dir}: {len(frames)} frames from {source} in {frontend_s:.1f} s CPU "
          f"({duration:.1f} s of data); frontend per frame median / p95 / max "
          f"{np.median(frontend_ms):.1f} / {np.percentile(frontend_ms, 95):.1f} / "
          f"{frontend_ms.max():.1f} ms CPU")
    base = SlamConfig()
    table = []
    for label, feats in FEATURES.items():
        if label not in features:
            continue
        cfg = dataclasses.replace(base, features=feats)
        for name in backends:
            reps = repeats if label == features[0] else 1
            # the default iSAM2 and its variants run round-robin (one run of each per
            # round, then one lazy pipeline of each): their ratios share the load
            cfgs = [(name, cfg)]
            if name == "isam2" and label == features[0]:
                cfgs += [(f"isam2 {spec}", isam2_variant(cfg, spec)) for spec in variants]
            runs: dict[str, list[dict[str, Any]]] = {tag: [] for tag, _ in cfgs}
            lazies: dict[str, list[dict[str, float]]] = {tag: [] for tag, _ in cfgs}
            lazy_on = source == "images" and name != "ekf" and label == features[0]
            for _ in range(reps):
                for tag, c in cfgs:
                    runs[tag].append(one_run(name, run, frames, c, ceiling))
                for tag, c in cfgs if lazy_on else ():
                    lazies[tag].append(lazy_pipeline(name, run, c))
            for tag, _ in cfgs:
                row = median_rows(runs[tag])
                row.update(features=label, backend=tag)
                row.update(pipeline_figures(row, run, frames, frontend_ms, duration))
                if lazy_on:
                    lazy = lazies[tag]
                    row.update({k: float(np.median([r[k] for r in lazy])) for k in lazy[0]})
                    row["pipe_lazy_x_realtime"] = duration / row["pipe_lazy_cpu_s"]
                table.append(row)
                print(f"  {label:14s} {tag} pos RMS {row['pos_rms_m']:.4f} m  "
                      f"({row['status']}, {row['online_cpu_s']:.1f} s CPU online)", flush=True)
    dr = drive(EkfSlam(run.rig.odometry, base, start_pose_of(run)), iter_steps(run.odometry, []))
    table.append({"features": "none (dead reckoning)", "backend": "-", **_errors(dr, run)})
    ekf_rows = [r for r in table if r["backend"] == "ekf"]
    isam2_rows = [r for r in table if r["backend"] == "isam2" and r["features"] == features[0]]
    for r in table:
        if "frame_median_ms" in r and ekf_rows:
            r["kf_cpu_ratio_vs_ekf"] = r["kf_cpu_median_ms"] / ekf_rows[0]["kf_cpu_median_ms"]
        if "online_x_realtime" in r:
            r["x_rt_vs_target"] = r["online_x_realtime"] / TARGET_X_REALTIME
            r["pipe_x_rt_vs_target"] = r["pipeline_x_realtime"] / TARGET_X_REALTIME
            r["kf_p95_vs_target"] = r["kf_cpu_p95_ms"] / TARGET_P95_MS
            if isam2_rows and str(r["backend"]).startswith("isam2"):
                r["cpu_vs_isam2"] = r["online_cpu_s"] / isam2_rows[0]["online_cpu_s"]
    print(markdown_table(table, ["features", "backend", "pos_rms_m", "pos_max_m", "head_rms_deg",
                                 "landmarks", "keyframes", "traj_sha1", "bracket_settled"]))
    print()
    first = [r for r in table if r.get("features") == features[0]]
    print(f"timings (median of {repeats} runs for {features[0]}; CPU time of this process "
          f"unless 'wall'):")
    print(markdown_table(first, ["backend", "step_cpu_median_ms", "step_cpu_p95_ms",
                                 "step_cpu_max_ms", "kf_cpu_median_ms", "kf_cpu_p95_ms",
                                 "kf_cpu_max_ms", "kf_cpu_ratio_vs_ekf", "update_median_ms",
                                 "update_p95_ms", "estimate_median_ms", "final_s", "total_s",
                                 "cpu_s"]))
    print()
    print("speed targets (x real time = data duration / CPU time; pipeline = the frontend "
          "on each image + the backend step that uses it):")
    print(markdown_table(first, ["backend", "online_cpu_s", "online_x_realtime",
                                 "x_rt_vs_target", "pipeline_x_realtime", "pipe_x_rt_vs_target",
                                 "pipe_kf_x_realtime",
                                 "pipe_frame_median_ms", "pipe_frame_p95_ms", "pipe_frame_max_ms",
                                 "kf_p95_vs_target", "cpu_vs_isam2"]))
    if any("pipe_lazy_x_realtime" in r for r in first):
        print("the pipeline as lampsam slam runs it for the smoothers (lazy frames: the frontend "
              "only on the frames a step reads, timed inside it), measured:")
        print(markdown_table([r for r in first if "pipe_lazy_x_realtime" in r],
                             ["backend", "frames_read", "keyframes", "pipe_lazy_cpu_s",
                              "pipe_lazy_x_realtime", "pipe_lazy_frame_median_ms",
                              "pipe_lazy_frame_p95_ms", "pipe_lazy_frame_max_ms"]))
    print(f"{duration:.1f} s of data; frontend {frontend_s:.1f} s CPU for {len(frames)} frames; "
          f"targets: >= {TARGET_X_REALTIME:.0f}x real time, keyframe p95 <= {TARGET_P95_MS:.0f} ms "
          f"(ratios vs target: x real time >= 1 and p95 <= 1 meet them); update/estimate/final/"
          f"total columns are wall clock; load average {load0:.1f} at the start, "
          f"{os.getloadavg()[0]:.1f} now, on {os.cpu_count()} cores")


def bench_mrclam(duration: float | None) -> None:
    from lampsam.datasets.mrclam import mrclam_run
    from lampsam.datasets.paths import shared_dataset

    root = shared_dataset("mrclam_ds0")
    if root is None:
        raise SystemExit("mrclam_ds0 not found (set LAMPSAM_DATA)")
    table = []
    for known in (True, False):
        run = mrclam_run(root, known_ids=known, duration=duration)
        made, _ = make_frames(run, "rangebearing")
        frames = list(made)
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
    p.add_argument("--isam2-variant", action="append", default=[], metavar="KEY=VALUE[,...]",
                   help="lab: also iSAM2 with these [isam2] settings (repeatable)")
    p.add_argument("--mrclam", action="store_true")
    p.add_argument("--duration", type=float, default=None, help="MRCLAM: first seconds only")
    args = p.parse_args()
    logging.basicConfig(level=logging.WARNING)
    print(f"OPENBLAS_NUM_THREADS={os.environ.get('OPENBLAS_NUM_THREADS', 'unset')}")
    if args.lab is not None:
        bench_lab(args.lab, args.frames, args.repeats, args.max_frames,
                  tuple(args.backends.split(",")), tuple(args.features.split(",")),
                  tuple(args.isam2_variant))
    if args.mrclam:
        bench_mrclam(args.duration)
    if args.lab is None and not args.mrclam:
        p.error("give --lab RUN_DIR and/or --mrclam")


if __name__ == "__main__":
    main()
