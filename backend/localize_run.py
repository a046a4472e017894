"""Run localize-only tracking over a logged run, and save the map of a SLAM run.

- :func:`run_localize_only`: ``lampsam slam RUN2 --map MAP --localize-only``: the
  run's ceiling frames and odometry through :class:`lampsam.backend.localize_only.MapLocalizer`
  from a start pose (the run's known start, ``--start X,Y,THETA``, or a global
  localizer's ``result.json``), the results written as :func:`lampsam.backend.slam.write_results`
  writes a SLAM run's (``landmarks.csv`` is the map, unchanged).
- :func:`save_map`: ``lampsam slam RUN --save-map MAP``: the finished SLAM result's
  landmarks, the backend's corner patches and the run's rig as a ceiling map folder
  (:mod:`lampsam.backend.ceiling_map_io`).
"""

from __future__ import annotations

import json
import logging
import math
import time
from collections.abc import Iterable, Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from lampsam.arrays import FloatArray
from lampsam.backend.ceiling import CeilingModel
from lampsam.backend.ceiling_map_io import CeilingMap, corner_patches, map_from_estimates, write_map
from lampsam.backend.config import SlamConfig
from lampsam.backend.interface import Frame, SlamBackend, SlamResult
from lampsam.backend.localize_only import LocalizeConfig, MapLocalizer
from lampsam.backend.map_calibration import calibrate_map
from lampsam.backend.map_frame import MapFrame, map_frame
from lampsam.backend.map_smoother import MapSmoother, MapSmootherConfig
from lampsam.backend.slam import (
    drive,
    iter_steps,
    make_frames,
    start_pose_of,
    summary,
    write_results,
)
from lampsam.datasets.logrun import LoggedRun
from lampsam.datasets.odometry import Pose2OdometryLog, Pose2OdometryModel
from lampsam.errors import DatasetError, EstimationError, InputError
from lampsam.observe import Observer

log = logging.getLogger(__name__)

Step = tuple[float, FloatArray, Frame | None]


@dataclass(frozen=True)
class Start:
    """Where localize-only tracking starts.

    Attributes:
        pose: (3,) ``world_T_body`` in the map's frame, m and rad.
        cov: (3, 3) its covariance, or None (:class:`LocalizeConfig`'s sigmas).
        t: run time of the pose, s; steps up to it are skipped (None: the run's start).
        source: what the start is, for ``summary.json``.
    """

    pose: FloatArray
    cov: FloatArray | None = None
    t: float | None = None
    source: str = "the run's known start pose"


#: standard deviations of a typed ``--start`` (m, m, rad): a pose read off a plan or
#: measured by hand, looser than the run's known start (:class:`LocalizeConfig`'s 1 mm)
TYPED_START_SIGMA = (0.02, 0.02, 0.01)

#: ``source.map_check`` of a map saved without the pass-split test (``save_map(check=False)``)
MAP_CHECK_NOT_RUN = "not run (lampsam slam --no-map-check): no calibration figures"


def parse_start(text: str) -> Start:
    """``X,Y,THETA`` (m, m, rad) as a :class:`Start` at the run's first step, with the
    covariance of :data:`TYPED_START_SIGMA`.

    Raises:
        InputError: not three finite numbers.
    """
    try:
        vals = [float(v) for v in text.split(",")]
    except ValueError:
        vals = []
    if len(vals) != 3 or not all(math.isfinite(v) for v in vals):
        raise InputError(f"--start {text!r}: expected X,Y,THETA (m, m, rad), three numbers")
    return Start(np.array(vals), np.diag(np.square(TYPED_START_SIGMA)), source=f"--start {text}")


def start_from_result(path: str | Path) -> Start:
    """The pose of a ``lampsam localize`` answer (``result.json``) as a :class:`Start`.

    Uses ``pose``, ``covariance`` and, when present, ``trial.t`` (the run time of
    the answer: tracking starts there).

    Raises:
        DatasetError: missing file, bad JSON, a missing key, or an answer that is not
            ``localized``.
    """
    path = Path(path)
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise DatasetError("missing: the result.json of `lampsam localize`", path) from None
    except (OSError, json.JSONDecodeError) as exc:
        raise DatasetError(f"not readable JSON: {exc}", path) from None
    if not isinstance(doc, dict):
        raise DatasetError("must be a JSON object (result.json of `lampsam localize`)", path)
    for key in ("status", "pose", "covariance"):
        if key not in doc:
            raise DatasetError(f"missing key {key!r}", path)
    if doc["status"] != "localized":
        raise DatasetError(f"key 'status' is {doc['status']!r}: the global localizer gave no pose "
                           "to start from", path)
    try:
        pose = np.asarray(doc["pose"], float).reshape(3)
        cov = np.asarray(doc["covariance"], float).reshape(3, 3)
    except (TypeError, ValueError):
        raise DatasetError("keys 'pose' (3 numbers) and 'covariance' (3 x 3) are malformed",
                           path) from None
    if not (np.all(np.isfinite(pose)) and np.all(np.isfinite(cov))):
        raise DatasetError("keys 'pose' and 'covariance' must be finite", path)
    trial = doc.get("trial")
    t = trial.get("t") if isinstance(trial, dict) else None
    return Start(pose, cov, None if t is None else float(t), f"global localization {path}")


