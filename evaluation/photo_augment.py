"""Photo robustness: the labelled photos under known transforms, scored per transform family.

Stand-in for photos of rooms we do not have (issue 20): each labelled photo
(:mod:`lampsam.evaluation.photo_labels`) is changed by a transform whose effect
on the labels is known exactly, and the detector's path of
``lampsam frontend-eval --photos`` (:func:`lampsam.evaluation.gallery.detect_photo`)
is scored on the result with :func:`lampsam.evaluation.photo_eval.score_photo`.

Geometric families are plane projective maps ``H`` (3x3, source full-resolution
pixels to output pixels, pixel centres at integers); the image is warped by
``H`` and every labelled rectangle's ends and sides are mapped by it
(:func:`warp_region`), so the labels are as exact as the originals:

* ``rotation``: about the photo's centre by 0-360 deg (a camera turned about its axis);
* ``tilt``: ``H = K R K^-1``, the image of the same scene after the camera turns by
  10-30 deg about a random axis in the image plane (``K``: 70 deg pinhole), re-centred;
* ``scale``: the whole photo resampled by 0.5-2x (another sensor resolution);
* ``crop``: 30-80 % of the photo's area at a random place (a narrower view: lamps
  larger in the frame, more of them cut by the border).

Rotation and tilt keep the largest rectangle of the photo's aspect inside the
warped photo (:func:`inscribed_crop`), so no pixel is invented: the output is a
photo another camera pose could have taken, with lamps cut by its border as a
real frame cuts them. A labelled region not wholly inside the source photo is
marked occluded (not countable) in the output.

Photometric families change the colour photo before the grey conversion:
``exposure`` (+-1 stop, in linear light, clipped at white as a sensor
saturates), ``gamma`` (0.6-1.6 on the 8-bit levels), ``white_balance`` (red
and blue gains 0.6-1.5 against green, in linear light), ``blur`` (Gaussian,
sigma 1-12 px of a 4000 px photo), ``noise`` (Gaussian, sigma 2-16 grey
levels, per pixel and channel) and ``jpeg`` (re-encoded at quality 50-95).

A bright window in view (:func:`paste_window`): a barred window, flat saturated or
a textured sky, pasted where it hides the fewest lamps, its panes labelled
``window`` (``scripts/window_photos.py``; docs/photo-labels.md, last section).

Every draw comes from one seeded :class:`numpy.random.Generator`.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path

import cv2
import numpy as np

from lampsam.arrays import FloatArray, ImageU8
from lampsam.errors import LampsamError
from lampsam.evaluation.gallery import detect_photo
from lampsam.evaluation.photo_eval import PhotoEvalSettings, PhotoScore, score_photo, total
from lampsam.evaluation.photo_labels import PhotoLabels, Region, read_labels
from lampsam.frontend.lamp_config import LampDetectorConfig
from lampsam.frontend.resolution import ResolutionPolicy

GEOMETRIC = ("rotation", "tilt", "scale", "crop")
PHOTOMETRIC = ("exposure", "gamma", "white_balance", "blur", "noise", "jpeg")
FAMILIES = ("identity", *GEOMETRIC, *PHOTOMETRIC)
FOV_DEG = 70.0  # the photos' assumed horizontal field of view (gallery.photo_camera)


@dataclass(frozen=True)
class Transform:
    """One drawn transform.

    Attributes:
        family: one of :data:`FAMILIES`.
        value: the family's drawn parameter (deg, factor, stops, gamma, px, grey levels
            or JPEG quality; see the module docstring).
        homography: shape (3, 3) source full-resolution pixels -> output pixels
            (identity for photometric families).
        size: output ``(width, height)``, px.
        extra: further parameters (tilt azimuth, white-balance gains, crop origin).
    """

    family: str
    value: float
    homography: FloatArray
    size: tuple[int, int]
    extra: dict[str, float] = field(default_factory=dict)


def rotation_about(centre: FloatArray, angle_deg: float) -> FloatArray:
    """shape (3, 3) rotation by ``angle_deg`` (from +col towards +row) about pixel ``centre``."""
    a = math.radians(angle_deg)
    c, s = math.cos(a), math.sin(a)
    t = np.asarray(centre, dtype=np.float64)
    r = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return translation(t) @ r @ translation(-t)


def translation(d: FloatArray) -> FloatArray:
    """shape (3, 3) translation by ``d`` (2,) px."""
    return np.array([[1.0, 0.0, d[0]], [0.0, 1.0, d[1]], [0.0, 0.0, 1.0]])


def tilt_homography(size: tuple[int, int], tilt_deg: float, azimuth_deg: float) -> FloatArray:
    """``K R K^-1``: the image map of a camera turned by ``tilt_deg`` about an in-plane axis.

    The axis lies in the image plane at ``azimuth_deg`` from +col; ``K`` is a
    :data:`FOV_DEG` pinhole centred on the image. Points on the ceiling plane
    map exactly (a pure rotation of the camera moves every ray, whatever its
    depth, by the same homography). The result is shifted so that the image
    centre stays where it was.
    """
    w, h = size
    f = 0.5 * w / math.tan(math.radians(0.5 * FOV_DEG))
    k = np.array([[f, 0.0, 0.5 * (w - 1)], [0.0, f, 0.5 * (h - 1)], [0.0, 0.0, 1.0]])
    az = math.radians(azimuth_deg)
    axis = np.array([math.cos(az), math.sin(az), 0.0]) * math.radians(tilt_deg)
    r, _ = cv2.Rodrigues(axis)
    hom = k @ r @ np.linalg.inv(k)
    c = np.array([0.5 * (w - 1), 0.5 * (h - 1)])
    return translation(c - apply_h(hom, c[None, :])[0]) @ hom


def apply_h(hom: FloatArray, pts: FloatArray) -> FloatArray:
    """Points ``pts`` (N, 2) mapped by the homography ``hom`` (3, 3)."""
    p = np.asarray(pts, dtype=np.float64)
    q = np.c_[p, np.ones(len(p))] @ hom.T
    return q[:, :2] / q[:, 2:3]


def inscribed_crop(hom: FloatArray, size: tuple[int, int]) -> tuple[FloatArray, tuple[int, int]]:
    """The warp followed by the largest centred crop of the source's aspect inside the warped photo.

    Args:
        hom: shape (3, 3) source -> warped pixels.
        size: source ``(width, height)``.

    Returns:
        ``(homography source -> crop pixels, crop (width, height))``.
    """
    w, h = size
    quad = apply_h(hom, np.array([[0.0, 0.0], [w - 1.0, 0.0], [w - 1.0, h - 1.0], [0.0, h - 1.0]]))
    centre = apply_h(hom, np.array([[0.5 * (w - 1), 0.5 * (h - 1)]]))[0]
    poly = quad.astype(np.float32).reshape(-1, 1, 2)
    aspect = w / h

    def fits(t: float) -> bool:
        half = np.array([0.5 * aspect * t, 0.5 * t])
        corners = centre + half * np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]])
        return all(cv2.pointPolygonTest(poly, (float(x), float(y)), False) >= 0 for x, y in corners)

    lo, hi = 0.0, float(max(w, h)) * 2.0
    for _ in range(40):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if fits(mid) else (lo, mid)
    out_h = int(math.floor(lo))
    out_w = int(math.floor(lo * aspect))
    origin = centre - 0.5 * np.array([out_w - 1, out_h - 1])
    return translation(-origin) @ hom, (out_w, out_h)


def draw_transform(
    family: str, rng: np.random.Generator, size: tuple[int, int]
) -> Transform:
    """Draw one transform of ``family`` for a photo of ``size`` ``(width, height)``."""
    w, h = size
    eye = np.eye(3)
    if family == "identity":
        return Transform(family, 0.0, eye, size)
    if family == "rotation":
        a = float(rng.uniform(0.0, 360.0))
        hom, out = inscribed_crop(rotation_about(np.array([0.5 * (w - 1), 0.5 * (h - 1)]), a), size)
        return Transform(family, a, hom, out)
    if family == "tilt":
        t, az = float(rng.uniform(10.0, 30.0)), float(rng.uniform(0.0, 360.0))
        hom, out = inscribed_crop(tilt_homography(size, t, az), size)
        return Transform(family, t, hom, out, {"azimuth_deg": az})
    if family == "scale":
        s = float(math.exp(rng.uniform(math.log(0.5), math.log(2.0))))
        out = (round(w * s), round(h * s))
        sx, sy = out[0] / w, out[1] / h  # cv2.resize: x' = sx (x + 0.5) - 0.5
        hom = np.array([[sx, 0.0, 0.5 * sx - 0.5], [0.0, sy, 0.5 * sy - 0.5], [0.0, 0.0, 1.0]])
        return Transform(family, s, hom, out)
    if family == "crop":
        frac = float(rng.uniform(0.3, 0.8))
        cw, ch = round(w * math.sqrt(frac)), round(h * math.sqrt(frac))
        x0, y0 = int(rng.integers(0, w - cw + 1)), int(rng.integers(0, h - ch + 1))
        return Transform(family, frac, translation(np.array([-x0, -y0])), (cw, ch),
                         {"x0": x0, "y0": y0})
    draws: dict[str, Callable[[], float]] = {
        "exposure": lambda: float(rng.uniform(-1.0, 1.0)),
        "gamma": lambda: float(math.exp(rng.uniform(math.log(0.6), math.log(1.6)))),
        "blur": lambda: float(rng.uniform(1.0, 12.0)) * w / 4000.0,
        "noise": lambda: float(rng.uniform(2.0, 16.0)),
        "jpeg": lambda: float(rng.integers(50, 96)),
    }
    if family == "white_balance":
        gr, gb = (float(math.exp(rng.uniform(math.log(0.6), math.log(1.5)))) for _ in range(2))
        return Transform(family, gr / gb, eye, size, {"gain_r": gr, "gain_b": gb})
    if family not in draws:
        raise LampsamError(f"photo augmentation: unknown family {family!r} (known: {list(FAMILIES)})")
    return Transform(family, draws[family](), eye, size)


def _to_linear(bgr: ImageU8) -> FloatArray:
    """sRGB 8-bit -> linear light in [0, 1] (IEC 61966-2-1 curve)."""
    c = bgr.astype(np.float32) / 255.0
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


def _to_srgb(lin: FloatArray) -> ImageU8:
    """Linear light (clipped to [0, 1]) -> sRGB 8-bit."""
    c = np.clip(lin, 0.0, 1.0)
    s = np.where(c <= 0.0031308, 12.92 * c, 1.055 * np.power(c, 1.0 / 2.4) - 0.055)
    return np.asarray(np.clip(np.rint(255.0 * s), 0, 255), dtype=np.uint8)


def apply_photometric(bgr: ImageU8, tr: Transform, rng: np.random.Generator) -> ImageU8:
    """A photometric transform of a colour photo (H, W, 3) uint8 BGR; the same photo for geometric ones."""
    fam = tr.family
    if fam == "exposure":
        return _to_srgb(_to_linear(bgr) * 2.0**tr.value)
    if fam == "white_balance":
        gains = np.array([tr.extra["gain_b"], 1.0, tr.extra["gain_r"]], dtype=np.float32)
        return _to_srgb(_to_linear(bgr) * gains)
    if fam == "gamma":
        lut = np.clip(np.rint(255.0 * (np.arange(256) / 255.0) ** tr.value), 0, 255).astype(np.uint8)
        return np.asarray(cv2.LUT(bgr, lut), dtype=np.uint8)
    if fam == "blur":
        return np.asarray(cv2.GaussianBlur(bgr, (0, 0), tr.value), dtype=np.uint8)
    if fam == "noise":
        noisy = bgr.astype(np.float32) + rng.normal(0.0, tr.value, bgr.shape).astype(np.float32)
        return np.asarray(np.clip(np.rint(noisy), 0, 255), dtype=np.uint8)
    if fam == "jpeg":
        ok, buf = cv2.imencode(".jpg", bgr, [cv2.IMWRITE_JPEG_QUALITY, int(tr.value)])
        if not ok:
            raise LampsamError("photo augmentation: JPEG encoding failed")
        return np.asarray(cv2.imdecode(buf, cv2.IMREAD_COLOR), dtype=np.uint8)
    return bgr


def apply_geometric(grey: ImageU8, tr: Transform) -> ImageU8:
    """The grey photo mapped by the transform's homography into its output size."""
    if tr.family in ("identity", *PHOTOMETRIC):
        return grey
    if tr.family == "crop":
        x0, y0 = int(tr.extra["x0"]), int(tr.extra["y0"])
        return np.ascontiguousarray(grey[y0 : y0 + tr.size[1], x0 : x0 + tr.size[0]])
    if tr.family == "scale":
        interp = cv2.INTER_AREA if tr.value < 1.0 else cv2.INTER_LINEAR
        return np.asarray(cv2.resize(grey, tr.size, interpolation=interp), dtype=np.uint8)
    out = cv2.warpPerspective(grey, tr.homography, tr.size, flags=cv2.INTER_LINEAR,
                              borderMode=cv2.BORDER_REPLICATE)
    return np.asarray(out, dtype=np.uint8)


