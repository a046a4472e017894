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

import dataclasses
import logging
import multiprocessing as mp
import queue
import threading
import time
from collections import deque
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field
from multiprocessing.connection import Connection
from multiprocessing.context import ForkContext, SpawnContext
from multiprocessing.synchronize import Event as EventLike
from typing import cast

import gtsam
import numpy as np

from lampsam.arrays import FloatArray
from lampsam.backend.config import SlamConfig
from lampsam.backend.graph import GraphSlam
from lampsam.backend.interface import Frame, SlamBackend, SlamResult, StepEstimate
from lampsam.backend.keyframes import KeyframeMirror
from lampsam.backend.odometry import OdometryConstants, motion_model
from lampsam.backend.pipelined import PackedFrame, pack_frame, unpack_frame
from lampsam.backend.pose_cov import pose_array
from lampsam.datasets.logrun import CameraModel
from lampsam.errors import LampsamError
from lampsam.frontend.measurements import CeilingFrame
from lampsam.interrupt import stop_requested

log = logging.getLogger(__name__)

_POLL_S = 0.5  # how often a waiting caller checks that the worker is alive
_STOP = "stop"
#: The worker sends its estimates when it has caught up with the caller, or after this
#: many steps: a caller far behind wakes once per batch instead of once per step.
_REPLY_BATCH = 16
_FLOOR = 1e-14  # covariance floor of the odometry composition (the covariance is unused)


class WorkerError(LampsamError):
    """The mapping worker failed (its message) or died."""


@dataclass
class WorkerClocks:
    """Where the mapping worker's time goes besides its steps (process CPU s, or wall s).

    Attributes:
        startup_cpu_s: building the backend, before ``("ready", ...)``.
        inbox_cpu_s: taking the steps from the inbox: reading and unpickling the
            messages, unpacking the frames.
        reply_cpu_s: sending the estimates back (pickled and written to the pipe).
        finish_cpu_s: after the stop mark: the backend's final optimisation
            (``finish``).
        idle_s: wall clock blocked on an empty inbox, waiting for the caller.
        online_cpu_s: process CPU from start to the stop mark (start-up, steps, inbox,
            replies).
        online_wall_s: wall clock from start to the stop mark; ``online_wall_s -
            online_cpu_s - idle_s`` is the time the worker wanted a core and had none
            (other processes' load).
    """

    startup_cpu_s: float = 0.0
    inbox_cpu_s: float = 0.0
    reply_cpu_s: float = 0.0
    finish_cpu_s: float = 0.0
    idle_s: float = 0.0
    online_cpu_s: float = 0.0
    online_wall_s: float = 0.0


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
            worker's iSAM2 updates (:class:`CatchUp`; empty when off).
        clocks: the worker's time besides its steps (:class:`WorkerClocks`).
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


def worker_context() -> ForkContext | SpawnContext:
    """The multiprocessing context of the mapping worker: ``fork`` when this process
    runs a single thread (the child starts at once with every module already
    imported, ~1 s of interpreter start-up and GTSAM import saved), else ``spawn``
    (forking a process whose other threads may hold locks can deadlock the child)."""
    if threading.active_count() == 1 and "fork" in mp.get_all_start_methods():
        return cast(ForkContext, mp.get_context("fork"))
    return cast(SpawnContext, mp.get_context("spawn"))


class _Backlog:
    """The steps the worker has taken from its inbox and not yet run, in order;
    ``framed`` counts those with a measurement frame (each a possible keyframe),
    ``newest`` is the index of the newest step taken."""

    def __init__(self, inbox: queue.Queue[object]) -> None:
        self.inbox = inbox
        self.items: deque[object] = deque()
        self.framed = 0
        self.newest = -1

    def append(self, item: object) -> None:
        self.items.append(item)
        if item != _STOP:
            step = cast(tuple[int, float, FloatArray, tuple[str, object]], item)
            self.newest = step[0]
            if step[3][1] is not None:
                self.framed += 1

    def drain(self) -> None:
        """Take every step already waiting in the inbox (without blocking)."""
        while True:
            try:
                self.append(self.inbox.get_nowait())
            except queue.Empty:
                return

    def pop(self) -> object:
        item = self.items.popleft()
        if item != _STOP and cast(tuple[int, float, FloatArray, tuple[str, object]],
                                  item)[3][1] is not None:
            self.framed -= 1
        return item


