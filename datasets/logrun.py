"""The logged-run format: the sensor rig, readers and writers (``docs/log-format.md``).

A logged run is a directory written by a robot, the simulator or a public-data
adapter, and read by every backend::

    rig.yaml                 required  camera + odometry model (:class:`Rig`)
    odometry.csv             required  t,d_left,d_right  (wheel travel since the previous line, m)
                                       -- or odometry_pose2.csv (Pose2 increments) or
                                       odometry_poses.tum (absolute odometry poses):
                                       lampsam.datasets.odometry
    images.csv + images/     optional  t,file            (8-bit grey PNG, one per line)
    groundtruth.tum          optional  TUM ``t x y z qx qy qz qw`` (planar, yaw-only quaternion)
    landmarks.csv            optional  id,type,x,y,z,phi,length,width (true landmarks)
    rangebearing.csv         optional  t,landmark_id,range,bearing (landmark datasets)
    truth/projections.csv    optional  simulator truth: every landmark's projection per image
    meta.yaml                optional  free-form provenance (world, seed, version)

Every reader validates what it reads: a missing file, a malformed line, a
non-finite number or a time stamp that does not increase raises
:class:`lampsam.errors.DatasetError` naming the file and the 1-based line.
Frames and angles follow ``docs/conventions.md``.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import warnings
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TextIO

import cv2
import numpy as np
import yaml

from lampsam.arrays import BoolArray, FloatArray, ImageU8, IntArray
from lampsam.datasets.odometry import (
    ODOMETRY_POSE2_FILE,
    ODOMETRY_POSES_FILE,
    Pose2OdometryLog,
    pose2_odometry_from_poses,
    read_pose2_odometry,
    write_pose2_odometry,
)
from lampsam.errors import DatasetError

log = logging.getLogger(__name__)

FORMAT_VERSION = 1
"""Version of the logged-run format written by :func:`write_run`."""

RIG_FILE = "rig.yaml"
ODOMETRY_FILE = "odometry.csv"
IMAGES_FILE = "images.csv"
IMAGES_DIR = "images"
GROUNDTRUTH_FILE = "groundtruth.tum"
LANDMARKS_FILE = "landmarks.csv"
RANGE_BEARING_FILE = "rangebearing.csv"
PROJECTIONS_FILE = "truth/projections.csv"
META_FILE = "meta.yaml"

ODOMETRY_HEADER = ("t", "d_left", "d_right")
IMAGES_HEADER = ("t", "file")
LANDMARKS_HEADER = ("id", "type", "x", "y", "z", "phi", "length", "width")
RANGE_BEARING_HEADER = ("t", "landmark_id", "range", "bearing")
PROJECTIONS_HEADER = (
    "frame", "t", "id", "type", "col", "row", "angle_px", "visible", "fully_visible",
)  # fmt: skip

LANDMARK_TYPES = ("lamp_rect", "lamp_round", "lamp_square", "corner")
"""Landmark types of ``landmarks.csv``; ``lamp_rect`` lamps have an axis ``phi``."""

DEFAULT_BODY_R_CAMERA = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
"""Upward camera, image top = robot forward (conventions.md)."""


def _frozen_array(a: Any, shape: tuple[int, ...], name: str) -> FloatArray:
    """A read-only float64 copy of ``a`` with the given shape, or ValueError."""
    arr = np.array(a, dtype=np.float64)
    if arr.shape != shape:
        raise ValueError(f"{name} must have shape {shape}, got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} must be finite")
    arr.setflags(write=False)
    return arr


# --------------------------------------------------------------------------- rig
@dataclass(frozen=True, eq=False)
class CameraModel:
    """Pinhole camera with OpenCV distortion, mounted on the robot body.

    Attributes:
        width: image width, px (default 320).
        height: image height, px (default 240).
        fx: focal length along columns, px (default 92.376 = 120 deg horizontal field of view).
        fy: focal length along rows, px.
        cx: principal point column, px (OpenCV: origin at the centre of the top-left pixel).
        cy: principal point row, px.
        dist: (5,) OpenCV distortion ``(k1, k2, p1, p2, k3)`` (default zeros).
        body_t_camera: (3,) optical centre in the body frame, m; ``z`` is its height
            above the floor (default ``(0.1, 0, 0.3)``).
        body_R_camera: (3, 3) columns = camera ``x, y, z`` axes in body coordinates
            (default: optical axis up, image top = robot forward).
    """

    width: int = 320
    height: int = 240
    fx: float = 160.0 / math.tan(math.radians(60.0))
    fy: float = 160.0 / math.tan(math.radians(60.0))
    cx: float = 159.5
    cy: float = 119.5
    dist: FloatArray = field(default_factory=lambda: np.zeros(5))
    body_t_camera: FloatArray = field(default_factory=lambda: np.array([0.1, 0.0, 0.3]))
    body_R_camera: FloatArray = field(default_factory=lambda: DEFAULT_BODY_R_CAMERA.copy())

    def __post_init__(self) -> None:
        """Validate and freeze the arrays (ValueError on bad values)."""
        object.__setattr__(self, "dist", _frozen_array(self.dist, (5,), "dist"))
        object.__setattr__(
            self, "body_t_camera", _frozen_array(self.body_t_camera, (3,), "body_t_camera")
        )
        rot = _frozen_array(self.body_R_camera, (3, 3), "body_R_camera")
        if not np.allclose(rot.T @ rot, np.eye(3), atol=1e-6) or np.linalg.det(rot) < 0:
            raise ValueError("body_R_camera must be a rotation matrix")
        object.__setattr__(self, "body_R_camera", rot)
        if self.width <= 0 or self.height <= 0 or self.fx <= 0 or self.fy <= 0:
            raise ValueError("image size and focal lengths must be positive")

    @classmethod
    def from_fov(
        cls, width: int = 320, height: int = 240, hfov_deg: float = 120.0, **kwargs: Any
    ) -> CameraModel:
        """A camera with square pixels, centred principal point and the given horizontal FOV.

        Args:
            width: image width, px.
            height: image height, px.
            hfov_deg: horizontal field of view of the undistorted pinhole, degrees.
            **kwargs: other :class:`CameraModel` fields (``dist``, ``body_t_camera``, ...).
        """
        f = (width / 2.0) / math.tan(math.radians(hfov_deg) / 2.0)
        return cls(
            width=width, height=height, fx=f, fy=f,
            cx=(width - 1) / 2.0, cy=(height - 1) / 2.0, **kwargs,
        )  # fmt: skip

    def K(self) -> FloatArray:  # noqa: N802 (the usual name of the intrinsic matrix)
        """The (3, 3) intrinsic matrix."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def z_cam(self) -> float:
        """Height of the optical centre above the floor, m."""
        return float(self.body_t_camera[2])

    def camera_rays(self, px: FloatArray) -> FloatArray:
        """Undistorted camera rays ``(x_n, y_n)`` (z = 1) of pixels, via ``cv2.undistortPoints``.

        Args:
            px: (N, 2) pixels ``(col, row)``.

        Returns:
            (N, 2) normalised camera coordinates (camera frame, OpenCV axes).
        """
        pts = np.ascontiguousarray(np.asarray(px, dtype=np.float64).reshape(-1, 1, 2))
        if pts.shape[0] == 0:
            return np.zeros((0, 2))
        if not np.any(self.dist):
            out = np.empty((pts.shape[0], 2))
            out[:, 0] = (pts[:, 0, 0] - self.cx) / self.fx
            out[:, 1] = (pts[:, 0, 1] - self.cy) / self.fy
            return out
        und = cv2.undistortPoints(
            pts,
            self.K(),
            self.dist,
            criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-12),
        )
        return np.asarray(und, dtype=np.float64).reshape(-1, 2)

    def normalized_from_pixels(self, px: FloatArray) -> FloatArray:
        """Normalised ceiling coordinates ``m = (u, v)`` of pixels (conventions.md).

        Undistorts each pixel to the camera ray ``(x_n, y_n, 1)``, rotates it into
        body axes ``b = body_R_camera @ ray`` and returns ``(b_x / b_z, b_y / b_z)``:
        forward and left per metre of height above the camera.

        Args:
            px: (N, 2) pixels ``(col, row)``.

        Returns:
            (N, 2) ``(u, v)``; rows whose ray does not point upwards are NaN.
        """
        rays = self.camera_rays(px)
        cam = np.column_stack([rays, np.ones(len(rays))])
        body = cam @ self.body_R_camera.T
        with np.errstate(divide="ignore", invalid="ignore"):
            m = body[:, :2] / body[:, 2:3]
        m[body[:, 2] <= 1e-12] = np.nan
        return m

    def pixels_from_normalized(self, m: FloatArray) -> FloatArray:
        """Pixels of normalised ceiling coordinates (inverse of :meth:`normalized_from_pixels`).

        Args:
            m: (N, 2) ``(u, v)`` (body forward, left per metre of height).

        Returns:
            (N, 2) pixels ``(col, row)`` via ``cv2.projectPoints`` (with distortion);
            rows whose ray is behind the camera are NaN.
        """
        m = np.asarray(m, dtype=np.float64).reshape(-1, 2)
        if len(m) == 0:
            return np.zeros((0, 2))
        body = np.column_stack([m, np.ones(len(m))])
        cam = body @ self.body_R_camera  # = (body_R_camera.T @ b.T).T
        px, _ = cv2.projectPoints(
            np.ascontiguousarray(cam.reshape(-1, 1, 3)),
            np.zeros(3),
            np.zeros(3),
            self.K(),
            self.dist,
        )
        px = np.asarray(px, dtype=np.float64).reshape(-1, 2)
        px[cam[:, 2] <= 1e-12] = np.nan
        return px

    def to_dict(self) -> dict[str, Any]:
        """Plain-Python mapping for YAML."""
        return {
            "width": int(self.width),
            "height": int(self.height),
            "fx": float(self.fx),
            "fy": float(self.fy),
            "cx": float(self.cx),
            "cy": float(self.cy),
            "dist": [float(x) for x in self.dist],
            "body_t_camera": [float(x) for x in self.body_t_camera],
            "body_R_camera": [[float(x) for x in row] for row in self.body_R_camera],
        }


