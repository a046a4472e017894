"""Run a SLAM backend over a logged run, and write its results.

:func:`run_slam` reads a run (``lampsam.datasets.logrun.read_run``), makes the
measurement frames (ceiling images through the frontend, the simulator's truth
projections, or the run's range-bearing log), merges them with the wheel odometry
into time-ordered steps, feeds a backend and writes:

- ``OUT/trajectory.tum``: the estimated pose at every step (TUM, the run's clock);
- ``OUT/landmarks.csv``: ``id, type, x, y, z, phi, n_obs``, the covariance
  entries (``cov_xx, cov_xy, cov_xz, cov_yy, cov_yz, cov_zz, var_phi``; NaN where a
  landmark kind has no such coordinate) and ``flag`` (``seen_once`` for landmarks
  seen fewer than ``association.min_observations`` times, kept unless
  ``association.prune_once_seen``);
- ``OUT/summary.json``: counts, per-step time (median / p95 / max), total time and,
  when the run has ground truth, position and heading errors (RMS, max) with no
  alignment (the start pose is known).

If the run is interrupted (SIGINT or SIGTERM, see :mod:`lampsam.interrupt`: the
current step finishes) or a step fails, the steps finished so far are still written
(status ``"interrupted"`` / ``"failed: ..."``). If the final optimisation fails or
is interrupted, the online per-step estimates are written under the name of the
estimator that made them (batch: ``isam2`` or ``odometry``) with status
``"final optimisation failed: ..."``. Files are written atomically.
"""

from __future__ import annotations

import csv
import logging
import math
import time
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import Any

import numpy as np

from lampsam.arrays import FloatArray
from lampsam.backend.ceiling import CeilingModel
from lampsam.backend.ceiling_graph import CeilingHandler
from lampsam.backend.config import SlamConfig
from lampsam.backend.ekf import EkfSlam
from lampsam.backend.graph import BatchSlam, Isam2Slam
from lampsam.backend.interface import Frame, SlamBackend, SlamResult, StepEstimate, empty_result
from lampsam.backend.odometry import OdometryConstants
from lampsam.datasets.logrun import (
    CameraModel,
    LoggedRun,
    OdometryLog,
    RangeBearingLog,
    Trajectory,
    read_run,
    write_tum,
)
from lampsam.datasets.odometry import Pose2OdometryLog, Pose2OdometryModel
from lampsam.errors import EstimationError, LampsamError
from lampsam.factors.geometry import wrap_angle, wrap_axis
from lampsam.frontend.measurements import (
    CeilingFrame,
    CornerObservation,
    LampObservation,
    RangeBearingFrame,
    RangeBearingObservation,
)
from lampsam.interrupt import interruptible
from lampsam.observe import emit
from lampsam.safe_io import atomic_path, write_json_atomic

log = logging.getLogger(__name__)

BACKENDS = ("ekf", "isam2", "batch")
#: Backends that read a frame only when it can become a keyframe
#: (:func:`lampsam.backend.keyframes.keyframe_observations`): fed lazy frames.
LAZY_BACKENDS = ("isam2", "batch")
FRAME_SOURCES = ("auto", "images", "truth", "rangebearing")


def make_backend(name: str, odometry: OdometryConstants, config: SlamConfig, start_pose: FloatArray,
                 camera: CameraModel | None = None) -> SlamBackend:
    """Construct a backend by name.

    Args:
        name: ``"ekf"``, ``"isam2"`` or ``"batch"``.
        odometry: the odometry model's constants: ``run.rig.odometry`` (wheel) or a
            :class:`~lampsam.datasets.odometry.Pose2OdometryModel`.
        config: the SLAM config.
        start_pose: (3,) known start pose ``world_T_body``, m and rad.
        camera: the upward camera for ceiling frames (builds the ceiling observation
            model and graph handler), or None for range-bearing frames.

    Raises:
        EstimationError: an unknown backend name.
    """
    model = None
    handler: CeilingHandler | None = None
    if camera is not None:
        model = CeilingModel.from_camera(camera)
        if name != "ekf":
            handler = CeilingHandler(model)
    if name == "ekf":
        return EkfSlam(odometry, config, start_pose, model)
    if name == "isam2":
        return Isam2Slam(odometry, config, start_pose, model, handler)
    if name == "batch":
        return BatchSlam(odometry, config, start_pose, model, handler)
    raise EstimationError(f"unknown backend {name!r}; choose from {', '.join(BACKENDS)}")