def _inbox_steps(backlog: _Backlog, stop: EventLike, at: list[float], index: list[int],
                 flush: Callable[[], None], clocks: WorkerClocks
                 ) -> Iterator[tuple[float, FloatArray, Frame | None]]:
    """The worker's steps from its inbox until the stop mark. A set ``stop`` (the caller
    was interrupted) or a dead caller raises :class:`KeyboardInterrupt`, which
    :func:`~lampsam.backend.slam.drive` turns into status ``"interrupted"``. Before each
    step the inbox is drained into ``backlog`` (so a catching-up backend sees what
    waits), ``index[0]`` is set to the step's index and ``at[0]`` to the process CPU
    clock; ``flush`` (send the estimates made so far) is called whenever nothing
    waits, before waiting for the caller, and at the stop mark. The CPU spent here (flushes apart) adds to
    ``clocks.inbox_cpu_s``, the wall clock blocked on the empty inbox to
    ``clocks.idle_s``."""
    parent = mp.parent_process()
    while True:
        c0 = time.process_time()
        if stop.is_set():
            raise KeyboardInterrupt("stopped by the tracking process")
        backlog.drain()
        if not backlog.items:
            r0 = time.process_time()
            flush()  # caught up: the caller gets every estimate before the worker waits
            clocks.reply_cpu_s += time.process_time() - r0
            c0 += time.process_time() - r0
            w0 = time.perf_counter()
            try:
                item = backlog.inbox.get(timeout=_POLL_S)
            except queue.Empty:
                clocks.idle_s += time.perf_counter() - w0
                if parent is not None and not parent.is_alive():
                    raise KeyboardInterrupt("the tracking process died") from None
                continue
            clocks.idle_s += time.perf_counter() - w0
            backlog.append(item)
        item = backlog.pop()
        if item == _STOP:
            flush()  # every step's estimate back before the final optimisation
            clocks.inbox_cpu_s += time.process_time() - c0
            return
        i, t, samples, packed = cast(tuple[int, float, FloatArray, object], item)
        index[0] = i
        frame = _unpack(packed)
        at[0] = time.process_time()
        clocks.inbox_cpu_s += at[0] - c0
        yield t, samples, frame


class CatchUp(SlamBackend):
    """A graph backend that catches up when behind: one iSAM2 update for several keyframes.

    While ``waiting()`` (framed steps queued behind this one) is positive, each
    keyframe is associated against the prediction from the newest iSAM2 estimate
    plus odometry and its update deferred
    (:meth:`~lampsam.backend.graph.GraphSlam.step` with ``update=False``), up to
    ``max_keyframes`` keyframes, which then go to iSAM2 in one update: what a
    real-time SLAM system does when its mapping lags, instead of falling further
    behind one update per keyframe. With nothing queued every keyframe is updated at
    once, as without the wrapper.

    Args:
        inner: the backend (its iSAM2, or the batch backend's online pass).
        max_keyframes: keyframes per update at most (``[online] catch_up``, >= 1).
        waiting: how many framed steps wait behind the current one.
    """

    def __init__(self, inner: GraphSlam, max_keyframes: int, waiting: Callable[[], int]) -> None:
        self.inner = inner
        self.name = inner.name
        self.max_keyframes = max_keyframes
        self.waiting = waiting
        #: keyframes in each iSAM2 update this run made (1: a keyframe updated alone)
        self.update_sizes: list[int] = []

    def step(self, t: float, wheel: FloatArray, frame: Frame | None) -> StepEstimate:
        """One step; defers a keyframe's update while framed steps wait (see class).

        The update of ``max_keyframes`` deferred keyframes runs in the step that made
        the last of them, and its estimate is then the updated one.
        """
        before = self.inner.n_deferred
        behind = self.waiting() > 0
        est = self.inner.step(t, wheel, frame, update=not behind)
        if not behind:
            if before + est.keyframe:
                self.update_sizes.append(before + int(est.keyframe))
        elif self.inner.n_deferred >= self.max_keyframes:
            self.update_sizes.append(self.inner.n_deferred)
            self.inner.update()
            est = dataclasses.replace(est, pose=self.inner.current_pose())
        return est

    def finish(self, status: str = "ok") -> SlamResult:
        """The inner backend's result (the keyframes still deferred updated first)."""
        if self.inner.n_deferred:
            self.update_sizes.append(self.inner.n_deferred)
        return self.inner.finish(status)


