"""Overlay gallery of the ceiling frontend on real photos (``lampsam gallery``).

Each photo is read as grey in its sensor orientation (EXIF rotation ignored, so
the phone photos of ``ceiling_photos`` are 4000x3000 landscape like a camera
frame), run through the frontend at 320x240 (``INTER_AREA``, the robot camera's
frame) and at the photo's working width, and drawn with its detections:
oriented lamps green with their long axis (``+-2 sigma1``), point lamps blue,
border lamps red, corners yellow.

The working-width column is :func:`detect_photo`, the one path that
``lampsam frontend-eval --photos`` scores too: the width chosen from the
photo's lamps and the second look inside long or border-cut blobs
(:func:`lampsam.frontend.resolution.detect_photo_lamps`, docs/photo-labels.md).
The camera model is a pinhole with a 70 deg horizontal field of view
(:func:`photo_camera`: the phone's intrinsics are unknown; it only affects
``m``, not what is drawn).
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING

import cv2
import numpy as np

from lampsam.arrays import ImageU8
from lampsam.datasets.logrun import CameraModel
from lampsam.errors import LampsamError
from lampsam.evaluation.outputs import ensure_dir
from lampsam.frontend.corners import CornerDetections, detect_corner_pixels
from lampsam.frontend.lamp_config import LampDetectorConfig
from lampsam.frontend.lamps import LampDetections, detect_lamps
from lampsam.frontend.pipeline import FrontendConfig, check_image
from lampsam.frontend.resolution import (
    ResolutionPolicy,
    detect_photo_lamps,
    lamp_config_for_width,
    resize_width,
    small_photo_warning,
)
from lampsam.safe_io import atomic_path

if TYPE_CHECKING:
    from matplotlib.axes import Axes

log = logging.getLogger(__name__)

REFERENCE_WIDTH = 320
"""Image width the default settings are tuned for, px."""


@dataclass(frozen=True)
class GalleryEntry:
    """Detections on one photo at one size.

    Attributes:
        name: file name.
        width: image width, px.
        height: image height, px.
        threshold: lamp threshold used (grey level) or None.
        n_lamps: lamps not touching the border.
        n_oriented: of those, with ``R_ori > ratio_threshold``.
        n_border: lamps touching the border (not used).
        n_corners: corners.
        time_ms: lamps + corners wall time, ms.
    """

    name: str
    width: int
    height: int
    threshold: float | None
    n_lamps: int
    n_oriented: int
    n_border: int
    n_corners: int
    time_ms: float


#: Photo files ``make_gallery`` reads (OpenCV decodes them; case-insensitive).
PHOTO_SUFFIXES = (".jpg", ".jpeg", ".png", ".tif", ".tiff", ".bmp", ".webp")


def config_for_width(width: int, base: FrontendConfig | None = None) -> FrontendConfig:
    """Scale the size-dependent settings from 320 px wide images to ``width``.

    Areas scale with ``s^2`` and distances with ``s``, ``s = width / 320``.

    Args:
        width: image width, px.
        base: settings at 320 px (defaults if None).
    """
    base = base or FrontendConfig()
    s = width / REFERENCE_WIDTH
    if abs(s - 1.0) < 1e-9:
        return base
    # Area only, as before: the gallery's full-size column keeps the 320 px reach (scaling it
    # takes a 4000 px photo from ~10 to ~17 s CPU); frontend-eval --photos scales both.
    lamps = lamp_config_for_width(base.lamps, width, scale_reach=False)
    corners = replace(
        base.corners,
        min_spacing_px=max(int(round(base.corners.min_spacing_px * s)), 1),
        lamp_margin_px=max(int(round(base.corners.lamp_margin_px * s)), 1),
    )
    return replace(base, lamps=lamps, corners=corners)


def load_photo(path: str | Path, size: tuple[int, int] | None) -> ImageU8:
    """A photo as grey uint8 in sensor orientation, optionally resized.

    Args:
        path: image file.
        size: ``(width, height)`` to resize to with ``INTER_AREA``, or None (full size).

    Raises:
        LampsamError: the file is missing or not an image.
    """
    read = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE | cv2.IMREAD_IGNORE_ORIENTATION)
    if read is None:
        raise LampsamError(f"{path}: cannot read the image (missing or not an image)")
    small = small_photo_warning(read.shape[1], read.shape[0])
    if small:
        log.warning("%s: %s", path, small)
    if jpeg_cut_short(Path(path)):
        log.warning("%s: the JPEG is cut short (no end-of-image marker): its lower part is "
                    "decoded grey and its lamps there are missed", path)
    if size is not None:
        read = cv2.resize(read, size, interpolation=cv2.INTER_AREA)
    return np.asarray(read, dtype=np.uint8)


def jpeg_cut_short(path: Path) -> bool:
    """True when ``path`` is a JPEG (starts with SOI ``FF D8``) whose last bytes, trailing
    zeros and whitespace aside, are not the EOI marker ``FF D9``: a truncated file, which
    OpenCV decodes with the missing rows grey and only a message on stderr."""
    try:
        with open(path, "rb") as fh:
            head = fh.read(2)
            fh.seek(0, 2)
            size = fh.tell()
            fh.seek(max(size - 64, 0))
            tail = fh.read()
    except OSError:
        return False
    return head == b"\xff\xd8" and not tail.rstrip(b"\x00 \r\n\t").endswith(b"\xff\xd9")


def photo_camera(width: int, height: int) -> CameraModel:
    """A photo's camera at a working size: a 70 deg pinhole (a phone's is not known)."""
    return CameraModel.from_fov(width, height, 70.0)


def detect_photo(
    full: ImageU8,
    lamps: LampDetectorConfig | None = None,
    policy: ResolutionPolicy | None = None,
) -> tuple[LampDetections, LampDetectorConfig]:
    """Lamps of a full-resolution photo as ``frontend-eval --photos`` and the gallery find them.

    Args:
        full: shape (H, W) uint8 grey photo at full resolution.
        lamps: detector settings at 320 px (defaults if None; scaled to the working width).
        policy: resolution policy (default: width from the photo's lamps, second look on).

    Returns:
        ``(detections in working-width pixels, the scaled settings)``; the working
        size is ``detections.mask.shape``.
    """
    base = FrontendConfig().lamps if lamps is None else lamps
    return detect_photo_lamps(full, photo_camera, base, policy)


def run_photo(
    image: ImageU8, config: FrontendConfig | None = None
) -> tuple[LampDetections, CornerDetections, float]:
    """Lamps and corners of one photo.

    Args:
        image: shape (H, W) uint8 grey.
        config: frontend settings (default: :func:`config_for_width` of the width).

    Returns:
        ``(lamps, corners, wall time ms)``.
    """
    img = check_image(image, None)
    h, w = img.shape
    config = config or config_for_width(w)
    camera = photo_camera(w, h)
    t0 = time.perf_counter()
    lamps = detect_lamps(img, camera, config.lamps)
    corners = detect_corner_pixels(img, lamps.mask, config.corners)
    return lamps, corners, 1e3 * (time.perf_counter() - t0)


def plot_detections(
    ax: Axes, image: ImageU8, lamps: LampDetections, corners: CornerDetections, title: str = ""
) -> list[object]:
    """Draw an image with its lamps and corners on a matplotlib axis.

    Args:
        ax: a matplotlib ``Axes``.
        image: shape (H, W) uint8.
        lamps: the lamp detections of ``image``.
        corners: the corner detections of ``image``.
        title: axis title.

    Returns:
        The artists drawn.
    """
    arts: list[object] = [ax.imshow(image, cmap="gray", vmin=0, vmax=255)]
    for lm, mo in zip(lamps.lamps, lamps.moments, strict=True):
        colour = "red" if lm.touches_border else ("lime" if lm.axis is not None else "deepskyblue")
        cx, cy = lm.pixel
        arts += ax.plot([cx], [cy], "o", ms=3, color=colour)
        if lm.axis is not None or lm.touches_border:
            e = 2.0 * mo.sigma1 * np.array([math.cos(mo.theta), math.sin(mo.theta)])
            xs, ys = [cx - e[0], cx + e[0]], [cy - e[1], cy + e[1]]
            arts += ax.plot(xs, ys, "-", lw=1.2, color=colour)
    if corners.pixels.shape[0]:
        arts += ax.plot(corners.pixels[:, 0], corners.pixels[:, 1], "+", ms=4, color="yellow")
    ax.set_title(title, fontsize=7)
    ax.set_axis_off()
    return arts


def legend_handles() -> list[object]:
    """Legend entries for :func:`plot_detections`' markers and colours (one per kind)."""
    from matplotlib.lines import Line2D

    return [
        Line2D([], [], color="lime", marker="o", ms=4, lw=1.2,
               label="oriented lamp (centre, long axis ±2σ₁)"),
        Line2D([], [], color="deepskyblue", marker="o", ms=4, lw=0, label="point lamp (centre)"),
        Line2D([], [], color="red", marker="o", ms=4, lw=1.2, label="lamp at the border (not used)"),
        Line2D([], [], color="yellow", marker="+", ms=6, lw=0, markeredgecolor="goldenrod",
               label="FAST corner"),
    ]


def run_photo_working(
    full: ImageU8, config: FrontendConfig | None = None, policy: ResolutionPolicy | None = None
) -> tuple[ImageU8, LampDetections, CornerDetections, float]:
    """Lamps (:func:`detect_photo`) and corners of a full-resolution photo at its working width.

    Args:
        full: shape (H, W) uint8 grey photo at full resolution.
        config: frontend settings at 320 px (defaults if None; scaled to the working width).
        policy: resolution policy (defaults if None).

    Returns:
        ``(the working image, lamps, corners, wall time ms)``, pixels at the working width.
    """
    base = config or FrontendConfig()
    img = check_image(full, None)
    t0 = time.perf_counter()
    lamps, _ = detect_photo(img, base.lamps, policy)
    w = lamps.mask.shape[1]
    work = resize_width(img, w)
    corners = detect_corner_pixels(work, lamps.mask, config_for_width(w, base).corners)
    return work, lamps, corners, 1e3 * (time.perf_counter() - t0)


def make_gallery(
    photos_dir: str | Path,
    out_png: str | Path,
    full_size: bool = True,
    small_width: int = 320,
) -> list[GalleryEntry]:
    """Run the frontend on every photo of a folder (:data:`PHOTO_SUFFIXES`) and draw the
    gallery.

    A file that cannot be read as an image is skipped with a warning naming it (one bad
    photo does not cost the others).

    Args:
        photos_dir: folder of photos.
        out_png: the gallery image to write (one row per photo; columns: reduced size,
            working width).
        full_size: also run on the full-resolution photo at its working width
            (:func:`run_photo_working`, the path of ``frontend-eval --photos``).
        small_width: the reduced width, px; the height keeps the photo's aspect ratio
            (320 x 240 for a 4:3 photo).

    Returns:
        One entry per photo and size.

    Raises:
        LampsamError: the folder has no readable photos.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    files = sorted(p for p in Path(photos_dir).glob("*") if p.suffix.lower() in PHOTO_SUFFIXES)
    if not files:
        raise LampsamError(f"{photos_dir}: no photos ({', '.join(PHOTO_SUFFIXES)})")
    ensure_dir(Path(out_png).parent)
    sizes: list[int | None] = [small_width] + ([None] if full_size else [])  # None: working width
    fig, axes = plt.subplots(
        len(files), len(sizes), figsize=(4.0 * len(sizes), 3.0 * len(files)), squeeze=False
    )
    entries: list[GalleryEntry] = []
    for r, path in enumerate(files):
        try:
            full = load_photo(path, None)
        except LampsamError as exc:
            log.warning("%s; skipped", exc)
            for ax in axes[r]:
                ax.text(0.5, 0.5, f"{path.name}:\nnot readable, skipped", ha="center",
                        va="center", transform=ax.transAxes)
                ax.set_axis_off()
            continue
        for c, size in enumerate(sizes):
            if size is None:
                img, lamps, corners, ms = run_photo_working(full)
            else:
                img = resize_width(full, size)
                lamps, corners, ms = run_photo(img)
            used = [lm for lm in lamps.lamps if not lm.touches_border]
            entry = GalleryEntry(
                name=path.name,
                width=img.shape[1],
                height=img.shape[0],
                threshold=lamps.threshold,
                n_lamps=len(used),
                n_oriented=sum(lm.axis is not None for lm in used),
                n_border=len(lamps.lamps) - len(used),
                n_corners=int(corners.pixels.shape[0]),
                time_ms=ms,
            )
            entries.append(entry)
            log.info("%s", entry)
            shown = img
            if size is None and img.shape[1] > 1000:  # draw on a 1000 px wide copy
                shown = resize_width(img, 1000)
            scale = shown.shape[1] / img.shape[1]
            plot_detections(
                axes[r, c],
                shown,
                _scaled(lamps, scale),
                CornerDetections(corners.pixels * scale, corners.scores, corners.patches),
                f"{path.name} {img.shape[1]}x{img.shape[0]}"
                f"{' (working width)' if size is None else ''}:\n{entry.n_lamps} lamps "
                f"({entry.n_oriented} oriented), {entry.n_border} border, "
                f"{entry.n_corners} corners",
            )
    if not entries:
        plt.close(fig)
        names = ", ".join(p.name for p in files[:5]) + (", ..." if len(files) > 5 else "")
        raise LampsamError(f"{photos_dir}: none of its {len(files)} photos could be read "
                           f"({names})")
    fig.legend(handles=legend_handles(), loc="lower center", ncol=4, fontsize=8, frameon=False)
    fig.tight_layout(rect=(0, 0.9 / (3.0 * len(files)), 1, 1))
    with atomic_path(out_png) as tmp:
        fig.savefig(tmp, dpi=130)
    plt.close(fig)
    return entries


def _scaled(det: LampDetections, s: float) -> LampDetections:
    """Detections with pixel quantities scaled by ``s`` (for drawing on a resized image)."""
    lamps = tuple(replace(lm, pixel=lm.pixel * s) for lm in det.lamps)
    moms = tuple(replace(mo, centroid=mo.centroid * s, sigma1=mo.sigma1 * s) for mo in det.moments)
    return replace(det, lamps=lamps, moments=moms)