@dataclass(frozen=True)
class OdometryModel:
    """Differential-drive wheel odometry (paper 1, eqs. 13-15).

    Attributes:
        wheel_base: distance between the wheels ``b``, m (default 0.4).
        k_r: right-wheel slip constant, m: ``var(ds_r) = k_r |ds_r|`` (eq. 15; default 2e-5).
        k_l: left-wheel slip constant, m (default 2e-5).
    """

    wheel_base: float = 0.4
    k_r: float = 2e-5
    k_l: float = 2e-5

    def __post_init__(self) -> None:
        """Validate (ValueError on non-positive base or negative constants)."""
        if not (self.wheel_base > 0 and self.k_r >= 0 and self.k_l >= 0):
            raise ValueError("wheel_base must be > 0 and k_r, k_l >= 0")

    def to_dict(self) -> dict[str, Any]:
        """Plain-Python mapping for YAML."""
        return {
            "wheel_base": float(self.wheel_base),
            "k_r": float(self.k_r),
            "k_l": float(self.k_l),
        }


@dataclass(frozen=True)
class Rig:
    """The sensor rig of a run: the ceiling camera and the wheel odometry.

    Attributes:
        camera: the upward camera.
        odometry: the wheel-odometry model.
    """

    camera: CameraModel = field(default_factory=CameraModel)
    odometry: OdometryModel = field(default_factory=OdometryModel)

    @classmethod
    def from_dict(cls, data: Any, path: Path | None = None) -> Rig:
        """Build from the mapping of ``rig.yaml`` (sections ``camera``, ``odometry``).

        The camera may give ``hfov_deg`` instead of ``fx, fy, cx, cy``.

        Raises:
            DatasetError: a missing section, unknown key or bad value (naming ``path``).
        """
        if not isinstance(data, dict):
            raise DatasetError("rig must be a mapping with 'camera' and 'odometry'", path)
        try:
            cam = dict(data.get("camera") or {})
            odo = dict(data.get("odometry") or {})
            if "hfov_deg" in cam:
                camera = CameraModel.from_fov(**cam)
            else:
                camera = CameraModel(**cam)
            odometry = OdometryModel(**odo)
        except (TypeError, ValueError) as exc:
            raise DatasetError(f"invalid rig: {exc}", path) from exc
        return cls(camera=camera, odometry=odometry)

    def to_dict(self) -> dict[str, Any]:
        """Plain-Python mapping for YAML."""
        return {"camera": self.camera.to_dict(), "odometry": self.odometry.to_dict()}

    @classmethod
    def from_yaml(cls, path: str | Path) -> Rig:
        """Read ``rig.yaml``.

        Raises:
            DatasetError: missing file, invalid YAML or invalid rig.
        """
        path = Path(path)
        return cls.from_dict(_read_yaml(path), path)

    def to_yaml(self, path: str | Path) -> None:
        """Write ``rig.yaml``."""
        Path(path).write_text(yaml.safe_dump(self.to_dict(), sort_keys=False))