def warp_region(r: Region, hom: FloatArray) -> Region:
    """A labelled rectangle mapped by ``hom``: ends, side widths and area centroid.

    The axis runs between the images of the two short sides' midpoints, the
    length is their distance, the width the mean of the two mapped short
    sides, the centre the area centroid of the mapped corners (what the
    detector's coverage centroid measures). Exact for similarities; for a
    projective map the mapped rectangle is a quadrilateral and this is its
    best rotated rectangle.
    """
    a = math.radians(r.axis_deg)
    u = np.array([math.cos(a), math.sin(a)])
    v = np.array([-u[1], u[0]])
    c = np.asarray(r.centre, dtype=np.float64)
    ends = apply_h(hom, np.array([c - 0.5 * r.length * u, c + 0.5 * r.length * u]))
    sides = apply_h(hom, np.array([
        c - 0.5 * r.length * u - 0.5 * r.width * v, c - 0.5 * r.length * u + 0.5 * r.width * v,
        c + 0.5 * r.length * u - 0.5 * r.width * v, c + 0.5 * r.length * u + 0.5 * r.width * v,
    ]))
    d = ends[1] - ends[0]
    width = 0.5 * (np.linalg.norm(sides[1] - sides[0]) + np.linalg.norm(sides[3] - sides[2]))
    quad = sides[[0, 2, 3, 1]]
    m = cv2.moments(quad.astype(np.float32))
    centre = np.array([m["m10"] / m["m00"], m["m01"] / m["m00"]]) if m["m00"] > 0 else ends.mean(0)
    return replace(r, centre=centre, axis_deg=math.degrees(math.atan2(d[1], d[0])),
                   length=float(np.linalg.norm(d)), width=float(width))


