"""Live view of a run in Rerun (``--rerun [FILE.rrd | ADDRESS]`` on ``slam``, ``localize``, ``stereo``).

A :class:`LiveView` is an observer (:mod:`lampsam.observe`): the run loops report
each finished step and the view logs it to a Rerun recording stream, either saved
to an ``.rrd`` file (open it later with ``rerun FILE.rrd``) or streamed to a viewer
that is already running (``ADDRESS`` = ``host:port`` of ``rerun`` or a full
``rerun+http://...`` URL). Needs the optional ``rerun-sdk`` package
(``pip install 'lampsam[viz]'``); nothing else in lampsam imports it.

What is logged (timeline ``time``: the run's clock, s; ``update`` for localization):

- SLAM: ``camera/image`` the ceiling image with ``camera/image/lamps`` and
  ``camera/image/corners`` (the frame's detections) and, for the EKF, whose map
  exists at every step, ``camera/image/map`` (mapped landmarks projected with the
  current pose) and ``camera/image/associations`` (each detection joined to the
  projected landmark within :data:`ASSOCIATION_PX`); ``world/truth`` (path and
  landmarks, static), ``world/estimate`` (pose with its 3-sigma ellipse, path);
  ``world/map`` (landmarks with 3-sigma ellipses where readable: every
  :data:`MAP_EVERY` steps for the EKF, at the end for the smoothers);
  ``timing/step_ms``, ``counts/matched``, ``counts/new``.
- Localization: ``world/grid/occupied`` (static), ``world/particles`` (coloured by weight), ``world/candidates``
  (discs of the pose candidates), ``world/estimate``, ``localize/effective_n``,
  ``timing/update_ms``.
- Stereo: ``target/<estimator>`` pose and path in the target frame, ``target/truth``,
  ``timing/<estimator>_ms``.

World coordinates are metres in the map frame (x right, y up in the 2-D view).
"""

from __future__ import annotations

import contextlib
import logging
import time
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any

import numpy as np

from lampsam.arrays import FloatArray
from lampsam.errors import LampsamError
from lampsam.evaluation.compare_plots import MAX_ELLIPSE_M, covariance_ellipse, major_sigma
from lampsam.observe import observing

log = logging.getLogger(__name__)

ASSOCIATION_PX = 12.0
"""Largest image distance, px, at which a detection is drawn joined to a projected landmark."""
MAP_EVERY = 10
"""Steps between two logs of the EKF's whole map (each costs O(landmarks))."""
PATH_EVERY = 5
"""Steps between two logs of the whole estimated path."""
BACKEND_RGB = {"ekf": (214, 39, 40), "isam2": (31, 119, 180), "batch": (44, 160, 44),
               "raw": (127, 127, 127)}
KIND_RGB = {"lamp": (255, 127, 14), "corner": (148, 103, 189), "point2": (23, 190, 207)}
TRUTH_RGB = (20, 20, 20)


class LiveViewError(LampsamError):
    """The live view cannot start (rerun-sdk missing, target unusable)."""


def _rerun() -> Any:
    """The ``rerun`` module, or a clear error naming the extra to install."""
    try:
        import rerun
    except ImportError as exc:
        raise LiveViewError("--rerun needs the rerun-sdk package: pip install 'lampsam[viz]'"
                            ) from exc
    return rerun