def _read_yaml(path: Path) -> Any:
    """Parse a YAML file, or DatasetError naming it."""
    try:
        text = path.read_text()
    except FileNotFoundError as exc:
        raise DatasetError("file not found", path) from exc
    except OSError as exc:
        raise DatasetError(f"cannot read: {exc}", path) from exc
    try:
        return yaml.safe_load(text)
    except yaml.YAMLError as exc:
        line = None
        mark = getattr(exc, "problem_mark", None)
        if mark is not None:
            line = int(mark.line) + 1
        raise DatasetError(f"invalid YAML: {exc}", path, line) from exc


# --------------------------------------------------------------------------- tables
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
        out[:, 2] = _wrap(out[:, 2])
        return out


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
        """(L,) True for lamps."""
        return np.array([t.startswith("lamp") for t in self.types], dtype=bool)

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
        return img

    def __iter__(self) -> Iterator[tuple[float, ImageU8]]:
        """Iterate ``(t, image)``."""
        for i in range(len(self)):
            yield float(self.t[i]), self.load(i)


@dataclass(frozen=True)
class LoggedRun:
    """Everything in a logged-run directory (``docs/log-format.md``).

    Attributes:
        path: the run directory.
        rig: sensor rig.
        odometry: wheel odometry.
        images: ceiling images, or None when the run has none (landmark datasets).
        groundtruth: true trajectory, or None.
        landmarks: true landmarks, or None.
        projections: simulator truth projections, or None.
        range_bearing: range-bearing measurements, or None.
        meta: contents of ``meta.yaml`` (empty when absent).
    """

    path: Path
    rig: Rig
    odometry: OdometryLog | Pose2OdometryLog
    images: ImageIndex | None = None
    groundtruth: Trajectory | None = None
    landmarks: LandmarkTable | None = None
    projections: ProjectionTable | None = None
    range_bearing: RangeBearingLog | None = None
    meta: dict[str, Any] = field(default_factory=dict)


