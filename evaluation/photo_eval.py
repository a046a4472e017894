"""The lamp detector measured against hand labels of real photos (``lampsam frontend-eval --photos``).

Each labelled photo (:mod:`lampsam.evaluation.photo_labels`) is read as grey
in sensor orientation, reduced to the working width (``INTER_AREA``; default
320 px, the robot camera's) and run through
:func:`lampsam.evaluation.gallery.detect_photo` (the path that ``lampsam
gallery`` draws) with the settings scaled to that width
(:func:`lampsam.frontend.resolution.lamp_config_for_width`). Blobs touching
the border are left out, as :func:`lampsam.frontend.pipeline.process_image`
does. The labels are scaled to the working size, then:

With ``auto_width`` the working width is chosen per photo from its lamps
(:func:`lampsam.frontend.resolution.width_for_lamps`); with ``second_look``
the blobs long for their frame or cut by the border are looked at again at
full resolution (:mod:`lampsam.frontend.second_look`).

* a detection is **true** when its centroid lies in a ``lamp`` rectangle
  grown by ``margin`` (``max(margin_px, margin_frac * width)``), or in the
  rectangle of a whole fitting (its modules merged: a detection of a fitting
  whose modules were not parted); otherwise it is false, and its kind is that
  of the region it lies in (``window``, ``skylight``, ``reflection``,
  ``lamp_fragment``, ``other``) or ``unlabelled``;
* precision = true detections / detections;
* recall = countable lamps with a true detection / countable lamps, where a
  lamp is countable when it is not occluded, lies entirely inside the image
  and covers at least the detector's ``min_area_px`` (a lamp the working
  resolution cannot show is reported as ``n_small``, not missed); a lamp is one
  module (docs/photo-labels.md), and a detection on a fitting's connector finds
  the module nearest to it;
* fitting recall (the other reading of a multi-module fitting): countable
  fittings (every module countable) with a true detection on any module /
  countable fittings; a fitting of one module is that module;
* centroid error: distance from the labelled centre to the nearest true
  detection, px at the working size (RMS and max, over countable lamps);
* axis error: for countable lamps at least twice as long as wide, the
  detection's image axis (eq. 5 of paper 1) against the labelled axis, modulo
  180 deg (RMS and max).

Photos labelled ``use: tune`` were used to choose detector settings; figures
are given for them and for the ``report`` photos separately.
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import numpy as np

from lampsam.angles import wrap_axis
from lampsam.errors import LampsamError
from lampsam.evaluation.gallery import detect_photo, load_photo
from lampsam.evaluation.photo_labels import PhotoLabels, Region, merge_regions, read_labels
from lampsam.frontend.lamp_config import LampDetectorConfig
from lampsam.frontend.lamps import LampDetections
from lampsam.frontend.pipeline import FrontendConfig
from lampsam.frontend.resolution import ResolutionPolicy
from lampsam.safe_io import write_text_atomic


@dataclass(frozen=True)
class PhotoEvalSettings:
    """Settings of the photo evaluation.

    Attributes:
        width: working image width, px (height keeps the aspect ratio) when
            ``auto_width`` is off.
        margin_px: a detection is on a lamp within this distance of its rectangle, px.
        margin_frac: ... or within this fraction of the lamp's width, if larger.
        auto_width: choose the working width per photo from its lamps
            (:func:`lampsam.frontend.resolution.width_for_lamps`).
        second_look: look at full resolution inside blobs long for their
            frame or cut by the border (:mod:`lampsam.frontend.second_look`).
    """

    width: int = 320
    margin_px: float = 2.0
    margin_frac: float = 0.25
    auto_width: bool = False
    second_look: bool = False


@dataclass
class PhotoScore:
    """Figures of one photo (or a sum over photos: see :func:`total`)."""

    name: str
    use: str
    width: int = 0
    n_detections: int = 0
    n_true: int = 0
    false_by_kind: dict[str, int] = field(default_factory=dict)
    n_lamps: int = 0
    n_found: int = 0
    n_small: int = 0
    n_split: int = 0
    n_fittings: int = 0
    n_fittings_found: int = 0
    centroid_err_px: list[float] = field(default_factory=list)
    axis_err_deg: list[float] = field(default_factory=list)

    @property
    def precision(self) -> float:
        """True detections / detections (NaN without detections)."""
        return self.n_true / self.n_detections if self.n_detections else math.nan

    @property
    def recall(self) -> float:
        """Countable lamps (modules) found / countable lamps (NaN without lamps)."""
        return self.n_found / self.n_lamps if self.n_lamps else math.nan

    @property
    def recall_fitting(self) -> float:
        """Countable fittings found / countable fittings (NaN without fittings)."""
        return self.n_fittings_found / self.n_fittings if self.n_fittings else math.nan

    def row(self) -> dict[str, object]:
        """The figures as a flat JSON-ready dict (RMS and max of the errors)."""

        def rms(v: list[float]) -> float:
            return float(np.sqrt(np.mean(np.square(v)))) if v else math.nan

        return {
            "photo": self.name,
            "use": self.use,
            "width": self.width,
            "detections": self.n_detections,
            "true": self.n_true,
            "false": dict(sorted(self.false_by_kind.items())),
            "lamps": self.n_lamps,
            "found": self.n_found,
            "too_small": self.n_small,
            "split": self.n_split,
            "precision": self.precision,
            "recall": self.recall,
            "fittings": self.n_fittings,
            "fittings_found": self.n_fittings_found,
            "recall_fitting": self.recall_fitting,
            "centroid_rms_px": rms(self.centroid_err_px),
            "centroid_max_px": max(self.centroid_err_px, default=math.nan),
            "axis_rms_deg": rms(self.axis_err_deg),
            "axis_max_deg": max(self.axis_err_deg, default=math.nan),
        }


def total(scores: list[PhotoScore], name: str, use: str) -> PhotoScore:
    """The sum of several photos' figures (precision and recall pooled over detections and lamps)."""
    out = PhotoScore(name, use)
    for s in scores:
        out.n_detections += s.n_detections
        out.n_true += s.n_true
        for k, v in s.false_by_kind.items():
            out.false_by_kind[k] = out.false_by_kind.get(k, 0) + v
        out.n_lamps += s.n_lamps
        out.n_found += s.n_found
        out.n_small += s.n_small
        out.n_split += s.n_split
        out.n_fittings += s.n_fittings
        out.n_fittings_found += s.n_fittings_found
        out.centroid_err_px += s.centroid_err_px
        out.axis_err_deg += s.axis_err_deg
    return out


