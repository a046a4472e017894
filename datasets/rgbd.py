"""Readers of RGB-D sequences: the TUM RGB-D layout and the slambook2 sample.

TUM RGB-D layout (written by :mod:`lampsam.datasets.kinect_sim`, and the public
TUM benchmark's)::

    rgb.txt, depth.txt   "timestamp filename" lines, '#' comments
    rgb/*.png            8-bit colour
    depth/*.png          16-bit depth, metres = value / depth_scale, 0 = no depth; or a
                         32-bit float image (TIFF) in metres, NaN / 0 = no depth
    groundtruth.txt      optional world_T_camera, TUM "t tx ty tz qx qy qz qw"
    kinect.yaml          optional intrinsics + depth_scale (lampsam runs); without it
                         the camera must be given

slambook2 ``ch5/rgbd`` (``../shared/data/rgbd_slambook2``): ``color/{1..5}.png``
(640x480), ``depth/{1..5}.pgm`` (16-bit, metres = value / 1000), ``pose.txt``
``tx ty tz qx qy qz qw`` per line = world_T_camera; fx = 518.0, fy = 519.0,
cx = 325.5, cy = 253.5. Its world frame is the first camera's convention
(``y`` roughly down), so :attr:`RgbdSequence.world_up` is ``(0, -1, 0)`` there.

Camera frame (OpenCV): ``x`` right, ``y`` down, ``z`` the optical axis; depth is
the ``z`` coordinate of the point.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from lampsam.arrays import FloatArray, ImageU8, ImageU16
from lampsam.datasets.textio import data_lines, read_yaml
from lampsam.datasets.tum import pose_from_tum_fields, read_tum_3d
from lampsam.errors import DatasetError
from lampsam.strict_keys import array, number

log = logging.getLogger(__name__)

SLAMBOOK2_FX = 518.0
SLAMBOOK2_FY = 519.0
SLAMBOOK2_CX = 325.5
SLAMBOOK2_CY = 253.5
SLAMBOOK2_DEPTH_SCALE = 1000.0


@dataclass(frozen=True)
class RgbdCamera:
    """Pinhole RGB-D camera (colour and depth registered).

    Attributes:
        width: image columns.
        height: image rows.
        fx, fy: focal lengths, pixels.
        cx, cy: principal point, pixels (OpenCV convention).
        depth_scale: stored depth value per metre (TUM 5000, slambook2 1000).
        min_depth: nearest trusted depth, metres (default 0.3).
        max_depth: farthest trusted depth, metres (default 6.0).
        body_T_camera: (4, 4) camera pose on the robot (default identity: no robot).
    """

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    depth_scale: float
    min_depth: float = 0.3
    max_depth: float = 6.0
    body_T_camera: FloatArray = field(default_factory=lambda: np.eye(4))  # noqa: N815

    def K(self) -> FloatArray:  # noqa: N802
        """Intrinsic matrix (3, 3)."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])


