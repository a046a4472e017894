"""Hand labels of real ceiling photos: the file format, its reader, and the labelling tool.

A label file is JSON (``tests/data/ceiling_photo_labels.json`` for the shared
photos)::

    {"format": "lampsam-photo-labels/1",
     "photos": {"430_db_photo.jpg": {
         "width": 4000, "height": 3000, "use": "tune",
         "regions": [{"kind": "lamp", "centre": [x, y], "axis_deg": a,
                      "length": l, "width": w, "occluded": false}, ...]}}}

Every region is a rotated rectangle in the photo's full-resolution pixels
(``(col, row)``, sensor orientation, EXIF ignored as
:func:`lampsam.evaluation.gallery.load_photo` reads it): centre, long-axis
angle in degrees (from ``+col`` towards ``+row``, the image-space ``theta`` of
eq. 5 of paper 1), length and width in px. Kinds: ``lamp`` (one lit
module: the lit part of a luminaire bounded all round by unlit housing or
ceiling; a rod or beam in front of it does not part it),
``lamp_fragment`` (a lit end cap or piece detached from its tube), and the
bright regions that are not lamps: ``window``, ``skylight``, ``reflection``
(specular highlights on ducts, sunlit or lamp-lit white surfaces), ``other``
(signs). ``occluded``: the lamp is partly hidden (plants, beams), so its
visible centroid is not its centre. ``fitting`` (lamps only, optional int):
lamps with the same number are modules of one fitting, mounted end to end in
one housing or row and parted by a connector or end cap across their whole
lit width; the evaluation counts them as modules and as one fitting
(docs/photo-labels.md has the definition of one lamp). ``use`` says whether the photo was used to
tune the detector (``tune``) or only to report (``report``).

Tool: :func:`propose_regions` runs the lamp detector with relaxed settings
(every bright blob, dim or merged) and :func:`draw_proposals` numbers them on
the photo; one looks at the picture and writes a decision line per photo
(:func:`parse_decisions`), for example ``430: lamp 16 18 19+24; skylight
3-14``, where ``a+b`` merges proposals into one region (a lamp split by a
crossing rod) and ``a-b`` is a range; :func:`finalize_labels` writes the
label file. Script: ``scripts/label_photos.py``.
"""

from __future__ import annotations

import json
import math
import re
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Literal, cast, get_args

import cv2
import numpy as np

from lampsam.arrays import FloatArray, ImageU8
from lampsam.errors import LampsamError
from lampsam.safe_io import write_text_atomic

LABEL_FORMAT = "lampsam-photo-labels/1"

RegionKind = Literal["lamp", "lamp_fragment", "window", "skylight", "reflection", "other"]
REGION_KINDS: tuple[str, ...] = get_args(RegionKind)
NOT_LAMP_KINDS = ("window", "skylight", "reflection", "other")


@dataclass(frozen=True)
class Region:
    """One labelled region: a rotated rectangle in full-resolution pixels.

    Attributes:
        kind: what it is (see the module docstring).
        centre: shape (2,) ``(col, row)``, px.
        axis_deg: long-axis angle, degrees from ``+col`` towards ``+row`` (mod 180).
        length: extent along the axis, px.
        width: extent across it, px.
        occluded: partly hidden (lamps only).
        fitting: modules of one fitting share this number (lamps only; None: a
            fitting of one module).
    """

    kind: RegionKind
    centre: FloatArray
    axis_deg: float
    length: float
    width: float
    occluded: bool = False
    fitting: int | None = None

    def corners(self) -> FloatArray:
        """shape (4, 2) the rectangle's corners, px."""
        return np.asarray(
            cv2.boxPoints(
                (
                    (float(self.centre[0]), float(self.centre[1])),
                    (self.length, self.width),
                    self.axis_deg,
                )
            ),
            dtype=np.float64,
        )

    def contains(self, px: FloatArray, margin: float = 0.0) -> bool:
        """True when pixel ``px`` (2,) lies inside the rectangle grown by ``margin`` px on each side."""
        a = math.radians(self.axis_deg)
        d = np.asarray(px, dtype=np.float64) - self.centre
        along = d[0] * math.cos(a) + d[1] * math.sin(a)
        across = -d[0] * math.sin(a) + d[1] * math.cos(a)
        return abs(along) <= 0.5 * self.length + margin and abs(across) <= 0.5 * self.width + margin

    def scaled(self, s: float) -> Region:
        """The region in an image resized by ``s`` (pixel coordinates and sizes times ``s``)."""
        return replace(self, centre=self.centre * s, length=self.length * s, width=self.width * s)