def reply_due(n_pending: int, step: int, newest: int, replied: int, max_lag: int | None) -> bool:
    """Whether the worker sends its pending estimates after finishing ``step``.

    Every ``_REPLY_BATCH`` steps, and at once when the caller may be waiting on
    back-pressure for this very step: the caller, having sent up to ``newest``, waits
    while ``newest - (newest estimate it has) > max_lag``; the estimates it has end at
    ``replied``. Replying only in batches would keep it waiting while the worker works
    through its backlog, then leave the worker without steps while it resumes.

    Args:
        n_pending: estimates finished and not yet sent; step: the step just finished;
        newest: the newest step taken from the inbox; replied: the newest step sent
            back (-1: none); max_lag: the caller's back-pressure, steps (None: none).
    """
    if n_pending >= _REPLY_BATCH:
        return True
    return max_lag is not None and newest - step <= max_lag < newest - replied


def _send(outbox: Connection, message: object) -> None:
    """Write a message to the caller in this thread (a queue's feeder thread would wait
    for the GIL while GTSAM holds it in the next step: the estimates would come back a
    step late); a caller gone is nothing to report to."""
    try:
        outbox.send(message)
    except (BrokenPipeError, ConnectionResetError):
        pass


def _receive(inbox: Connection, timeout: float) -> object:
    """The worker's next message; :class:`queue.Empty` after ``timeout`` s without one.

    Raises:
        WorkerError: the worker's end closed without a ``"done"`` (it died).
    """
    if not inbox.poll(timeout):
        raise queue.Empty
    try:
        return inbox.recv()
    except EOFError:
        raise WorkerError("the mapping worker stopped without a word") from None


