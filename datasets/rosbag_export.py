"""Write a logged run as a ROS1 ``.bag`` or a ROS2 bag (``rosbags``, no ROS install).

So that simulated runs can be replayed in ROS tools (rviz, rqt_bag, Foxglove), and
so that :mod:`lampsam.datasets.rosbag_import` is tested by a round trip.

Topics written (all stamps on the run's clock, ``t`` s -> nearest ns):

==========================  ============================  ====================================
topic                       type                          content
==========================  ============================  ====================================
``/joint_states``           ``sensor_msgs/JointState``    wheel angles ``left_wheel_joint``,
                                                          ``right_wheel_joint``: cumulative
                                                          travel / ``wheel_radius``, rad
``/odom``                   ``nav_msgs/Odometry``         dead-reckoned pose (paper 1 eq. 13)
                                                          in ``odom`` -> ``base_link``; a
                                                          Pose2 run: the composed increments
                                                          and their summed covariance
``/camera/image_raw``       ``sensor_msgs/Image``         ``mono8`` (or ``.../compressed``,
                                                          ``CompressedImage`` PNG)
``/camera/camera_info``     ``sensor_msgs/CameraInfo``    intrinsics and lens model, per image
``/tf_static``              ``tf2_msgs/TFMessage``        ``base_link`` -> camera frame
``/ground_truth``           ``nav_msgs/Odometry``         true pose in ``map`` (if the run has it)
``/lampsam/rig``            ``std_msgs/String``           the run's ``rig.yaml`` text
==========================  ============================  ====================================

A run with Pose2-increment odometry (``odometry_pose2.csv``) has no wheel joints: it
is written as ``/odom`` only, each pose ``pose_i = pose_{i-1} delta_i`` (the first
increment taken from the origin) with pose covariance (x, y, yaw rows/cols)
``S_i = S_{i-1} + R_{i-1} C_i R_{i-1}^T``, the inverse of what
:func:`lampsam.datasets.rosbag_build.increment_covariances` undoes, so the import
gives the increments and covariances back. When no increment has a covariance
every message's covariance is zero, which the import reads as unknown again (NaN);
when only some lack one, those add the default
:class:`~lampsam.datasets.odometry.Pose2OdometryModel`'s travel-proportional
covariance (without the floor, which the backend adds), so they come back as the
covariance the backend would have used for them.
"""

from __future__ import annotations

import heapq
import logging
import os
import shutil
import uuid
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from lampsam.datasets.logrun import LoggedRun, read_run
from lampsam.datasets.motion import dead_reckoning
from lampsam.datasets.odometry import Pose2OdometryLog, Pose2OdometryModel
from lampsam.datasets.ros_messages import (
    compressed_message,
    image_message,
    make_header,
    ns_from_seconds,
    quaternion_xyzw,
)
from lampsam.errors import DatasetError
from lampsam.safe_io import TMP_PREFIX, check_output_dir, check_output_file

log = logging.getLogger(__name__)

BASE_FRAME = "base_link"
ODOM_FRAME = "odom"
MAP_FRAME = "map"
CAMERA_FRAME = "ceiling_camera_optical_frame"
WHEEL_JOINTS = ("left_wheel_joint", "right_wheel_joint")
TOPICS = {
    "joints": "/joint_states",
    "odometry": "/odom",
    "image": "/camera/image_raw",
    "camera_info": "/camera/camera_info",
    "tf_static": "/tf_static",
    "groundtruth": "/ground_truth",
    "rig": "/lampsam/rig",
}
"""Topic of each kind in an exported bag (``image`` gains ``/compressed`` when compressed)."""

_TF_MSGDEF = "geometry_msgs/TransformStamped[] transforms\n"


@dataclass(frozen=True)
class ExportSummary:
    """What :func:`export_bag` wrote.

    Attributes:
        path: the bag (ROS1: the ``.bag`` file; ROS2: the bag directory).
        counts: messages per topic.
    """

    path: Path
    counts: dict[str, int]


def typestore_for(ros1: bool) -> Any:
    """The ``rosbags`` typestore (Noetic or Humble), with ``tf2_msgs/TFMessage`` registered."""
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    store = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)
    if "tf2_msgs/msg/TFMessage" not in store.types:
        store.register(get_types_from_msg(_TF_MSGDEF, "tf2_msgs/msg/TFMessage"))
    return store