# --------------------------------------------------------------------------- CSV parsing
def _wrap(a: FloatArray) -> FloatArray:
    """Wrap angles to (-pi, pi]."""
    w = np.mod(np.asarray(a, dtype=np.float64) + np.pi, 2 * np.pi) - np.pi
    return np.where(w == -np.pi, np.pi, w)


def _open_text(path: Path) -> TextIO:
    """Open a text file, or DatasetError naming it."""
    try:
        return open(path, encoding="utf-8")
    except FileNotFoundError as exc:
        raise DatasetError("file not found", path) from exc
    except OSError as exc:
        raise DatasetError(f"cannot read: {exc}", path) from exc


def _parse_float(text: str, path: Path, line: int, column: str) -> float:
    """A finite float, or DatasetError naming file, line and column."""
    try:
        value = float(text)
    except ValueError as exc:
        raise DatasetError(f"column {column!r}: not a number: {text!r}", path, line) from exc
    if not math.isfinite(value):
        raise DatasetError(f"column {column!r}: non-finite value {text!r}", path, line)
    return value


def _parse_int(text: str, path: Path, line: int, column: str) -> int:
    """An integer, or DatasetError naming file, line and column."""
    try:
        return int(text)
    except ValueError as exc:
        raise DatasetError(f"column {column!r}: not an integer: {text!r}", path, line) from exc