def steps_after(steps: Iterable[Step], t0: float | None) -> Iterator[Step]:
    """The steps strictly after ``t0`` (all when None): the start pose is at ``t0``."""
    for step in steps:
        if t0 is None or step[0] > t0 + 1e-9:
            yield step


def check_rig(cmap: CeilingMap, run: LoggedRun) -> None:
    """Warn when the run's camera is not the one the map was made with."""
    a, b = cmap.rig.camera, run.rig.camera
    diffs = []
    if (a.width, a.height) != (b.width, b.height):
        diffs.append(f"image {b.width}x{b.height} (map {a.width}x{a.height})")
    if np.max(np.abs(np.asarray(a.body_t_camera) - np.asarray(b.body_t_camera))) > 0.01:
        diffs.append(f"body_t_camera {list(b.body_t_camera)} (map {list(a.body_t_camera)})")
    if diffs:
        log.warning("%s: the run's camera differs from the map's: %s; the run's is used",
                    run.path, "; ".join(diffs))


def run_localize_only(run: LoggedRun, cmap: CeilingMap, out: str | Path | None = None,
                      config: SlamConfig | None = None, frames: str = "auto",
                      start: Start | None = None, loc: LocalizeConfig | None = None,
                      max_dt: float = 0.5,
                      frame_list: list[Frame] | None = None,
                      smooth: MapSmootherConfig | None = None) -> SlamResult:
    """Track a run against a fixed ceiling map and write the results.

    Args:
        run: the run (its rig gives the camera; its truth, if any, the errors).
        cmap: the map (:func:`lampsam.backend.ceiling_map_io.read_map`).
        out: output directory (``trajectory.tum``, ``landmarks.csv`` = the map,
            ``summary.json`` with ``localize_only`` counts); None writes nothing.
        config: the SLAM config (gate, features, measurement noise).
        frames: frame source (:func:`lampsam.backend.slam.make_frames`; ceiling only).
        start: the start; None: the run's known start pose.
        loc: localize-only settings.
        max_dt: longest interval without a step, s.
        frame_list: already made frames (to share one frontend pass), else made here.
        smooth: also smooth the run at the end (:class:`lampsam.backend.map_smoother.MapSmoother`:
            ``trajectory.tum`` holds the smoothed poses, ``summary.json`` the map frame
            estimate); None: the filter alone.

    Raises:
        EstimationError: a run without ceiling frames, or a failed run.
    """
    config = config or SlamConfig()
    if frame_list is None:
        made, is_ceiling = make_frames(run, frames)
        if not is_ceiling:
            raise EstimationError(f"{run.path}: localize-only needs ceiling frames (images or "
                                  "truth projections), not range-bearing ones")
        frame_list = list(made)
    check_rig(cmap, run)
    start = start or Start(start_pose_of(run))
    odo = (Pose2OdometryModel() if isinstance(run.odometry, Pose2OdometryLog)
           else run.rig.odometry)
    backend: SlamBackend
    if smooth is None:
        backend = MapLocalizer(odo, config, start.pose, cmap,
                               CeilingModel.from_camera(run.rig.camera), loc, start.cov)
    else:
        backend = MapSmoother(odo, config, start.pose, cmap,
                              CeilingModel.from_camera(run.rig.camera), loc, start.cov, smooth)
    t0 = time.perf_counter()
    c0 = time.process_time()
    result = drive(backend, steps_after(iter_steps(run.odometry, frame_list, max_dt), start.t))
    result.extra["total_time_s"] = time.perf_counter() - t0
    result.extra["total_cpu_s"] = time.process_time() - c0
    if out is not None:
        write_results(Path(out), result, run)
        filt = backend.filter if isinstance(backend, MapSmoother) else backend
        assert isinstance(filt, MapLocalizer)
        _add_to_summary(Path(out), {"localize_only": {
            "start": start.source, "start_pose": [float(v) for v in start.pose],
            "start_time_s": start.t, "map_source": cmap.source,
            "release": filt.loc.release and filt.loc.map_mode == "priors",
            "released_landmarks": filt.release_report(),
            "release_blocked_frames": filt.release_blocked,
            "unseen_lamps": filt.unseen_report(),
            "lamp_sightings_unmatched": filt.lamps_unmatched}})
    if result.status.startswith("failed"):
        raise EstimationError(f"localize-only on {run.path}: {result.status}")
    return result


def _add_to_summary(out: Path, extra: dict[str, object]) -> None:
    from lampsam.safe_io import write_json_atomic

    path = out / "summary.json"
    doc = json.loads(path.read_text(encoding="utf-8"))
    doc.update(extra)
    write_json_atomic(path, doc)


