"""Frontend and estimator overlapped: ceiling frames made ahead in a worker.

A robot's camera and frontend run while the estimator works on the previous
frame. :func:`frame_source` gives the frames of a logged run in order, made
either in the calling thread (``"sequential"``: each frame when the estimator
asks for it, as :func:`lampsam.frontend.pipeline.iter_run`) or ahead of time by
a worker (``"process"``: a child process; ``"thread"``: a thread of this
process) that feeds a bounded queue of ``depth`` frames. The frames are the
same in every mode (the same :func:`~lampsam.frontend.pipeline.process_image`
on the same images; a process worker's frames come back through pickle, which
keeps every float bit for bit), so an estimator fed from either gives the same
trajectory. With a worker, the frontend's CPU time moves off the estimator's
thread: on a machine with a free second core the wall clock of a run drops
towards the larger of the two stages; on one core nothing is gained.

In ``"sequential"`` mode the frames are *lazy* (:class:`LazyFrame`, unless
``lazy=False``): the image is read and processed when the frame's lamps or corners
are first asked for. A smoother reads only the frames that can become keyframes
(:func:`lampsam.backend.keyframes.keyframe_observations`), so the others' images are
never processed; a consumer that reads every frame (the EKF, a live viewer) gets
every frame made, as before. The observations are the same either way.

Each source records, per frame, when it *arrived* (the image was available:
with ``pace`` the replay clock ``start + (t - t0) / pace``, else the moment the
source began reading it) and when its frame was *ready*, both
``time.perf_counter`` seconds (``CLOCK_MONOTONIC``, shared by the processes of
one machine), so a caller can time arrival -> pose estimate (latency).
"""

from __future__ import annotations

import logging
import multiprocessing as mp
import queue
import signal
import threading
import time
from collections.abc import Callable, Generator, Iterator
from dataclasses import dataclass, field
from typing import Literal, cast

import numpy as np

from lampsam.datasets.logrun import CameraModel
from lampsam.datasets.tables import ImageIndex
from lampsam.errors import FrontendError, LampsamError
from lampsam.frontend.measurements import CeilingFrame, CornerObservation, LampObservation
from lampsam.frontend.pipeline import FrontendConfig, process_indexed_image

log = logging.getLogger(__name__)

Mode = Literal["sequential", "thread", "process"]
MODES: tuple[Mode, ...] = ("sequential", "thread", "process")
_POLL_S = 0.5  # how often a waiting consumer checks that the worker is alive


@dataclass
class FrameTimes:
    """Per-frame clock readings of a source (``time.perf_counter`` s), in frame order.

    Attributes:
        arrival: when each image was available (see the module docstring).
        ready: when its frame was made.
        worker_cpu_s: CPU time for load + frontend of every frame, s: a process
            worker's whole CPU (with pickling the frames), a thread worker's
            thread, or (sequential) the caller's thread while making frames.
    """

    arrival: list[float] = field(default_factory=list)
    ready: list[float] = field(default_factory=list)
    worker_cpu_s: float = 0.0


@dataclass(frozen=True)
class PackedCorners:
    """A frame's corners as stacked arrays (row ``i`` is corner ``i``)."""

    m: np.ndarray  # (N, 2)
    cov_m: np.ndarray  # (N, 2, 2)
    pixel: np.ndarray  # (N, 2)
    patch: np.ndarray  # (N, P, P)
    score: list[float]
    landmark_id: list[int | None]


PackedFrame = tuple[float, int, tuple[LampObservation, ...],
                    PackedCorners | tuple[CornerObservation, ...]]