def frames_from_range_bearing(rb: RangeBearingLog) -> list[RangeBearingFrame]:
    """Group a range-bearing log into frames (one per distinct time stamp).

    Args:
        rb: the log; negative ids mean "unknown" (``landmark_id = None``).

    Returns:
        Frames in time order.
    """
    frames: list[RangeBearingFrame] = []
    if len(rb) == 0:
        return frames
    starts = np.flatnonzero(np.r_[True, np.diff(rb.t) > 0])
    ends = np.r_[starts[1:], len(rb)]
    for a, b in zip(starts, ends, strict=True):
        obs = tuple(
            RangeBearingObservation(float(rb.range[i]), float(wrap_angle(float(rb.bearing[i]))),
                                    int(rb.landmark_id[i]) if rb.landmark_id[i] >= 0 else None)
            for i in range(a, b))
        frames.append(RangeBearingFrame(float(rb.t[a]), obs))
    return frames


def frames_from_projections(run: LoggedRun, sigma_px: float, rng: np.random.Generator,
                            known_ids: bool = True) -> list[CeilingFrame]:
    """Ceiling frames from the simulator's truth projections (no image processing).

    Each visible projection becomes an observation: the pixel plus Gaussian noise
    (``sigma_px``) mapped to normalised coordinates with the run's camera; lamp
    axes from ``angle_px`` are mapped by projecting a short segment, plus 0.02 rad
    noise. Lamps that are
    not fully visible are skipped (as the frontend drops border blobs). Corners get
    no patch (NCC cannot be used: known association or gate alone).

    Args:
        run: a run with ``truth/projections.csv``.
        sigma_px: pixel noise standard deviation, px.
        rng: the random generator for the noise.
        known_ids: attach the true landmark ids.

    Returns:
        One frame per image index, in time order.

    Raises:
        EstimationError: the run has no truth projections or no images.
    """
    proj = run.projections
    if proj is None or run.images is None:
        raise EstimationError(f"{run.path}: no truth/projections.csv or images.csv")
    cam = run.rig.camera
    frames = []
    px_all = proj.pixel
    m_all = cam.normalized_from_pixels(px_all + rng.normal(0.0, sigma_px, px_all.shape))
    # d m / d pixel by finite differences, all rows at once: cov_m = sigma^2 J J^T
    h = 1e-3
    m0 = cam.normalized_from_pixels(px_all)
    j_col = (cam.normalized_from_pixels(px_all + [h, 0.0]) - m0) / h
    j_row = (cam.normalized_from_pixels(px_all + [0.0, h]) - m0) / h
    jac = np.stack([j_col, j_row], axis=2)  # (P, 2, 2)
    cov_all = sigma_px**2 * jac @ jac.transpose(0, 2, 1) + 1e-12 * np.eye(2)
    # lamp axes: the image segment along angle_px mapped to (u, v)
    ang = np.nan_to_num(proj.angle_px)
    d = 3.0 * np.column_stack([np.cos(ang), np.sin(ang)])
    seg = cam.normalized_from_pixels(px_all + d) - cam.normalized_from_pixels(px_all - d)
    axis_all = np.arctan2(seg[:, 1], seg[:, 0])
    sigma_axis = 0.02
    axis_noise = rng.normal(0.0, sigma_axis, len(axis_all))
    for i in range(len(run.images)):
        lamps, corners = [], []
        for r in proj.rows_of_frame(i):
            if not proj.visible[r]:
                continue
            lid = int(proj.ids[r]) if known_ids else None
            if proj.types[r].startswith("lamp"):
                if not proj.fully_visible[r]:
                    continue
                axis = None
                var_axis = math.inf
                if math.isfinite(proj.angle_px[r]):
                    axis = float(wrap_axis(float(axis_all[r] + axis_noise[r])))
                    var_axis = sigma_axis**2
                lamps.append(LampObservation(m=m_all[r], cov_m=cov_all[r], axis=axis,
                                             var_axis=var_axis,
                                             ratio=2.0 if axis is not None else 1.0, area_px=100.0,
                                             pixel=px_all[r], landmark_id=lid))
            else:
                corners.append(CornerObservation(m=m_all[r], cov_m=cov_all[r], pixel=px_all[r],
                                                 patch=np.zeros((1, 1), np.float32), score=1.0,
                                                 landmark_id=lid))
        frames.append(CeilingFrame(float(run.images.t[i]), i, tuple(lamps), tuple(corners)))
    return frames


