"""The logged-run directory: what it holds, and reading or writing it whole (``docs/log-format.md``).

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
Frames and angles follow ``docs/conventions.md``. The rig is
:mod:`lampsam.datasets.rig`, the tables :mod:`lampsam.datasets.tables`, TUM
files :mod:`lampsam.datasets.tum`.
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from lampsam.arrays import ImageU8
from lampsam.datasets.camera import CameraModel
from lampsam.datasets.odometry import (
    ODOMETRY_POSE2_FILE,
    ODOMETRY_POSES_FILE,
    Pose2OdometryLog,
    pose2_odometry_from_poses,
    read_pose2_odometry,
    write_pose2_odometry,
)
from lampsam.datasets.rig import OdometryModel, Rig
from lampsam.datasets.tables import (
    IMAGES_DIR,
    IMAGES_FILE,
    LANDMARK_TYPES,
    ImageIndex,
    ImageWriter,
    LandmarkTable,
    OdometryLog,
    ProjectionTable,
    ProjectionWriter,
    RangeBearingLog,
    Trajectory,
    read_image_index,
    read_landmarks,
    read_odometry,
    read_projections,
    read_range_bearing,
    write_landmarks,
    write_odometry,
    write_range_bearing,
)
from lampsam.datasets.textio import read_yaml
from lampsam.datasets.tum import read_tum, write_tum
from lampsam.errors import DatasetError
from lampsam.safe_io import write_text_atomic

# The run's parts are defined in their own modules (camera, rig, tables, tum);
# they are re-exported here so that ``lampsam.datasets.logrun`` stays the one
# import for code that reads or writes whole runs.
__all__ = [
    "FORMAT_VERSION",
    "GROUNDTRUTH_FILE",
    "IMAGES_DIR",
    "IMAGES_FILE",
    "LANDMARKS_FILE",
    "LANDMARK_TYPES",
    "META_FILE",
    "ODOMETRY_FILE",
    "PROJECTIONS_FILE",
    "RANGE_BEARING_FILE",
    "RIG_FILE",
    "CameraModel",
    "ImageIndex",
    "ImageWriter",
    "LandmarkTable",
    "LoggedRun",
    "OdometryLog",
    "OdometryModel",
    "ProjectionTable",
    "ProjectionWriter",
    "RangeBearingLog",
    "Rig",
    "Trajectory",
    "read_image_index",
    "read_landmarks",
    "read_odometry",
    "read_projections",
    "read_range_bearing",
    "read_run",
    "read_tum",
    "replace_rig",
    "write_landmarks",
    "write_meta",
    "write_odometry",
    "write_range_bearing",
    "write_run",
    "write_tum",
]

log = logging.getLogger(__name__)

FORMAT_VERSION = 1
"""Version of the logged-run format written by :func:`write_run`."""

RIG_FILE = "rig.yaml"
ODOMETRY_FILE = "odometry.csv"
GROUNDTRUTH_FILE = "groundtruth.tum"
LANDMARKS_FILE = "landmarks.csv"
RANGE_BEARING_FILE = "rangebearing.csv"
PROJECTIONS_FILE = "truth/projections.csv"
META_FILE = "meta.yaml"


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


#: Folders of other datasets that are not logged runs: (a file they hold, what to do).
_FOREIGN = (
    ("ds0_RS_Control.dat", "a MRCLAM folder: `lampsam slam DIR --mrclam` reads it"),
    ("Robot1_Odometry.dat", "a MRCLAM dataset folder: `lampsam slam DIR --mrclam` reads robot 1"),
    ("calib.txt", "a KITTI stereo sequence: `lampsam stereo-experiment` reads it (LAMPSAM_DATA)"),
    ("pose.txt", "an RGB-D (slambook2) folder: `lampsam build-map` reads it"),
    ("rgb.txt", "a TUM RGB-D folder: `lampsam build-map` reads it"),
    ("kinect.yaml", "a Kinect run without a ceiling camera (kinect-sim without --ceiling)"),
)


def _foreign_hint(path: Path) -> str:
    """``"; this looks like ..."`` for a known other dataset's folder, else ``""``."""
    for name, hint in _FOREIGN:
        if (path / name).exists() or (path / "kinect" / name).exists():
            return f"; this looks like {hint}"
    return ""


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
        raise DatasetError("run directory not found" if not path.exists()
                           else "not a directory (a logged run is a folder)", path)
    if not (path / RIG_FILE).exists():
        raise DatasetError(f"not a logged run: no {RIG_FILE} (docs/log-format.md)"
                           f"{_foreign_hint(path)}", path)
    rig = Rig.from_yaml(path / RIG_FILE)
    odometry: OdometryLog | Pose2OdometryLog
    if not any((path / f).exists() for f in (ODOMETRY_FILE, ODOMETRY_POSE2_FILE, ODOMETRY_POSES_FILE)):
        raise DatasetError(f"{ODOMETRY_FILE}: file not found (a run needs its odometry: "
                           f"{ODOMETRY_FILE} of wheel travel, or {ODOMETRY_POSE2_FILE} / "
                           f"{ODOMETRY_POSES_FILE}; docs/log-format.md)", path / ODOMETRY_FILE)
    if (path / ODOMETRY_FILE).exists() or not (
            (path / ODOMETRY_POSE2_FILE).exists() or (path / ODOMETRY_POSES_FILE).exists()):
        odometry = read_odometry(path / ODOMETRY_FILE)
        others = [f for f in (ODOMETRY_POSE2_FILE, ODOMETRY_POSES_FILE) if (path / f).exists()]
        if others:
            log.warning("%s: both %s and %s: using %s (wheel travel); is one left from an earlier "
                        "import?", path, ODOMETRY_FILE, " and ".join(others), ODOMETRY_FILE)
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
        # free-form provenance: an unreadable meta.yaml is reported and skipped, not fatal
        try:
            loaded = read_yaml(path / META_FILE)
            if loaded is not None and not isinstance(loaded, dict):
                raise DatasetError("meta.yaml must be a mapping", path / META_FILE)
            meta = loaded or {}
        except DatasetError as exc:
            log.warning("%s; its provenance (world, seed, complete) is ignored", exc)
    log.info(
        "read run %s: %d odometry, %d images, gt=%s, landmarks=%s",
        path, len(odometry), 0 if images is None else len(images), gt is not None, lms is not None,
    )  # fmt: skip
    return LoggedRun(
        path=path, rig=rig, odometry=odometry, images=images, groundtruth=gt,
        landmarks=lms, projections=proj, range_bearing=rb, meta=meta,
    )  # fmt: skip


# --------------------------------------------------------------------------- writers
def write_meta(path: str | Path, meta: dict[str, Any]) -> None:
    """Write ``meta.yaml`` (adds ``format_version``)."""
    data = {"format_version": FORMAT_VERSION, **meta}
    write_text_atomic(path, yaml.safe_dump(data, sort_keys=False))


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
