"""The ceiling frontend measured against truth.

Truth comes from the simulator (``truth/projections.csv`` of a logged run:
where every landmark projects in every image, lamp axes in pixels) or from
:func:`synthetic_sequence`, a small independent renderer used by the tests:
lamps (rotated rectangles and discs) and dark/bright ceiling plates (whose
corners are the corner truth) are drawn with OpenCV at 8x resolution and
reduced with ``INTER_AREA``, so edges are area-sampled (anti-aliased) like a
real camera's.

Metrics (:class:`FrontendMetrics`), over a whole run:

* lamp recall: truth lamps fully in view (``fully_visible``) that have a
  detection within ``gate_px`` of their projected centre;
* lamp precision: detections that lie within ``gate_px`` of some visible
  truth lamp (a detection near nothing is a false lamp);
* centroid error (px, RMS and max) of the matched fully-visible lamps;
* axis error (deg, RMS and max) for matched ``lamp_rect`` lamps detected with
  ``R_ori > ratio_threshold``, comparing the image-space axis (eq. 5) with the
  projected axis, modulo pi;
* the same on the ceiling, what the estimators use: the observation's ``m``
  against the truth centre's (its projected pixel mapped by the camera),
  RMS in ``m`` units (per metre of height), and its axis against the projected
  axis mapped to the ceiling at the centre (deg). Under a lens that bends
  lamps (fisheye, tilt) the pixel centroid is not the centre's image, so
  these, not the pixel figures, measure the frontend;
* corner repeatability: a detected corner is "true" when within
  ``corner_gate_px`` of a visible truth corner; over consecutive frames,
  repeatability = true corners of frame k seen again (same id) in frame k+1
  over those of frame k still visible in frame k+1;
* NCC matching precision: for each true corner of frame k still visible in
  k+1, predict its position at its truth projection in k+1, gate with
  ``ncc_gate_px`` (several candidates fall inside) and let :func:`match_ncc`
  choose; precision = choices with the right id over all choices made.
"""

from __future__ import annotations

import json
import logging
import math
from collections.abc import Iterable, Sequence
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import cv2
import numpy as np

from lampsam.angles import wrap_axis
from lampsam.arrays import BoolArray, FloatArray, ImageU8, IntArray
from lampsam.datasets.logrun import CameraModel, LandmarkTable, ProjectionTable, read_run
from lampsam.errors import LampsamError
from lampsam.evaluation.outputs import ensure_dir
from lampsam.frontend.ceiling_coords import PixelToCeiling
from lampsam.frontend.corners import detect_corner_pixels, match_ncc
from lampsam.frontend.lamp_models import size_gate_from_models
from lampsam.frontend.lamps import detect_lamps
from lampsam.frontend.pipeline import FrontendConfig, check_image
from lampsam.safe_io import write_text_atomic

log = logging.getLogger(__name__)

SUPERSAMPLE = 8
"""Supersampling factor of the synthetic renderer."""


@dataclass(frozen=True)
class FrameTruth:
    """Truth projections of one image.

    Attributes:
        ids: shape (K,) landmark ids.
        types: K type names (``lamp_rect``, ``lamp_round``, ``lamp_square``, ``corner``).
        pixel: shape (K, 2) projected ``(col, row)``, px.
        angle_px: shape (K,) projected long axis of ``lamp_rect`` lamps (rad,
            ``atan2(d_row, d_col)``, mod pi); NaN for others.
        visible: shape (K,) bool.
        fully_visible: shape (K,) bool (lamps entirely inside the image).
    """

    ids: IntArray
    types: tuple[str, ...]
    pixel: FloatArray
    angle_px: FloatArray
    visible: BoolArray
    fully_visible: BoolArray

    def is_lamp(self) -> BoolArray:
        """shape (K,) True for lamps."""
        return np.array([t.startswith("lamp") for t in self.types], dtype=bool)


