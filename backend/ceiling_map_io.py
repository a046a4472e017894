"""The saved ceiling map: write it once after mapping, read it back every day.

A ceiling map is a folder (format described in docs/ceiling-map.md)::

    MAP/
      map.yaml        what the map is: format and version, frames and units, the rig
                      (camera and odometry, as a run's rig.yaml) it was made with,
                      the run and backend that made it, landmark counts, file names
      landmarks.csv   one row per landmark: id, type, x, y, z, phi, n_obs, the
                      upper triangle of its 4x4 covariance over (x, y, z, phi) and
                      (version 2) its 4x3 gain on the map frame's offset
      patches.npz     corner appearance: ``ids`` (K,) int64 and ``patches`` (K, P, P)
                      float32, zero-mean unit-norm grey patches (NCC = dot product)

Frames and units (docs/conventions.md): positions in the mapping run's world frame,
metres, ``z`` above the floor (not above the camera); ``phi`` the lamp's long axis in
the world, radians in ``[0, pi)`` (NaN for round lamps and corners); covariances in
m^2, m rad, rad^2. The CSV is written with 17 significant digits so that reading it
back gives the same floats bit for bit.

Version 2 adds the map's correlation as a frame-uncertainty factor model
(:mod:`lampsam.backend.map_frame`): ``frame_uncertainty`` in ``map.yaml`` (the
reference point and the 3 x 3 covariance ``S`` of the frame offset ``g = (dx, dy,
dtheta)``) and twelve ``g_*`` columns per landmark (``C_l``, row-major over rows
``x, y, z, phi`` and columns ``dx, dy, dtheta``), empty when the map has none. The
reader accepts versions 1 (no frame: ``CeilingMap.frame`` is None) and 2.

Every file is written atomically (:func:`lampsam.safe_io.atomic_path`), ``map.yaml``
last: a complete ``map.yaml`` means the map is complete. The reader is strict: a
missing file, a missing or unknown key, a wrong format or version, a bad number or
a duplicate id is a :class:`lampsam.errors.DatasetError` naming the file and the
key or line.
"""

from __future__ import annotations

import csv
import math
import zipfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from lampsam.arrays import FloatArray
from lampsam.backend.interface import LandmarkEstimate, LandmarkKind
from lampsam.backend.map_frame import MapFrame
from lampsam.datasets.rig import Rig
from lampsam.datasets.textio import read_text
from lampsam.errors import DatasetError
from lampsam.safe_io import atomic_path

#: ``format`` key of ``map.yaml``.
MAP_FORMAT = "lampsam-ceiling-map"
#: Version written (2: the frame-uncertainty columns; 3: the optional ``calibration`` key);
#: the reader accepts 1, 2 and 3.
MAP_VERSION = 3
MAP_VERSIONS = (1, 2, 3)
MAP_FILE = "map.yaml"
LANDMARKS_FILE = "landmarks.csv"
PATCHES_FILE = "patches.npz"

#: Columns of ``landmarks.csv``; ``c_ij`` is the covariance entry over (x, y, z, phi).
COLUMNS = ("id", "type", "x", "y", "z", "phi", "n_obs",
           "c_xx", "c_xy", "c_xz", "c_xphi", "c_yy", "c_yz", "c_yphi", "c_zz", "c_zphi", "c_phiphi")
#: Version 2's extra columns: ``C_l[r, c]``, rows x, y, z, phi; columns dx, dy, dtheta.
GAIN_COLUMNS = tuple(f"g_{r}_{c}" for r in ("x", "y", "z", "phi") for c in ("dx", "dy", "dth"))
_UPPER = [(i, j) for i in range(4) for j in range(i, 4)]
_MAP_KEYS = {"format", "format_version", "frame", "units", "rig", "source", "counts", "files"}
_FRAME_KEY = "frame_uncertainty"  # version 2, optional
_CAL_KEY = "calibration"  # version 3, optional
_CAL_FIELDS = ("landmarks_split", "failed", "inflated", "nees_mean", "nees_median", "chi2_per_row")
_CAL_COUNTS = ("landmarks_split", "failed", "inflated")
_CEILING_KINDS = (LandmarkKind.LAMP.value, LandmarkKind.CORNER.value)