def _read_csv(
    path: Path,
    header: Sequence[str],
    parsers: Sequence[Callable[[str, Path, int, str], Any]],
    allow_empty: bool = False,
) -> tuple[list[list[Any]], list[int]]:
    """Read a comma-separated table with an exact header line.

    Blank lines and lines starting with ``#`` are skipped.

    Returns:
        The parsed rows and their 1-based line numbers.

    Raises:
        DatasetError: missing file, wrong header, wrong column count, bad value,
            or no data rows (unless ``allow_empty``).
    """
    rows: list[list[Any]] = []
    lines: list[int] = []
    with _open_text(path) as fh:
        header_seen = False
        for lineno, raw in enumerate(fh, start=1):
            text = raw.strip()
            if not text or text.startswith("#"):
                continue
            fields = [f.strip() for f in text.split(",")]
            if not header_seen:
                if tuple(fields) != tuple(header):
                    raise DatasetError(
                        f"expected header {','.join(header)!r}, got {text!r}", path, lineno
                    )
                header_seen = True
                continue
            if len(fields) != len(header):
                raise DatasetError(
                    f"malformed line: expected {len(header)} fields, got {len(fields)}",
                    path,
                    lineno,
                )
            rows.append(
                [p(f, path, lineno, c) for p, f, c in zip(parsers, fields, header, strict=True)]
            )
            lines.append(lineno)
    if not header_seen:
        raise DatasetError(f"empty file (expected header {','.join(header)!r})", path)
    if not rows and not allow_empty:
        raise DatasetError("no data lines (empty log)", path)
    return rows, lines


def _check_time(
    t: FloatArray, lines: Sequence[int] | None, path: Path, strict: bool = True
) -> None:
    """DatasetError at the first time stamp that does not increase (or decreases if not strict).

    ``lines`` are the data lines' numbers; None re-scans ``path`` for them on error.
    """
    if len(t) < 2:
        return
    dt = np.diff(t)
    bad = np.flatnonzero(dt <= 0 if strict else dt < 0)
    if len(bad):
        k = int(bad[0]) + 1
        what = "does not increase" if strict else "goes backwards"
        line_nos = lines if lines is not None else _data_line_numbers(path)
        raise DatasetError(f"time stamp {t[k]!r} {what} (previous {t[k - 1]!r})", path, line_nos[k])


def _str_field(text: str, path: Path, line: int, column: str) -> str:
    """A non-empty string field."""
    if not text:
        raise DatasetError(f"column {column!r}: empty", path, line)
    return text


# --------------------------------------------------------------------------- readers
def _fast_columns(path: Path, header: Sequence[str], kinds: str) -> tuple[list[Any], None] | None:
    """Parse a well-formed table with ``np.loadtxt`` (C speed); None when anything is off.

    ``kinds`` has one letter per column: ``f`` finite float, ``n`` float allowing NaN,
    ``i`` integer, ``s`` non-empty string, ``b`` 0/1. On None the caller re-reads the
    file line by line with :func:`_read_csv`, which names the offending line. Line
    numbers are not returned (see :func:`_data_line_numbers`).
    """
    skip = 0
    try:
        with open(path, encoding="utf-8") as fh:
            for raw in fh:
                skip += 1
                line = raw.strip()
                if line and not line.startswith("#"):
                    if line != ",".join(header):
                        return None
                    break
            else:
                return None
    except (OSError, UnicodeDecodeError):
        return None
    num_idx = [j for j, k in enumerate(kinds) if k != "s"]
    str_idx = [j for j, k in enumerate(kinds) if k == "s"]
    cols: list[Any] = [None] * len(kinds)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("error")  # "empty input file" and friends -> slow path
            if num_idx:
                a = np.loadtxt(path, delimiter=",", skiprows=skip, usecols=num_idx, ndmin=2,
                               dtype=np.float64, comments="#", encoding="utf-8")  # fmt: skip
            if str_idx:
                st = np.loadtxt(path, delimiter=",", skiprows=skip, usecols=str_idx, ndmin=2,
                                dtype=str, comments="#", encoding="utf-8")  # fmt: skip
    except (ValueError, UserWarning):
        return None
    rows = len(a) if num_idx else len(st)
    if rows == 0:
        return None
    for c, j in enumerate(num_idx):
        col = a[:, c]
        kind = kinds[j]
        if kind == "n":
            if np.any(np.isinf(col)):
                return None
            cols[j] = col.copy()
            continue
        if not np.all(np.isfinite(col)):
            return None
        if kind == "f":
            cols[j] = col.copy()
        elif kind == "i":
            if not np.all(col == np.round(col)) or np.any(np.abs(col) > 2**53):
                return None
            cols[j] = col.astype(np.int64)
        else:  # "b"
            if not np.all((col == 0) | (col == 1)):
                return None
            cols[j] = col == 1
    for c, j in enumerate(str_idx):
        strs = [x.strip() for x in st[:, c].tolist()]
        if not all(strs):
            return None
        cols[j] = strs
    if num_idx and str_idx and len(st) != len(a):
        return None
    return cols, None