def _mapping_worker(backend: str, odometry: OdometryConstants, config: SlamConfig,
                    start_pose: FloatArray, camera: CameraModel | None,
                    inbox: queue.Queue[object], outbox: Connection, stop: EventLike,
                    finish: bool, max_lag: int | None) -> None:
    """Worker process: ``("ready", 0)`` once the backend is built, then step it on each
    ``(i, t, samples, frame)`` and send back ``("steps", [(i, pose, keyframe, step CPU s),
    ...])``, batched: when the inbox is empty, at the stop mark and when
    :func:`reply_due`. After the stop mark
    (or ``stop`` set) ``("done", result or None, cpu_s, keyframes per update, clocks)``
    (:attr:`DecoupledTimes.update_sizes`, :class:`WorkerClocks`), the result being the
    backend's ``finish`` through :func:`~lampsam.backend.slam.drive` (same statuses and
    fallbacks as a run in one process); ``("error", text)`` if the backend cannot be
    built."""
    import signal
    from collections.abc import Mapping

    from lampsam.backend.slam import drive, make_backend
    from lampsam.observe import observing

    # the caller coordinates stopping (a signal to the process group must not kill the
    # worker before it has written back what it finished)
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    c0, w0 = time.process_time(), time.perf_counter()
    try:
        be = make_backend(backend, odometry, config, start_pose, camera)
    except Exception as exc:  # sent to the caller, which raises it
        _send(outbox, ("error", f"{type(exc).__name__}: {exc}"))
        return
    _send(outbox, ("ready", 0.0))
    clocks = WorkerClocks(startup_cpu_s=time.process_time() - c0)
    at, index, replied = [0.0], [-1], [-1]
    pending: list[tuple[int, tuple[float, float, float], bool, float]] = []
    backlog = _Backlog(inbox)
    catch_up: CatchUp | None = None
    if config.online.catch_up > 1:
        if isinstance(be, GraphSlam) and be.isam is not None and be.smoother is None:
            be = catch_up = CatchUp(be, config.online.catch_up, lambda: backlog.framed)
        else:
            log.warning("[online] catch_up applies to iSAM2 without fixed lag: ignored")

    def flush() -> None:
        # a deferred keyframe's estimate is the prediction: its step (and those after
        # it) go back with the update that includes it, as the keyframe latency says
        if pending and (catch_up is None or not catch_up.inner.n_deferred):
            _send(outbox, ("steps", pending.copy()))
            replied[0] = pending[-1][0]
            pending.clear()

    def on_event(event: str, fields: Mapping[str, object]) -> None:
        if event == "slam.step":
            est = cast(StepEstimate, fields["estimate"])
            x, y, th = (float(v) for v in est.pose)
            pending.append((index[0], (x, y, th), bool(est.keyframe),
                            time.process_time() - at[0]))
            if reply_due(len(pending), index[0], backlog.newest, replied[0], max_lag):
                r0 = time.process_time()
                flush()
                clocks.reply_cpu_s += time.process_time() - r0

    def steps() -> Iterator[tuple[float, FloatArray, Frame | None]]:
        yield from _inbox_steps(backlog, stop, at, index, flush, clocks)
        clocks.online_cpu_s = time.process_time() - c0  # the stop mark: online work done
        clocks.online_wall_s = time.perf_counter() - w0

    result: SlamResult | None = None
    if finish:
        with observing(on_event):
            result = drive(be, steps())
        result.graph = None  # GTSAM's Python-callback factors do not pickle
    else:
        try:
            for t, samples, frame in steps():
                est = be.step(t, samples, frame)
                on_event("slam.step", {"estimate": est})
        except KeyboardInterrupt:
            pass
        except Exception as exc:  # sent to the caller, which raises it
            _send(outbox, ("error", f"{type(exc).__name__}: {exc}"))
            return
    if pending:
        _send(outbox, ("steps", pending.copy()))
    sizes = catch_up.update_sizes if catch_up is not None else []
    total = time.process_time() - c0
    if not clocks.online_cpu_s:  # stopped early: all of it
        clocks.online_cpu_s, clocks.online_wall_s = total, time.perf_counter() - w0
    clocks.finish_cpu_s = total - clocks.online_cpu_s
    _send(outbox, ("done", result, total, sizes, clocks))
    outbox.close()


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
    worker = ctx.Process(target=_mapping_worker, name="lampsam-mapping", daemon=True,
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
                take(_receive(outbox, _POLL_S))
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
                if len(u):
                    d, _ = motion.relative(u, _FLOOR)
                    o = o.compose(gtsam.Pose2(*d))
                # the backend's frame: None where it will not read it (a lazy frame's
                # image then never processed), as it decides (KeyframeMirror)
                sent = frame if mirror is None or mirror.reads(u, frame) else None
                chain.append(o)
                times.t.append(t)
                times.framed.append(frame is not None)
                times.back.append(float("nan"))
                times.keyframe.append(False)
                times.backend_pose.append(np.full(3, np.nan))
                times.step_cpu.append(float("nan"))
                times.sent.append(time.perf_counter())
                inbox.put((i, t, samples, _pack(sent)))
                while True:  # every estimate already back
                    try:
                        take(_receive(outbox, 0.0))
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
                        take(_receive(outbox, _POLL_S))
                    except queue.Empty:
                        if not worker.is_alive():
                            raise WorkerError("the mapping worker died after "
                                              f"{anchor_j + 1} steps") from None
                times.lag_wait_s += time.perf_counter() - w0
                if done:  # the worker ended early (its backend failed): nothing more to map
                    break
            inbox.put(_STOP)
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