def pack_frame(frame: CeilingFrame) -> PackedFrame:
    """A frame in a form that pickles ~4x faster: the corners' arrays stacked.

    A frame's ~44 corners hold ~180 small arrays (``m``, ``cov_m``, ``pixel``,
    ``patch``); pickling them one by one is most of the cost of sending a frame
    between processes. Stacked, they are four arrays; :func:`unpack_frame` gives
    back corners whose arrays are rows of those (same values, bit for bit).
    Corners of unequal array shapes are sent as they are.
    """
    cs = frame.corners
    if cs and len({(c.m.shape, c.cov_m.shape, c.pixel.shape, c.patch.shape, c.patch.dtype)
                   for c in cs}) == 1:
        packed: PackedCorners | tuple[CornerObservation, ...] = PackedCorners(
            np.stack([c.m for c in cs]), np.stack([c.cov_m for c in cs]),
            np.stack([c.pixel for c in cs]), np.stack([c.patch for c in cs]),
            [c.score for c in cs], [c.landmark_id for c in cs])
    else:
        packed = cs
    return frame.t, frame.index, frame.lamps, packed


def unpack_frame(packed: PackedFrame) -> CeilingFrame:
    """The frame :func:`pack_frame` packed."""
    t, index, lamps, cs = packed
    if isinstance(cs, PackedCorners):
        corners = tuple(CornerObservation(cs.m[i], cs.cov_m[i], cs.pixel[i], cs.patch[i],
                                          cs.score[i], cs.landmark_id[i])
                        for i in range(len(cs.score)))
    else:
        corners = cs
    return CeilingFrame(t, index, lamps, corners)


class LazyFrame(CeilingFrame):
    """A ceiling frame whose image is read and processed on first access.

    ``t`` and ``index`` are known at once; :attr:`lamps` and :attr:`corners` (and
    :meth:`resolve`) run ``make`` once and keep its frame. Pickled, it is the
    plain :class:`CeilingFrame` it resolves to.

    Args:
        t: time stamp, s; index: image index in the run.
        make: makes the frame (:func:`~lampsam.frontend.pipeline.process_indexed_image`: image load + frontend); may raise
            :class:`~lampsam.errors.FrontendError`, which then surfaces at the access.
    """

    _make: Callable[[], CeilingFrame] | None
    _frame: CeilingFrame | None

    def __init__(self, t: float, index: int, make: Callable[[], CeilingFrame]) -> None:
        object.__setattr__(self, "t", float(t))
        object.__setattr__(self, "index", int(index))
        object.__setattr__(self, "_make", make)
        object.__setattr__(self, "_frame", None)

    def resolve(self) -> CeilingFrame:
        """The frame, made on the first call."""
        frame = self._frame
        if frame is None:
            assert self._make is not None
            frame = self._make()
            object.__setattr__(self, "_frame", frame)
            object.__setattr__(self, "_make", None)
        return frame

    @property
    def loaded(self) -> bool:
        """Whether the frame was made (its image read and processed)."""
        return self._frame is not None

    @property  # type: ignore[override]
    def lamps(self) -> tuple[LampObservation, ...]:
        """The lamp observations (the frame made on first access)."""
        return self.resolve().lamps

    @property  # type: ignore[override]
    def corners(self) -> tuple[CornerObservation, ...]:
        """The corner observations (the frame made on first access)."""
        return self.resolve().corners

    def __reduce__(self) -> tuple[type[CeilingFrame], tuple[float, int, tuple[LampObservation, ...],
                                                            tuple[CornerObservation, ...]]]:
        """Pickled as the plain frame it resolves to."""
        frame = self.resolve()
        return CeilingFrame, (frame.t, frame.index, frame.lamps, frame.corners)


def _arrive(t: float, t0: float, start: float, pace: float | None) -> float:
    """The arrival time (``time.perf_counter`` clock) of a frame stamped ``t`` s: with
    ``pace`` (replay speed, x real time) ``start + (t - t0) / pace``, slept until then;
    without it, now."""
    if pace is None:
        return time.perf_counter()
    arrival = start + (t - t0) / pace
    wait = arrival - time.perf_counter()
    if wait > 0:
        time.sleep(wait)
    return arrival