def _inside_source(r: Region, w: int, h: int) -> bool:
    """The rectangle lies wholly inside the ``w`` x ``h`` source photo."""
    c = r.corners()
    return bool((c.min(axis=0) >= 0.0).all() and c[:, 0].max() <= w - 1 and c[:, 1].max() <= h - 1)


def warp_labels(labels: PhotoLabels, tr: Transform) -> PhotoLabels:
    """The photo's labels in the transformed photo (regions cut by the source's border: occluded)."""
    regions = tuple(
        replace(warp_region(r, tr.homography),
                occluded=r.occluded or not _inside_source(r, labels.width, labels.height))
        for r in labels.regions
    )
    return replace(labels, width=tr.size[0], height=tr.size[1], regions=regions)


def load_colour(path: str | Path) -> ImageU8:
    """A photo as BGR uint8 in sensor orientation (EXIF ignored, as ``load_photo`` reads it)."""
    bgr = cv2.imread(str(path), cv2.IMREAD_COLOR | cv2.IMREAD_IGNORE_ORIENTATION)
    if bgr is None:
        raise LampsamError(f"{path}: cannot read the image (missing or not an image)")
    return np.asarray(bgr, dtype=np.uint8)


@dataclass(frozen=True)
class AugmentSettings:
    """Settings of the robustness evaluation.

    Attributes:
        families: transform families to run (default all, identity first).
        samples: transforms drawn per photo and family (identity: one).
        seed: seed of the one ``numpy.random.Generator``.
        policy: the detector's resolution policy (default: width from the lamps, second look).
        eval_settings: matching rules of :func:`lampsam.evaluation.photo_eval.score_photo`.
    """

    families: tuple[str, ...] = FAMILIES
    samples: int = 4
    seed: int = 0
    policy: ResolutionPolicy = ResolutionPolicy()
    eval_settings: PhotoEvalSettings = PhotoEvalSettings()