def _data_line_numbers(path: Path) -> list[int]:
    """1-based line numbers of a table's data lines (after the header; no blanks/comments)."""
    out: list[int] = []
    header_seen = False
    with _open_text(path) as fh:
        for n, raw in enumerate(fh, start=1):
            line = raw.strip()
            if not line or line.startswith("#"):
                continue
            if header_seen:
                out.append(n)
            header_seen = True
    return out


def _columns(
    path: Path,
    header: Sequence[str],
    kinds: str,
    parsers: Sequence[Callable[[str, Path, int, str], Any]],
    allow_empty: bool = False,
) -> tuple[list[Any], list[int] | None]:
    """Columns of a table: the fast path, else the line-by-line parser (precise errors)."""
    fast = _fast_columns(path, header, kinds)
    if fast is not None:
        return fast
    rows, lines = _read_csv(path, header, parsers, allow_empty)
    cols: list[Any] = []
    for j, kind in enumerate(kinds):
        col = [r[j] for r in rows]
        if kind in "fn":
            cols.append(np.array(col, dtype=np.float64))
        elif kind == "i":
            cols.append(np.array(col, dtype=np.int64))
        elif kind == "b":
            cols.append(np.array(col, dtype=bool))
        else:
            cols.append(col)
    return cols, lines


def read_odometry(path: str | Path) -> OdometryLog:
    """Read ``odometry.csv`` (``t,d_left,d_right``).

    Raises:
        DatasetError: missing, malformed, non-finite, empty, or time not increasing.
    """
    path = Path(path)
    (t, dl, dr), lines = _columns(path, ODOMETRY_HEADER, "fff", [_parse_float] * 3)
    _check_time(t, lines, path)
    return OdometryLog(t=t, d_left=dl, d_right=dr)


def read_image_index(path: str | Path, shape: tuple[int, int] | None = None) -> ImageIndex:
    """Read ``images.csv`` (``t,file``; files relative to the csv's folder).

    Image files are not opened here (see :meth:`ImageIndex.load`).

    Raises:
        DatasetError: missing, malformed, empty, or time not increasing.
    """
    path = Path(path)
    (t, names), lines = _columns(path, IMAGES_HEADER, "fs", [_parse_float, _str_field])
    _check_time(t, lines, path)
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

    rows, lines = _read_csv(path, LANDMARKS_HEADER, [_parse_int, _type] + [_parse_float] * 6, True)
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
    parsers = [_parse_float, _parse_int, _parse_float, _parse_float]
    (t, lid, rng, brg), lines = _columns(path, RANGE_BEARING_HEADER, "fiff", parsers)
    _check_time(t, lines, path, strict=False)
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
        return _parse_float(text, p, line, column)

    def _bool(text: str, p: Path, line: int, column: str) -> bool:
        """``0``/``1`` as a bool, or DatasetError."""
        if text not in ("0", "1"):
            raise DatasetError(f"column {column!r}: expected 0 or 1, got {text!r}", p, line)
        return text == "1"

    parsers = [
        _parse_int,
        _parse_float,
        _parse_int,
        _str_field,
        _parse_float,
        _parse_float,
        _nan_ok,
        _bool,
        _bool,
    ]
    cols, lines = _columns(path, PROJECTIONS_HEADER, "ifisffnbb", parsers, allow_empty=True)
    frame, t, ids, types, col, row, angle, vis, full = cols
    _check_time(frame.astype(np.float64), lines, path, strict=False)
    return ProjectionTable(
        frame=frame, t=t, ids=ids, types=tuple(types),
        pixel=np.column_stack([col, row]).reshape(-1, 2), angle_px=angle,
        visible=vis, fully_visible=full,
    )  # fmt: skip