def score_photo(
    det: LampDetections,
    labels: PhotoLabels,
    image_size: tuple[int, int],
    config: LampDetectorConfig,
    settings: PhotoEvalSettings,
) -> PhotoScore:
    """Score one photo's detections against its labels (rules in the module docstring).

    Args:
        det: the detector's output on the photo at the working size.
        labels: the photo's labels (full-resolution pixels).
        image_size: ``(width, height)`` of the working image, px.
        config: the detector settings used (``min_area_px``).
        settings: evaluation settings.
    """
    w, h = image_size
    s = w / labels.width
    regions = [r.scaled(s) for r in labels.regions]
    lamps = [r for r in regions if r.kind == "lamp"]
    others = [r for r in regions if r.kind != "lamp"]
    out = PhotoScore(labels.name, labels.use)
    fittings = _fittings(lamps)
    whole = [merge_regions([lamps[i] for i in f], "lamp") if len(f) > 1 else None for f in fittings]
    hits: list[list[tuple[float, float | None]]] = [[] for _ in lamps]  # (distance, theta)
    for lamp_obs, mom in zip(det.lamps, det.moments, strict=True):
        if lamp_obs.touches_border:
            continue
        out.n_detections += 1
        px = np.asarray(mom.centroid, dtype=np.float64)
        best, best_d = -1, math.inf
        for i, r in enumerate(lamps):
            margin = max(settings.margin_px, settings.margin_frac * r.width)
            d = float(np.hypot(*(px - r.centre)))
            if r.contains(px, margin) and d < best_d:
                best, best_d = i, d
        for f, wr in zip(fittings, whole, strict=True):
            if best < 0 and wr is not None and wr.contains(px, max(settings.margin_px, settings.margin_frac * wr.width)):
                best = min(f, key=lambda i: float(np.hypot(*(px - lamps[i].centre))))
                best_d = float(np.hypot(*(px - lamps[best].centre)))
        if best >= 0:
            out.n_true += 1
            theta = mom.theta if mom.ratio > config.ratio_threshold else None
            hits[best].append((best_d, theta))
            continue
        kind = next((r.kind for r in others if r.contains(px, settings.margin_px)), "unlabelled")
        out.false_by_kind[kind] = out.false_by_kind.get(kind, 0) + 1
    for r, hit in zip(lamps, hits, strict=True):
        if not _countable(r, w, h, config):
            if not r.occluded and _inside(r, w, h):
                out.n_small += 1
            continue
        out.n_lamps += 1
        if not hit:
            continue
        out.n_found += 1
        out.n_split += len(hit) > 1
        d, theta = min(hit, key=lambda t: t[0])
        out.centroid_err_px.append(d)
        if r.length >= 2.0 * r.width and theta is not None:
            out.axis_err_deg.append(abs(math.degrees(wrap_axis(theta - math.radians(r.axis_deg)))))
    for f in fittings:
        if all(_countable(lamps[i], w, h, config) for i in f):
            out.n_fittings += 1
            out.n_fittings_found += any(hits[i] for i in f)
    return out