@dataclass
class TrialScore:
    """One photo under one transform."""

    family: str
    value: float
    score: PhotoScore


def run_trials(
    photos_dir: str | Path,
    labels_path: str | Path,
    settings: AugmentSettings | None = None,
    config: LampDetectorConfig | None = None,
    photos: tuple[str, ...] | None = None,
    progress: Callable[[TrialScore], None] | None = None,
) -> list[TrialScore]:
    """Every labelled photo (or those named in ``photos``) under every family's drawn transforms.

    The draws are made photo by photo, family by family, from one generator, so
    a run is reproduced by its seed and its photo and family lists.

    Raises:
        LampsamError: unreadable labels, a photo missing or of another size than its labels.
    """
    settings = settings or AugmentSettings()
    rng = np.random.default_rng(settings.seed)
    labels = read_labels(labels_path)
    out: list[TrialScore] = []
    for name, pl in labels.items():
        if photos is not None and name not in photos and name.split("_")[0] not in photos:
            continue
        bgr = load_colour(Path(photos_dir) / name)
        if bgr.shape[:2] != (pl.height, pl.width):
            raise LampsamError(f"{name}: {bgr.shape[1]}x{bgr.shape[0]} px, labels are for "
                               f"{pl.width}x{pl.height}")
        grey = np.asarray(cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY), dtype=np.uint8)
        for fam in settings.families:
            for _ in range(1 if fam == "identity" else settings.samples):
                tr = draw_transform(fam, rng, (pl.width, pl.height))
                img: ImageU8 = (
                    np.asarray(cv2.cvtColor(apply_photometric(bgr, tr, rng), cv2.COLOR_BGR2GRAY),
                               dtype=np.uint8)
                    if fam in PHOTOMETRIC else apply_geometric(grey, tr)
                )
                det, cfg = detect_photo(img, config, settings.policy)
                h, w = det.mask.shape
                sc = score_photo(det, warp_labels(pl, tr), (w, h), cfg, settings.eval_settings)
                sc.width = w
                trial = TrialScore(fam, tr.value, sc)
                out.append(trial)
                if progress is not None:
                    progress(trial)
    return out