def blueprint(kind: str) -> Any:
    """The viewer layout: the image and the world in separate 2-D views (pixels vs metres),
    time series of timing and counts, and the text log.

    Args:
        kind: ``"slam"``, ``"localize"`` or ``"stereo"``.
    """
    import rerun.blueprint as rrb

    if kind == "stereo":
        return rrb.Blueprint(rrb.Horizontal(
            rrb.Spatial2DView(origin="target", name="rig in the target frame [m] (y down)"),
            rrb.TimeSeriesView(origin="timing", name="step time [ms]"), column_shares=[2, 1]),
            collapse_panels=True)
    world = rrb.Spatial2DView(origin="world", name="world [m] (y down)")
    if kind == "localize":
        return rrb.Blueprint(rrb.Horizontal(world, rrb.Vertical(
            rrb.TimeSeriesView(origin="localize", name="particles"),
            rrb.TimeSeriesView(origin="timing", name="update time [ms]"),
            rrb.TextLogView(origin="log", name="log")), column_shares=[2, 1]),
            collapse_panels=True)
    return rrb.Blueprint(rrb.Horizontal(
        rrb.Vertical(rrb.Spatial2DView(origin="camera", name="ceiling camera [px]"),
                     rrb.TimeSeriesView(origin="timing", name="step time [ms]")),
        rrb.Vertical(world, rrb.Horizontal(
            rrb.TimeSeriesView(origin="counts", name="observations matched / new"),
            rrb.TextLogView(origin="log", name="log")), row_shares=[3, 1]),
        column_shares=[1, 2]), collapse_panels=True)


def open_stream(target: str, name: str, kind: str = "slam") -> Any:
    """A Rerun recording stream saving to ``target`` (``*.rrd``) or connected to a viewer.

    Args:
        target: an ``.rrd`` path (parent directories are created), ``host:port`` of a
            running viewer, or a ``rerun+http://`` URL.
        name: the recording's name (shown in the viewer).
        kind: the layout (:func:`blueprint`).

    Raises:
        LiveViewError: rerun-sdk is not installed, or the file cannot be created.
    """
    rr = _rerun()
    rec = rr.RecordingStream("lampsam")
    layout = blueprint(kind)
    if target.endswith(".rrd"):
        path = Path(target)
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            rec.save(str(path), default_blueprint=layout)
        except (OSError, RuntimeError) as exc:
            raise LiveViewError(f"{target}: cannot write the recording: {exc}") from exc
    else:
        url = target if "://" in target else f"rerun+http://{target}/proxy"
        rec.connect_grpc(url, default_blueprint=layout)
    rec.send_recording_name(name)
    return rec


def ellipse_strip(center: FloatArray, cov: FloatArray, n_sigma: float = 3.0) -> FloatArray:
    """Closed polyline (41, 2) of the ``n_sigma`` ellipse of a 2x2 covariance around ``center``."""
    return covariance_ellipse(cov, n_sigma, n=41) + np.asarray(center, float)[:2]


def weight_colors(log_weights: FloatArray) -> np.ndarray:
    """(N, 3) uint8 colours from dark blue (lightest) to yellow (heaviest), by normalised weight."""
    lw = np.asarray(log_weights, float)
    w = np.exp(lw - np.max(lw)) if len(lw) else lw
    u = np.clip(w, 0.0, 1.0)[:, None]
    lo, hi = np.array([48, 18, 120]), np.array([250, 230, 30])
    return (lo + u * (hi - lo)).astype(np.uint8)