def _lazy(images: ImageIndex, camera: CameraModel, config: FrontendConfig | None,
          pace: float | None, start: float | None, times: FrameTimes
          ) -> Iterator[LazyFrame]:
    """:class:`LazyFrame` s of the images in order (paced as :func:`_produce`); a frame
    made records its ready time and its CPU (this thread's) in ``times``."""
    t0 = float(images.t[0]) if len(images) else 0.0
    start = time.perf_counter() if start is None else start

    def maker(i: int, slot: int) -> Callable[[], CeilingFrame]:
        def make() -> CeilingFrame:
            c0 = time.thread_time()
            frame = process_indexed_image(images, i, camera, config)
            times.ready[slot] = time.perf_counter()
            times.worker_cpu_s += time.thread_time() - c0
            return frame
        return make

    for i in range(len(images)):
        t = float(images.t[i])
        arrival = _arrive(t, t0, start, pace)
        times.arrival.append(arrival)
        times.ready.append(time.perf_counter())
        yield LazyFrame(t, i, maker(i, len(times.ready) - 1))


def _produce(images: ImageIndex, camera: CameraModel, config: FrontendConfig | None,
             pace: float | None, start: float | None
             ) -> Iterator[tuple[CeilingFrame, float, float, float]]:
    """Load and process the images in order: ``(frame, arrival, ready, cpu_s)``
    (``cpu_s``: this thread's CPU time for the load and the frontend).

    With ``pace`` (replay speed, x real time) image ``i`` is not read before
    ``start + (t_i - t_0) / pace`` (``start`` None: now, when the source is up);
    without it, as fast as asked.
    """
    t0 = float(images.t[0]) if len(images) else 0.0
    start = time.perf_counter() if start is None else start
    for i in range(len(images)):
        t = float(images.t[i])
        arrival = _arrive(t, t0, start, pace)
        c0 = time.thread_time()
        frame = process_indexed_image(images, i, camera, config)
        yield frame, arrival, time.perf_counter(), time.thread_time() - c0


def _put(out: queue.Queue[object], item: object, stop: threading.Event) -> bool:
    """Put ``item`` once there is room; False if ``stop`` was set (or, in a worker
    process, the parent died) first."""
    parent = mp.parent_process()
    while not stop.is_set():
        try:
            out.put(item, timeout=_POLL_S)
            return True
        except queue.Full:
            if parent is not None and not parent.is_alive():
                return False
    return False


def _worker(images: ImageIndex, camera: CameraModel, config: FrontendConfig | None,
            pace: float | None, start: float | None, out: queue.Queue[object],
            stop: threading.Event, cv_threads: int | None, in_process: bool) -> None:
    """Worker body (thread or process): frames into ``out``, then ``("done", cpu_s)``
    or ``("error", message, is_lampsam_error)``; returns early when ``stop`` is set."""
    if in_process:
        # Ctrl-C reaches the whole process group: the parent stops the worker itself
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        if cv_threads is not None:
            import cv2

            cv2.setNumThreads(cv_threads)
        clock = time.process_time  # the queue's feeder thread pickles: count it
    else:
        clock = time.thread_time
    c0 = clock()
    try:
        for frame, arrival, ready, _ in _produce(images, camera, config, pace, start):
            item = (pack_frame(frame) if in_process else frame, arrival, ready)
            if not _put(out, item, stop):
                break
        else:
            _put(out, ("done", clock() - c0), stop)
    except Exception as exc:  # sent to the consumer, which raises it
        known = isinstance(exc, LampsamError)
        text = str(exc) if known else f"{type(exc).__name__}: {exc}"
        _put(out, ("error", text, known), stop)
    if in_process and stop.is_set():
        out.cancel_join_thread()  # type: ignore[attr-defined]  # do not wait on unread frames