@dataclass(frozen=True)
class MapLandmark:
    """One landmark of a saved ceiling map.

    Attributes:
        id: the mapping run's landmark id.
        kind: ``"lamp"`` or ``"corner"``.
        position: (3,) world position, m (``z`` above the floor).
        phi: lamp long axis in the world, rad in ``[0, pi)``, or None (round lamp,
            corner, or a lamp never seen with its axis).
        cov: (4, 4) covariance over ``(x, y, z, phi)``; the ``phi`` row and column
            are zero when ``phi`` is None.
        n_obs: observations the map was made with.
        patch: (P, P) float32 corner patch (zero-mean, unit-norm) or None.
    """

    id: int
    kind: str
    position: FloatArray
    phi: float | None
    cov: FloatArray
    n_obs: int
    patch: np.ndarray | None = None

    def state(self) -> FloatArray:
        """The EKF-form state: ``(x, y, z)`` or ``(x, y, z, phi)``."""
        if self.phi is None:
            return np.asarray(self.position, float).copy()
        return np.array([*self.position, self.phi], float)

    def state_cov(self) -> FloatArray:
        """Covariance of :meth:`state`: (3, 3) or (4, 4)."""
        d = 3 if self.phi is None else 4
        return np.asarray(self.cov, float)[:d, :d].copy()


@dataclass
class CeilingMap:
    """A ceiling map and what it was made with.

    Attributes:
        landmarks: the landmarks (lamps and corners).
        rig: the rig (camera, odometry) of the mapping run.
        source: free mapping of where it came from (``run``, ``backend``, ``steps``,
            ``position_rms_m`` ...), written under ``source:`` in ``map.yaml``.
        frame: the map frame's uncertainty and every landmark's gain on it
            (:mod:`lampsam.backend.map_frame`), or None (a version-1 map, a merged
            map, or a backend without a factor graph).
        calibration: per kind (``lamp``, ``corner``) the figures of the pass-split test
            of the saved covariances (:mod:`lampsam.backend.map_calibration`:
            ``landmarks_split``, ``failed``, ``inflated`` (0 when the test only reported,
            the default), ``nees_mean``, ``nees_median``, ``chi2_per_row``), or None (no
            test).
    """

    landmarks: list[MapLandmark]
    rig: Rig
    source: dict[str, Any] = field(default_factory=dict)
    frame: MapFrame | None = None
    calibration: dict[str, dict[str, float | int]] | None = None

    def by_kind(self, kind: str) -> list[MapLandmark]:
        """Landmarks of one kind, in file order."""
        return [lm for lm in self.landmarks if lm.kind == kind]


# --------------------------------------------------------------------------- building
def map_from_estimates(estimates: list[LandmarkEstimate], rig: Rig,
                       patches: dict[int, np.ndarray] | None = None,
                       source: dict[str, Any] | None = None) -> CeilingMap:
    """A :class:`CeilingMap` from a SLAM result's landmarks.

    Planar (``point2``) landmarks are not ceiling landmarks and are skipped; a NaN
    covariance (marginals unavailable) is kept as NaN.

    Args:
        estimates: :attr:`lampsam.backend.interface.SlamResult.landmarks`.
        rig: the mapping run's rig.
        patches: corner id -> (P, P) patch (:func:`corner_patches`).
        source: provenance for ``map.yaml``.
    """
    patches = patches or {}
    out = []
    for lm in estimates:
        if lm.type not in _CEILING_KINDS:
            continue
        k = lm.cov.shape[0]
        cov = np.zeros((4, 4))
        cov[:k, :k] = lm.cov
        patch = patches.get(lm.id) if lm.type == LandmarkKind.CORNER else None
        out.append(MapLandmark(int(lm.id), str(lm.type), np.asarray(lm.position, float).copy(),
                               None if lm.orientation is None else float(lm.orientation), cov,
                               int(lm.n_obs),
                               None if patch is None else np.asarray(patch, np.float32)))
    return CeilingMap(out, rig, dict(source or {}))


# --------------------------------------------------------------------------- writing
def _num(x: float) -> str:
    """17 significant digits: reading the text back gives the same double."""
    return repr(float(x)) if math.isfinite(x) else ("nan" if math.isnan(x) else str(float(x)))