@dataclass(frozen=True)
class EvalSettings:
    """Settings of the evaluation.

    Attributes:
        gate_px: a detection matches a truth lamp within this distance (default 4 px).
        corner_gate_px: a corner is true within this distance of a truth corner (2 px).
        ncc_gate_px: gate radius for the NCC test (default 12 px).
        min_ncc: NCC acceptance threshold (default 0.8).
    """

    gate_px: float = 4.0
    corner_gate_px: float = 2.0
    ncc_gate_px: float = 12.0
    min_ncc: float = 0.8


def _isnan(v: object) -> bool:
    """True for a float NaN (False for anything else)."""
    return isinstance(v, float) and math.isnan(v)


@dataclass
class FrontendMetrics:
    """Evaluation figures of the frontend over a run (see the module docstring)."""

    n_frames: int = 0
    n_truth_lamps_full: int = 0
    n_found: int = 0
    n_detections: int = 0
    n_false: int = 0
    lamp_recall: float = math.nan
    lamp_precision: float = math.nan
    centroid_rms_px: float = math.nan
    centroid_max_px: float = math.nan
    n_axis: int = 0
    axis_rms_deg: float = math.nan
    axis_max_deg: float = math.nan
    m_rms: float = math.nan
    m_max: float = math.nan
    n_axis_m: int = 0
    axis_m_rms_deg: float = math.nan
    n_corners_mean: float = math.nan
    corner_true_fraction: float = math.nan
    corner_repeatability: float = math.nan
    n_ncc_tests: int = 0
    n_ncc_matches: int = 0
    ncc_precision: float = math.nan
    ncc_match_rate: float = math.nan
    source: str = ""
    targets_met: dict[str, bool] = field(default_factory=dict)

    def to_json(self, path: str | Path) -> None:
        """Write the figures as JSON (NaN as null)."""
        data = {k: (None if _isnan(v) else v) for k, v in asdict(self).items()}
        ensure_dir(Path(path).parent)
        write_text_atomic(path, json.dumps(data, indent=2) + "\n")

    def summary(self) -> str:
        """Human-readable lines."""
        return "\n".join([
            f"source: {self.source}  frames: {self.n_frames}",
            f"lamps fully in view: {self.n_truth_lamps_full}, found {self.n_found} "
            f"(recall {100 * self.lamp_recall:.2f} %)",
            f"detections: {self.n_detections}, false {self.n_false} "
            f"(precision {100 * self.lamp_precision:.2f} %)",
            f"centroid error: RMS {self.centroid_rms_px:.3f} px, max {self.centroid_max_px:.3f} px",
            f"axis error (R_ori > thr, {self.n_axis} lamps): RMS {self.axis_rms_deg:.3f} deg, "
            f"max {self.axis_max_deg:.3f} deg",
            f"on the ceiling: m error RMS {self.m_rms:.5f}, max {self.m_max:.5f} (per m of height); "
            f"axis RMS {self.axis_m_rms_deg:.3f} deg ({self.n_axis_m} lamps)",
            f"corners/frame {self.n_corners_mean:.1f}, "
            f"true {100 * self.corner_true_fraction:.1f} %, "
            f"repeatability {100 * self.corner_repeatability:.1f} %",
            f"NCC: {self.n_ncc_matches}/{self.n_ncc_tests} matched "
            f"(rate {100 * self.ncc_match_rate:.1f} %), precision {100 * self.ncc_precision:.2f} %",
            f"targets met: {self.targets_met}",
        ])  # fmt: skip


# --------------------------------------------------------------------------- evaluation
def _nearest(a: FloatArray, b: FloatArray) -> tuple[IntArray, FloatArray]:
    """For each row of ``a`` (N, 2), the nearest row of ``b`` (M, 2) and its distance."""
    if a.shape[0] == 0 or b.shape[0] == 0:
        return np.full(a.shape[0], -1, dtype=np.int64), np.full(a.shape[0], np.inf)
    d = np.linalg.norm(a[:, None, :] - b[None, :, :], axis=2)
    j = np.argmin(d, axis=1)
    return j.astype(np.int64), d[np.arange(a.shape[0]), j]


