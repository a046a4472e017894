"""``lampsam slam RUN --online decoupled``: a whole SLAM run with tracking decoupled from mapping.

The counterpart of :func:`lampsam.backend.slam.run_slam` for
:func:`lampsam.backend.tracking.run_decoupled`: this process reads the run, makes
the frames (the frontend, here or in a worker as ``--frontend`` says) and gives
every step's *tracked* pose at once (the backend's newest estimate composed with
the odometry since), while a worker process steps the backend and, at the end, runs
its final optimisation. Written to ``out``:

- ``trajectory.tum``, ``landmarks.csv``: the backend's result, as ``run_slam`` writes
  them (the same backend on the same steps: the same numbers);
- ``tracked.tum``: the tracked pose of every step, as given online;
- ``summary.json``: ``run_slam``'s summary plus ``online_*`` keys: the tracked
  pose's latency (the frame's image read -> its pose, ms: frontend + tracking; for
  frames not made from images, the step ready -> its pose), the keyframe latency
  (a keyframe handed to the worker -> its estimate back, ms), the wall clock and its
  x real time until the worker finished the last step, both processes' CPU and the
  worker's start-up.

On SIGINT / SIGTERM (:mod:`lampsam.interrupt`) both stop after their current step
and everything finished is written with status ``"interrupted"``: the tracked poses
given so far and the worker's result of the steps it finished.
"""

from __future__ import annotations

import logging
import time
from pathlib import Path

import numpy as np

from lampsam.arrays import FloatArray
from lampsam.backend.config import SlamConfig
from lampsam.backend.interface import Frame, SlamResult, empty_result
from lampsam.backend.pipelined import FrameTimes, Mode, frame_source
from lampsam.backend.slam import iter_steps, make_frames, start_pose_of, write_results
from lampsam.backend.tracking import DecoupledTimes, run_decoupled
from lampsam.datasets.logrun import LoggedRun, Trajectory
from lampsam.datasets.tables import OdometryLog
from lampsam.datasets.tum import write_tum
from lampsam.errors import EstimationError
from lampsam.interrupt import interruptible

log = logging.getLogger(__name__)

ONLINE_MODES = ("sequential", "decoupled")
#: Default back-pressure of a replayed log, steps (15 = 1 s of the lab camera's frames).
DEFAULT_MAX_LAG = 15


def _percentiles(ms: FloatArray, name: str) -> dict[str, float]:
    """``{name}_median/_p95/_max`` of a latency array (ms); NaN when empty."""
    if not len(ms):
        return {f"{name}_{k}": float("nan") for k in ("median", "p95", "max")}
    return {f"{name}_median": float(np.median(ms)), f"{name}_p95": float(np.percentile(ms, 95)),
            f"{name}_max": float(np.max(ms))}


def online_figures(tm: DecoupledTimes, arrival: FloatArray | None, duration_s: float,
                   start: float, tracking_cpu_s: float) -> dict[str, float]:
    """The decoupled run's latencies and throughput (the ``online_*`` summary keys).

    Args:
        tm: the run's records (:func:`run_decoupled`).
        arrival: (F,) when each frame's image began to be read
            (``time.perf_counter`` s), in frame order; None: latency from the step ready.
        duration_s: the data's duration, s.
        start: ``time.perf_counter()`` when the run began (before the worker started).
        tracking_cpu_s: this process's CPU time for the run (frontend + tracking), s.

    Returns:
        ``online_tracked_latency_ms_{median,p95,max}`` (frames only),
        ``online_keyframe_latency_ms_{median,p95,max}``, ``online_wall_s``,
        ``online_x_real_time`` (data duration / wall clock until the last step's
        estimate), ``online_tracking_cpu_s``, ``online_backend_cpu_s`` (the worker's
        whole process CPU), ``online_backend_step_cpu_s`` (its steps alone),
        ``online_backend_online_cpu_s`` (until the stop mark: the final optimisation
        apart), ``online_backend_inbox_cpu_s`` (taking the steps: unpickling,
        unpacking), ``online_backend_finish_cpu_s`` (the final optimisation),
        ``online_backend_idle_s`` (wall clock the worker waited for steps),
        ``online_backend_stalled_s`` (wall clock until the stop mark neither computing
        nor waiting for steps: mostly waiting for a core, i.e. other processes' load),
        ``online_lag_wait_s`` (wall clock the tracker waited on back-pressure),
        ``online_worker_startup_s``, ``online_anchor_lag_p95_steps`` and, for
        ``[online] catch_up``, ``online_catch_up_updates`` (iSAM2 updates of more
        than one keyframe), ``online_catch_up_keyframes`` (the keyframes in them) and
        ``online_keyframes_per_update_max`` (1 when catch-up never triggered or is off).
    """
    n = len(tm.out)
    out = np.asarray(tm.out, float)
    framed = np.asarray(tm.framed[:n], bool)
    if arrival is not None and len(arrival) >= framed.sum():
        lat = 1e3 * (out[framed] - np.asarray(arrival, float)[:int(framed.sum())])
    else:
        lat = 1e3 * (out - np.asarray(tm.given[:n], float))[framed]
    back, sent = np.asarray(tm.back, float), np.asarray(tm.sent, float)
    kf = np.asarray(tm.keyframe, bool) & np.isfinite(back)
    wall = tm.worker_done - start
    step_cpu = np.asarray(tm.step_cpu, float)
    lag = np.arange(n) - np.asarray(tm.anchor, float)
    sizes = np.asarray(tm.update_sizes, int)
    return {**_percentiles(lat, "online_tracked_latency_ms"),
            **_percentiles(1e3 * (back - sent)[kf], "online_keyframe_latency_ms"),
            "online_wall_s": float(wall), "online_x_real_time": float(duration_s / wall),
            "online_tracking_cpu_s": float(tracking_cpu_s),
            "online_backend_cpu_s": float(tm.worker_cpu_s),
            "online_backend_step_cpu_s": float(np.nansum(step_cpu)),
            "online_backend_online_cpu_s": float(tm.clocks.online_cpu_s),
            "online_backend_inbox_cpu_s": float(tm.clocks.inbox_cpu_s),
            "online_backend_finish_cpu_s": float(tm.clocks.finish_cpu_s),
            "online_backend_idle_s": float(tm.clocks.idle_s),
            "online_backend_stalled_s": float(tm.clocks.online_wall_s - tm.clocks.online_cpu_s
                                              - tm.clocks.idle_s),
            "online_lag_wait_s": float(tm.lag_wait_s),
            "online_worker_startup_s": float(tm.worker_ready - start),
            "online_anchor_lag_p95_steps": float(np.percentile(lag, 95)) if n else float("nan"),
            "online_catch_up_updates": float(np.sum(sizes > 1)),
            "online_catch_up_keyframes": float(np.sum(sizes[sizes > 1])),
            "online_keyframes_per_update_max": float(sizes.max()) if len(sizes) else 1.0}