@dataclass(frozen=True, eq=False)
class RgbdSequence:
    """An RGB-D sequence with colour/depth pairs associated by time.

    Attributes:
        root: the sequence directory.
        camera: the camera.
        t: (N,) frame times, seconds (the depth image's time stamp).
        rgb_files: N colour files.
        depth_files: N depth files.
        world_T_camera: (N, 4, 4) camera poses, or None when the sequence has none.
        world_up: (3,) unit "up" direction in the world frame (for projecting to the floor).
    """

    root: Path
    camera: RgbdCamera
    t: FloatArray
    rgb_files: tuple[Path, ...]
    depth_files: tuple[Path, ...]
    world_T_camera: FloatArray | None = None  # noqa: N815
    world_up: FloatArray = field(default_factory=lambda: np.array([0.0, 0.0, 1.0]))

    def __len__(self) -> int:
        """Number of frames."""
        return len(self.depth_files)

    def load_rgb(self, i: int) -> ImageU8:
        """Colour image ``i`` as uint8 (H, W, 3) RGB.

        Raises:
            DatasetError: missing/unreadable file or wrong size.
        """
        path = self.rgb_files[i]
        img = cv2.imread(str(path), cv2.IMREAD_COLOR)
        if img is None:
            raise DatasetError("colour image missing or unreadable", path)
        _check_shape(img, self.camera, path)
        return np.asarray(cv2.cvtColor(img, cv2.COLOR_BGR2RGB), dtype=np.uint8)

    def load_depth(self, i: int) -> ImageU16:
        """Depth image ``i`` as uint16 (H, W) (metres = value / ``camera.depth_scale``).

        Raises:
            DatasetError: missing/unreadable file, not 16-bit single channel, wrong size.
        """
        path = self.depth_files[i]
        img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if img is None:
            raise DatasetError("depth image missing or unreadable", path)
        if img.dtype == np.float32 and img.ndim == 2:
            img = depth_metres_to_u16(img, self.camera.depth_scale, path)
        if img.dtype != np.uint16 or img.ndim != 2:
            raise DatasetError(
                f"depth image must be 16-bit single channel (or 32-bit float metres), got "
                f"{img.dtype} {img.shape}", path
            )
        _check_shape(img, self.camera, path)
        check_depth_range(img, self.camera, path)
        return np.asarray(img, dtype=np.uint16)


# Folders warned about a depth range that does not fit the camera, and files warned about
# holding no depth (one warning each: a map build reads each frame more than once).
_RANGE_WARNED: set[Path] = set()
_EMPTY_WARNED: set[Path] = set()

# Below this share of the present depth pixels inside [min_depth, max_depth] the
# depth_scale is suspected (a TUM folder read at 1000 instead of 5000 puts ~all of it beyond).
SUSPECT_IN_RANGE = 0.2


def depth_metres_to_u16(depth_m: np.ndarray, depth_scale: float, path: Path) -> np.ndarray:
    """A 32-bit float depth image in metres as the camera's 16-bit units.

    Args:
        depth_m: (H, W) float32 depth, metres; NaN, inf and values <= 0 mean no depth.
        depth_scale: stored value per metre of the result.
        path: the file, for the warning.

    Returns:
        (H, W) uint16, ``round(depth_m * depth_scale)``, 0 where there is no depth;
        values beyond 65535 (over 13.1 m at scale 5000) are set to 0 with a warning.
    """
    d = np.asarray(depth_m, dtype=np.float64)
    ok = np.isfinite(d) & (d > 0)
    scaled = np.where(ok, np.rint(np.where(ok, d, 0.0) * depth_scale), 0.0)
    over = scaled > 65535
    if np.any(over):
        log.warning("%s: %d float depth pixels beyond %.1f m do not fit 16 bits at depth_scale "
                    "%g: read as no depth", path, int(over.sum()), 65535 / depth_scale,
                    depth_scale)
        scaled[over] = 0
    return scaled.astype(np.uint16)


def check_depth_range(depth: np.ndarray, camera: RgbdCamera, path: Path) -> None:
    """Warn when a depth frame holds no depth, or hardly any inside the camera's range.

    An all-zero frame is warned about once per file (it adds nothing to a map); a frame whose
    present pixels lie mostly outside ``[min_depth, max_depth]`` once per folder (the
    usual cause is a wrong ``depth_scale``: TUM stores 5000 per metre, a RealSense or
    slambook2 1000).
    """
    present = depth > 0
    n = int(present.sum())
    if n == 0:
        if path in _EMPTY_WARNED:
            return
        _EMPTY_WARNED.add(path)
        log.warning("%s: the depth image holds no depth (every pixel 0): the frame adds nothing",
                    path)
        return
    z = depth[present].astype(np.float64) / camera.depth_scale
    inside = float(np.mean((z >= camera.min_depth) & (z <= camera.max_depth)))
    if inside < SUSPECT_IN_RANGE and path.parent not in _RANGE_WARNED:
        _RANGE_WARNED.add(path.parent)
        log.warning(
            "%s: only %.0f %% of the depth pixels lie within %.1f-%.1f m at depth_scale %g "
            "(median %.2f m): is depth_scale right (TUM 5000, RealSense / slambook2 1000 per "
            "metre)? Pixels outside the range are not used", path, 100 * inside,
            camera.min_depth, camera.max_depth, camera.depth_scale, float(np.median(z)))


