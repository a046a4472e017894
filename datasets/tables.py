"""The tables of a logged run: in-memory types, readers and writers (``docs/log-format.md``).

One dataclass per table, each with its reader and writer:

    odometry.csv           :class:`OdometryLog`      t,d_left,d_right (wheel travel, m)
    images.csv + images/   :class:`ImageIndex`       t,file (8-bit grey PNG)
    landmarks.csv          :class:`LandmarkTable`    id,type,x,y,z,phi,length,width
    rangebearing.csv       :class:`RangeBearingLog`  t,landmark_id,range,bearing
    truth/projections.csv  :class:`ProjectionTable`  simulator truth per image
    (TUM trajectories)     :class:`Trajectory`       read and written by :mod:`lampsam.datasets.tum`

Readers raise :class:`lampsam.errors.DatasetError` naming the file and the
1-based line of a malformed line, a non-finite number or a time stamp out of
order. Times are seconds, lengths metres, angles radians (``docs/conventions.md``).
"""

from __future__ import annotations

import math
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from lampsam.angles import wrap_angle
from lampsam.arrays import BoolArray, FloatArray, ImageU8, IntArray
from lampsam.datasets.textio import (
    check_speed,
    check_time,
    columns,
    parse_float,
    parse_int,
    read_csv,
    str_field,
)
from lampsam.errors import DatasetError
from lampsam.safe_io import atomic_path

IMAGES_FILE = "images.csv"
IMAGES_DIR = "images"

ODOMETRY_HEADER = ("t", "d_left", "d_right")
IMAGES_HEADER = ("t", "file")
LANDMARKS_HEADER = ("id", "type", "x", "y", "z", "phi", "length", "width")
RANGE_BEARING_HEADER = ("t", "landmark_id", "range", "bearing")
PROJECTIONS_HEADER = (
    "frame", "t", "id", "type", "col", "row", "angle_px", "visible", "fully_visible",
)  # fmt: skip

LANDMARK_TYPES = ("lamp_rect", "lamp_round", "lamp_square", "corner")
# zlib level of the ceiling images lampsam writes. 0 stores the pixels unfiltered:
# on 320x240 lab frames 0.17 ms decode against 0.97 ms at OpenCV's default (level 1,
# filtered) and 0.29 against 1.6 ms encode, for 77 against 41 kB a frame
# (docs/frontend-speed.md); the pixels read back are the same at every level.
PNG_COMPRESSION = 0
"""Landmark types of ``landmarks.csv``; ``lamp_rect`` lamps have an axis ``phi``."""


@dataclass(frozen=True, eq=False)
class OdometryLog:
    """Wheel odometry: travel of each wheel since the previous sample.

    Attributes:
        t: (N,) time stamps, s, strictly increasing.
        d_left: (N,) left-wheel travel since the previous line, m (first: since start).
        d_right: (N,) right-wheel travel, m.
    """

    t: FloatArray
    d_left: FloatArray
    d_right: FloatArray

    def __len__(self) -> int:
        """Number of samples."""
        return int(len(self.t))


@dataclass(frozen=True, eq=False)
class Trajectory:
    """Planar trajectory.

    Attributes:
        t: (K,) time stamps, s, strictly increasing.
        poses: (K, 3) ``world_T_body = (x, y, theta)``, m and rad.
    """

    t: FloatArray
    poses: FloatArray

    def __len__(self) -> int:
        """Number of poses."""
        return int(len(self.t))

    def interpolate(self, t: FloatArray) -> FloatArray:
        """Poses at times ``t`` (linear in x, y, unwrapped theta; clamped at the ends).

        Args:
            t: (M,) query times, s.

        Returns:
            (M, 3) poses, theta wrapped to (-pi, pi].
        """
        t = np.asarray(t, dtype=np.float64)
        th = np.unwrap(self.poses[:, 2])
        out = np.column_stack([
            np.interp(t, self.t, self.poses[:, 0]),
            np.interp(t, self.t, self.poses[:, 1]),
            np.interp(t, self.t, th),
        ])  # fmt: skip
        out[:, 2] = wrap_angle(out[:, 2])
        return out