def read_tum(path: str | Path) -> Trajectory:
    """Read a TUM trajectory ``t x y z qx qy qz qw`` as planar poses.

    Space separated; blank lines and ``#`` comments are skipped.

    ``theta`` is the yaw of the quaternion; ``z`` and any roll/pitch are dropped.

    Raises:
        DatasetError: missing, malformed, non-finite, empty, zero quaternion or time
            not increasing.
    """
    path = Path(path)
    t_list: list[float] = []
    rows: list[list[float]] = []
    lines: list[int] = []
    with _open_text(path) as fh:
        for lineno, raw in enumerate(fh, start=1):
            text = raw.strip()
            if not text or text.startswith("#"):
                continue
            fields = text.split()
            if len(fields) != 8:
                raise DatasetError(
                    f"malformed line: expected 8 fields 't x y z qx qy qz qw', got {len(fields)}",
                    path,
                    lineno,
                )
            vals = [
                _parse_float(f, path, lineno, c)
                for f, c in zip(fields, "t x y z qx qy qz qw".split(), strict=True)
            ]
            qx, qy, qz, qw = vals[4:]
            if qx * qx + qy * qy + qz * qz + qw * qw < 1e-12:
                raise DatasetError("zero quaternion", path, lineno)
            yaw = math.atan2(2.0 * (qw * qz + qx * qy), 1.0 - 2.0 * (qy * qy + qz * qz))
            t_list.append(vals[0])
            rows.append([vals[1], vals[2], yaw])
            lines.append(lineno)
    if not rows:
        raise DatasetError("no poses (empty trajectory)", path)
    t = np.array(t_list)
    _check_time(t, lines, path)
    poses = np.array(rows)
    poses[:, 2] = _wrap(poses[:, 2])
    return Trajectory(t=t, poses=poses)


def read_run(path: str | Path) -> LoggedRun:
    """Read a logged-run directory.

    Args:
        path: the run directory.

    Returns:
        The run; optional parts that are absent are None.

    Raises:
        DatasetError: the directory, ``rig.yaml`` or ``odometry.csv`` is missing, or any
            present file is invalid (naming the file and line).
    """
    path = Path(path)
    if not path.is_dir():
        raise DatasetError("run directory not found", path)
    rig = Rig.from_yaml(path / RIG_FILE)
    odometry: OdometryLog | Pose2OdometryLog
    if (path / ODOMETRY_FILE).exists() or not (
            (path / ODOMETRY_POSE2_FILE).exists() or (path / ODOMETRY_POSES_FILE).exists()):
        odometry = read_odometry(path / ODOMETRY_FILE)
    elif (path / ODOMETRY_POSE2_FILE).exists():
        odometry = read_pose2_odometry(path / ODOMETRY_POSE2_FILE)
    else:
        odo_poses = read_tum(path / ODOMETRY_POSES_FILE)
        odometry = pose2_odometry_from_poses(odo_poses.t, odo_poses.poses)
    cam = rig.camera
    images = None
    if (path / IMAGES_FILE).exists():
        images = read_image_index(path / IMAGES_FILE, shape=(cam.height, cam.width))
    gt = read_tum(path / GROUNDTRUTH_FILE) if (path / GROUNDTRUTH_FILE).exists() else None
    lms = read_landmarks(path / LANDMARKS_FILE) if (path / LANDMARKS_FILE).exists() else None
    proj = read_projections(path / PROJECTIONS_FILE) if (path / PROJECTIONS_FILE).exists() else None
    rb = (
        read_range_bearing(path / RANGE_BEARING_FILE)
        if (path / RANGE_BEARING_FILE).exists()
        else None
    )
    meta: dict[str, Any] = {}
    if (path / META_FILE).exists():
        loaded = _read_yaml(path / META_FILE)
        if loaded is not None and not isinstance(loaded, dict):
            raise DatasetError("meta.yaml must be a mapping", path / META_FILE)
        meta = loaded or {}
    log.info(
        "read run %s: %d odometry, %d images, gt=%s, landmarks=%s",
        path, len(odometry), 0 if images is None else len(images), gt is not None, lms is not None,
    )  # fmt: skip
    return LoggedRun(
        path=path, rig=rig, odometry=odometry, images=images, groundtruth=gt,
        landmarks=lms, projections=proj, range_bearing=rb, meta=meta,
    )  # fmt: skip


# --------------------------------------------------------------------------- writers
def _fmt(x: float, digits: int) -> str:
    """Fixed-point float without trailing noise (``nan`` stays ``nan``)."""
    if not math.isfinite(x):
        return "nan"
    return f"{x:.{digits}f}"


def write_odometry(path: str | Path, odometry: OdometryLog) -> None:
    """Write ``odometry.csv`` (time to 1 us, travel to 1 nm)."""
    with open(path, "w", encoding="utf-8") as fh:
        fh.write(",".join(ODOMETRY_HEADER) + "\n")
        for t, dl, dr in zip(odometry.t, odometry.d_left, odometry.d_right, strict=True):
            fh.write(f"{t:.6f},{dl:.9f},{dr:.9f}\n")