@dataclass(frozen=True)
class PhotoLabels:
    """The labels of one photo.

    Attributes:
        name: file name of the photo.
        width: full-resolution width the labels are in, px.
        height: full-resolution height, px.
        use: ``tune`` (used to choose settings) or ``report`` (only measured).
        regions: the labelled regions.
    """

    name: str
    width: int
    height: int
    use: Literal["tune", "report"]
    regions: tuple[Region, ...]


def _need(obj: dict, key: str, where: str) -> object:
    """``obj[key]`` or a :class:`LampsamError` naming the key and where it was missing."""
    if not isinstance(obj, dict) or key not in obj:
        raise LampsamError(f"{where}: missing key {key!r}")
    return obj[key]


def _number(v: object, where: str) -> float:
    """A finite float, or a :class:`LampsamError` naming ``where``."""
    if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(float(v)):
        raise LampsamError(f"{where}: expected a finite number, got {v!r}")
    return float(v)


def _region(raw: object, where: str) -> Region:
    """One region from its JSON object (strict: unknown keys are errors)."""
    if not isinstance(raw, dict):
        raise LampsamError(f"{where}: expected an object, got {type(raw).__name__}")
    allowed = {"kind", "centre", "axis_deg", "length", "width", "occluded", "fitting", "note"}
    unknown = sorted(set(raw) - allowed)
    if unknown:
        raise LampsamError(f"{where}: unknown key(s) {unknown} (allowed: {sorted(allowed)})")
    kind = _need(raw, "kind", where)
    if kind not in REGION_KINDS:
        raise LampsamError(f"{where}.kind: {kind!r} is not one of {list(REGION_KINDS)}")
    centre = _need(raw, "centre", where)
    if not isinstance(centre, list) or len(centre) != 2:
        raise LampsamError(f"{where}.centre: expected [col, row], got {centre!r}")
    length = _number(_need(raw, "length", where), f"{where}.length")
    width = _number(_need(raw, "width", where), f"{where}.width")
    if length <= 0 or width <= 0:
        raise LampsamError(f"{where}: length and width must be > 0 (got {length}, {width})")
    occluded = raw.get("occluded", False)
    if not isinstance(occluded, bool):
        raise LampsamError(f"{where}.occluded: expected true or false, got {occluded!r}")
    fitting = raw.get("fitting")
    if fitting is not None and (isinstance(fitting, bool) or not isinstance(fitting, int)):
        raise LampsamError(f"{where}.fitting: expected an integer, got {fitting!r}")
    return Region(
        kind=cast(RegionKind, kind),
        centre=np.array([_number(c, f"{where}.centre") for c in centre]),
        axis_deg=_number(_need(raw, "axis_deg", where), f"{where}.axis_deg"),
        length=length,
        width=width,
        occluded=occluded,
        fitting=fitting,
    )


def read_labels(path: str | Path) -> dict[str, PhotoLabels]:
    """Read a label file (format in the module docstring).

    Args:
        path: the JSON file.

    Returns:
        Labels by photo file name.

    Raises:
        LampsamError: unreadable file, wrong format tag, missing or unknown
            keys, wrong types; the message names the file and the key path.
    """
    path = Path(path)
    try:
        raw = json.loads(path.read_text(encoding="utf-8"))
    except UnicodeDecodeError as exc:
        raise LampsamError(f"{path}: not a text file: byte {exc.start} is not UTF-8 "
                           "(a label file is JSON)") from None
    except OSError as exc:
        raise LampsamError(f"{path}: cannot read the label file ({exc.strerror})") from exc
    except json.JSONDecodeError as exc:
        raise LampsamError(f"{path}:{exc.lineno}: not JSON ({exc.msg})") from exc
    fmt = _need(raw, "format", str(path))
    if fmt != LABEL_FORMAT:
        raise LampsamError(f"{path}: format {fmt!r}, expected {LABEL_FORMAT!r}")
    photos = _need(raw, "photos", str(path))
    if not isinstance(photos, dict):
        raise LampsamError(f"{path}: 'photos' must be an object keyed by file name")
    out: dict[str, PhotoLabels] = {}
    for name, entry in photos.items():
        where = f"{path}: photos.{name}"
        use = _need(entry, "use", where)
        if use not in ("tune", "report"):
            raise LampsamError(f"{where}.use: {use!r} is not 'tune' or 'report'")
        regions = _need(entry, "regions", where)
        if not isinstance(regions, list):
            raise LampsamError(f"{where}.regions: expected a list")
        out[name] = PhotoLabels(
            name=name,
            width=int(_number(_need(entry, "width", where), f"{where}.width")),
            height=int(_number(_need(entry, "height", where), f"{where}.height")),
            use=cast(Literal["tune", "report"], use),
            regions=tuple(_region(r, f"{where}.regions[{i}]") for i, r in enumerate(regions)),
        )
    return out