def lamp_mask(types: Sequence[str]) -> BoolArray:
    """(L,) True where a landmark type names a lamp (``lamp``, ``lamp_rect``, ``lamp_round``,
    ``lamp_square``...: any type starting with ``lamp``); corners and the rest False."""
    return np.array([str(t).startswith("lamp") for t in types], dtype=bool)


@dataclass(frozen=True, eq=False)
class LandmarkTable:
    """True landmarks of a world.

    Attributes:
        ids: (L,) integer ids, unique.
        types: (L,) type names (:data:`LANDMARK_TYPES`).
        xyz: (L, 3) world position, m (``z`` = height above the floor; lamps: centre).
        phi: (L,) long-axis direction of ``lamp_rect`` lamps in the world, rad mod pi
            (others: 0 or the square's yaw).
        length: (L,) lamp length (round: diameter; square: side), m; corners 0.
        width: (L,) lamp width, m; corners 0.
    """

    ids: IntArray
    types: tuple[str, ...]
    xyz: FloatArray
    phi: FloatArray
    length: FloatArray
    width: FloatArray

    def __len__(self) -> int:
        """Number of landmarks."""
        return int(len(self.ids))

    def index_of(self, landmark_id: int) -> int:
        """Row of a landmark id (KeyError if absent)."""
        hits = np.flatnonzero(self.ids == landmark_id)
        if len(hits) == 0:
            raise KeyError(landmark_id)
        return int(hits[0])

    def is_lamp(self) -> BoolArray:
        """(L,) True for lamps (:func:`lamp_mask`)."""
        return lamp_mask(self.types)

    def select(self, mask: BoolArray) -> LandmarkTable:
        """The rows where ``mask`` is True."""
        return LandmarkTable(
            ids=self.ids[mask],
            types=tuple(t for t, k in zip(self.types, mask, strict=True) if k),
            xyz=self.xyz[mask], phi=self.phi[mask],
            length=self.length[mask], width=self.width[mask],
        )  # fmt: skip


@dataclass(frozen=True, eq=False)
class ProjectionTable:
    """Simulator truth: where every landmark projects in every image (``truth/projections.csv``).

    One row per (image, landmark) whose centre lies in front of the camera and
    projects inside the image (lamps also when only partly inside).

    Attributes:
        frame: (P,) image index (row of ``images.csv``, 0-based).
        t: (P,) image time stamp, s.
        ids: (P,) landmark id.
        types: (P,) landmark type (as in ``landmarks.csv``).
        pixel: (P, 2) projection ``(col, row)`` of the landmark (lamp: its centre), px,
            computed with ``cv2.projectPoints`` including distortion.
        angle_px: (P,) ``atan2(d_row, d_col)`` of the projected long axis of a ``lamp_rect``,
            wrapped to (-pi/2, pi/2]; NaN for other types.
        visible: (P,) the point is inside the image and not hidden by a lower surface or lamp.
        fully_visible: (P,) lamps: every outline point is inside the image with a 1 px
            margin and none is hidden; corners: equal to ``visible``.
    """

    frame: IntArray
    t: FloatArray
    ids: IntArray
    types: tuple[str, ...]
    pixel: FloatArray
    angle_px: FloatArray
    visible: BoolArray
    fully_visible: BoolArray

    def __len__(self) -> int:
        """Number of rows."""
        return int(len(self.frame))

    def rows_of_frame(self, frame: int) -> IntArray:
        """Row indices belonging to one image."""
        lo, hi = np.searchsorted(self.frame, [frame, frame + 1])
        return np.arange(lo, hi)


@dataclass(frozen=True, eq=False)
class RangeBearingLog:
    """Range-bearing landmark measurements (landmark datasets such as MRCLAM).

    Attributes:
        t: (N,) time stamps, s, non-decreasing (several per instant allowed).
        landmark_id: (N,) landmark id (negative: unknown).
        range: (N,) range from the body origin, m.
        bearing: (N,) bearing in the body frame, rad (CCW from body x).
    """

    t: FloatArray
    landmark_id: IntArray
    range: FloatArray
    bearing: FloatArray

    def __len__(self) -> int:
        """Number of measurements."""
        return int(len(self.t))