def _fittings(lamps: list[Region]) -> list[list[int]]:
    """Indices of the lamps (modules) of each fitting: by ``fitting`` number, one each without."""
    groups: dict[int, list[int]] = {}
    out: list[list[int]] = []
    for i, r in enumerate(lamps):
        if r.fitting is None:
            out.append([i])
        elif r.fitting in groups:
            groups[r.fitting].append(i)
        else:
            groups[r.fitting] = [i]
            out.append(groups[r.fitting])
    return out


def _inside(r: Region, w: int, h: int) -> bool:
    """The rectangle lies entirely inside a ``w`` x ``h`` image (0.5 px margin)."""
    c = r.corners()
    return bool(
        (c.min(axis=0) >= 0.5).all() and c[:, 0].max() <= w - 1.5 and c[:, 1].max() <= h - 1.5
    )


def _countable(r: Region, w: int, h: int, config: LampDetectorConfig) -> bool:
    """A lamp that recall counts: not occluded, inside the image, at least ``min_area_px``."""
    return not r.occluded and _inside(r, w, h) and r.length * r.width >= config.min_area_px


def evaluate_photos(
    photos_dir: str | Path,
    labels_path: str | Path,
    settings: PhotoEvalSettings | None = None,
    config: LampDetectorConfig | None = None,
) -> list[PhotoScore]:
    """Run the detector on every labelled photo found in ``photos_dir`` and score it.

    Args:
        photos_dir: folder of the photos (file names as in the labels).
        labels_path: the label file.
        settings: evaluation settings (defaults if None).
        config: detector settings at 320 px (scaled to the working width; defaults if None).

    Returns:
        One score per photo (label-file order), then ``tune`` and ``report``
        totals for the uses present, then the total over all photos.

    Raises:
        LampsamError: unreadable labels, a labelled photo missing from the
            folder, or a photo whose size differs from its labels'.
    """
    settings = settings or PhotoEvalSettings()
    labels = read_labels(labels_path)
    scores: list[PhotoScore] = []
    for name, pl in labels.items():
        path = Path(photos_dir) / name
        if not path.exists():
            raise LampsamError(f"{labels_path}: photo {name!r} is not in {photos_dir}")
        full = load_photo(path, None)
        if full.shape != (pl.height, pl.width):
            raise LampsamError(
                f"{path}: {full.shape[1]}x{full.shape[0]} px, but its labels are for "
                f"{pl.width}x{pl.height}"
            )
        base = FrontendConfig() if config is None else replace(FrontendConfig(), lamps=config)
        policy = ResolutionPolicy(
            width=settings.width, auto=settings.auto_width, second_look=settings.second_look
        )
        det, cfg = detect_photo(full, base.lamps, policy)
        h, w = det.mask.shape
        score = score_photo(det, pl, (w, h), cfg, settings)
        score.width = w
        scores.append(score)
    out = list(scores)
    for use in ("tune", "report"):
        part = [s for s in scores if s.use == use]
        if part:
            out.append(total(part, f"total ({use})", use))
    out.append(total(scores, "total", "all"))
    return out


def format_table(scores: list[PhotoScore]) -> str:
    """A text table of the scores (one line per photo or total)."""
    head = (
        f"{'photo':18s} {'use':6s} {'width':>5s} {'det':>4s} {'true':>4s} {'prec':>6s} {'lamps':>5s} "
        f"{'found':>5s} {'recall':>6s} {'fits':>5s} {'f_rec':>6s} {'small':>5s} {'split':>5s} {'c_rms px':>8s} "
        f"{'ax_rms deg':>10s}  false by kind"
    )
    lines = [head]
    for s in scores:
        r = s.row()
        lines.append(
            f"{s.name:18s} {s.use:6s} {s.width or '':>5} {s.n_detections:4d} {s.n_true:4d} {s.precision:6.3f} "
            f"{s.n_lamps:5d} {s.n_found:5d} {s.recall:6.3f} {s.n_fittings:5d} {s.recall_fitting:6.3f} "
            f"{s.n_small:5d} {s.n_split:5d} "
            f"{r['centroid_rms_px']:8.2f} {r['axis_rms_deg']:10.2f}  "
            + (", ".join(f"{k} {v}" for k, v in sorted(s.false_by_kind.items())) or "-")
        )
    return "\n".join(lines)


def write_scores(scores: list[PhotoScore], path: str | Path, settings: PhotoEvalSettings) -> None:
    """Write the scores and the settings as JSON."""
    write_text_atomic(
        path,
        json.dumps({"settings": asdict(settings), "photos": [s.row() for s in scores]}, indent=1)
        + "\n",
    )