def _pose_msg(store: Any, x: float, y: float, th: float) -> Any:
    """A ``geometry_msgs/Pose`` of a planar pose."""
    t = store.types
    q = quaternion_xyzw(np.array([[np.cos(th), -np.sin(th), 0], [np.sin(th), np.cos(th), 0],
                                  [0, 0, 1.0]]))  # fmt: skip
    return t["geometry_msgs/msg/Pose"](
        position=t["geometry_msgs/msg/Point"](x=float(x), y=float(y), z=0.0),
        orientation=t["geometry_msgs/msg/Quaternion"](
            x=float(q[0]), y=float(q[1]), z=float(q[2]), w=float(q[3])
        ),
    )


def _odometry_msg(store: Any, ns: int, frame: str, pose: np.ndarray, seq: int,
                  cov: np.ndarray | None = None) -> Any:
    """A ``nav_msgs/Odometry`` holding a planar pose (zero twist; covariance ``cov``
    (3, 3) x, y, yaw placed in the 6x6, else zero)."""
    t = store.types
    full = np.zeros((6, 6))
    if cov is not None:
        full[np.ix_([0, 1, 5], [0, 1, 5])] = cov
    vec = t["geometry_msgs/msg/Vector3"]
    return t["nav_msgs/msg/Odometry"](
        header=make_header(store, ns, frame, seq), child_frame_id=BASE_FRAME,
        pose=t["geometry_msgs/msg/PoseWithCovariance"](
            pose=_pose_msg(store, *pose), covariance=full.reshape(36)),
        twist=t["geometry_msgs/msg/TwistWithCovariance"](
            twist=t["geometry_msgs/msg/Twist"](linear=vec(x=0.0, y=0.0, z=0.0),
                                               angular=vec(x=0.0, y=0.0, z=0.0)),
            covariance=np.zeros(36)),
    )  # fmt: skip


def _camera_info_msg(store: Any, ns: int, run: LoggedRun, seq: int) -> Any:
    """The ``sensor_msgs/CameraInfo`` of the run's camera."""
    from lampsam.datasets.calibration import intrinsics_of

    info = intrinsics_of(run.rig.camera).to_camera_info()
    cls = store.types["sensor_msgs/msg/CameraInfo"]
    names = ("d", "k", "r", "p") if "k" in cls.__dataclass_fields__ else ("D", "K", "R", "P")
    arrays = {
        names[0]: np.asarray(info["distortion_coefficients"]["data"], dtype=float),
        names[1]: np.asarray(info["camera_matrix"]["data"], dtype=float),
        names[2]: np.asarray(info["rectification_matrix"]["data"], dtype=float),
        names[3]: np.asarray(info["projection_matrix"]["data"], dtype=float),
    }
    roi = store.types["sensor_msgs/msg/RegionOfInterest"](
        x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)
    return cls(
        header=make_header(store, ns, CAMERA_FRAME, seq), height=run.rig.camera.height,
        width=run.rig.camera.width, distortion_model=info["distortion_model"],
        binning_x=0, binning_y=0, roi=roi, **arrays,
    )  # fmt: skip


def _tf_static_msg(store: Any, ns: int, run: LoggedRun) -> Any:
    """The ``tf2_msgs/TFMessage`` with ``base_link`` -> camera (the rig's mounting)."""
    t = store.types
    cam = run.rig.camera
    q = quaternion_xyzw(cam.body_R_camera)
    tr = t["geometry_msgs/msg/TransformStamped"](
        header=make_header(store, ns, BASE_FRAME), child_frame_id=CAMERA_FRAME,
        transform=t["geometry_msgs/msg/Transform"](
            translation=t["geometry_msgs/msg/Vector3"](
                x=float(cam.body_t_camera[0]), y=float(cam.body_t_camera[1]),
                z=float(cam.body_t_camera[2])),
            rotation=t["geometry_msgs/msg/Quaternion"](
                x=float(q[0]), y=float(q[1]), z=float(q[2]), w=float(q[3]))),
    )  # fmt: skip
    return t["tf2_msgs/msg/TFMessage"](transforms=[tr])