@dataclass(frozen=True)
class ImageIndex:
    """Time-stamped ceiling images of a run.

    Attributes:
        t: (M,) time stamps, s, strictly increasing.
        files: M image paths (absolute, or relative to the working directory).
        shape: expected ``(height, width)``; None skips the size check.
        index_path: the ``images.csv`` the index came from (for error messages).
    """

    t: FloatArray
    files: list[Path]
    shape: tuple[int, int] | None = None
    index_path: Path | None = None

    def __len__(self) -> int:
        """Number of images."""
        return int(len(self.t))

    def load(self, i: int) -> ImageU8:
        """Image ``i`` as uint8 (H, W).

        Raises:
            DatasetError: the file is missing or unreadable, not 8-bit grey or of the
                wrong size; the message names the image and its line in ``images.csv``.
        """
        path = self.files[i]
        where = f" (line {i + 2} of {self.index_path})" if self.index_path is not None else ""
        if not path.is_file():
            raise DatasetError(f"image file not found{where}", path)
        img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if img is None:
            raise DatasetError(f"cannot decode image (corrupt or not an image){where}", path)
        if img.dtype != np.uint8 or img.ndim != 2:
            raise DatasetError(
                f"expected an 8-bit single-channel image, got {img.dtype} {img.shape}{where}",
                path,
            )
        if self.shape is not None and img.shape != tuple(self.shape):
            raise DatasetError(
                f"image size {img.shape} differs from the rig's {self.shape}{where}", path
            )
        return np.asarray(img, dtype=np.uint8)

    def __iter__(self) -> Iterator[tuple[float, ImageU8]]:
        """Iterate ``(t, image)``."""
        for i in range(len(self)):
            yield float(self.t[i]), self.load(i)


def read_odometry(path: str | Path) -> OdometryLog:
    """Read ``odometry.csv`` (``t,d_left,d_right``).

    Raises:
        DatasetError: missing, malformed, non-finite, empty, time not increasing, or a
            wheel faster than ``textio.MAX_SPEED`` (100 m/s) in a sample.
    """
    path = Path(path)
    (t, dl, dr), lines = columns(path, ODOMETRY_HEADER, "fff", [parse_float] * 3)
    check_time(t, lines, path)
    check_speed(t, np.column_stack([dl, dr]), lines, path, "d_left/d_right")
    return OdometryLog(t=t, d_left=dl, d_right=dr)


def read_image_index(path: str | Path, shape: tuple[int, int] | None = None) -> ImageIndex:
    """Read ``images.csv`` (``t,file``; files relative to the csv's folder).

    Image files are not opened here (see :meth:`ImageIndex.load`).

    Raises:
        DatasetError: missing, malformed, empty, or time not increasing.
    """
    path = Path(path)
    (t, names), lines = columns(path, IMAGES_HEADER, "fs", [parse_float, str_field])
    check_time(t, lines, path)
    files = [path.parent / name for name in names]
    return ImageIndex(t=t, files=files, shape=shape, index_path=path)


def read_landmarks(path: str | Path) -> LandmarkTable:
    """Read ``landmarks.csv`` (``id,type,x,y,z,phi,length,width``).

    Raises:
        DatasetError: missing, malformed, non-finite, unknown type or duplicate id.
    """
    path = Path(path)

    def _type(text: str, p: Path, line: int, column: str) -> str:
        """A known landmark type, or DatasetError."""
        if text not in LANDMARK_TYPES:
            raise DatasetError(f"column {column!r}: unknown landmark type {text!r}", p, line)
        return text

    rows, lines = read_csv(path, LANDMARKS_HEADER, [parse_int, _type] + [parse_float] * 6, True)
    ids = np.array([r[0] for r in rows], dtype=np.int64)
    _, first = np.unique(ids, return_index=True)
    if len(first) != len(ids):
        dup = sorted(set(range(len(ids))) - set(first.tolist()))[0]
        raise DatasetError(f"duplicate landmark id {ids[dup]}", path, lines[dup])
    num = np.array([r[2:] for r in rows], dtype=np.float64).reshape(-1, 6)
    return LandmarkTable(
        ids=ids, types=tuple(r[1] for r in rows), xyz=num[:, 0:3],
        phi=num[:, 3], length=num[:, 4], width=num[:, 5],
    )  # fmt: skip


