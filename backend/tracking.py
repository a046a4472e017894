"""Tracking decoupled from mapping: per-frame poses from odometry, keyframe work in a worker.

Real-time SLAM systems split a cheap *tracking* loop, which gives a pose for every
frame, from a *mapping* loop, which runs the expensive keyframe optimisation
(PTAM, Klein & Murray 2007; ORB-SLAM's tracking and local-mapping threads). Here the
whole online backend (:meth:`~lampsam.backend.interface.SlamBackend.step`: keyframe
decision, association, the iSAM2 update) runs in a worker process, one step after
the other, and the caller's loop gives each frame's pose at once as

    ``x_i = x_j * o_j^-1 * o_i``

with ``x_j`` the backend's estimate of the newest step ``j <= i`` it has finished
(``world_T_body``) and ``o_i`` the dead-reckoned odometry chain (the product of
every step's odometry increment from the start, in its own frame), so
``o_j^-1 o_i`` is the odometry from step ``j`` to step ``i``. When the worker keeps
up, ``j = i - 1`` or ``i`` and the pose is the backend's own; behind a slow keyframe
the pose is the last estimate plus odometry, as between keyframes in the backend
itself (:class:`~lampsam.backend.graph.GraphSlam`). A process, not a thread: GTSAM's
Python calls hold the GIL (an optimisation in a thread stalled the calling thread for
its whole duration, measured), so a thread would not bound the tracking latency.

:func:`run_decoupled` records per step when it was handed over and when the
backend's estimate came back, so a caller can report the tracking latency (frame
ready -> pose out), the keyframe latency (hand-over -> estimate back) and the
throughput (data duration / wall clock until the worker finished) separately.
"""

from __future__ import annotations

import logging
import multiprocessing as mp
import queue
import time
from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import cast

import gtsam
import numpy as np

from lampsam.arrays import FloatArray
from lampsam.backend.config import SlamConfig
from lampsam.backend.interface import Frame
from lampsam.backend.odometry import OdometryConstants, motion_model
from lampsam.backend.pipelined import PackedFrame, pack_frame, unpack_frame
from lampsam.backend.pose_cov import pose_array
from lampsam.datasets.logrun import CameraModel
from lampsam.errors import LampsamError
from lampsam.frontend.measurements import CeilingFrame

log = logging.getLogger(__name__)

_POLL_S = 0.5  # how often a waiting caller checks that the worker is alive
_STOP = "stop"
_FLOOR = 1e-14  # covariance floor of the odometry composition (the covariance is unused)


@dataclass
class DecoupledTimes:
    """Per-step records of :func:`run_decoupled` (``time.perf_counter`` s, step order).

    Attributes:
        t: (N,) step times, s of data.
        pose: (N, 3) the tracked pose given at each step ``world_T_body``, m and rad.
        anchor: (N,) the backend step the pose was composed from (``j`` above).
        out: when each step's pose was given.
        sent: when each step went to the worker.
        back: when the worker's estimate of each step came back (NaN: never read).
        keyframe: whether the backend made the step a keyframe.
        backend_pose: (N, 3) the backend's own online estimate of each step.
        step_cpu: (N,) the worker's process CPU time for each step, s.
        worker_cpu_s: the worker process's CPU time for the steps (process clock).
        worker_done: when the worker had finished the last step.
    """

    t: list[float] = field(default_factory=list)
    pose: list[FloatArray] = field(default_factory=list)
    anchor: list[int] = field(default_factory=list)
    out: list[float] = field(default_factory=list)
    sent: list[float] = field(default_factory=list)
    back: list[float] = field(default_factory=list)
    keyframe: list[bool] = field(default_factory=list)
    backend_pose: list[FloatArray] = field(default_factory=list)
    step_cpu: list[float] = field(default_factory=list)
    worker_cpu_s: float = 0.0
    worker_done: float = float("nan")


def _pack(frame: Frame | None) -> object:
    """A step's frame for the queue (ceiling frames stacked, :func:`pack_frame`)."""
    if isinstance(frame, CeilingFrame):
        return ("ceiling", pack_frame(frame))
    return ("raw", frame)


def _unpack(item: object) -> Frame | None:
    kind, payload = cast(tuple[str, object], item)
    if kind == "ceiling":
        return unpack_frame(cast(PackedFrame, payload))
    return cast(Frame | None, payload)


def _mapping_worker(backend: str, odometry: OdometryConstants, config: SlamConfig,
                    start_pose: FloatArray, camera: CameraModel | None,
                    inbox: queue.Queue[object], outbox: queue.Queue[object]) -> None:
    """Worker process: ``("ready", 0)`` once the backend is built, then step it on each
    ``(i, t, samples, frame)`` and send back ``(i, pose, keyframe, step CPU s)``; ``("done", cpu_s)``
    after the stop mark, or ``("error", text)``."""
    import signal

    from lampsam.backend.slam import make_backend

    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the caller stops the worker itself
    c0 = time.process_time()
    try:
        be = make_backend(backend, odometry, config, start_pose, camera)
        outbox.put(("ready", 0.0))
        while True:
            item = inbox.get()
            if item == _STOP:
                break
            i, t, samples, packed = cast(tuple[int, float, FloatArray, object], item)
            c = time.process_time()
            est = be.step(t, samples, _unpack(packed))
            outbox.put((i, np.asarray(est.pose, float), bool(est.keyframe),
                        time.process_time() - c))
        outbox.put(("done", time.process_time() - c0))
    except Exception as exc:  # sent to the caller, which raises it
        outbox.put(("error", f"{type(exc).__name__}: {exc}"))