def write_labels(labels: dict[str, PhotoLabels], path: str | Path) -> None:
    """Write labels in the format :func:`read_labels` reads (one region per line)."""
    lines = ["{", f'  "format": "{LABEL_FORMAT}",', '  "photos": {']
    names = sorted(labels)
    for i, name in enumerate(names):
        pl = labels[name]
        lines.append(
            f'    "{name}": {{"width": {pl.width}, "height": {pl.height}, "use": "{pl.use}", "regions": ['
        )
        for j, r in enumerate(pl.regions):
            obj = {
                "kind": r.kind,
                "centre": [round(float(r.centre[0]), 1), round(float(r.centre[1]), 1)],
                "axis_deg": round(r.axis_deg, 1),
                "length": round(r.length, 1),
                "width": round(r.width, 1),
            }
            if r.occluded:
                obj["occluded"] = True
            if r.fitting is not None:
                obj["fitting"] = r.fitting
            lines.append("      " + json.dumps(obj) + ("," if j + 1 < len(pl.regions) else ""))
        lines.append("    ]}" + ("," if i + 1 < len(names) else ""))
    lines += ["  }", "}", ""]
    write_text_atomic(path, "\n".join(lines))


def propose_regions(image: ImageU8, full_width: int) -> list[Region]:
    """Candidate regions of one photo: every bright blob the detector sees with relaxed checks.

    The detector (:func:`lampsam.frontend.lamps.detect_lamps`, settings scaled
    to the image width) runs without the dimness, contrast and glare-merger
    tests, so that windows, skylights and highlights are proposed too. Each
    blob becomes the rectangle of equal second moments (a uniform rectangle of
    length ``l`` has ``sigma1 = l / sqrt(12)``, eq. 6 of paper 1).

    Args:
        image: shape (h, w) uint8 grey, the photo resized for labelling.
        full_width: the photo's full-resolution width (the regions are scaled to it).

    Returns:
        Regions of kind ``other`` (to be decided), in the detector's order.
    """
    from lampsam.datasets.logrun import CameraModel
    from lampsam.evaluation.gallery import config_for_width
    from lampsam.frontend.lamps import detect_lamps

    h, w = image.shape
    cfg = replace(
        config_for_width(w).lamps,
        max_peak_drop_grey=None,
        min_blob_contrast_grey=10.0,
        min_fill=0.0,
    )
    det = detect_lamps(image, CameraModel.from_fov(w, h, 70.0), cfg)
    s = full_width / w
    return [
        Region(
            kind="other",
            centre=np.asarray(mo.centroid, dtype=np.float64) * s,
            axis_deg=math.degrees(mo.theta),
            length=math.sqrt(12.0) * mo.sigma1 * s,
            width=math.sqrt(12.0) * mo.sigma2 * s,
        )
        for mo in det.moments
    ]


def draw_proposals(image: ImageU8, regions: list[Region], full_width: int) -> np.ndarray:
    """The photo (BGR) with each proposal's rectangle and number drawn (for deciding by eye)."""
    out = cv2.cvtColor(image, cv2.COLOR_GRAY2BGR)
    s = image.shape[1] / full_width
    for i, r in enumerate(regions):
        rs = r.scaled(s)
        cv2.polylines(out, [rs.corners().astype(np.int32)], True, (0, 255, 0), 1)
        at = (int(rs.centre[0]) + 4, int(rs.centre[1]) - 4)
        cv2.putText(out, str(i), at, cv2.FONT_HERSHEY_SIMPLEX, 0.5, (255, 0, 255), 2)
    return out