def iter_steps(odometry: OdometryLog | Pose2OdometryLog, frames: Iterable[Frame], max_dt: float = 0.5
               ) -> Iterator[tuple[float, FloatArray, Frame | None]]:
    """Merge odometry and frames into time-ordered steps.

    A step is made at every frame time, with the odometry samples stamped after the
    previous step and up to the frame; between frames a frame-less step is made at
    least every ``max_dt`` seconds of odometry; the last odometry makes a final step.

    Args:
        odometry: wheel odometry (``t``, ``d_left``, ``d_right``) or Pose2 increments.
        frames: frames in time order.
        max_dt: longest interval without a step, s.

    Yields:
        ``(t, samples (K, m), frame or None)``: wheel travel ``(d_left, d_right)``
        (m = 2) or Pose2 increments (m = 12, :meth:`Pose2OdometryLog.samples`).

    Raises:
        EstimationError: frames going back in time.
    """
    t_odo = odometry.t
    wheel = (odometry.samples() if isinstance(odometry, Pose2OdometryLog)
             else np.column_stack([odometry.d_left, odometry.d_right]))
    n = len(t_odo)
    i = 0
    last_t = float(t_odo[0]) if n else -math.inf

    def ticks(j: int) -> Iterator[tuple[float, FloatArray, Frame | None]]:
        nonlocal i, last_t
        for k in range(i, j):
            if t_odo[k] - last_t >= max_dt:
                yield float(t_odo[k]), wheel[i : k + 1], None
                last_t = float(t_odo[k])
                i = k + 1

    prev_frame_t = -math.inf
    for frame in frames:
        if frame.t < prev_frame_t:
            raise EstimationError(
                f"frame at t={frame.t:.3f} s goes back in time (previous {prev_frame_t:.3f})")
        prev_frame_t = frame.t
        j = int(np.searchsorted(t_odo, frame.t, side="right"))
        yield from ticks(j)
        yield float(frame.t), wheel[i:j], frame
        last_t = max(last_t, float(frame.t))
        i = max(i, j)
    yield from ticks(n)
    if i < n:
        yield float(t_odo[-1]), wheel[i:n], None


def start_pose_of(run: LoggedRun) -> FloatArray:
    """The known start pose: ground truth at the first odometry time, else the origin."""
    if run.groundtruth is not None and len(run.groundtruth):
        return run.groundtruth.interpolate(np.array([run.odometry.t[0]]))[0]
    log.warning("%s: no ground truth; the start pose is taken as the origin", run.path)
    return np.zeros(3)


