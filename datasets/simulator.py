"""Simulated ceiling-camera runs: ``lampsam simulate WORLD --out RUN``.

One shared clock: wheel odometry at ``simulation.odometry_rate_hz`` (30 Hz by
default) and an image at every k-th odometry sample (15 Hz). The robot follows
the world's waypoints (:func:`lampsam.datasets.motion.follow_waypoints`); the
logged wheel travel gets eq.-15 slip noise. Written (``docs/log-format.md``):
``rig.yaml``, ``odometry.csv``, ``groundtruth.tum`` (at every odometry time),
``landmarks.csv``, ``meta.yaml`` first, then ``images/`` + ``images.csv`` and
``truth/projections.csv`` frame by frame (flushed), so an interrupted run leaves
the finished frames readable; ``meta.yaml`` gets ``complete: true`` at the end.

Images are rendered by :class:`lampsam.datasets.render_ceiling.CeilingRenderer`
in a pool of worker processes; each frame's sensor noise comes from its own
generator seeded with ``(seed, frame)``, so the output does not depend on the
number of workers.
"""

from __future__ import annotations

import logging
import math
import multiprocessing as mp
import os
import time
from pathlib import Path
from typing import Any

import cv2
import numpy as np

import lampsam
from lampsam.arrays import FloatArray
from lampsam.datasets.ceiling_truth import occluders, project_landmarks
from lampsam.datasets.logrun import (
    META_FILE,
    PROJECTIONS_FILE,
    ImageWriter,
    LandmarkTable,
    OdometryLog,
    ProjectionTable,
    ProjectionWriter,
    Trajectory,
    write_meta,
    write_run,
)
from lampsam.datasets.motion import dead_reckoning, follow_waypoints, noisy_wheel_travel
from lampsam.datasets.render_ceiling import CeilingRenderer
from lampsam.datasets.tables import PNG_COMPRESSION, encode_png
from lampsam.datasets.world import World, load_world
from lampsam.datasets.world_landmarks import world_landmarks
from lampsam.errors import DatasetError

log = logging.getLogger(__name__)

# Per-process renderer state (built in-process, or by the pool initializer in each worker).
_STATE: dict[str, Any] = {}


def _init_state(world: World, seed: int, png_compression: int = PNG_COMPRESSION) -> None:
    """Build the renderer, landmarks and occluders once per process."""
    renderer = CeilingRenderer(world)
    _STATE.update(
        renderer=renderer,
        landmarks=world_landmarks(world),
        occluders=occluders(world),
        seed=seed,
        png_compression=png_compression,
    )


def _worker_init(world: World, seed: int, png_compression: int = PNG_COMPRESSION) -> None:
    """Pool initializer: one OpenCV thread per worker, then the state."""
    cv2.setNumThreads(1)
    if not _STATE:
        _init_state(world, seed, png_compression)


def render_frame(index: int, pose: FloatArray) -> tuple[bytes, ProjectionTable]:
    """Render one frame in the current process.

    Args:
        index: frame number (seeds the sensor noise with ``(seed, index)``).
        pose: (3,) true body pose.

    Returns:
        ``(png bytes, truth projections)``.
    """
    renderer: CeilingRenderer = _STATE["renderer"]
    rng = np.random.default_rng([int(_STATE["seed"]), int(index)])
    img = renderer.render(pose, rng)
    png = encode_png(img, int(_STATE.get("png_compression", PNG_COMPRESSION)),
                     f"frame {index}")
    truth = project_landmarks(
        renderer.camera, pose, _STATE["landmarks"], _STATE["occluders"], renderer.m_max
    )
    return png, truth


def _render_task(args: tuple[int, FloatArray]) -> tuple[int, bytes, ProjectionTable]:
    """Pool task: render frame ``i`` at ``pose``."""
    i, pose = args
    png, truth = render_frame(i, pose)
    return i, png, truth