def frame_source(images: ImageIndex, camera: CameraModel, config: FrontendConfig | None = None,
                 mode: Mode = "process", depth: int = 8, pace: float | None = None,
                 start: float | None = None, times: FrameTimes | None = None,
                 cv_threads: int | None = 1, lazy: bool = True
                 ) -> Generator[CeilingFrame, None, None]:
    """The frames of a run's images, in order, made now or ahead by a worker.

    Args:
        images: the run's image index (``run.images``).
        camera: the run's camera (``run.rig.camera``).
        config: frontend settings (defaults if None).
        mode: ``"sequential"`` (in the caller's thread when asked), ``"thread"`` or
            ``"process"`` (a worker making up to ``depth`` frames ahead).
        depth: the queue's size, frames (>= 1); bounds the memory and how far the
            worker runs ahead.
        pace: replay speed (x real time) at which images become available; None:
            as soon as read.
        start: ``time.perf_counter()`` at which the first image arrives when paced
            (default: when the source is up, i.e. after a worker process started).
        times: filled with each frame's arrival / ready clock readings.
        cv_threads: OpenCV threads in a process worker (None leaves OpenCV's
            default); a thread worker shares the caller's setting.
        lazy: ``"sequential"``: give :class:`LazyFrame` s (each image read and
            processed when its frame is first read; a bad image raises then); False:
            every frame made before it is given.

    Yields:
        One :class:`CeilingFrame` per image, in time order. Closing the generator
        (or dropping it) stops the worker.

    Raises:
        FrontendError: an image is unusable (named by file), raised when its
            frame is due.
        LampsamError: the worker process died without saying why.
        ValueError: an unknown mode or ``depth < 1``.
    """
    if mode not in MODES:
        raise ValueError(f"unknown pipeline mode {mode!r}; choose from {', '.join(MODES)}")
    if depth < 1:
        raise ValueError(f"pipeline depth must be >= 1, got {depth}")
    times = times if times is not None else FrameTimes()
    if mode == "sequential" and lazy:
        yield from _lazy(images, camera, config, pace, start, times)
        return
    if mode == "sequential":
        for frame, arrival, ready, cpu in _produce(images, camera, config, pace, start):
            times.arrival.append(arrival)
            times.ready.append(ready)
            times.worker_cpu_s += cpu
            yield frame
        return
    yield from _from_worker(images, camera, config, mode, depth, pace, start, times, cv_threads)


def _from_worker(images: ImageIndex, camera: CameraModel, config: FrontendConfig | None,
                 mode: Mode, depth: int, pace: float | None, start: float | None,
                 times: FrameTimes,
                 cv_threads: int | None) -> Generator[CeilingFrame, None, None]:
    """Start a worker, yield its frames in order, stop it however the caller ends."""
    if mode == "process":
        ctx = mp.get_context("spawn")  # no fork of a parent holding GTSAM / OpenCV threads
        out: queue.Queue[object] = ctx.Queue(depth)  # type: ignore[assignment]
        stop: threading.Event = ctx.Event()  # type: ignore[assignment]
        worker: threading.Thread | mp.process.BaseProcess = ctx.Process(
            target=_worker, args=(images, camera, config, pace, start, out, stop, cv_threads, True),
            name="lampsam-frontend", daemon=True)
    else:
        out = queue.Queue(depth)
        stop = threading.Event()
        worker = threading.Thread(
            target=_worker, args=(images, camera, config, pace, start, out, stop, None, False),
            name="lampsam-frontend", daemon=True)
    worker.start()
    try:
        while True:
            try:
                item = out.get(timeout=_POLL_S)
            except queue.Empty:
                if not worker.is_alive():
                    raise LampsamError(f"the frontend worker ({mode}) stopped without a word "
                                       f"after {len(times.ready)} frames") from None
                continue
            if isinstance(item, tuple) and isinstance(item[0], str):
                if item[0] == "done":
                    times.worker_cpu_s = float(item[1])
                    return
                message, known = str(item[1]), bool(item[2])
                if known:
                    raise FrontendError(message)
                raise LampsamError(f"frontend worker failed: {message}")
            got = cast(tuple[object, float, float], item)
            frame = (unpack_frame(cast(PackedFrame, got[0])) if mode == "process"
                     else cast(CeilingFrame, got[0]))
            times.arrival.append(got[1])
            times.ready.append(got[2])
            yield frame
    finally:
        stop.set()
        if isinstance(worker, threading.Thread):
            worker.join(timeout=5.0)
        else:
            worker.join(timeout=5.0)
            if worker.is_alive():
                log.warning("frontend worker still running after 5 s: terminating it")
                worker.terminate()
                worker.join(timeout=1.0)