def _check_shape(img: np.ndarray, camera: RgbdCamera, path: Path) -> None:
    """Raise a DatasetError naming ``path`` when ``img`` is not the camera's size."""
    if img.shape[:2] != (camera.height, camera.width):
        raise DatasetError(
            f"image is {img.shape[1]}x{img.shape[0]}, camera is {camera.width}x{camera.height}",
            path,
        )


def _read_list(path: Path) -> tuple[list[float], list[Path]]:
    """A TUM ``timestamp filename`` list; relative names are resolved against the list's folder."""
    if not path.exists():
        raise DatasetError("file list not found", path)
    times: list[float] = []
    files: list[Path] = []
    for lineno, text in data_lines(path):
        parts = text.split()
        if len(parts) != 2:
            raise DatasetError(
                f"expected 'timestamp filename', got {len(parts)} fields", path, lineno
            )
        try:
            t = float(parts[0])
        except ValueError as exc:
            raise DatasetError(f"bad timestamp {parts[0]!r}", path, lineno) from exc
        if not math.isfinite(t):
            raise DatasetError("timestamp is not finite", path, lineno)
        if times and t <= times[-1]:
            raise DatasetError(f"time goes backwards ({t} after {times[-1]})", path, lineno)
        times.append(t)
        files.append(path.parent / parts[1])
    if not times:
        raise DatasetError("no frames listed", path)
    return times, files


def camera_from_yaml(path: Path) -> RgbdCamera:
    """The camera of a lampsam ``kinect.yaml`` (written by ``kinect_sim``).

    Keys other than the camera's (provenance, the simulator's settings) are ignored.

    Raises:
        DatasetError: unreadable or invalid YAML (file and line), a missing key, or a
            value of the wrong type or shape (the key named).
    """
    meta = read_yaml(path)
    if not isinstance(meta, dict):
        raise DatasetError("expected a mapping of camera keys (width, height, fx, ...), got "
                           + ("an empty file" if meta is None else type(meta).__name__), path)

    def fail(key: str, problem: str) -> DatasetError:
        return DatasetError(f"camera key {key}: {problem}", path)

    def num(key: str, default: float | None = None, integer: bool = False) -> float:
        return number(meta, key, "", fail=fail, default=default, integer=integer)

    T = np.eye(4)
    T[:3, :3] = array(meta, "body_R_camera", (3, 3), "", fail=fail)
    T[:3, 3] = array(meta, "body_t_camera", (3,), "", fail=fail)
    return RgbdCamera(
        width=int(num("width", integer=True)),
        height=int(num("height", integer=True)),
        fx=num("fx"),
        fy=num("fy"),
        cx=num("cx"),
        cy=num("cy"),
        depth_scale=num("depth_scale"),
        min_depth=num("min_depth", default=0.3),
        max_depth=num("max_depth", default=6.0),
        body_T_camera=T,
    )