def write_map(folder: str | Path, cmap: CeilingMap) -> Path:
    """Write ``map.yaml``, ``landmarks.csv`` and ``patches.npz`` to ``folder`` (created).

    Returns:
        The folder.
    """
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    with atomic_path(folder / LANDMARKS_FILE) as tmp, open(tmp, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(COLUMNS + GAIN_COLUMNS)
        for lm in cmap.landmarks:
            phi = math.nan if lm.phi is None else lm.phi
            gain = (cmap.frame.gains.get(lm.id) if cmap.frame is not None else None)
            w.writerow([lm.id, lm.kind, *(_num(v) for v in lm.position), _num(phi), lm.n_obs,
                        *(_num(lm.cov[i, j]) for i, j in _UPPER),
                        *([_num(v) for v in np.asarray(gain, float).ravel()] if gain is not None
                          else [""] * len(GAIN_COLUMNS))])
    with_patch = [lm for lm in cmap.landmarks if lm.patch is not None]
    size = int(with_patch[0].patch.shape[0]) if with_patch else 0  # type: ignore[union-attr]
    with_patch = [lm for lm in with_patch if lm.patch is not None and lm.patch.shape == (size, size)]
    with atomic_path(folder / PATCHES_FILE) as tmp, open(tmp, "wb") as fh:
        np.savez_compressed(
            fh, ids=np.array([lm.id for lm in with_patch], np.int64),
            patches=(np.stack([np.asarray(lm.patch, np.float32) for lm in with_patch])
                     if with_patch else np.zeros((0, size, size), np.float32)))
    doc = {
        "format": MAP_FORMAT,
        "format_version": MAP_VERSION,
        "frame": {"world": "the mapping run's world frame: x, y on the floor, z up, z = 0 the "
                           "floor (docs/conventions.md)",
                  "phi": "lamp long axis in the world, from +x towards +y, mod pi"},
        "units": {"position": "m", "angle": "rad", "covariance": "m^2, m rad, rad^2"},
        "rig": cmap.rig.to_dict(),
        "source": cmap.source,
        "counts": {"lamps": len(cmap.by_kind("lamp")), "corners": len(cmap.by_kind("corner")),
                   "patches": len(with_patch), "patch_size_px": size},
        "files": {"landmarks": LANDMARKS_FILE, "patches": PATCHES_FILE},
    }
    if cmap.frame is not None:
        doc[_FRAME_KEY] = {
            "meaning": "g = (dx, dy, dtheta): the map frame's offset in the world, a rotation "
                       "dtheta about center then a translation; g ~ N(0, cov); landmark l's "
                       "error = C_l g + r_l (columns g_*), r_l independent",
            "center": [float(v) for v in cmap.frame.center],
            "cov": [[float(v) for v in row] for row in cmap.frame.cov]}
    if cmap.calibration is not None:
        doc[_CAL_KEY] = {
            "meaning": "pass-split test (lampsam.backend.map_calibration): NEES per dof of "
                       "the difference between a landmark's estimates from alternate passes; "
                       "'failed': landmarks above the test's threshold; 'inflated': those "
                       "that had (nees - 1) times their sightings-only covariance added to "
                       "their position covariance (0: the test only reported)",
            **{kind: {k: (int(v) if k in _CAL_COUNTS else float(v))
                      for k, v in figs.items()} for kind, figs in cmap.calibration.items()}}
    with atomic_path(folder / MAP_FILE) as tmp:
        tmp.write_text(yaml.safe_dump(doc, sort_keys=False), encoding="utf-8")
    return folder


# --------------------------------------------------------------------------- reading
def _fail(path: Path, msg: str) -> DatasetError:
    return DatasetError(msg, path)


def _float(path: Path, line: int, col: str, text: str) -> float:
    try:
        return float(text)
    except ValueError:
        raise _fail(path, f"line {line}, column {col}: {text!r} is not a number") from None


def _read_landmarks(path: Path, version: int) -> tuple[list[MapLandmark], dict[int, FloatArray]]:
    """The landmarks and (version 2) the gains of the rows that have them."""
    if not path.is_file():
        raise _fail(path, "missing: a ceiling map needs its landmarks file")
    rows = list(csv.reader(read_text(path).splitlines()))
    columns = COLUMNS if version == 1 else COLUMNS + GAIN_COLUMNS
    if not rows or tuple(rows[0]) != columns:
        got = ",".join(rows[0]) if rows else "(empty file)"
        raise _fail(path, f"line 1: header must be {','.join(columns)}; got {got}")
    out: list[MapLandmark] = []
    gains: dict[int, FloatArray] = {}
    seen: set[int] = set()
    for line, row in enumerate(rows[1:], start=2):
        if not row:
            continue
        if len(row) != len(columns):
            raise _fail(path, f"line {line}: {len(row)} fields, expected {len(columns)}")
        rec = dict(zip(columns, row, strict=True))
        try:
            lid = int(rec["id"])
            n_obs = int(rec["n_obs"])
        except ValueError:
            raise _fail(path, f"line {line}: id and n_obs must be integers") from None
        if lid in seen:
            raise _fail(path, f"line {line}: duplicate id {lid}")
        seen.add(lid)
        kind = rec["type"]
        if kind not in _CEILING_KINDS:
            raise _fail(path, f"line {line}, column type: {kind!r} is not one of "
                              f"{', '.join(_CEILING_KINDS)}")
        pos = np.array([_float(path, line, c, rec[c]) for c in ("x", "y", "z")])
        if not np.all(np.isfinite(pos)):
            raise _fail(path, f"line {line}: x, y, z must be finite")
        phi_v = _float(path, line, "phi", rec["phi"])
        cov = np.zeros((4, 4))
        for (i, j), col in zip(_UPPER, COLUMNS[7:], strict=True):
            cov[i, j] = cov[j, i] = _float(path, line, col, rec[col])
        out.append(MapLandmark(lid, kind, pos, None if math.isnan(phi_v) else phi_v, cov, n_obs))
        if version > 1 and any(rec[c] != "" for c in GAIN_COLUMNS):
            gains[lid] = np.array([_float(path, line, c, rec[c]) for c in GAIN_COLUMNS]
                                  ).reshape(4, 3)
    return out, gains


def _read_frame(path: Path, doc: object, gains: dict[int, FloatArray]) -> MapFrame | None:
    """``frame_uncertainty`` of ``map.yaml`` with the landmarks' gains, or None."""
    if doc is None:
        if gains:
            raise _fail(path, f"landmarks have g_* gains but key {_FRAME_KEY!r} is missing")
        return None
    try:
        if not isinstance(doc, dict):
            raise TypeError
        center: FloatArray = np.asarray(doc["center"], np.float64).reshape(2)
        cov: FloatArray = np.asarray(doc["cov"], np.float64).reshape(3, 3)
    except (TypeError, KeyError, ValueError):
        raise _fail(path, f"key {_FRAME_KEY!r} needs 'center' (2 numbers) and 'cov' "
                          "(3 x 3)") from None
    if not (np.all(np.isfinite(center)) and np.all(np.isfinite(cov))):
        raise _fail(path, f"key {_FRAME_KEY!r}: 'center' and 'cov' must be finite")
    if np.min(np.linalg.eigvalsh(0.5 * (cov + cov.T))) <= 0.0:
        raise _fail(path, f"key '{_FRAME_KEY}.cov' is not positive definite")
    return MapFrame(center, cov, gains)


def _read_calibration(path: Path, doc: object) -> dict[str, dict[str, float | int]] | None:
    """``calibration`` of ``map.yaml`` (per kind, the pass-split figures), or None."""
    if doc is None:
        return None
    if not isinstance(doc, dict):
        raise _fail(path, f"key {_CAL_KEY!r} must be a mapping")
    out: dict[str, dict[str, float | int]] = {}
    for kind, figs in doc.items():
        if kind == "meaning":
            continue
        if kind not in _CEILING_KINDS:
            raise _fail(path, f"key '{_CAL_KEY}.{kind}': not one of {', '.join(_CEILING_KINDS)}")
        if not isinstance(figs, dict) or set(figs) != set(_CAL_FIELDS):
            raise _fail(path, f"key '{_CAL_KEY}.{kind}' needs exactly {', '.join(_CAL_FIELDS)}")
        try:
            out[kind] = {k: (int(figs[k]) if k in _CAL_COUNTS else float(figs[k]))
                         for k in _CAL_FIELDS}
        except (TypeError, ValueError):
            raise _fail(path, f"key '{_CAL_KEY}.{kind}': every field must be a number") from None
    return out


def _read_patches(path: Path, ids: set[int]) -> dict[int, np.ndarray]:
    if not path.is_file():
        raise _fail(path, "missing: a ceiling map needs its patches file (may hold 0 patches)")
    try:
        with np.load(path, allow_pickle=False) as z:
            if "ids" not in z.files or "patches" not in z.files:
                raise _fail(path, f"needs arrays 'ids' and 'patches'; has {', '.join(z.files)}")
            pid = np.asarray(z["ids"])
            pat = np.asarray(z["patches"])
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as exc:
        raise _fail(path, f"not a readable .npz: {exc or type(exc).__name__}") from None
    if pid.ndim != 1 or pat.ndim != 3 or len(pid) != len(pat) or pat.shape[1] != pat.shape[2]:
        raise _fail(path, f"'ids' must be (K,) and 'patches' (K, P, P); got {pid.shape} and {pat.shape}")
    unknown = [int(i) for i in pid if int(i) not in ids]
    if unknown:
        raise _fail(path, f"patch for id {unknown[0]} which is not a landmark of the map "
                          f"({len(unknown)} such)")
    return {int(i): pat[k].astype(np.float32) for k, i in enumerate(pid)}


def read_map(folder: str | Path) -> CeilingMap:
    """Read a ceiling map folder written by :func:`write_map` (strict; module docstring).

    Raises:
        DatasetError: naming the file and the key or line at fault.
    """
    folder = Path(folder)
    meta_path = folder / MAP_FILE
    if not folder.is_dir():
        raise _fail(folder, "not a ceiling map folder (written by `lampsam slam --save-map`)")
    if not meta_path.is_file():
        raise _fail(meta_path, "missing: not a ceiling map (written by `lampsam slam --save-map`)")
    try:
        doc = yaml.safe_load(read_text(meta_path))
    except yaml.YAMLError as exc:
        raise _fail(meta_path, f"invalid YAML: {exc}") from None
    if not isinstance(doc, dict):
        raise _fail(meta_path, "must be a mapping")
    missing = sorted(_MAP_KEYS - set(doc))
    if missing:
        raise _fail(meta_path, f"missing key {missing[0]!r}")
    unknown = sorted(set(doc) - _MAP_KEYS - {_FRAME_KEY, _CAL_KEY})
    if unknown:
        raise _fail(meta_path, f"unknown key {unknown[0]!r}")
    if doc["format"] != MAP_FORMAT:
        raise _fail(meta_path, f"key 'format': {doc['format']!r} is not {MAP_FORMAT!r}")
    version = doc["format_version"]
    if version not in MAP_VERSIONS or isinstance(version, bool):
        raise _fail(meta_path, f"key 'format_version': {version!r} is not supported "
                               f"(this lampsam reads versions {', '.join(map(str, MAP_VERSIONS))})")
    for key, since in ((_FRAME_KEY, 2), (_CAL_KEY, 3)):
        if version < since and key in doc:
            raise _fail(meta_path, f"unknown key {key!r} (version {version})")
    files = doc["files"]
    if not isinstance(files, dict) or set(files) != {"landmarks", "patches"}:
        raise _fail(meta_path, "key 'files' must map 'landmarks' and 'patches' to file names")
    rig = Rig.from_dict(doc["rig"], meta_path, strict=True)
    landmarks, gains = _read_landmarks(folder / str(files["landmarks"]), int(version))
    frame = _read_frame(meta_path, doc.get(_FRAME_KEY), gains)
    counts = doc["counts"] if isinstance(doc["counts"], dict) else {}
    for kind, key in (("lamp", "lamps"), ("corner", "corners")):
        n = sum(lm.kind == kind for lm in landmarks)
        if counts.get(key) != n:
            raise _fail(meta_path, f"key 'counts.{key}': {counts.get(key)!r} but "
                                   f"{files['landmarks']} has {n}")
    patches = _read_patches(folder / str(files["patches"]), {lm.id for lm in landmarks})
    landmarks = [MapLandmark(lm.id, lm.kind, lm.position, lm.phi, lm.cov, lm.n_obs,
                             patches.get(lm.id)) for lm in landmarks]
    source = doc["source"] if isinstance(doc["source"], dict) else {}
    return CeilingMap(landmarks, rig, source, frame, _read_calibration(meta_path, doc.get(_CAL_KEY)))


def corner_patches(backend: object) -> dict[int, np.ndarray]:
    """Corner id -> reference patch kept by a finished SLAM backend.

    The graph backends keep each landmark's first-sight patch on its
    :class:`~lampsam.backend.handlers.GraphLandmark` (``_landmarks``), the EKF on its
    state slot (``_slots``); :class:`~lampsam.backend.interface.SlamResult` does not
    carry them.
    """
    store = getattr(backend, "_landmarks", None) or getattr(backend, "_slots", None) or {}
    out: dict[int, np.ndarray] = {}
    for lid, rec in dict(store).items():
        patch = getattr(rec, "patch", None)
        if patch is not None and np.ndim(patch) == 2 and np.size(patch) > 1:
            out[int(lid)] = np.asarray(patch, np.float32)
    return out