def write_tum(path: str | Path, trajectory: Trajectory) -> None:
    """Write a planar trajectory as TUM (``z = 0``, yaw-only quaternion), readable by evo."""
    with open(path, "w", encoding="utf-8") as fh:
        fh.write("# t x y z qx qy qz qw\n")
        for t, (x, y, th) in zip(trajectory.t, trajectory.poses, strict=True):
            fh.write(
                f"{t:.6f} {x:.9f} {y:.9f} 0 0 0 {math.sin(th / 2):.12f} {math.cos(th / 2):.12f}\n"
            )


def write_landmarks(path: str | Path, landmarks: LandmarkTable) -> None:
    """Write ``landmarks.csv``."""
    with open(path, "w", encoding="utf-8") as fh:
        fh.write(",".join(LANDMARKS_HEADER) + "\n")
        for i in range(len(landmarks)):
            x, y, z = landmarks.xyz[i]
            fh.write(
                f"{int(landmarks.ids[i])},{landmarks.types[i]},{x:.6f},{y:.6f},{z:.6f},"
                f"{landmarks.phi[i]:.9f},{landmarks.length[i]:.6f},{landmarks.width[i]:.6f}\n"
            )


def write_range_bearing(path: str | Path, rb: RangeBearingLog) -> None:
    """Write ``rangebearing.csv`` (used by public-data adapters, e.g. MRCLAM)."""
    with open(path, "w", encoding="utf-8") as fh:
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


class ImageWriter:
    """Writes ceiling images and ``images.csv`` one frame at a time (flushed after each).

    An interrupted run leaves a valid index of the frames already written.
    """

    def __init__(self, run_dir: str | Path):
        """Create ``images/`` and ``images.csv`` in ``run_dir``."""
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
        if not cv2.imwrite(str(self.run_dir / rel), image):
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


def write_meta(path: str | Path, meta: dict[str, Any]) -> None:
    """Write ``meta.yaml`` (adds ``format_version``)."""
    data = {"format_version": FORMAT_VERSION, **meta}
    Path(path).write_text(yaml.safe_dump(data, sort_keys=False))


def write_run(
    path: str | Path,
    rig: Rig,
    odometry: OdometryLog | Pose2OdometryLog,
    groundtruth: Trajectory | None = None,
    landmarks: LandmarkTable | None = None,
    range_bearing: RangeBearingLog | None = None,
    images: Sequence[tuple[float, ImageU8]] | None = None,
    meta: dict[str, Any] | None = None,
) -> Path:
    """Write a logged run (all parts except truth projections, see :class:`ProjectionWriter`).

    Args:
        path: run directory (created).
        rig: the sensor rig -> ``rig.yaml``.
        odometry: -> ``odometry.csv``.
        groundtruth: -> ``groundtruth.tum``.
        landmarks: -> ``landmarks.csv``.
        range_bearing: -> ``rangebearing.csv``.
        images: ``(t, uint8 (H, W))`` pairs -> ``images.csv`` + ``images/``; for long runs
            use :class:`ImageWriter` directly instead.
        meta: -> ``meta.yaml``.

    Returns:
        The run directory.
    """
    path = Path(path)
    path.mkdir(parents=True, exist_ok=True)
    rig.to_yaml(path / RIG_FILE)
    if isinstance(odometry, Pose2OdometryLog):
        write_pose2_odometry(path / ODOMETRY_POSE2_FILE, odometry)
    else:
        write_odometry(path / ODOMETRY_FILE, odometry)
    if groundtruth is not None:
        write_tum(path / GROUNDTRUTH_FILE, groundtruth)
    if landmarks is not None:
        write_landmarks(path / LANDMARKS_FILE, landmarks)
    if range_bearing is not None:
        write_range_bearing(path / RANGE_BEARING_FILE, range_bearing)
    if images is not None:
        writer = ImageWriter(path)
        try:
            for t, img in images:
                writer.write(t, img)
        finally:
            writer.close()
    write_meta(path / META_FILE, dict(meta or {}))
    return path


def replace_rig(rig: Rig, **camera_changes: Any) -> Rig:
    """A copy of ``rig`` with some camera fields replaced (convenience for tests)."""
    return dataclasses.replace(rig, camera=dataclasses.replace(rig.camera, **camera_changes))