def read_range_bearing(path: str | Path) -> RangeBearingLog:
    """Read ``rangebearing.csv`` (``t,landmark_id,range,bearing``).

    Raises:
        DatasetError: missing, malformed, non-finite, empty or time going backwards.
    """
    path = Path(path)
    parsers = [parse_float, parse_int, parse_float, parse_float]
    (t, lid, rng, brg), lines = columns(path, RANGE_BEARING_HEADER, "fiff", parsers)
    check_time(t, lines, path, strict=False)
    return RangeBearingLog(t=t, landmark_id=lid, range=rng, bearing=brg)


def read_projections(path: str | Path) -> ProjectionTable:
    """Read ``truth/projections.csv`` (see :class:`ProjectionTable`).

    Raises:
        DatasetError: missing, malformed or frames out of order.
    """
    path = Path(path)

    def _nan_ok(text: str, p: Path, line: int, column: str) -> float:
        """A float that may be ``nan`` (but not inf)."""
        if text.lower() == "nan":
            return math.nan
        return parse_float(text, p, line, column)

    def _bool(text: str, p: Path, line: int, column: str) -> bool:
        """``0``/``1`` as a bool, or DatasetError."""
        if text not in ("0", "1"):
            raise DatasetError(f"column {column!r}: expected 0 or 1, got {text!r}", p, line)
        return text == "1"

    parsers = [
        parse_int,
        parse_float,
        parse_int,
        str_field,
        parse_float,
        parse_float,
        _nan_ok,
        _bool,
        _bool,
    ]
    cols, lines = columns(path, PROJECTIONS_HEADER, "ifisffnbb", parsers, allow_empty=True)
    frame, t, ids, types, col, row, angle, vis, full = cols
    check_time(frame.astype(np.float64), lines, path, strict=False)
    return ProjectionTable(
        frame=frame, t=t, ids=ids, types=tuple(types),
        pixel=np.column_stack([col, row]).reshape(-1, 2), angle_px=angle,
        visible=vis, fully_visible=full,
    )  # fmt: skip


def _fmt(x: float, digits: int) -> str:
    """Fixed-point float without trailing noise (``nan`` stays ``nan``)."""
    if not math.isfinite(x):
        return "nan"
    return f"{x:.{digits}f}"


def write_odometry(path: str | Path, odometry: OdometryLog) -> None:
    """Write ``odometry.csv`` (time to 1 us, travel to 1 nm)."""
    with atomic_path(path) as tmp, open(tmp, "w", encoding="utf-8") as fh:
        fh.write(",".join(ODOMETRY_HEADER) + "\n")
        for t, dl, dr in zip(odometry.t, odometry.d_left, odometry.d_right, strict=True):
            fh.write(f"{t:.6f},{dl:.9f},{dr:.9f}\n")

def write_landmarks(path: str | Path, landmarks: LandmarkTable) -> None:
    """Write ``landmarks.csv``."""
    with atomic_path(path) as tmp, open(tmp, "w", encoding="utf-8") as fh:
        fh.write(",".join(LANDMARKS_HEADER) + "\n")
        for i in range(len(landmarks)):
            x, y, z = landmarks.xyz[i]
            fh.write(
                f"{int(landmarks.ids[i])},{landmarks.types[i]},{x:.6f},{y:.6f},{z:.6f},"
                f"{landmarks.phi[i]:.9f},{landmarks.length[i]:.6f},{landmarks.width[i]:.6f}\n"
            )


def write_range_bearing(path: str | Path, rb: RangeBearingLog) -> None:
    """Write ``rangebearing.csv`` (used by public-data adapters, e.g. MRCLAM)."""
    with atomic_path(path) as tmp, open(tmp, "w", encoding="utf-8") as fh:
        fh.write(",".join(RANGE_BEARING_HEADER) + "\n")
        for t, i, r, b in zip(rb.t, rb.landmark_id, rb.range, rb.bearing, strict=True):
            fh.write(f"{t:.6f},{int(i)},{r:.9f},{b:.9f}\n")