def evaluate_frames(
    frames: Iterable[tuple[ImageU8, FrameTruth]],
    camera: PixelToCeiling,
    config: FrontendConfig | None = None,
    settings: EvalSettings | None = None,
    source: str = "",
) -> FrontendMetrics:
    """Run the frontend on images with known truth and measure it.

    Args:
        frames: ``(image (H, W) uint8, truth)`` pairs in time order.
        camera: the camera model (``normalized_from_pixels``, ``width``, ``height``).
        config: frontend settings.
        settings: evaluation settings.
        source: a label for the report.

    Returns:
        The metrics; ``targets_met`` checks the issue's targets (recall >= 99 %,
        no false lamp, centroid RMS <= 0.3 px, axis RMS <= 0.5 deg).
    """
    config = config or FrontendConfig()
    settings = settings or EvalSettings()
    res = FrontendMetrics(source=source)
    cen_err: list[float] = []
    ax_err: list[float] = []
    m_err: list[float] = []
    ax_m_err: list[float] = []
    n_corners: list[int] = []
    n_true_corners = 0
    rep_num = rep_den = 0
    ncc_correct = 0
    prev: tuple[FloatArray, np.ndarray, IntArray, FrameTruth] | None = None
    for img, truth in frames:
        img = check_image(img, camera)
        res.n_frames += 1
        det = detect_lamps(img, camera, config.lamps)
        used = [i for i, lm in enumerate(det.lamps) if not lm.touches_border]
        px = np.array([det.lamps[i].pixel for i in used]).reshape(-1, 2)
        lamp = truth.is_lamp()
        vis = lamp & truth.visible
        full = lamp & truth.fully_visible
        res.n_detections += len(used)
        _, dist = _nearest(px, truth.pixel[vis])
        res.n_false += int(np.sum(dist > settings.gate_px))
        full_idx = np.flatnonzero(full)
        res.n_truth_lamps_full += full_idx.size
        j, d = _nearest(truth.pixel[full_idx], px)
        # Truth on the ceiling: the centre's pixel and two points 0.5 px along the axis, mapped.
        tpx = truth.pixel[full_idx]
        ang = np.nan_to_num(truth.angle_px[full_idx])
        half = 0.5 * np.column_stack([np.cos(ang), np.sin(ang)])
        tm = np.asarray(
            camera.normalized_from_pixels(np.concatenate([tpx, tpx + half, tpx - half]))
        ).reshape(3, -1, 2)
        for k, (t_i, d_i, j_i) in enumerate(zip(full_idx, d, j, strict=True)):
            if d_i > settings.gate_px:
                continue
            res.n_found += 1
            cen_err.append(float(d_i))
            mom = det.moments[used[j_i]]
            if truth.types[t_i] == "lamp_rect" and mom.ratio > config.lamps.ratio_threshold:
                ax_err.append(abs(wrap_axis(mom.theta - float(truth.angle_px[t_i]))))
            obs = det.lamps[used[j_i]]
            m_err.append(float(np.hypot(*(obs.m - tm[0, k]))))
            if truth.types[t_i] == "lamp_rect" and obs.axis is not None:
                du, dv = tm[1, k] - tm[2, k]
                ax_m_err.append(abs(wrap_axis(obs.axis - math.atan2(dv, du))))
        # Corners.
        cd = detect_corner_pixels(img, det.mask, config.corners)
        n_corners.append(cd.pixels.shape[0])
        corner_rows = np.flatnonzero(~lamp & truth.visible)
        jc, dc = _nearest(cd.pixels, truth.pixel[corner_rows])
        if corner_rows.size:
            ids = np.where(dc <= settings.corner_gate_px, truth.ids[corner_rows[np.maximum(jc, 0)]], -1)
        else:  # no truth corner in view (the camera sees past the ceiling's edge)
            ids = np.full(cd.pixels.shape[0], -1)
        n_true_corners += int(np.sum(ids >= 0))
        if prev is not None:
            p_pix, p_patch, p_ids, _ = prev
            visible_now = set(truth.ids[corner_rows].tolist())
            seen_now = set(ids[ids >= 0].tolist())
            old = [int(i) for i in p_ids if i >= 0 and int(i) in visible_now]
            rep_den += len(old)
            rep_num += sum(1 for i in old if i in seen_now)
            # NCC: predict at the truth projection, gate, choose.
            sel = [k for k, i in enumerate(p_ids) if i >= 0 and int(i) in visible_now]
            if sel:
                id_to_row = {int(truth.ids[r]): r for r in corner_rows}
                pred = np.array([truth.pixel[id_to_row[int(p_ids[k])]] for k in sel])
                idx, _ = match_ncc(
                    p_patch[sel], pred, cd.patches, cd.pixels, settings.ncc_gate_px,
                    min_ncc=settings.min_ncc,
                )  # fmt: skip
                res.n_ncc_tests += len(sel)
                made = idx >= 0
                res.n_ncc_matches += int(made.sum())
                ncc_correct += int(np.sum(ids[idx[made]] == p_ids[np.array(sel)[made]]))
        prev = (cd.pixels, cd.patches, ids, truth)
    if res.n_truth_lamps_full:
        res.lamp_recall = res.n_found / res.n_truth_lamps_full
    if res.n_detections:
        res.lamp_precision = 1.0 - res.n_false / res.n_detections
    if cen_err:
        e = np.array(cen_err)
        res.centroid_rms_px = float(np.sqrt(np.mean(e * e)))
        res.centroid_max_px = float(e.max())
    if ax_err:
        a = np.degrees(np.array(ax_err))
        res.n_axis = int(a.size)
        res.axis_rms_deg = float(np.sqrt(np.mean(a * a)))
        res.axis_max_deg = float(a.max())
    if m_err:
        e = np.array(m_err)
        res.m_rms, res.m_max = float(np.sqrt(np.mean(e * e))), float(e.max())
    if ax_m_err:
        a = np.degrees(np.array(ax_m_err))
        res.n_axis_m = int(a.size)
        res.axis_m_rms_deg = float(np.sqrt(np.mean(a * a)))
    if n_corners:
        res.n_corners_mean = float(np.mean(n_corners))
        total = int(np.sum(n_corners))
        res.corner_true_fraction = n_true_corners / total if total else math.nan
    if rep_den:
        res.corner_repeatability = rep_num / rep_den
    if res.n_ncc_tests:
        res.ncc_match_rate = res.n_ncc_matches / res.n_ncc_tests
    if res.n_ncc_matches:
        res.ncc_precision = ncc_correct / res.n_ncc_matches
    res.targets_met = {
        "recall>=99%": bool(res.lamp_recall >= 0.99),
        "no_false_lamps": res.n_false == 0,
        "centroid_rms<=0.3px": bool(res.centroid_rms_px <= 0.3),
        "axis_rms<=0.5deg": bool(res.axis_rms_deg <= 0.5),
    }
    return res


