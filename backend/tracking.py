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
The worker's side (its inbox, replies, clocks and catch-up) is
:mod:`lampsam.backend.mapping_worker`.

:func:`run_decoupled` records per step when it was handed over and when the
backend's estimate came back, so a caller can report the tracking latency (frame
ready -> pose out), the keyframe latency (hand-over -> estimate back) and the
throughput (data duration / wall clock until the worker finished) separately.
"""

from __future__ import annotations

import logging
import queue
import time
from collections.abc import Iterable
from dataclasses import dataclass, field
from multiprocessing.synchronize import Event as EventLike
from typing import cast

import gtsam
import numpy as np

from lampsam.arrays import FloatArray
from lampsam.backend.config import SlamConfig
from lampsam.backend.interface import Frame, SlamResult
from lampsam.backend.keyframes import KeyframeMirror
from lampsam.backend.mapping_worker import (
    POLL_S,
    STOP,
    WorkerClocks,
    WorkerError,
    mapping_worker,
    pack_odometry,
    pack_step_frame,
    receive,
    worker_context,
)
from lampsam.backend.odometry import OdometryConstants, motion_model
from lampsam.backend.pose_cov import pose_array
from lampsam.datasets.logrun import CameraModel
from lampsam.errors import LampsamError
from lampsam.interrupt import stop_requested

log = logging.getLogger(__name__)

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
        framed: whether each step carried a measurement frame.
        given: when each step was taken from the caller's iterator (its frame ready).
        cpu_out: the calling thread's CPU clock (``time.thread_time``) when each
            step's pose was given: differences are the CPU per step of making the
            step (e.g. the frontend) and tracking it.
        worker_cpu_s: the worker process's CPU time, start-up and final optimisation
            included (process clock).
        worker_ready: when the worker had built the backend (its start-up ends).
        worker_done: when the worker had finished the last step.
        update_sizes: with ``[online] catch_up`` > 1, the keyframes in each of the
            worker's iSAM2 updates (:class:`~lampsam.backend.mapping_worker.CatchUp`; empty when off).
        clocks: the worker's time besides its steps (:class:`~lampsam.backend.mapping_worker.WorkerClocks`).
        lag_wait_s: wall clock this process waited on back-pressure (``max_lag``).
        result: the backend's :class:`~lampsam.backend.interface.SlamResult` after
            its ``finish`` (``run_decoupled(finish=True)``; None otherwise, or when
            the worker was given up on).
        interrupted: the caller's steps were stopped by a signal
            (:mod:`lampsam.interrupt`).
        failure: the error that stopped the caller's steps (e.g. an unreadable
            image), or None.
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
    framed: list[bool] = field(default_factory=list)
    given: list[float] = field(default_factory=list)
    cpu_out: list[float] = field(default_factory=list)
    worker_cpu_s: float = 0.0
    worker_ready: float = float("nan")
    worker_done: float = float("nan")
    update_sizes: list[int] = field(default_factory=list)
    clocks: WorkerClocks = field(default_factory=WorkerClocks)
    lag_wait_s: float = 0.0
    result: SlamResult | None = None
    interrupted: bool = False
    failure: str | None = None


def run_decoupled(steps: Iterable[tuple[float, FloatArray, Frame | None]], backend: str,
                  odometry: OdometryConstants, config: SlamConfig, start_pose: FloatArray,
                  camera: CameraModel | None = None, times: DecoupledTimes | None = None,
                  finish: bool = False, max_lag: int | None = None) -> DecoupledTimes:
    """Track every step at once while a worker process runs the backend (see module doc).

    The worker is started first and the steps are handed over as they come, so its
    start-up (a fresh interpreter importing GTSAM) overlaps the first frames; until
    its first estimate is back the tracked pose is the start pose plus odometry.

    Args:
        steps: ``(t, odometry samples, frame or None)`` in time order
            (:func:`lampsam.backend.slam.iter_steps`; wrapped in
            :func:`lampsam.interrupt.interruptible` by callers that honour signals).
        backend: the online backend's name (:func:`~lampsam.backend.slam.make_backend`).
        odometry: the odometry model's constants; config: the SLAM config.
        start_pose: (3,) known start pose ``world_T_body``, m and rad.
        camera: the upward camera for ceiling frames, or None.
        times: filled as the run goes (a new one if None).
        finish: also run the backend's final optimisation in the worker and return its
            result (``times.result``), as :func:`~lampsam.backend.slam.drive` does.
        max_lag: back-pressure, steps: after giving step ``i``'s pose, wait until the
            worker has finished step ``i - max_lag`` before taking the next step (0:
            every pose is the previous step's estimate plus one step of odometry; None:
            never wait). A camera cannot be slowed, so a robot runs with None;
            replaying a log faster than the backend keeps up, a bound keeps the tracked
            poses what they would be on a robot whose backend keeps up within
            ``max_lag`` steps (unbounded, the tracker runs ahead on odometry alone and
            its poses are dead reckoning from an old estimate). The wait delays the
            next step's reading, not this step's pose.

    Returns:
        The per-step records (:class:`DecoupledTimes`), with every finished step's
        backend estimate (the worker is waited for at the end). A
        :class:`KeyboardInterrupt` from ``steps`` (a stop signal) stops the worker
        after the step it is on: ``times.interrupted`` is set and the steps it had
        not begun stay NaN; a second one gives up waiting for it.

    Raises:
        WorkerError: the worker failed (its message) or died.
    """
    if max_lag is not None and max_lag < 0:
        raise ValueError(f"max_lag must be >= 0 or None, got {max_lag}")
    times = times if times is not None else DecoupledTimes()
    motion = motion_model(odometry)
    # a graph backend reads a frame only when it can become a keyframe: the others are
    # not sent (nor made, when lazy); the EKF reads every frame
    mirror = KeyframeMirror(motion, config) if backend in ("isam2", "batch") else None
    ctx = worker_context()
    inbox: queue.Queue[object] = ctx.Queue()  # type: ignore[assignment]
    outbox, worker_end = ctx.Pipe(duplex=False)  # estimates back: (read end, write end)
    stop: EventLike = ctx.Event()
    worker = ctx.Process(target=mapping_worker, name="lampsam-mapping", daemon=True,
                         args=(backend, odometry, config, np.asarray(start_pose, float), camera,
                               inbox, worker_end, stop, finish, max_lag))
    worker.start()
    worker_end.close()  # the worker's copy only: its exit closes the pipe
    chain: list[gtsam.Pose2] = []  # o_i: the odometry chain of every step
    anchor_j, anchor_x = -1, gtsam.Pose2(*np.asarray(start_pose, float))
    done: list[bool] = []

    def take(message: object) -> None:
        nonlocal anchor_j, anchor_x
        item = cast(tuple[str, object, object], message)
        if item[0] == "ready":
            times.worker_ready = time.perf_counter()
            log.info("mapping worker ready (%s backend built)", backend)
            return
        if item[0] == "done":
            times.result = cast(SlamResult | None, item[1])
            times.worker_cpu_s = float(cast(float, item[2]))
            done_item = cast(tuple[str, object, float, list[int], WorkerClocks], message)
            times.update_sizes = list(done_item[3])
            times.clocks = done_item[4]
            done.append(True)
            return
        if item[0] != "steps":
            raise WorkerError(f"mapping worker failed: {item[1]}")
        now = time.perf_counter()
        if anchor_j < 0:  # an observable state: a stop from here on keeps these steps
            log.info("first estimates back from the mapping worker")
        for j, pose, kf, cpu in cast(list[tuple[int, tuple[float, float, float], bool, float]],
                                     item[1]):
            times.back[j] = now
            times.step_cpu[j] = cpu
            times.keyframe[j] = kf
            times.backend_pose[j] = np.array(pose)
            if j > anchor_j:
                anchor_j, anchor_x = j, gtsam.Pose2(*pose)

    def wait_for_worker() -> None:
        while not done:
            if not times.interrupted and stop_requested() is not None:
                # a stop signal after the last step was sent: the worker stops after
                # the step it is on rather than working through its backlog
                times.interrupted = True
                stop.set()
                log.warning("interrupted: the mapping worker stops after its current step "
                            "(a second signal gives up on it)")
            try:
                take(receive(outbox, POLL_S))
            except queue.Empty:
                if not worker.is_alive():
                    raise WorkerError("the mapping worker stopped without a word after "
                                       f"{anchor_j + 1} steps") from None

    try:
        try:
            o = gtsam.Pose2()
            for i, (t, samples, frame) in enumerate(steps):
                times.given.append(time.perf_counter())
                u = motion.check(t, samples)
                # the backend's frame: None where it will not read it (a lazy frame's
                # image then never processed), as it decides (KeyframeMirror)
                sent = frame if mirror is None or mirror.reads(u, frame) else None
                if len(u):  # the step's motion: the mirror's, else composed here
                    d = mirror.step_motion if mirror is not None else None
                    if d is None:
                        d, _ = motion.relative(u, _FLOOR)
                    o = o.compose(gtsam.Pose2(*d))
                chain.append(o)
                times.t.append(t)
                times.framed.append(frame is not None)
                times.back.append(float("nan"))
                times.keyframe.append(False)
                times.backend_pose.append(np.full(3, np.nan))
                times.step_cpu.append(float("nan"))
                times.sent.append(time.perf_counter())
                inbox.put((i, t, samples, pack_step_frame(sent),
                           pack_odometry(mirror.advanced if mirror is not None else None)))
                while True:  # every estimate already back
                    try:
                        take(receive(outbox, 0.0))
                    except queue.Empty:
                        break
                if anchor_j < 0:
                    x = anchor_x.compose(o)
                else:
                    x = anchor_x.compose(chain[anchor_j].between(o))
                times.pose.append(pose_array(x))
                times.anchor.append(anchor_j)
                times.out.append(time.perf_counter())
                times.cpu_out.append(time.thread_time())
                w0 = time.perf_counter()
                while max_lag is not None and i - anchor_j > max_lag and not done:
                    try:  # back-pressure: wait for the worker to come within max_lag
                        take(receive(outbox, POLL_S))
                    except queue.Empty:
                        if not worker.is_alive():
                            raise WorkerError("the mapping worker died after "
                                              f"{anchor_j + 1} steps") from None
                times.lag_wait_s += time.perf_counter() - w0
                if done:  # the worker ended early (its backend failed): nothing more to map
                    break
            inbox.put(STOP)
            log.info("all %d steps sent to the mapping worker", len(chain))
        except KeyboardInterrupt:  # a stop signal between steps: the worker stops too
            times.interrupted = True
            stop.set()
            log.warning("interrupted: waiting for the mapping worker to finish its step "
                        "(a second signal gives up on it)")
        except LampsamError as exc:  # bad input met mid-run: keep what the worker finished
            if not isinstance(exc, WorkerError):
                times.failure = str(exc)
                stop.set()
                log.error("%s", exc)
            else:
                raise
        try:
            wait_for_worker()
        except KeyboardInterrupt:
            times.interrupted = True
            log.warning("second stop signal: the mapping worker's final result is given up")
        finished = [b for b in times.back if b == b]
        times.worker_done = max(finished, default=float("nan"))
        return times
    finally:
        if not done and worker.is_alive():  # stopped early: do not wait for the backlog
            worker.terminate()
        worker.join(timeout=5.0)
        if worker.is_alive():
            log.warning("mapping worker still running after 5 s: terminating it")
            worker.terminate()
            worker.join(timeout=1.0)
        # steps the worker never read stay in the inbox's pipe; without this, this
        # process's exit would wait forever for its feeder thread to write them to a
        # pipe that nobody reads (a stop while the worker lagged far behind)
        inbox.cancel_join_thread()  # type: ignore[attr-defined]
        outbox.close()


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