def make_frames(run: LoggedRun, source: str, rng_seed: int = 0, sigma_px: float = 0.5,
                frontend: str = "sequential", lazy: bool = False
                ) -> tuple[list[Frame] | Iterable[Frame], bool]:
    """The run's measurement frames.

    Args:
        run: the run.
        source: ``"auto"`` (range-bearing log if present, else images), ``"images"``
            (frontend), ``"truth"`` (simulator projections), ``"rangebearing"``.
        rng_seed: seed of the pixel noise for ``"truth"``.
        sigma_px: pixel noise for ``"truth"``.
        frontend: where the frontend runs for ``"images"``: ``"sequential"`` (when
            each frame is due) or ahead in a ``"thread"`` / ``"process"``
            (:func:`lampsam.backend.pipelined.frame_source`; the same frames).
        lazy: ``"images"`` with the ``"sequential"`` frontend: lazy frames
            (:class:`~lampsam.backend.pipelined.LazyFrame`: each image read and
            processed when the consumer first reads the frame, so a smoother's
            frames between keyframes are never made; a bad image raises then).

    Returns:
        ``(frames, is_ceiling)``.

    Raises:
        EstimationError: the run has neither images nor range-bearing measurements,
            or the requested source is absent.
    """
    if source not in FRAME_SOURCES:
        raise EstimationError(f"unknown frame source {source!r}; choose from {FRAME_SOURCES}")
    if source == "auto":
        if run.range_bearing is not None:
            source = "rangebearing"
        elif run.images is not None:
            source = "images"
        else:
            raise EstimationError(f"{run.path}: the run has no images and no range-bearing "
                                  "measurements: nothing to do SLAM with")
    if source == "rangebearing":
        if run.range_bearing is None:
            raise EstimationError(f"{run.path}: no rangebearing.csv")
        return frames_from_range_bearing(run.range_bearing), False
    if run.images is None or len(run.images) == 0:
        raise EstimationError(f"{run.path}: the run has no images")
    if source == "truth":
        return frames_from_projections(run, sigma_px, np.random.default_rng(rng_seed)), True
    if frontend != "sequential" or lazy:
        from lampsam.backend.pipelined import frame_source

        return frame_source(run.images, run.rig.camera, mode=frontend,  # type: ignore[arg-type]
                            lazy=lazy), True
    from lampsam.frontend.pipeline import iter_run

    return iter_run(run), True


def drive(backend: SlamBackend, steps: Iterable[tuple[float, FloatArray, Frame | None]]
          ) -> SlamResult:
    """Feed steps to a backend; on interruption or failure return what is finished.

    Args:
        backend: the backend.
        steps: ``(t, wheel, frame)`` in time order.

    Returns:
        The result; its status says ``"interrupted"`` or ``"failed: <reason>"`` when
        the run did not finish (the failure is also logged).
    """
    status = "ok"
    t_step: float | None = None
    online: list[StepEstimate] = []
    log.info("%s: stepping through the run", backend.name)
    try:
        for t, wheel, frame in interruptible(steps):
            t_step = t
            estimate = backend.step(t, wheel, frame)
            online.append(estimate)
            if len(online) == 1:  # an observable state: a stop from here on keeps a step
                log.info("%s: first step done (t=%.3f s)", backend.name, t)
            emit("slam.step", t=t, frame=frame, estimate=estimate, backend=backend)
    except KeyboardInterrupt as exc:  # SIGINT or SIGTERM (lampsam.interrupt), between steps
        status = "interrupted"
        log.warning("interrupted (%s): writing the %d steps finished so far",
                    exc or "KeyboardInterrupt", len(online))
    except LampsamError as exc:  # estimation failure, or bad input met mid-run (names the file)
        status = f"failed: {exc}"
        log.error("%s", exc)
    except Exception as exc:  # a defect: keep the finished steps, say where it happened
        where = f" at t={t_step:.3f} s" if t_step is not None else ""
        status = f"failed{where}: {type(exc).__name__}: {exc}"
        log.error("step%s failed: %s: %s (run with -vv for the traceback); "
                  "the steps finished so far are kept", where, type(exc).__name__, exc)
        log.debug("traceback", exc_info=True)
    try:
        result = backend.finish(status)
        emit("slam.finish", result=result)
        return result
    except (KeyboardInterrupt, Exception) as exc:  # keep the online estimate, say what it is
        reason = "interrupted" if isinstance(exc, KeyboardInterrupt) else f"{type(exc).__name__}: {exc}"
        source = online_source(backend)
        log.error("final optimisation failed (%s): writing the online %s estimate of %d steps",
                  reason, source, len(online))
        log.debug("traceback", exc_info=True)
        return online_result(source, online, f"final optimisation failed: {reason}")


def online_source(backend: SlamBackend) -> str:
    """The estimator behind a backend's per-step estimates (batch: its online pass)."""
    if isinstance(backend, BatchSlam):
        return "isam2" if backend.online else "odometry"
    return backend.name