def merge_regions(regions: list[Region], kind: RegionKind) -> Region:
    """One rectangle covering several (a lamp split by a seam or a crossing rod).

    The axis is the area-weighted mean axis (doubled-angle average, mod 180);
    the extent covers every input rectangle's corners along and across it.
    """
    wts = np.array([r.length * r.width for r in regions])
    ang2 = np.radians([2.0 * r.axis_deg for r in regions])
    axis = 0.5 * math.degrees(math.atan2(float(wts @ np.sin(ang2)), float(wts @ np.cos(ang2))))
    a = math.radians(axis)
    u, v = np.array([math.cos(a), math.sin(a)]), np.array([-math.sin(a), math.cos(a)])
    pts = np.concatenate([r.corners() for r in regions])
    pu, pv = pts @ u, pts @ v
    cu, cv = 0.5 * (pu.min() + pu.max()), 0.5 * (pv.min() + pv.max())
    return Region(kind, cu * u + cv * v, axis, float(np.ptp(pu)), float(np.ptp(pv)))


_DECISION = re.compile(r"^\s*(\w+)\s*:\s*(.*)$")


def parse_decisions(text: str) -> dict[str, list[tuple[str, list[list[int]]]]]:
    """Parse decision lines ``PHOTO: kind ids...; kind ids...``.

    ``PHOTO`` is the start of a photo file name (``430``); ``ids`` are
    proposal numbers, ``a-b`` ranges and ``a+b`` merges; a kind may be
    followed by ``(occluded)``. Lines starting with ``#`` are comments.

    Returns:
        ``{photo prefix: [(kind, [[ids of one region], ...]), ...]}``.

    Raises:
        LampsamError: a line or kind that does not parse (naming the line).
    """
    out: dict[str, list[tuple[str, list[list[int]]]]] = {}
    for lineno, line in enumerate(text.splitlines(), 1):
        if not line.strip() or line.lstrip().startswith("#"):
            continue
        m = _DECISION.match(line)
        if m is None:
            raise LampsamError(f"decisions line {lineno}: expected 'PHOTO: kind ids; ...'")
        groups: list[tuple[str, list[list[int]]]] = []
        for part in filter(None, (p.strip() for p in m.group(2).split(";"))):
            kind, *items = part.split()
            if kind.removesuffix("(occluded)") not in REGION_KINDS:
                raise LampsamError(f"decisions line {lineno}: unknown kind {kind!r}")
            regions: list[list[int]] = []
            for item in items:
                if "-" in item:
                    lo, hi = item.split("-")
                    regions += [[i] for i in range(int(lo), int(hi) + 1)]
                else:
                    regions.append([int(i) for i in item.split("+")])
            groups.append((kind, regions))
        out[m.group(1)] = groups
    return out


def finalize_labels(
    proposals: dict[str, list[Region]],
    decisions: dict[str, list[tuple[str, list[list[int]]]]],
    sizes: dict[str, tuple[int, int]],
    tune: set[str],
) -> dict[str, PhotoLabels]:
    """Labels from proposals and decisions (see :func:`parse_decisions`).

    Proposals no decision names are dropped (not worth a label).

    Raises:
        LampsamError: a decision for an unknown photo or proposal number.
    """
    out: dict[str, PhotoLabels] = {}
    for prefix, groups in decisions.items():
        names = [n for n in proposals if n.startswith(prefix)]
        if len(names) != 1:
            raise LampsamError(f"decisions: {prefix!r} names {len(names)} photos")
        name = names[0]
        props = proposals[name]
        regions: list[Region] = []
        for kind, items in groups:
            occluded = kind.endswith("(occluded)")
            k = cast(RegionKind, kind.removesuffix("(occluded)"))
            for ids in items:
                if any(i >= len(props) for i in ids):
                    raise LampsamError(f"decisions {prefix}: proposal {ids} out of range")
                reg = merge_regions([props[i] for i in ids], k)
                regions.append(replace(reg, occluded=occluded))
        w, h = sizes[name]
        out[name] = PhotoLabels(name, w, h, "tune" if prefix in tune else "report", tuple(regions))
    return out