def run_decoupled(steps: Iterable[tuple[float, FloatArray, Frame | None]], backend: str,
                  odometry: OdometryConstants, config: SlamConfig, start_pose: FloatArray,
                  camera: CameraModel | None = None, times: DecoupledTimes | None = None
                  ) -> DecoupledTimes:
    """Track every step at once while a worker process runs the backend (see module doc).

    Args:
        steps: ``(t, odometry samples, frame or None)`` in time order
            (:func:`lampsam.backend.slam.iter_steps`).
        backend: the online backend's name (:func:`~lampsam.backend.slam.make_backend`).
        odometry: the odometry model's constants; config: the SLAM config.
        start_pose: (3,) known start pose ``world_T_body``, m and rad.
        camera: the upward camera for ceiling frames, or None.
        times: filled as the run goes (a new one if None).

    Returns:
        The per-step records (:class:`DecoupledTimes`), with every step's backend
        estimate (the worker is waited for at the end).

    Raises:
        LampsamError: the worker failed (its message) or died.
    """
    times = times if times is not None else DecoupledTimes()
    motion = motion_model(odometry)
    ctx = mp.get_context("spawn")  # no fork of a parent holding GTSAM / OpenCV threads
    inbox: queue.Queue[object] = ctx.Queue()  # type: ignore[assignment]
    outbox: queue.Queue[object] = ctx.Queue()  # type: ignore[assignment]
    worker = ctx.Process(target=_mapping_worker, name="lampsam-mapping", daemon=True,
                         args=(backend, odometry, config, np.asarray(start_pose, float), camera,
                               inbox, outbox))
    worker.start()
    chain: list[gtsam.Pose2] = []  # o_i: the odometry chain of every step
    anchor_j, anchor_x = -1, gtsam.Pose2(*np.asarray(start_pose, float))
    done_cpu: list[float] = []
    ready: list[bool] = []

    def take(item: object) -> None:
        nonlocal anchor_j, anchor_x
        if isinstance(item, tuple) and isinstance(item[0], str):
            if item[0] == "ready":
                ready.append(True)
                return
            if item[0] == "done":
                done_cpu.append(float(item[1]))
                return
            raise LampsamError(f"mapping worker failed: {item[1]}")
        j, pose, kf, cpu = cast(tuple[int, FloatArray, bool, float], item)
        times.back[j] = time.perf_counter()
        times.step_cpu[j] = cpu
        times.keyframe[j] = kf
        times.backend_pose[j] = pose
        if j > anchor_j:
            anchor_j, anchor_x = j, gtsam.Pose2(*pose)

    try:
        while not ready:  # the backend built (imports, GTSAM) before the first step
            try:
                take(outbox.get(timeout=_POLL_S))
            except queue.Empty:
                if not worker.is_alive():
                    raise LampsamError("the mapping worker died while starting") from None
        o = gtsam.Pose2()
        for i, (t, samples, frame) in enumerate(steps):
            u = motion.check(t, samples)
            if len(u):
                d, _ = motion.relative(u, _FLOOR)
                o = o.compose(gtsam.Pose2(*d))
            chain.append(o)
            times.t.append(t)
            times.back.append(float("nan"))
            times.keyframe.append(False)
            times.backend_pose.append(np.full(3, np.nan))
            times.step_cpu.append(float("nan"))
            times.sent.append(time.perf_counter())
            inbox.put((i, t, samples, _pack(frame)))
            while True:  # every estimate already back
                try:
                    take(outbox.get_nowait())
                except queue.Empty:
                    break
            if anchor_j < 0:
                x = anchor_x.compose(o)
            else:
                x = anchor_x.compose(chain[anchor_j].between(o))
            times.pose.append(pose_array(x))
            times.anchor.append(anchor_j)
            times.out.append(time.perf_counter())
        inbox.put(_STOP)
        while not done_cpu:
            try:
                take(outbox.get(timeout=_POLL_S))
            except queue.Empty:
                if not worker.is_alive():
                    raise LampsamError("the mapping worker stopped without a word after "
                                       f"{anchor_j + 1} steps") from None
        times.worker_cpu_s = done_cpu[0]
        times.worker_done = max((b for b in times.back if b == b), default=float("nan"))
        return times
    finally:
        if not done_cpu and worker.is_alive():  # stopped early: do not wait for the backlog
            worker.terminate()
        worker.join(timeout=5.0)
        if worker.is_alive():
            log.warning("mapping worker still running after 5 s: terminating it")
            worker.terminate()
            worker.join(timeout=1.0)


def replay_latency(t: FloatArray, step_cpu: FloatArray, pace: float) -> FloatArray:
    """Each step's latency (s) on a dedicated core: steps arriving at ``t / pace``, served in turn.

    The Lindley recursion ``f_i = max(a_i, f_(i-1)) + c_i`` with arrival
    ``a_i = (t_i - t_0) / pace`` and service ``c_i`` the step's measured CPU time;
    the latency is ``f_i - a_i``. What the worker's queue would do on a core of its
    own, from CPU times measured on a shared machine (where wall-clock latencies
    reflect the other processes' load, not this pipeline's).

    Args:
        t: (N,) step times, s of data; step_cpu: (N,) CPU time per step, s.
        pace: replay speed, x real time (1: a robot's camera).
    """
    a = (np.asarray(t, float) - float(t[0])) / pace
    out = np.empty(len(a))
    f = -np.inf
    for i, (ai, ci) in enumerate(zip(a, np.asarray(step_cpu, float), strict=True)):
        f = max(ai, f) + ci
        out[i] = f - ai
    return out