class ProjectionWriter:
    """Appends rows to ``truth/projections.csv`` frame by frame (flushed after each frame)."""

    def __init__(self, path: str | Path):
        """Create the file and write the header."""
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._fh = open(self.path, "w", encoding="utf-8")  # noqa: SIM115 (closed in close())
        self._fh.write(",".join(PROJECTIONS_HEADER) + "\n")

    def write_frame(self, frame: int, t: float, table: ProjectionTable) -> None:
        """Append one image's rows (``table.frame``/``t`` are ignored and replaced)."""
        for k in range(len(table.ids)):
            col, row = table.pixel[k]
            self._fh.write(
                f"{frame},{t:.6f},{int(table.ids[k])},{table.types[k]},{col:.4f},{row:.4f},"
                f"{_fmt(float(table.angle_px[k]), 6)},"
                f"{int(table.visible[k])},{int(table.fully_visible[k])}\n"
            )
        self._fh.flush()

    def close(self) -> None:
        """Close the file."""
        self._fh.close()


def png_params(compression: int = PNG_COMPRESSION) -> list[int]:
    """OpenCV PNG writer flags for a zlib level 0-9 (0: stored, no row filter).

    Raises:
        ValueError: a level outside 0-9.
    """
    if not 0 <= int(compression) <= 9:
        raise ValueError(f"PNG compression must be 0-9, got {compression}")
    params = [cv2.IMWRITE_PNG_COMPRESSION, int(compression)]
    if compression == 0:  # row filters only help deflate; unfiltered rows decode as a copy
        params += [cv2.IMWRITE_PNG_FILTER, cv2.IMWRITE_PNG_FILTER_NONE]
    return params


def encode_png(image: ImageU8, compression: int = PNG_COMPRESSION, what: str = "image"
               ) -> bytes:
    """``image`` as PNG bytes at a zlib level 0-9 (:func:`png_params`).

    Raises:
        DatasetError: OpenCV could not encode it (``what`` names it).
        ValueError: a level outside 0-9.
    """
    ok, png = cv2.imencode(".png", image, png_params(compression))
    if not ok:
        raise DatasetError(f"PNG encoding failed for {what}")
    return bytes(png.tobytes())


class ImageWriter:
    """Writes ceiling images and ``images.csv`` one frame at a time (flushed after each).

    An interrupted run leaves a valid index of the frames already written.
    """

    def __init__(self, run_dir: str | Path, png_compression: int = PNG_COMPRESSION):
        """Create ``images/`` and ``images.csv`` in ``run_dir``; :meth:`write` encodes
        at zlib level ``png_compression`` (0-9, :data:`PNG_COMPRESSION`)."""
        self._png_params = png_params(png_compression)
        self.run_dir = Path(run_dir)
        (self.run_dir / IMAGES_DIR).mkdir(parents=True, exist_ok=True)
        self._fh = open(self.run_dir / IMAGES_FILE, "w", encoding="utf-8")  # noqa: SIM115
        self._fh.write(",".join(IMAGES_HEADER) + "\n")
        self.count = 0

    def write(self, t: float, image: ImageU8) -> Path:
        """Write the next image (uint8 (H, W)) as ``images/NNNNNN.png`` and index it."""
        if image.dtype != np.uint8 or image.ndim != 2:
            raise ValueError("images must be uint8 (H, W)")
        rel = f"{IMAGES_DIR}/{self.count:06d}.png"
        if not cv2.imwrite(str(self.run_dir / rel), image, self._png_params):
            raise DatasetError("cannot write image", self.run_dir / rel)
        self._fh.write(f"{t:.6f},{rel}\n")
        self._fh.flush()
        self.count += 1
        return self.run_dir / rel

    def write_encoded(self, t: float, png: bytes) -> Path:
        """Write the next image from PNG bytes (e.g. encoded by a worker process) and index it."""
        rel = f"{IMAGES_DIR}/{self.count:06d}.png"
        try:
            (self.run_dir / rel).write_bytes(png)
        except OSError as exc:
            raise DatasetError(f"cannot write image: {exc}", self.run_dir / rel) from exc
        self._fh.write(f"{t:.6f},{rel}\n")
        self._fh.flush()
        self.count += 1
        return self.run_dir / rel

    def close(self) -> None:
        """Close the index."""
        self._fh.close()