class LiveView:
    """Observer that logs SLAM, localization and stereo events to one Rerun stream.

    Args:
        rec: the recording stream (:func:`open_stream`).
        run: the SLAM or localization run (:class:`lampsam.datasets.logrun.LoggedRun`),
            for its images, camera and ground truth; None for stereo.
        stereo_truth: (N, 3) true ``target_T_camera`` of a stereo run, or None.
    """

    def __init__(self, rec: Any, run: Any = None, stereo_truth: FloatArray | None = None) -> None:
        self.rr = _rerun()
        self.rec = rec
        self.run = run
        self._paths: dict[str, list[FloatArray]] = {}
        self._n_steps = 0
        self._update = 0
        self._last_wall = time.perf_counter()
        self._model: Any = None
        if run is not None:
            self._log_truth(run)
            camera = getattr(getattr(run, "rig", None), "camera", None)
            if camera is not None:
                from lampsam.backend.ceiling import CeilingModel

                self._model = CeilingModel.from_camera(camera)
        if stereo_truth is not None and len(stereo_truth):
            rec.log("target/truth", self.rr.LineStrips2D([np.asarray(stereo_truth)[:, :2]],
                                                         colors=[TRUTH_RGB]), static=True)

    # ------------------------------------------------------------------ dispatch
    def __call__(self, event: str, fields: Mapping[str, Any]) -> None:
        """Log one event (see :mod:`lampsam.observe`); unknown events are ignored."""
        handler = {"slam.step": self._slam_step, "slam.finish": self._slam_finish,
                   "localize.particles": self._particles, "localize.candidates": self._candidates,
                   "localize.estimate": self._loc_estimate, "localize.start": self._grid,
                   "stereo.step": self._stereo_step}.get(event)
        if handler is not None:
            handler(fields)

    def close(self) -> None:
        """Flush and close the stream (the ``.rrd`` file is complete after this)."""
        self.rec.flush()
        self.rec.disconnect()

    # ------------------------------------------------------------------ SLAM
    def _log_truth(self, run: Any) -> None:
        rr, rec = self.rr, self.rec
        gt = getattr(run, "groundtruth", None)
        if gt is not None and len(gt.t):
            rec.log("world/truth/path", rr.LineStrips2D([gt.poses[:, :2]], colors=[TRUTH_RGB],
                                                        radii=[0.01]), static=True)
        lm = getattr(run, "landmarks", None)
        if lm is not None and len(lm.ids):
            types = np.array(["lamp" if str(t).startswith("lamp") else str(t) for t in lm.types])
            xy = np.asarray(lm.xyz, float)[:, :2]
            rec.log("world/truth/landmarks", rr.Points2D(
                xy, radii=np.where(types == "lamp", 0.08, 0.03),
                colors=[(90, 90, 90)], labels=None), static=True)

    def _slam_step(self, f: Mapping[str, Any]) -> None:
        rr, rec = self.rr, self.rec
        est, frame = f["estimate"], f.get("frame")
        backend: Any = f.get("backend")
        name = getattr(backend, "name", "slam")
        rec.set_time("time", duration=float(f["t"]))
        pose = np.asarray(est.pose, float)
        rec.log("world/estimate/pose", rr.Points2D([pose[:2]], radii=[0.05],
                                                   colors=[BACKEND_RGB.get(name, (0, 0, 0))]))
        rec.log("world/estimate/heading", rr.Arrows2D(
            origins=[pose[:2]], vectors=[[0.3 * np.cos(pose[2]), 0.3 * np.sin(pose[2])]],
            colors=[BACKEND_RGB.get(name, (0, 0, 0))]))
        if np.all(np.isfinite(est.cov[:2, :2])):
            rec.log("world/estimate/ellipse", rr.LineStrips2D(
                [ellipse_strip(pose, est.cov[:2, :2])], colors=[BACKEND_RGB.get(name, (0, 0, 0))]))
        path = self._paths.setdefault(name, [])
        path.append(pose[:2])
        self._n_steps += 1
        if self._n_steps % PATH_EVERY == 0:
            rec.log("world/estimate/path", rr.LineStrips2D([np.array(path)],
                                                           colors=[BACKEND_RGB.get(name, (0, 0, 0))]))
        rec.log("timing/step_ms", rr.Scalars([1e3 * float(est.time_s)]))
        rec.log("counts/matched", rr.Scalars([float(est.n_matched)]))
        rec.log("counts/new", rr.Scalars([float(est.n_new)]))
        if hasattr(backend, "landmarks") and self._n_steps % MAP_EVERY == 0:
            self._log_map(backend.landmarks())
        if frame is not None and hasattr(frame, "lamps"):
            self._log_image(frame, pose, backend)

    def _log_image(self, frame: Any, pose: FloatArray, backend: Any) -> None:
        rr, rec = self.rr, self.rec
        images = getattr(self.run, "images", None) if self.run is not None else None
        if images is not None:
            try:
                img = images.load(int(frame.index))
                rec.log("camera/image", rr.Image(img).compress(jpeg_quality=80))
            except (LampsamError, OSError, IndexError) as exc:
                log.debug("live view: image %s not shown: %s", frame.index, exc)
        det = {"lamps": np.array([o.pixel for o in frame.lamps], float).reshape(-1, 2),
               "corners": np.array([o.pixel for o in frame.corners], float).reshape(-1, 2)}
        rec.log("camera/image/lamps", rr.Points2D(det["lamps"], radii=[4.0],
                                                  colors=[KIND_RGB["lamp"]]))
        rec.log("camera/image/corners", rr.Points2D(det["corners"], radii=[2.0],
                                                    colors=[KIND_RGB["corner"]]))
        if not hasattr(backend, "landmarks") or self._model is None:
            return
        lms = backend.landmarks()
        if not lms:
            return
        pts = np.array([lm.position for lm in lms], float)
        m, _, _, vis = self._model.project_many(pose, pts)
        px = self.run.rig.camera.pixels_from_normalized(m[vis])
        rec.log("camera/image/map", rr.Points2D(px, radii=[3.0], colors=[(0, 200, 255)]))
        allpx = np.vstack([det["lamps"], det["corners"]])
        if len(px) and len(allpx):
            d = np.linalg.norm(allpx[:, None, :] - px[None, :, :], axis=2)
            j = np.argmin(d, axis=1)
            ok = d[np.arange(len(allpx)), j] < ASSOCIATION_PX
            segs = np.stack([allpx[ok], px[j[ok]]], axis=1)
            rec.log("camera/image/associations", rr.LineStrips2D(list(segs), colors=[(0, 255, 0)]))

    def _log_map(self, landmarks: list[Any]) -> None:
        rr, rec = self.rr, self.rec
        if not landmarks:
            return
        xy = np.array([lm.position[:2] for lm in landmarks], float)
        kinds = [lm.type for lm in landmarks]
        cov = np.array([np.asarray(lm.cov, float)[:2, :2] for lm in landmarks])
        rec.log("world/map/landmarks", rr.Points2D(
            xy, radii=[0.06 if k == "lamp" else 0.025 for k in kinds],
            colors=[KIND_RGB.get(k, (0, 0, 0)) for k in kinds]))
        semi = 3.0 * major_sigma(cov)
        ok = np.isfinite(semi) & (semi <= MAX_ELLIPSE_M)
        rec.log("world/map/ellipses", rr.LineStrips2D(
            [ellipse_strip(p, c) for p, c in zip(xy[ok], cov[ok], strict=True)],
            colors=[KIND_RGB.get(k, (0, 0, 0)) for k, o in zip(kinds, ok, strict=True) if o]))
        rec.log("world/map/not_drawn", rr.Scalars([float(np.sum(~ok))]))

    def _slam_finish(self, f: Mapping[str, Any]) -> None:
        rr, rec = self.rr, self.rec
        result = f["result"]
        if len(result.times):
            rec.set_time("time", duration=float(result.times[-1]))
            rec.log("world/estimate/path", rr.LineStrips2D(
                [result.poses[:, :2]], colors=[BACKEND_RGB.get(result.backend, (0, 0, 0))]))
        self._log_map(result.landmarks)
        rec.log("log", rr.TextLog(f"{result.backend}: {result.status}, {len(result.times)} steps, "
                                  f"{len(result.landmarks)} landmarks, {result.n_pruned} pruned"))

    # ------------------------------------------------------------------ localization
    def _tick(self) -> float:
        now = time.perf_counter()
        dt, self._last_wall = now - self._last_wall, now
        return 1e3 * dt

    def _grid(self, f: Mapping[str, Any]) -> None:
        """The occupied cells of the grid, static (grey points one cell wide)."""
        from lampsam.localization.grid import occupied_mask

        grid = f["grid"]
        iy, ix = np.nonzero(occupied_mask(grid))
        xy = grid.cell_to_world(np.column_stack([ix, iy]))
        self.rec.log("world/grid/occupied", self.rr.Points2D(
            xy, radii=[0.5 * grid.resolution], colors=[(110, 110, 110)]), static=True)

    def _particles(self, f: Mapping[str, Any]) -> None:
        rr, rec = self.rr, self.rec
        self._update += 1
        rec.set_time("update", sequence=self._update)
        p = np.asarray(f["particles"], float)
        lw = np.asarray(f["log_weights"], float)
        rec.log("world/particles", rr.Points2D(p[:, :2], radii=[0.02], colors=weight_colors(lw)))
        w = np.exp(lw - np.max(lw))
        w /= np.sum(w)
        rec.log("localize/effective_n", rr.Scalars([float(1.0 / np.sum(w**2))]))
        rec.log("localize/particles", rr.Scalars([float(len(p))]))
        rec.log("timing/update_ms", rr.Scalars([self._tick()]))

    def _candidates(self, f: Mapping[str, Any]) -> None:
        rr, rec = self.rr, self.rec
        rec.set_time("update", sequence=self._update)
        cands = f["candidates"]
        poses = np.array([np.asarray(c.pose, float) for c in cands]).reshape(-1, 3)
        a = np.linspace(0.0, 2.0 * np.pi, 41)
        discs = [np.column_stack([p[0] + c.radius * np.cos(a), p[1] + c.radius * np.sin(a)])
                 for p, c in zip(poses, cands, strict=True)]
        rec.log("world/candidates/discs", rr.LineStrips2D(discs, colors=[(255, 127, 14)]))
        rec.log("world/candidates/heading", rr.Arrows2D(
            origins=poses[:, :2], vectors=0.4 * np.column_stack([np.cos(poses[:, 2]),
                                                                 np.sin(poses[:, 2])]),
            colors=[(255, 127, 14)]))
        rec.log("log", rr.TextLog(f"turn: {len(cands)} pose candidates"))
        self._tick()

    def _loc_estimate(self, f: Mapping[str, Any]) -> None:
        rr, rec = self.rr, self.rec
        rec.set_time("update", sequence=self._update)
        pose = np.asarray(f["pose"], float)
        rec.log("world/estimate/pose", rr.Points2D([pose[:2]], radii=[0.08], colors=[(214, 39, 40)]))
        rec.log("world/estimate/heading", rr.Arrows2D(
            origins=[pose[:2]], vectors=[[0.5 * np.cos(pose[2]), 0.5 * np.sin(pose[2])]],
            colors=[(214, 39, 40)]))
        rec.log("log", rr.TextLog(f"attempt {f.get('attempt', '?')}: x {pose[0]:.2f} m, "
                                  f"y {pose[1]:.2f} m, heading {np.degrees(pose[2]):.1f} deg"))

    # ------------------------------------------------------------------ stereo
    def _stereo_step(self, f: Mapping[str, Any]) -> None:
        rr, rec = self.rr, self.rec
        name, step = str(f["estimator"]), f["step"]
        rec.set_time("time", duration=float(f["t"]))
        rec.log(f"timing/{name}_ms", rr.Scalars([1e3 * float(f.get("time_s", 0.0))]))
        if not step.valid:
            return
        pose = np.asarray(step.pose, float)
        color = BACKEND_RGB.get(name, (0, 0, 0))
        rec.log(f"target/{name}/pose", rr.Points2D([pose[:2]], radii=[0.03], colors=[color]))
        path = self._paths.setdefault(f"stereo/{name}", [])
        path.append(pose[:2])
        if len(path) % PATH_EVERY == 0:
            rec.log(f"target/{name}/path", rr.LineStrips2D([np.array(path)], colors=[color]))


def rerun_target(option: str | None, out: str | Path) -> str | None:
    """The ``--rerun`` target: None (no live view), the given one, or ``OUT/live.rrd`` when bare."""
    if option is None:
        return None
    return option or str(Path(out) / "live.rrd")


@contextlib.contextmanager
def live_view(target: str | None, name: str, run: Any = None,
              stereo_truth: FloatArray | None = None, kind: str = "slam"
              ) -> Iterator[LiveView | None]:
    """Stream the runs inside the block to Rerun (``target`` None: do nothing).

    Args:
        target: see :func:`open_stream`, or None.
        name: the recording's name.
        run, stereo_truth: see :class:`LiveView`.
        kind: the viewer layout (:func:`blueprint`).
    """
    if not target:
        yield None
        return
    view = LiveView(open_stream(target, name, kind), run, stereo_truth)
    try:
        with observing(view):
            yield view
    finally:
        view.close()
        log.info("live view: %s", target)