def _messages(
    run: LoggedRun, store: Any, compressed: bool, wheel_radius: float
) -> Iterator[tuple[int, str, str, Any]]:
    """All messages ``(ns, topic, msgtype, message)`` in time order."""
    odo = run.odometry
    t0 = ns_from_seconds(float(odo.t[0]))

    def fixed() -> Iterator[tuple[int, str, str, Any]]:
        string = store.types["std_msgs/msg/String"]
        yield t0, TOPICS["rig"], "std_msgs/msg/String", string(data=yaml.safe_dump(run.rig.to_dict(), sort_keys=False))
        yield t0, TOPICS["tf_static"], "tf2_msgs/msg/TFMessage", _tf_static_msg(store, t0, run)

    def pose2() -> Iterator[tuple[int, str, str, Any]]:
        assert isinstance(odo, Pose2OdometryLog)
        poses, covs = compose_pose2(odo)
        for k, t in enumerate(odo.t):
            ns = ns_from_seconds(float(t))
            yield ns, TOPICS["odometry"], "nav_msgs/msg/Odometry", _odometry_msg(
                store, ns, ODOM_FRAME, poses[k], k, covs[k])

    def joints() -> Iterator[tuple[int, str, str, Any]]:
        if isinstance(odo, Pose2OdometryLog):
            yield from pose2()
            return
        cum_l, cum_r = np.cumsum(odo.d_left), np.cumsum(odo.d_right)
        poses = dead_reckoning(np.column_stack([odo.d_left, odo.d_right]),
                               run.rig.odometry.wheel_base, np.zeros(3))  # fmt: skip
        js = store.types["sensor_msgs/msg/JointState"]
        for k, t in enumerate(odo.t):
            ns = ns_from_seconds(float(t))
            yield ns, TOPICS["joints"], "sensor_msgs/msg/JointState", js(
                header=make_header(store, ns, BASE_FRAME, k), name=list(WHEEL_JOINTS),
                position=np.array([cum_l[k], cum_r[k]]) / wheel_radius,
                velocity=np.zeros(0), effort=np.zeros(0),
            )  # fmt: skip
            yield ns, TOPICS["odometry"], "nav_msgs/msg/Odometry", _odometry_msg(
                store, ns, ODOM_FRAME, poses[k], k)

    def images() -> Iterator[tuple[int, str, str, Any]]:
        if run.images is None:
            return
        topic = TOPICS["image"] + ("/compressed" if compressed else "")
        for k in range(len(run.images)):
            ns = ns_from_seconds(float(run.images.t[k]))
            if compressed:
                png = run.images.files[k].read_bytes()  # the run's own PNG, byte for byte
                msg = compressed_message(store, ns, CAMERA_FRAME, png, k)
                yield ns, topic, "sensor_msgs/msg/CompressedImage", msg
            else:
                img = run.images.load(k)
                yield ns, topic, "sensor_msgs/msg/Image", image_message(store, ns, CAMERA_FRAME, img, k)
            yield ns, TOPICS["camera_info"], "sensor_msgs/msg/CameraInfo", _camera_info_msg(
                store, ns, run, k)

    def truth() -> Iterator[tuple[int, str, str, Any]]:
        if run.groundtruth is None:
            return
        for k, t in enumerate(run.groundtruth.t):
            ns = ns_from_seconds(float(t))
            yield ns, TOPICS["groundtruth"], "nav_msgs/msg/Odometry", _odometry_msg(
                store, ns, MAP_FRAME, run.groundtruth.poses[k], k)

    yield from heapq.merge(fixed(), joints(), images(), truth(), key=lambda m: m[0])


def compose_pose2(odo: Pose2OdometryLog) -> tuple[np.ndarray, np.ndarray]:
    """Absolute poses (N, 3) and their covariances (N, 3, 3) from Pose2 increments.

    ``pose_i = pose_{i-1} delta_i`` from the origin; ``S_i = S_{i-1} + R C_i R^T`` with
    ``R = diag(Rot(theta_{i-1}), 1)``; a NaN covariance adds the default model's
    (none at all when every one is NaN). Module docstring.
    """
    n = len(odo)
    known = np.all(np.isfinite(odo.cov), axis=(1, 2))
    model = Pose2OdometryModel()
    floor = np.diag([model.var_floor_xy, model.var_floor_xy, model.var_floor_theta])
    poses = np.zeros((n, 3))
    covs = np.zeros((n, 3, 3))
    x = y = th = 0.0
    acc = np.zeros((3, 3))
    for i in range(n):
        dx, dy, dth = (float(v) for v in odo.delta[i])
        c, s = np.cos(th), np.sin(th)
        rot = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        if known[i]:
            acc = acc + rot @ odo.cov[i] @ rot.T
        elif known.any():
            acc = acc + rot @ (model.sample_cov(odo.delta[i], odo.cov[i]) - floor) @ rot.T
        x, y = x + c * dx - s * dy, y + s * dx + c * dy
        th = float(np.arctan2(np.sin(th + dth), np.cos(th + dth)))
        poses[i] = (x, y, th)
        covs[i] = acc
    return poses, covs