def truth_of_frame(projections: ProjectionTable, frame: int) -> FrameTruth:
    """The rows of a ``ProjectionTable`` (``lampsam.datasets.logrun``) for one image."""
    rows = projections.rows_of_frame(frame)
    return FrameTruth(
        ids=projections.ids[rows],
        types=tuple(projections.types[r] for r in rows),
        pixel=projections.pixel[rows],
        angle_px=projections.angle_px[rows],
        visible=projections.visible[rows],
        fully_visible=projections.fully_visible[rows],
    )


def evaluate_run(
    run_dir: str | Path,
    out: str | Path | None = None,
    config: FrontendConfig | None = None,
    settings: EvalSettings | None = None,
    max_frames: int | None = None,
    lamp_models: bool = False,
) -> FrontendMetrics:
    """Evaluate the frontend on a simulated logged run (``lampsam frontend-eval``).

    Args:
        run_dir: a run directory with images and ``truth/projections.csv``.
        out: JSON file to write (None: ``<run_dir>/frontend_eval.json``).
        config: frontend settings.
        settings: evaluation settings.
        max_frames: evaluate only the first frames (None: all).
        lamp_models: check blob sizes against the run's lamp models
            (``landmarks.csv``; :mod:`lampsam.frontend.lamp_models`).

    Returns:
        The metrics (also written as JSON).

    Raises:
        LampsamError: the run cannot be read or has no images or no truth, or
            ``max_frames`` is below 1.
    """
    if max_frames is not None and max_frames < 1:
        raise LampsamError(f"{run_dir}: max_frames must be at least 1, got {max_frames}")
    out_path = Path(out) if out is not None else Path(run_dir) / "frontend_eval.json"
    run = read_run(run_dir)
    if run.images is None or len(run.images) == 0:
        raise LampsamError(f"{run_dir}: the run has no ceiling images")
    if run.projections is None:
        raise LampsamError(f"{run_dir}: no truth/projections.csv (only simulated runs have truth)")
    ensure_dir(out_path.parent)  # before the work, after the input is known good
    images, projections = run.images, run.projections
    if lamp_models:
        if run.landmarks is None:
            raise LampsamError(f"{run_dir}: --lamp-models needs landmarks.csv (simulated runs)")
        config = with_lamp_models(config or FrontendConfig(), run.landmarks, run.rig.camera.z_cam)
    n = len(images) if max_frames is None else min(max_frames, len(images))

    def frames() -> Iterable[tuple[ImageU8, FrameTruth]]:
        for i in range(n):
            yield images.load(i), truth_of_frame(projections, i)

    res = evaluate_frames(frames(), run.rig.camera, config, settings, source=str(run_dir))
    res.to_json(out_path)
    log.info("frontend evaluation written to %s", out_path)
    return res