def read_tum_rgbd(
    path: str | Path, camera: RgbdCamera | None = None, max_dt: float = 0.02
) -> RgbdSequence:
    """Read a TUM RGB-D directory.

    Colour frames are associated to depth frames by nearest time stamp (within
    ``max_dt``); unmatched depth frames are dropped with a logged warning, and so are
    frames without a ``groundtruth.txt`` pose within ``max_dt`` when some others have one
    (when none has, the sequence is read without poses, with a warning).

    Args:
        path: the directory with ``rgb.txt`` and ``depth.txt``.
        camera: the camera; default read from ``kinect.yaml`` in the directory.
        max_dt: association tolerance, seconds.

    Returns:
        The sequence (``world_T_camera`` from ``groundtruth.txt`` at the frame times,
        when present and covering them; else None).

    Raises:
        DatasetError: missing lists/camera, malformed lines.
    """
    root = Path(path)
    if not root.is_dir():
        raise DatasetError("RGB-D directory not found", root)
    if camera is None:
        if not (root / "kinect.yaml").is_file():
            raise DatasetError(
                "no kinect.yaml: a TUM RGB-D folder needs its camera in kinect.yaml beside rgb.txt "
                "(width, height, fx, fy, cx, cy in px; depth_scale, 5000 for TUM; body_t_camera "
                "[x, y, z] m and body_R_camera 3x3 on the robot; optional min_depth, max_depth m: "
                "docs/log-format.md), or pass the camera from Python", root)
        camera = camera_from_yaml(root / "kinect.yaml")
    t_rgb, f_rgb = _read_list(root / "rgb.txt")
    t_depth, f_depth = _read_list(root / "depth.txt")
    t_rgb_a = np.array(t_rgb)
    keep_t: list[float] = []
    keep_rgb: list[Path] = []
    keep_depth: list[Path] = []
    for t, f in zip(t_depth, f_depth, strict=True):
        j = int(np.argmin(np.abs(t_rgb_a - t)))
        if abs(t_rgb_a[j] - t) <= max_dt:
            keep_t.append(t)
            keep_rgb.append(f_rgb[j])
            keep_depth.append(f)
    dropped = len(t_depth) - len(keep_t)
    if dropped:
        log.warning(
            "%s: %d depth frames without a colour frame within %.3f s dropped",
            root,
            dropped,
            max_dt,
        )
    if not keep_t:
        raise DatasetError("no colour/depth pairs", root)
    poses = None
    gt = root / "groundtruth.txt"
    if gt.exists():  # optional; a directory of that name is an error (read_tum_3d)
        t_gt, T_gt = read_tum_3d(gt)
        idx = np.searchsorted(t_gt, keep_t)
        idx = np.clip(idx, 0, len(t_gt) - 1)
        prev = np.clip(idx - 1, 0, len(t_gt) - 1)
        best = np.where(np.abs(t_gt[prev] - keep_t) < np.abs(t_gt[idx] - keep_t), prev, idx)
        posed = np.abs(t_gt[best] - keep_t) <= max_dt
        if np.all(posed):
            poses = T_gt[best]
        elif np.any(posed):
            # The TUM benchmark's motion capture often starts after the camera: keep the
            # frames that have a pose rather than losing every pose.
            log.warning(
                "%s: %d of %d frames have no pose within %.3f s (poses span %.3f-%.3f s, "
                "frames %.3f-%.3f s): those frames are dropped", gt, int((~posed).sum()),
                len(keep_t), max_dt, t_gt[0], t_gt[-1], keep_t[0], keep_t[-1])
            keep = np.flatnonzero(posed)
            keep_t = [keep_t[k] for k in keep]
            keep_rgb = [keep_rgb[k] for k in keep]
            keep_depth = [keep_depth[k] for k in keep]
            poses = T_gt[best[keep]]
        else:
            log.warning(
                "%s: no frame has a pose within %.3f s (poses span %.3f-%.3f s, frames "
                "%.3f-%.3f s): the sequence is read without poses", gt, max_dt, t_gt[0],
                t_gt[-1], keep_t[0], keep_t[-1])
    if poses is not None:
        check_upright(poses, np.array([0.0, 0.0, 1.0]), gt)
    return RgbdSequence(root, camera, np.array(keep_t), tuple(keep_rgb), tuple(keep_depth), poses)


# A camera whose image-down axis lies further than this from the world's down, while it
# does not look at the floor, is taken for a pose file in another world convention.
TILT_WARN_DEG = 60.0