def export_bag(
    run_dir: str | Path, out: str | Path, ros1: bool = False, compressed: bool = False,
    wheel_radius: float = 0.05, mcap: bool = False, force: bool = False,
) -> ExportSummary:
    """Write the run at ``run_dir`` as a bag (topics in the module docstring).

    Args:
        run_dir: a logged run (:func:`lampsam.datasets.logrun.read_run`).
        out: ROS1: the ``.bag`` file; ROS2: the bag directory (absent or empty).
        ros1: write ROS1 (Noetic) instead of ROS2 (Humble, CDR).
        compressed: images as ``CompressedImage`` holding the run's PNG files.
        wheel_radius: radius used to turn wheel travel into joint angles, m.
        mcap: ROS2 storage MCAP instead of SQLite 3 (``.db3``).
        force: as every writer's ``--force``
            (:func:`lampsam.safe_io.check_output_file` / ``check_output_dir``): ROS1
            replaces an existing file; ROS2 writes into a non-empty directory,
            replacing the files of the same names (``metadata.yaml`` last, so the
            bag reads whole or as before until the last rename; other files stay).

    Raises:
        DatasetError: unreadable run.
        InputError: ``out`` exists without ``force`` (the other writers' message),
            or is a directory where a file belongs (ROS1) or the reverse (ROS2).
    """
    from rosbags.rosbag1 import Writer as Writer1
    from rosbags.rosbag2 import StoragePlugin
    from rosbags.rosbag2 import Writer as Writer2

    out = check_output_file(out, force) if ros1 else check_output_dir(out, force)
    run = read_run(run_dir)
    if not wheel_radius > 0:
        raise DatasetError(f"wheel radius must be positive, got {wheel_radius}")
    store = typestore_for(ros1)
    # written under a temporary name beside ``out`` and renamed when closed: a kill
    # leaves no bag at ``out`` (a ROS1 bag cut short has no index)
    tmp = out.with_name(f"{TMP_PREFIX}{uuid.uuid4().hex[:8]}-{out.name}")
    writer: Any = (
        Writer1(tmp) if ros1
        else Writer2(tmp, version=9,
                     storage_plugin=StoragePlugin.MCAP if mcap else StoragePlugin.SQLITE3)
    )  # fmt: skip
    conns: dict[str, Any] = {}
    counts: dict[str, int] = {}
    try:
        with writer:
            for ns, topic, msgtype, msg in _messages(run, store, compressed, wheel_radius):
                if topic not in conns:
                    conns[topic] = writer.add_connection(topic, msgtype, typestore=store)
                data = (store.serialize_ros1(msg, msgtype) if ros1
                        else store.serialize_cdr(msg, msgtype))  # fmt: skip
                writer.write(conns[topic], ns, data)
                counts[topic] = counts.get(topic, 0) + 1
        if not ros1:  # the storage files inside are named after the directory
            for f in tmp.iterdir():
                if f.name.startswith(tmp.name):
                    f.rename(tmp / (out.name + f.name[len(tmp.name):]))
            meta = tmp / "metadata.yaml"
            meta.write_text(meta.read_text(encoding="utf-8").replace(tmp.name, out.name),
                            encoding="utf-8")
            if out.is_dir() and any(out.iterdir()):  # --force: into the directory
                for f in sorted(tmp.iterdir(), key=lambda f: f.name == meta.name):
                    os.replace(f, out / f.name)
                tmp.rmdir()
        if tmp.exists():
            os.replace(tmp, out)  # a ROS1 file over the old one; a ROS2 bag over an empty dir
    except BaseException:
        if tmp.is_dir():
            shutil.rmtree(tmp, ignore_errors=True)
        else:
            tmp.unlink(missing_ok=True)
        raise
    log.info("exported %s -> %s: %s", run_dir, out, counts)
    return ExportSummary(path=out, counts=counts)