def with_lamp_models(config: FrontendConfig, landmarks: LandmarkTable, z_cam: float) -> FrontendConfig:
    """``config`` with the lamp size gate of a landmark table's lamps (heights above ``z_cam``).

    Raises:
        LampsamError: the table has no lamps.
    """
    idx = [i for i, t in enumerate(landmarks.types) if t.startswith("lamp")]
    if not idx:
        raise LampsamError("lamp models: the run's landmarks.csv has no lamps")
    gate = size_gate_from_models(
        [landmarks.types[i] for i in idx],
        landmarks.length[idx],
        landmarks.width[idx],
        landmarks.xyz[idx, 2] - z_cam,
    )
    return replace(config, lamps=replace(config.lamps, size_gate=gate))


# --------------------------------------------------------------------------- synthetic scenes
@dataclass(frozen=True)
class SyntheticScene:
    """A flat ceiling in pixel units of a reference view, for :func:`synthetic_sequence`.

    Attributes:
        lamps: shape (L, 5) ``(x, y, length, width, angle)``: centre (px), size (px),
            long-axis angle (rad); ``width == length`` and ``round_lamp`` draws a disc.
        round_lamp: shape (L,) bool, draw a disc of diameter ``length``.
        plates: shape (Q, 5) ``(x, y, length, width, angle)`` rectangles of other
            grey levels (vents, panels, beams); their corners are the corner truth.
        plate_grey: shape (Q,) grey level of each plate.
        background: ceiling grey level.
        lamp_grey: lamp grey level (255 = saturated).
    """

    lamps: FloatArray
    round_lamp: BoolArray
    plates: FloatArray
    plate_grey: FloatArray
    background: float = 70.0
    lamp_grey: float = 240.0