def check_upright(world_T_camera: FloatArray, world_up: FloatArray, path: Path) -> bool:
    """Warn when the camera poses look like another world convention than ``world_up``.

    A TUM RGB-D ``groundtruth.txt`` is z-up (motion capture); poses from a visual SLAM
    system are often in the first camera's frame (y down, z forward). Read as z-up, such a
    drive maps on the wrong plane. Flagged when, on the median frame, the image-down axis
    (camera ``y``) lies over :data:`TILT_WARN_DEG` from the world's down while the optical
    axis does not point at the floor (a camera looking down at the floor is left alone).

    Args:
        world_T_camera: (N, 4, 4) camera poses.
        world_up: (3,) the world's up direction.
        path: the pose file, for the warning.

    Returns:
        True when it warned.
    """
    up = np.asarray(world_up, float) / np.linalg.norm(world_up)
    down_cos = np.clip(world_T_camera[:, :3, 1] @ -up, -1.0, 1.0)
    tilt = float(np.degrees(np.arccos(np.median(down_cos))))
    looks_down = float(np.median(world_T_camera[:, :3, 2] @ up)) < -0.5
    if tilt <= TILT_WARN_DEG or looks_down:
        return False
    log.warning("%s: the camera's image-down axis lies %.0f deg from the world's down "
                "(%s) on the median frame: these poses look like another convention "
                "(a visual SLAM trajectory in the first camera's frame: y down, z forward) "
                "than the z-up motion-capture frame a TUM groundtruth.txt is read in, or the "
                "camera looks up at the ceiling; a floor map from them lies on the wrong plane",
                path, tilt,
                "-z" if np.allclose(up, [0, 0, 1]) else f"-{up.round(3).tolist()}")
    return True


def read_slambook2(path: str | Path) -> RgbdSequence:
    """Read the slambook2 ``ch5/rgbd`` sample (module docstring).

    Args:
        path: the folder with ``color/``, ``depth/`` and ``pose.txt``.

    Returns:
        The 5-frame sequence with ``t = 0, 1, ...`` and ``world_up = (0, -1, 0)``.

    Raises:
        DatasetError: missing files or malformed ``pose.txt``.
    """
    root = Path(path)
    pose_file = root / "pose.txt"
    if not pose_file.exists():
        raise DatasetError("pose.txt not found", pose_file)
    poses = []
    for lineno, text in data_lines(pose_file):
        try:
            vals = [float(v) for v in text.split()]
        except ValueError as exc:
            raise DatasetError(f"bad number: {exc}", pose_file, lineno) from exc
        if len(vals) != 7 or not all(math.isfinite(v) for v in vals):
            raise DatasetError(
                "expected 7 finite numbers 'tx ty tz qx qy qz qw'", pose_file, lineno
            )
        poses.append(pose_from_tum_fields(vals))
    if not poses:
        raise DatasetError("no poses (empty file)", pose_file)
    n = len(poses)
    unposed = sorted(f.name for f in (root / "color").glob("*.png")
                     if f.stem.isdigit() and int(f.stem) > n)
    if unposed:
        log.warning("%s: %d poses, so %d colour frames beyond %d.png (%s) are not used",
                    pose_file, n, len(unposed), n, ", ".join(unposed[:5]))
    rgb = tuple(root / "color" / f"{i + 1}.png" for i in range(n))
    depth = tuple(root / "depth" / f"{i + 1}.pgm" for i in range(n))
    for f in rgb + depth:
        if not f.is_file():
            raise DatasetError("frame file missing", f)
    camera = RgbdCamera(
        640,
        480,
        SLAMBOOK2_FX,
        SLAMBOOK2_FY,
        SLAMBOOK2_CX,
        SLAMBOOK2_CY,
        SLAMBOOK2_DEPTH_SCALE,
        0.3,
        7.0,
    )
    return RgbdSequence(
        root,
        camera,
        np.arange(n, dtype=float),
        rgb,
        depth,
        np.stack(poses),
        np.array([0.0, -1.0, 0.0]),
    )