def online_result(source: str, online: list[StepEstimate], status: str) -> SlamResult:
    """A result made of the per-step (online) estimates alone: no map, labelled ``source``.

    Used when the final optimisation fails or is interrupted: the steps are kept,
    as estimated online, under the name of the estimator that produced them.
    """
    if not online:
        return empty_result(source, status)
    return SlamResult(
        backend=source,
        times=np.array([e.t for e in online], float),
        poses=np.array([e.pose for e in online], float),
        pose_covs=np.array([e.cov for e in online], float),
        landmarks=[],
        step_times_s=np.array([e.time_s for e in online], float),
        keyframes=np.array([e.keyframe for e in online], bool),
        status=status,
    )


def pose2_model_for(run: LoggedRun | None, config: SlamConfig) -> Pose2OdometryModel:
    """The Pose2 odometry noise model of a run: ``rig.yaml``'s ``pose2_odometry``
    section if it has one (it describes the robot), else the config's."""
    if run is not None and run.rig.pose2_odometry is not None:
        return run.rig.pose2_odometry
    return config.pose2_odometry


def run_slam(run_dir: str | Path, backend: str = "isam2",
             features: tuple[str, ...] | None = None, out: str | Path | None = None,
             config: SlamConfig | None = None, frames: str = "auto",
             max_dt: float = 0.5, run: LoggedRun | None = None,
             start_pose: FloatArray | None = None, frontend: str = "sequential") -> SlamResult:
    """Run one backend over a logged run and write the results.

    Args:
        run_dir: the run directory (ignored when ``run`` is given).
        backend: ``"ekf"``, ``"isam2"`` or ``"batch"``.
        features: ceiling features, a subset of ``("lamps", "corners")``; None keeps
            ``config.features``.
        out: output directory (created); None writes nothing.
        config: the SLAM config (defaults when None).
        frames: frame source, see :func:`make_frames`.
        max_dt: longest interval without a step, s (see :func:`iter_steps`).
        run: an already loaded run (e.g. from :func:`lampsam.datasets.mrclam.mrclam_run`).
        start_pose: (3,) known start pose ``world_T_body``; None takes it from the
            run (:func:`start_pose_of`: ground truth at the first odometry time, else
            the origin).
        frontend: ``"sequential"``, ``"thread"`` or ``"process"`` (see :func:`make_frames`).

    Returns:
        The result (also written to ``out``).

    Raises:
        EstimationError: unusable input (no frames, unknown backend or features).
        lampsam.errors.DatasetError: the run cannot be read.
    """
    import dataclasses

    config = config or SlamConfig()
    if features is not None:
        bad = set(features) - {"lamps", "corners"}
        if bad or not features:
            raise EstimationError(f"features must be a non-empty subset of lamps,corners; got {features}")
        config = dataclasses.replace(config, features=tuple(features))
    if run is None:
        run = read_run(run_dir)
    if backend not in BACKENDS:
        raise EstimationError(f"unknown backend {backend!r}; choose from {', '.join(BACKENDS)}")
    # the smoothers read only the frames that can become keyframes: the others' images
    # are never processed (the EKF reads every frame: made as they come)
    frame_list, is_ceiling = make_frames(run, frames, frontend=frontend,
                                         lazy=backend in LAZY_BACKENDS)
    start = start_pose_of(run) if start_pose is None else np.asarray(start_pose, float).reshape(3)
    odo_model = (pose2_model_for(run, config) if isinstance(run.odometry, Pose2OdometryLog)
                 else run.rig.odometry)
    be = make_backend(backend, odo_model, config, start,
                      run.rig.camera if is_ceiling else None)
    t0 = time.perf_counter()
    result = drive(be, iter_steps(run.odometry, frame_list, max_dt))
    total = time.perf_counter() - t0
    result.extra["total_time_s"] = total
    if out is not None:
        write_results(Path(out), result, run)
    if result.status.startswith("failed"):
        raise EstimationError(f"{backend} on {run.path}: {result.status} "
                              f"(steps finished so far written to {out})")
    return result


# --------------------------------------------------------------------------- writers
def write_trajectory(path: Path, result: SlamResult) -> None:
    """Write the estimated poses as a TUM trajectory (the run's clock)."""
    write_tum(path, Trajectory(t=result.times, poses=result.poses))