def family_totals(trials: list[TrialScore], uses: tuple[str, ...]) -> dict[str, PhotoScore]:
    """Pooled scores per family over the trials of photos whose ``use`` is in ``uses``."""
    fams = list(dict.fromkeys(t.family for t in trials))
    return {
        f: total([t.score for t in trials if t.family == f and t.score.use in uses], f, "/".join(uses))
        for f in fams
    }


def format_families(totals: dict[str, PhotoScore]) -> str:
    """A text table: one line per family (precision, recall, errors, false detections by kind)."""
    lines = [f"{'family':14s} {'det':>5s} {'prec':>6s} {'lamps':>5s} {'recall':>6s} {'fits':>5s} "
             f"{'f_rec':>6s} {'split':>5s} {'c_rms px':>8s} {'ax_rms deg':>10s}  false by kind"]
    for fam, s in totals.items():
        r = s.row()
        lines.append(
            f"{fam:14s} {s.n_detections:5d} {s.precision:6.3f} {s.n_lamps:5d} {s.recall:6.3f} "
            f"{s.n_fittings:5d} {s.recall_fitting:6.3f} "
            f"{s.n_split:5d} {r['centroid_rms_px']:8.2f} {r['axis_rms_deg']:10.2f}  "
            + (", ".join(f"{k} {v}" for k, v in sorted(s.false_by_kind.items())) or "-")
        )
    return "\n".join(lines)