def frame_of_result(result: SlamResult, cmap: CeilingMap) -> MapFrame | None:
    """The map's frame uncertainty (:func:`lampsam.backend.map_frame.map_frame`) from a
    smoother's final graph; None for the EKF (no graph), without marginals, or when the
    information matrix is singular (logged)."""
    if result.graph is None or not cmap.landmarks:
        return None
    if not all(np.all(np.isfinite(lm.cov)) for lm in cmap.landmarks):
        log.warning("map frame not saved: landmark marginals unavailable")
        return None
    try:
        return map_frame(result.graph.factors, result.graph.values,
                         [(lm.id, lm.position, lm.cov, lm.phi is not None) for lm in cmap.landmarks])
    except EstimationError as exc:
        log.warning("map frame not saved: %s", exc)
        return None


def calibrated(result: SlamResult, cmap: CeilingMap, inflate: bool = False) -> CeilingMap:
    """The map with the pass-split test's figures (:mod:`lampsam.backend.map_calibration`)
    on the smoother's final graph and, with ``inflate``, its inconsistent landmarks'
    covariances inflated; the map unchanged for the EKF (no graph), without marginals, or
    when the test cannot be made (logged)."""
    if result.graph is None or not cmap.landmarks:
        return cmap
    if not all(np.all(np.isfinite(lm.cov)) for lm in cmap.landmarks):
        return cmap
    try:
        out, figs = calibrate_map(cmap, result.graph.factors, result.graph.values, inflate=inflate)
    except EstimationError as exc:
        log.warning("map covariances not calibrated: %s", exc)
        return cmap
    for f in figs.values():
        log.info("map pass-split test, %ss: %d of %d failed, %d inflated (NEES per dof "
                 "mean %.2f, median %.2f)", f.kind, f.failed, f.landmarks_split, f.inflated,
                 f.nees_mean, f.nees_median)
    return out


def save_map(folder: str | Path, result: SlamResult, run: LoggedRun,
             backend: SlamBackend | None = None, calibrate: bool = False,
             check: bool = True) -> CeilingMap:
    """Write a SLAM result's map (with the backend's corner patches) as a ceiling map.

    Args:
        folder: the map folder (created; files replaced atomically).
        result: the finished SLAM result.
        run: the mapping run (its rig is stored with the map).
        backend: the finished backend (for corner patches), or None (no patches).
        calibrate: inflate the covariances of landmarks that fail the pass-split test
            (:func:`calibrated`); default False: the smoother's marginals as they are, the
            test's figures recorded in ``map.yaml`` (inflating made localize-only less
            accurate on lab: docs/ceiling-map.md).
        check: run the pass-split test at all (default True, its figures under
            ``calibration`` in ``map.yaml``); False (``lampsam slam --no-map-check``) skips
            it, writes no ``calibration`` and records ``map_check: not run`` under
            ``source`` (a free mapping every map reader accepts).

    Returns:
        The map written.

    Raises:
        ValueError: ``calibrate`` without ``check`` (inflating needs the test).
    """
    if calibrate and not check:
        raise ValueError("save_map: calibrate=True needs check=True (inflation uses the test)")
    s = summary(result, run.groundtruth)
    source = {"run": str(run.path), "backend": result.backend, "status": result.status,
              "steps": int(len(result.times)),
              "landmarks_seen_once_not_saved": len(result.provisional)}
    if "error" in s:
        source["position_rms_m"] = float(s["error"]["position_rms_m"])
    if not check:
        source["map_check"] = MAP_CHECK_NOT_RUN
    cmap = map_from_estimates(result.landmarks, run.rig,
                              corner_patches(backend) if backend is not None else None, source)
    cmap.frame = frame_of_result(result, cmap)
    if check:
        cmap = calibrated(result, cmap, inflate=calibrate)
    write_map(folder, cmap)
    log.info("ceiling map written to %s: %d lamps, %d corners", folder,
             len(cmap.by_kind("lamp")), len(cmap.by_kind("corner")))
    return cmap


class BackendCapture:
    """An observer (:mod:`lampsam.observe`) that keeps the backend of ``slam.step`` events.

    :func:`lampsam.backend.slam.run_slam` returns the result, not the backend whose
    corner patches :func:`save_map` needs; this observer remembers it and passes
    every event on to ``inner`` (a live view), if any.
    """

    def __init__(self, inner: Observer | None = None) -> None:
        self.inner = inner
        self.backend: SlamBackend | None = None

    def __call__(self, event: str, fields: Mapping[str, Any]) -> None:
        """Remember the backend; forward the event."""
        if event == "slam.step" and self.backend is None:
            backend = fields.get("backend")
            if isinstance(backend, SlamBackend):
                self.backend = backend
        if self.inner is not None:
            self.inner(event, fields)