def write_landmarks(path: Path, result: SlamResult) -> None:
    """Write the map: ``id, type, x, y, z, phi, n_obs``, covariance entries and ``flag``
    (empty, or ``seen_once`` for :attr:`SlamResult.provisional` landmarks)."""
    header = ["id", "type", "x", "y", "z", "phi", "n_obs",
              "cov_xx", "cov_xy", "cov_xz", "cov_yy", "cov_yz", "cov_zz", "var_phi", "flag"]
    with atomic_path(path) as tmp, open(tmp, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(header)
        flagged = [(lm, "") for lm in result.landmarks] + [(lm, "seen_once")
                                                          for lm in result.provisional]
        for lm, flag in flagged:
            c = np.full((4, 4), np.nan)
            k = lm.cov.shape[0]
            c[:k, :k] = lm.cov
            phi = lm.orientation if lm.orientation is not None else float("nan")
            vals = [*lm.position, phi, c[0, 0], c[0, 1], c[0, 2], c[1, 1], c[1, 2], c[2, 2],
                    c[3, 3] if k == 4 else float("nan")]
            w.writerow([lm.id, lm.type, *(f"{v:.6g}" for v in vals[:4]), lm.n_obs,
                        *(f"{v:.6g}" for v in vals[4:]), flag])


def errors_vs_truth(result: SlamResult, truth: Trajectory) -> tuple[FloatArray, FloatArray]:
    """Position and heading errors at the steps inside the truth's time span, no alignment.

    Args:
        result: the SLAM result.
        truth: the ground-truth trajectory.

    Returns:
        ``(position_error (M,) m, heading_error (M,) rad, wrapped)``.
    """
    inside = (result.times >= truth.t[0]) & (result.times <= truth.t[-1])
    gt = truth.interpolate(result.times[inside])
    est = result.poses[inside]
    pos = np.hypot(est[:, 0] - gt[:, 0], est[:, 1] - gt[:, 1])
    head = np.asarray(wrap_angle(est[:, 2] - gt[:, 2]), float)
    return pos, head


def summary(result: SlamResult, truth: Trajectory | None) -> dict[str, Any]:
    """The ``summary.json`` content (see module docstring)."""
    st = result.step_times_s * 1e3
    frames_ms = st[result.keyframes] if result.keyframes.any() else st
    out: dict[str, Any] = {
        "backend": result.backend,
        "status": result.status,
        "steps": int(len(result.times)),
        "keyframes": int(result.keyframes.sum()),
        "landmarks": len(result.landmarks),
        "landmarks_pruned": int(result.n_pruned),
        "landmarks_pruned_by_reason": {k: int(v) for k, v in sorted(result.pruned.items())},
        "landmarks_seen_once": len(result.provisional),
        "time_per_frame_ms": {
            "median": float(np.median(frames_ms)) if len(frames_ms) else None,
            "p95": float(np.percentile(frames_ms, 95)) if len(frames_ms) else None,
            "max": float(np.max(frames_ms)) if len(frames_ms) else None,
        },
        "final_optimisation_s": result.final_time_s,
        **{k: v for k, v in result.extra.items()},
    }
    if truth is not None and len(result.times):
        pos, head = errors_vs_truth(result, truth)
        if len(pos):
            out["error"] = {
                "alignment": "none (known start pose)",
                "position_rms_m": float(np.sqrt(np.mean(pos**2))),
                "position_max_m": float(np.max(pos)),
                "heading_rms_deg": float(np.degrees(np.sqrt(np.mean(head**2)))),
                "heading_max_deg": float(np.degrees(np.max(np.abs(head)))),
                "n": int(len(pos)),
            }
    return out


def write_results(out: Path, result: SlamResult, run: LoggedRun) -> None:
    """Write ``trajectory.tum``, ``landmarks.csv`` and ``summary.json`` to ``out``.

    Each file is written atomically (each writer goes through
    :func:`lampsam.safe_io.atomic_path`), the summary last: a complete ``summary.json``
    means the other two are complete.
    """
    out.mkdir(parents=True, exist_ok=True)
    write_trajectory(out / "trajectory.tum", result)
    write_landmarks(out / "landmarks.csv", result)
    write_json_atomic(out / "summary.json", summary(result, run.groundtruth))
    log.info("results written to %s", out)