def _fallback_result(backend: str, tm: DecoupledTimes, status: str) -> SlamResult:
    """The worker's per-step estimates as a result, when its own never came back."""
    ok = np.isfinite(np.asarray(tm.back, float))
    if not ok.any():
        return empty_result(backend, status)
    n = len(ok)
    return SlamResult(backend=backend, times=np.asarray(tm.t, float)[ok],
                      poses=np.asarray(tm.backend_pose, float)[ok],
                      pose_covs=np.full((int(ok.sum()), 3, 3), np.nan), landmarks=[],
                      step_times_s=np.asarray(tm.step_cpu[:n], float)[ok],
                      keyframes=np.asarray(tm.keyframe, bool)[ok], status=status)


def run_slam_decoupled(run: LoggedRun, backend: str, out: Path | None,
                       config: SlamConfig | None = None, frames: str = "auto",
                       frontend: Mode = "sequential", max_dt: float = 0.5,
                       max_lag: int | None = DEFAULT_MAX_LAG) -> tuple[SlamResult, DecoupledTimes]:
    """Run one backend over a logged run with decoupled tracking; write the results.

    Args:
        run: the loaded run.
        backend: ``"ekf"``, ``"isam2"`` or ``"batch"`` (its online pass in the worker).
        out: output directory (see the module docstring); None writes nothing.
        config: the SLAM config (defaults when None).
        frames: frame source (:func:`~lampsam.backend.slam.make_frames`).
        frontend: where image frames are made: ``"sequential"`` (this process, between
            tracked steps), ``"thread"`` or ``"process"``
            (:func:`~lampsam.backend.pipelined.frame_source`).
        max_dt: longest interval without a step, s.
        max_lag: how many steps the tracked pose may run ahead of the backend's
            newest estimate before this process waits (:func:`run_decoupled`); None:
            never wait (what a robot's camera does; on a log replayed faster than the
            backend, the tracked poses then become dead reckoning).

    Returns:
        ``(backend result, per-step records)``; the result's ``extra`` holds the
        :func:`online_figures`.

    Raises:
        EstimationError: the run failed (what was finished is written first).
        lampsam.errors.LampsamError: the mapping worker failed or died.
    """
    config = config or SlamConfig()
    if not isinstance(run.odometry, OdometryLog):
        raise EstimationError(f"{run.path}: --online decoupled needs wheel odometry "
                              "(a ceiling or range-bearing run directory)")
    w0, c0 = time.perf_counter(), time.process_time()
    ftimes = FrameTimes()
    source: list[Frame] | object
    source, is_ceiling = make_frames(run, frames)
    if is_ceiling and frames in ("auto", "images") and run.images is not None:
        source = frame_source(run.images, run.rig.camera, mode=frontend, times=ftimes)
    steps = iter_steps(run.odometry, source, max_dt)  # type: ignore[arg-type]
    log.info("tracking each step here, the %s backend in a worker process", backend)
    tm = run_decoupled(interruptible(steps), backend, run.rig.odometry, config,
                       start_pose_of(run), run.rig.camera if is_ceiling else None, finish=True,
                       max_lag=max_lag)
    cpu = time.process_time() - c0
    if tm.interrupted:
        status = "interrupted"
    elif tm.failure is not None:
        status = f"failed: {tm.failure}"
    else:
        status = "ok"
    result = tm.result if tm.result is not None else _fallback_result(
        backend, tm, status if status != "ok" else "failed: no result from the mapping worker")
    if status != "ok" and result.status == "ok":
        result.status = status
    duration = float(run.odometry.t[-1] - run.odometry.t[0]) if len(run.odometry.t) else 0.0
    arrival = np.asarray(ftimes.arrival, float) if ftimes.arrival else None
    result.extra.update(online_figures(tm, arrival, duration, w0, cpu))
    if out is not None:
        out = Path(out)
        out.mkdir(parents=True, exist_ok=True)
        write_tum(out / "tracked.tum", Trajectory(t=np.asarray(tm.t, float),
                                                  poses=np.asarray(tm.pose, float).reshape(-1, 3)))
        write_results(out, result, run)
    if result.status.startswith("failed"):
        raise EstimationError(f"{backend} on {run.path} (decoupled): {result.status} "
                              f"(steps finished so far written to {out})")
    return result, tm