def window_rect(labels: PhotoLabels, size: tuple[int, int]) -> tuple[int, int]:
    """Top-left ``(col, row)`` of a ``size`` px window pasted where it hides the fewest lamps.

    Candidates on a 12 x 12 grid of positions over the photo; the score is the
    number of lamp centres inside the window (ties: the first in raster order).
    """
    ww, wh = size
    cols = np.linspace(0, labels.width - ww, 12).astype(int)
    rows = np.linspace(0, labels.height - wh, 12).astype(int)
    centres = np.array([r.centre for r in labels.regions if r.kind == "lamp"]).reshape(-1, 2)
    best, best_n = (0, 0), math.inf
    for r0 in rows.tolist():
        for c0 in cols.tolist():
            inside = ((centres[:, 0] >= c0 - 0.1 * ww) & (centres[:, 0] <= c0 + 1.1 * ww)
                      & (centres[:, 1] >= r0 - 0.1 * wh) & (centres[:, 1] <= r0 + 1.1 * wh))
            n = int(np.count_nonzero(inside))
            if n < best_n:
                best, best_n = (c0, r0), n
    return best


def paste_window(
    grey: ImageU8,
    labels: PhotoLabels,
    frac: tuple[float, float] = (0.36, 0.29),
    panes: tuple[int, int] = (3, 2),
    bar_frac: float = 0.012,
    textured: bool = False,
    rng: np.random.Generator | None = None,
) -> tuple[ImageU8, PhotoLabels]:
    """A photo with a bright window pasted in, and its labels with the window added.

    The window (the audit's case, docs/failures.md: a 360x220 px saturated pane
    with glazing bars in a 1000 px photo) covers ``frac`` of the photo's width
    and height, split into ``panes`` (columns, rows) by dark bars ``bar_frac``
    of the photo's width thick (grey 70, a frame round the outside too). Panes
    are 255 (flat, saturated) or, ``textured``, sky 235-255 with a vertical
    gradient and seeded noise (clipped at 255). Lamps whose centres the window
    covers are marked occluded; each pane is labelled ``window``.

    Args:
        grey: shape (H, W) uint8 full-resolution photo.
        labels: its labels.
        frac: window width and height as fractions of the photo's.
        panes: panes across and down.
        bar_frac: bar thickness / photo width.
        textured: sky texture instead of flat saturated panes.
        rng: the generator for the texture (needed when ``textured``).
    """
    h, w = grey.shape
    ww, wh = int(round(frac[0] * w)), int(round(frac[1] * h))
    c0, r0 = window_rect(labels, (ww, wh))
    bar = max(int(round(bar_frac * w)), 1)
    out = grey.copy()
    if textured:
        if rng is None:
            raise ValueError("paste_window: a textured window needs a generator")
        grad = np.linspace(255.0, 235.0, wh)[:, None] * np.ones((1, ww))
        sky = np.clip(grad + rng.normal(0.0, 6.0, (wh, ww)), 0, 255)
        pane_img = sky.astype(np.uint8)
    else:
        pane_img = np.full((wh, ww), 255, dtype=np.uint8)
    out[r0:r0 + wh, c0:c0 + ww] = pane_img
    regions = []
    xs = np.linspace(0, ww - bar, panes[0] + 1).round().astype(int)
    ys = np.linspace(0, wh - bar, panes[1] + 1).round().astype(int)
    for x in xs.tolist():
        out[r0:r0 + wh, c0 + x:c0 + x + bar] = 70
    for y in ys.tolist():
        out[r0 + y:r0 + y + bar, c0:c0 + ww] = 70
    for i in range(panes[0]):
        for j in range(panes[1]):
            x_lo, x_hi = c0 + xs[i] + bar, c0 + xs[i + 1]
            y_lo, y_hi = r0 + ys[j] + bar, r0 + ys[j + 1]
            regions.append(Region("window", np.array([(x_lo + x_hi - 1) / 2, (y_lo + y_hi - 1) / 2]),
                                  0.0, float(x_hi - x_lo), float(y_hi - y_lo)))

    def covered(r: Region) -> bool:
        cx, cy = r.centre.tolist()
        return bool(c0 <= cx < c0 + ww and r0 <= cy < r0 + wh)

    kept = tuple(replace(r, occluded=True) if r.kind == "lamp" and covered(r) else r
                 for r in labels.regions)
    return out, replace(labels, regions=kept + tuple(regions))