def random_scene(rng: np.random.Generator, size: tuple[int, int] = (900, 700)) -> SyntheticScene:
    """A random ceiling: a grid of lamps (most rectangular, some round) and plates.

    Args:
        rng: random generator.
        size: ``(width, height)`` of the ceiling area, px.
    """
    w, h = size
    lamps = []
    rnd = []
    for x in np.arange(80.0, w - 50, 120.0):
        for y in np.arange(70.0, h - 50, 110.0):
            is_round = rng.random() < 0.2
            length = rng.uniform(10, 14) if is_round else rng.uniform(28, 44)
            width = length if is_round else rng.uniform(6, 10)
            lamps.append((x + rng.uniform(-15, 15), y + rng.uniform(-15, 15), length, width,
                          rng.uniform(-math.pi / 2, math.pi / 2)))  # fmt: skip
            rnd.append(is_round)
    plates: list[tuple[float, float, float, float, float]] = []
    grey: list[float] = []
    lam = np.array(lamps)
    for _ in range(5000):
        if len(plates) >= 40:
            break
        p = (rng.uniform(0, w), rng.uniform(0, h), rng.uniform(14, 40), rng.uniform(10, 30),
             rng.uniform(-math.pi / 2, math.pi / 2))  # fmt: skip
        if np.min(np.hypot(lam[:, 0] - p[0], lam[:, 1] - p[1])) < 52:
            continue
        if plates and np.min(np.hypot(*(np.array(plates)[:, :2] - p[:2]).T)) < 55:
            continue
        plates.append(p)
        grey.append(rng.choice([25.0, 40.0, 120.0, 140.0]))
    return SyntheticScene(
        lamps=lam, round_lamp=np.array(rnd), plates=np.array(plates), plate_grey=np.array(grey)
    )


def _rect_points(spec: FloatArray) -> FloatArray:
    """shape (4, 2) corners of a rotated rectangle ``(x, y, length, width, angle)``."""
    x, y, length, width, ang = spec
    c, s = math.cos(ang), math.sin(ang)
    half = np.array([[1, 1], [-1, 1], [-1, -1], [1, -1]]) * np.array([length, width]) / 2
    rot = np.array([[c, -s], [s, c]])
    return half @ rot.T + np.array([x, y])