def simulate_trajectory(
    world: World, seed: int, duration: float | None = None
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """True motion and noisy wheel odometry of a world's path.

    Args:
        world: the world (path, speed, rates, odometry model).
        seed: seeds the wheel-slip noise (``np.random.default_rng(seed)``).
        duration: seconds to simulate (default: the whole path).

    Returns:
        ``(t (N,), true poses (N, 3), true wheel (N, 2), noisy wheel (N, 2))``; wheel
        columns are ``(left, right)`` travel since the previous sample, m.

    Raises:
        DatasetError: the world has no path.
    """
    if len(world.waypoints) < 2:
        raise DatasetError(f"world {world.name!r} has no path (needs >= 2 waypoints)", world.source)
    odo = world.rig.odometry
    t, poses, wheel = follow_waypoints(
        world.waypoints,
        speed=world.speed,
        rate_hz=world.simulation.odometry_rate_hz,
        wheel_base=odo.wheel_base,
        start_heading=world.start_heading,
        duration=duration,
    )
    noisy = noisy_wheel_travel(wheel, odo.k_r, odo.k_l, np.random.default_rng(seed))
    return t, poses, wheel, noisy


def simulate_world(
    world: str | Path | World,
    out: Path,
    seed: int = 0,
    duration: float | None = None,
    workers: int | None = None,
    png_compression: int = PNG_COMPRESSION,
) -> Path:
    """Simulate a ceiling-camera run and write it as a logged run.

    Args:
        world: built-in world name (``lab``, ``corridor``), a world YAML path, or a
            loaded :class:`World`.
        out: run directory to write (created; existing files are overwritten).
        seed: random seed (odometry noise; image noise per frame with ``(seed, frame)``).
        duration: seconds to simulate (default: the whole path).
        workers: rendering processes (default: ``min(2, cpu_count)``; 1 = in-process).
        png_compression: zlib level 0-9 of the images (default 0: stored, the
            fastest to read back; :data:`lampsam.datasets.tables.PNG_COMPRESSION`).

    Returns:
        The run directory.

    Raises:
        DatasetError: unknown/invalid world, no path, a negative duration, or a
            PNG level outside 0-9.
    """
    if not 0 <= png_compression <= 9:
        raise DatasetError(f"PNG compression must be 0-9, got {png_compression}")
    w = world if isinstance(world, World) else load_world(world)
    if duration is not None and not duration > 0:
        raise DatasetError(f"duration must be positive, got {duration}")
    out = Path(out)
    t0 = time.perf_counter()
    t, poses, _, noisy = simulate_trajectory(w, seed, duration)
    step = int(round(w.simulation.odometry_rate_hz / w.simulation.image_rate_hz))
    frame_idx = np.arange(0, len(t), step)
    rig = w.rig
    dr = dead_reckoning(noisy[1:], rig.odometry.wheel_base, poses[0])
    drift = np.hypot(*(dr[:, :2] - poses[1:, :2]).T) if len(dr) else np.zeros(1)
    landmarks: LandmarkTable = world_landmarks(w)
    meta: dict[str, Any] = {
        "generator": "lampsam.datasets.simulator",
        "lampsam_version": lampsam.__version__,
        "world": w.name,
        "world_file": str(w.source) if w.source else None,
        "seed": int(seed),
        "duration": float(t[-1]),
        "odometry_rate_hz": float(w.simulation.odometry_rate_hz),
        "image_rate_hz": float(w.simulation.image_rate_hz),
        "n_odometry": len(t),
        "n_images": len(frame_idx),
        "path_length_m": float(np.sum(np.abs(0.5 * (noisy[:, 0] + noisy[:, 1])))),
        "dead_reckoning_final_error_m": float(drift[-1]),
        "dead_reckoning_max_error_m": float(drift.max()),
        "complete": False,
    }
    write_run(
        out,
        rig,
        OdometryLog(t=t, d_left=noisy[:, 0], d_right=noisy[:, 1]),
        groundtruth=Trajectory(t=t, poses=poses),
        landmarks=landmarks,
        meta=meta,
    )
    log.info(
        "%s: %.1f s, %d odometry samples, %d images, dead-reckoning drift %.2f m (max %.2f m)",
        w.name, t[-1], len(t), len(frame_idx), drift[-1], drift.max(),
    )  # fmt: skip
    n_workers = workers if workers is not None else min(2, os.cpu_count() or 1)
    tasks = [(k, poses[i]) for k, i in enumerate(frame_idx)]
    images = ImageWriter(out)
    proj = ProjectionWriter(out / PROJECTIONS_FILE)
    t_render = time.perf_counter()
    try:
        if n_workers <= 1:
            _init_state(w, seed, png_compression)
            results = map(_render_task, tasks)
            _consume(results, t, frame_idx, images, proj)
        else:
            # "spawn", not "fork": forking a process whose OpenCV thread pool (or any
            # other thread) holds a lock can deadlock the child. Each worker builds its
            # own renderer (about a second).
            _STATE.clear()
            ctx = mp.get_context("spawn")
            with ctx.Pool(n_workers, initializer=_worker_init,
                          initargs=(w, seed, png_compression)) as pool:
                _consume(pool.imap(_render_task, tasks, chunksize=4), t, frame_idx, images, proj)
    finally:
        images.close()
        proj.close()
        _STATE.clear()
    render_s = time.perf_counter() - t_render
    meta.update(
        complete=True,
        render_seconds=round(render_s, 2),
        render_workers=int(n_workers),
        total_seconds=round(time.perf_counter() - t0, 2),
    )
    write_meta(out / META_FILE, meta)
    log.info(
        "rendered %d frames in %.1f s (%.1f ms/frame, %d workers) -> %s",
        len(frame_idx), render_s, 1000 * render_s / max(len(frame_idx), 1), n_workers, out,
    )  # fmt: skip
    return out


def _consume(
    results: Any, t: FloatArray, frame_idx: np.ndarray, images: ImageWriter, proj: ProjectionWriter
) -> None:
    """Write rendered frames in order as they arrive."""
    n = len(frame_idx)
    report = max(1, n // 10)
    for k, png, truth in results:
        ti = float(t[frame_idx[k]])
        images.write_encoded(ti, png)
        proj.write_frame(k, ti, truth)
        if (k + 1) % report == 0:
            log.info("frame %d/%d", k + 1, n)


def dead_reckoning_drift(
    world: str | Path | World, seed: int, duration: float | None = None
) -> float:
    """Final position error (m) of eq.-13 dead reckoning on a simulated run's noisy odometry.

    Args:
        world: world name, YAML path or :class:`World`.
        seed: odometry-noise seed.
        duration: seconds (default: the whole path).
    """
    w = world if isinstance(world, World) else load_world(world)
    _, poses, _, noisy = simulate_trajectory(w, seed, duration)
    dr = dead_reckoning(noisy[1:], w.rig.odometry.wheel_base, poses[0])
    return float(math.hypot(*(dr[-1, :2] - poses[-1, :2])))
