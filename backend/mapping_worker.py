"""The mapping worker of :mod:`lampsam.backend.tracking`: the backend stepped in its own process.

The worker takes ``(i, t, samples, frame, odometry)`` steps from its inbox (a
``multiprocessing`` queue fed by the tracking process, frames packed by
:func:`~lampsam.backend.pipelined.pack_frame`; a graph backend's odometry since its
last keyframe as the tracker's :class:`~lampsam.backend.keyframes.KeyframeMirror`
composed it, :func:`pack_odometry`, so the worker does not compose it again), steps the backend on each
(:func:`~lampsam.backend.slam.drive`, so the statuses and fallbacks of a run in one
process hold) and writes its estimates back through a pipe, in its own thread:
batched, but at once when the tracker is waiting for them (:func:`reply_due`) and at
the stop mark, before the final optimisation. It times what it does besides its steps
(:class:`WorkerClocks`). :class:`CatchUp` lets a lagging iSAM2 worker update several
keyframes at once (``[online] catch_up``).
"""

from __future__ import annotations

import dataclasses
import logging
import multiprocessing as mp
import queue
import threading
import time
from collections import deque
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from multiprocessing.connection import Connection
from multiprocessing.context import ForkContext, SpawnContext
from multiprocessing.synchronize import Event as EventLike
from typing import cast

import numpy as np

from lampsam.arrays import FloatArray
from lampsam.backend.config import SlamConfig
from lampsam.backend.graph import GraphSlam
from lampsam.backend.interface import Frame, SlamBackend, SlamResult, StepEstimate
from lampsam.backend.keyframes import Advanced
from lampsam.backend.odometry import OdometryConstants
from lampsam.backend.pipelined import PackedFrame, pack_frame, unpack_frame
from lampsam.datasets.logrun import CameraModel
from lampsam.errors import LampsamError
from lampsam.frontend.measurements import CeilingFrame

log = logging.getLogger(__name__)

#: :func:`pack_odometry`'s form: ``(delta (3,), cov (9,), first_rel or None)`` or None.
PackedOdometry = tuple[tuple[float, ...], tuple[float, ...],
                       tuple[tuple[float, ...], tuple[float, ...]] | None] | None
#: An inbox item: ``(i, t, samples, packed frame, packed odometry)``.
_Step = tuple[int, float, FloatArray, tuple[str, object], PackedOdometry]

POLL_S = 0.5  # how often a waiting process checks that the other is alive
STOP = "stop"  # the inbox's stop mark: no more steps
#: The worker sends its estimates when it has caught up with the caller, or after this
#: many steps (or when the caller waits for them, :func:`reply_due`).
_REPLY_BATCH = 16


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


def pack_odometry(advanced: Advanced | None) -> PackedOdometry:
    """A step's advanced odometry (:attr:`~lampsam.backend.keyframes.KeyframeMirror.advanced`)
    as plain floats for the queue (pickling three small arrays cost ~10x the floats)."""
    if advanced is None:
        return None
    delta, cov, first = advanced
    return (tuple(delta.tolist()), tuple(cov.ravel().tolist()),
            None if first is None else (tuple(first[0].tolist()), tuple(first[1].ravel().tolist())))


def unpack_odometry(packed: PackedOdometry) -> Advanced | None:
    """The arrays :func:`pack_odometry` packed (float64 round-trips exactly)."""
    if packed is None:
        return None
    delta, cov, first = packed
    return (np.array(delta, float), np.array(cov, float).reshape(3, 3),
            None if first is None else (np.array(first[0], float),
                                        np.array(first[1], float).reshape(3, 3)))


def pack_step_frame(frame: Frame | None) -> object:
    """A step's frame for the queue (ceiling frames stacked, :func:`pack_frame`)."""
    if isinstance(frame, CeilingFrame):
        return ("ceiling", pack_frame(frame))
    return ("raw", frame)


def unpack_step_frame(item: object) -> Frame | None:
    """The frame :func:`pack_step_frame` packed."""
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
        if item != STOP:
            step = cast(_Step, item)
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
        if item != STOP and cast(_Step, item)[3][1] is not None:
            self.framed -= 1
        return item


def _inbox_steps(backlog: _Backlog, stop: EventLike, at: list[float], index: list[int],
                 flush: Callable[[], None], clocks: WorkerClocks,
                 give: Callable[[Advanced | None], None] | None = None
                 ) -> Iterator[tuple[float, FloatArray, Frame | None]]:
    """The worker's steps from its inbox until the stop mark. A set ``stop`` (the caller
    was interrupted) or a dead caller raises :class:`KeyboardInterrupt`, which
    :func:`~lampsam.backend.slam.drive` turns into status ``"interrupted"``. Before each
    step the inbox is drained into ``backlog`` (so a catching-up backend sees what
    waits), ``index[0]`` is set to the step's index and ``at[0]`` to the process CPU
    clock; ``flush`` (send the estimates made so far) is called whenever nothing
    waits, before waiting for the caller, and at the stop mark; ``give`` (if any) is handed
    the step's advanced odometry just before the step is yielded
    (:meth:`~lampsam.backend.graph.GraphSlam.give_odometry`). The CPU spent here (flushes apart) adds to
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
                item = backlog.inbox.get(timeout=POLL_S)
            except queue.Empty:
                clocks.idle_s += time.perf_counter() - w0
                if parent is not None and not parent.is_alive():
                    raise KeyboardInterrupt("the tracking process died") from None
                continue
            clocks.idle_s += time.perf_counter() - w0
            backlog.append(item)
        item = backlog.pop()
        if item == STOP:
            flush()  # every step's estimate back before the final optimisation
            clocks.inbox_cpu_s += time.process_time() - c0
            return
        i, t, samples, packed, odometry = cast(_Step, item)
        index[0] = i
        frame = unpack_step_frame(packed)
        if give is not None:
            give(unpack_odometry(odometry))
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


def receive(inbox: Connection, timeout: float) -> object:
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


def mapping_worker(backend: str, odometry: OdometryConstants, config: SlamConfig,
                    start_pose: FloatArray, camera: CameraModel | None,
                    inbox: queue.Queue[object], outbox: Connection, stop: EventLike,
                    finish: bool, max_lag: int | None) -> None:
    """Worker process: ``("ready", 0)`` once the backend is built, then step it on each
    ``(i, t, samples, frame, odometry)`` and send back ``("steps", [(i, pose, keyframe, step CPU s),
    ...])``, batched: when the inbox is empty, at the stop mark and when
    :func:`reply_due`. After the stop mark (or ``stop`` set) ``("done", result or None,
    cpu_s, keyframes per update, clocks)``
    (:attr:`lampsam.backend.tracking.DecoupledTimes.update_sizes`,
    :class:`WorkerClocks`), the result being the backend's ``finish`` through
    :func:`~lampsam.backend.slam.drive` (same statuses and fallbacks as a run in one
    process); ``("error", text)`` if the backend cannot be built."""
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
    # a graph backend takes the odometry the caller's KeyframeMirror already composed
    give = be.give_odometry if isinstance(be, GraphSlam) else None
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
        yield from _inbox_steps(backlog, stop, at, index, flush, clocks, give)
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