def render_view(
    scene: SyntheticScene,
    view: tuple[float, float, float],
    size: tuple[int, int] = (320, 240),
    noise_grey: float = 2.0,
    rng: np.random.Generator | None = None,
) -> tuple[ImageU8, FrameTruth]:
    """Render the scene seen through a similarity ``view`` with truth.

    The image pixel of a scene point ``p`` is ``R(psi) (p - o)`` with
    ``view = (o_x, o_y, psi)``: the view's origin and rotation. Polygons are
    filled at :data:`SUPERSAMPLE` x and area-averaged down.

    Args:
        scene: the ceiling.
        view: ``(o_x, o_y, psi)``, px, px, rad.
        size: ``(width, height)`` of the image.
        noise_grey: sigma of additive Gaussian noise (grey levels).
        rng: generator for the noise (None: no noise).

    Returns:
        The uint8 image and its truth (lamp ids ``0..L-1``, plate corner ids
        ``1000 + 4 q + k``).
    """
    w, h = size
    ox, oy, psi = view
    c, s = math.cos(psi), math.sin(psi)
    rot = np.array([[c, -s], [s, c]])
    ss = SUPERSAMPLE

    def to_img(pts: FloatArray) -> FloatArray:
        return (pts - np.array([ox, oy])) @ rot.T

    big = np.full((h * ss, w * ss), scene.background, np.float32)

    def fill(pts_img: FloatArray, grey: float) -> None:
        big_pts = (pts_img + 0.5) * ss - 0.5
        cv2.fillPoly(big, [np.round(big_pts * 16).astype(np.int32)], float(grey), cv2.LINE_8, 4)

    ids: list[int] = []
    types: list[str] = []
    pix: list[FloatArray] = []
    ang: list[float] = []
    vis: list[bool] = []
    full: list[bool] = []
    for q, spec in enumerate(scene.plates):
        pts = to_img(_rect_points(spec))
        fill(pts, float(scene.plate_grey[q]))
        for k in range(4):
            ids.append(1000 + 4 * q + k)
            types.append("corner")
            pix.append(pts[k])
            ang.append(math.nan)
            inside = bool(0 <= pts[k, 0] <= w - 1 and 0 <= pts[k, 1] <= h - 1)
            vis.append(inside)
            full.append(inside)
    for li, spec in enumerate(scene.lamps):
        centre = to_img(spec[None, :2])[0]
        if scene.round_lamp[li]:
            r = spec[2] / 2
            big_c = (centre + 0.5) * ss - 0.5
            cv2.circle(big, tuple(int(v) for v in np.round(big_c * 16)), int(round(r * ss * 16)),
                       float(scene.lamp_grey), -1, cv2.LINE_8, 4)  # fmt: skip
            outline = centre + r * np.array([[1, 0], [-1, 0], [0, 1], [0, -1]])
            ang.append(math.nan)
            types.append("lamp_round")
        else:
            outline = to_img(_rect_points(spec))
            fill(outline, scene.lamp_grey)
            ang.append(wrap_axis(spec[4] + psi))
            types.append("lamp_rect")
        ids.append(li)
        pix.append(centre)
        inside = (
            (outline[:, 0] >= 1)
            & (outline[:, 0] <= w - 2)
            & (outline[:, 1] >= 1)
            & (outline[:, 1] <= h - 2)
        )
        vis.append(bool(0 <= centre[0] <= w - 1 and 0 <= centre[1] <= h - 1))
        full.append(bool(inside.all()))
    img = cv2.resize(big, (w, h), interpolation=cv2.INTER_AREA)
    if rng is not None and noise_grey > 0:
        img = img + rng.normal(0.0, noise_grey, img.shape)
    out = np.clip(np.round(img), 0, 255).astype(np.uint8)
    truth = FrameTruth(
        ids=np.array(ids, dtype=np.int64),
        types=tuple(types),
        pixel=np.array(pix).reshape(-1, 2),
        angle_px=np.array(ang),
        visible=np.array(vis, dtype=bool),
        fully_visible=np.array(full, dtype=bool),
    )
    return out, truth


def synthetic_sequence(
    rng: np.random.Generator,
    n_frames: int = 20,
    size: tuple[int, int] = (320, 240),
    step_px: float = 6.0,
    turn_rad: float = 0.02,
    noise_grey: float = 2.0,
) -> list[tuple[ImageU8, FrameTruth]]:
    """A short rendered run: the view slides and turns over a random ceiling.

    Args:
        rng: random generator (scene and noise).
        n_frames: number of images.
        size: image ``(width, height)``.
        step_px: translation between frames, px.
        turn_rad: rotation between frames, rad.
        noise_grey: image noise sigma, grey levels.

    Returns:
        ``(image, truth)`` pairs.
    """
    scene = random_scene(rng)
    out = []
    for k in range(n_frames):
        view = (150.0 + step_px * k, 120.0 + 0.5 * step_px * k, turn_rad * k)
        out.append(render_view(scene, view, size, noise_grey, rng))
    return out


def evaluate_synthetic(
    rng: np.random.Generator, n_frames: int = 20, config: FrontendConfig | None = None
) -> FrontendMetrics:
    """:func:`evaluate_frames` on :func:`synthetic_sequence` with a 320x240 camera."""
    frames = synthetic_sequence(rng, n_frames)
    return evaluate_frames(frames, CameraModel(), config, source="synthetic rendering")


def report(metrics: Sequence[FrontendMetrics]) -> str:
    """Summaries of several evaluations, one block each."""
    return "\n\n".join(m.summary() for m in metrics)
