"""Read a ROS1 ``.bag`` or ROS2 bag (``.db3`` / ``.mcap``) into a logged run (``rosbags``).

Topics are chosen by message type: when one topic has the type of a kind it is
used; when several do, the conventional name wins (``/odom``, ``/ground_truth``,
``/tf_static``, ...), else ``topics={"KIND": "NAME"}`` (CLI ``--topic KIND=NAME``)
must choose. Kinds:

==============  ==========================================  =================================
kind            type                                        becomes
==============  ==========================================  =================================
``joints``      ``sensor_msgs/JointState``                  ``odometry.csv`` (with
                                                            ``wheel_joints``, ``wheel_radius``)
``odometry``    ``nav_msgs/Odometry``                       ``odometry_pose2.csv`` (Pose2
                                                            increments and their covariance)
``image``       ``sensor_msgs/Image`` / ``CompressedImage``  ``images.csv`` + ``images/``
``camera_info`` ``sensor_msgs/CameraInfo``                  ``rig.yaml`` camera intrinsics
``tf_static``   ``tf2_msgs/TFMessage``                      ``rig.yaml`` camera mounting
``depth``       ``sensor_msgs/Image`` (16UC1 / 32FC1)       ``depth.csv`` + ``depth/`` (mm PNG)
``scan``        ``sensor_msgs/LaserScan``                   ``scans.csv``
``groundtruth`` ``nav_msgs/Odometry``                       ``groundtruth.tum``
``rig``         ``std_msgs/String`` (``/lampsam/rig``)      ``rig.yaml`` as written by export
==============  ==========================================  =================================

Times are the messages' header stamps (the bag's sensor clock), in seconds. A
message whose stamp does not increase on its topic is skipped and counted. The
rig comes from ``rig`` (a ``rig.yaml`` path), else the bag's ``/lampsam/rig``,
else ``camera_info`` + ``tf_static`` + ``wheel_base`` / ``k_wheel``; it is
checked as strictly as a ``rig.yaml``.

``nav_msgs/Odometry`` becomes Pose2 increments ``delta_i = pose_{i-1}^-1 pose_i``
(:func:`~lampsam.datasets.odometry.increments_from_poses`). Their covariance is
approximated from the messages' absolute pose covariances (rows/cols x, y, yaw of
the 6x6, in the header's odometry frame, as REP 105 has it) by
:func:`~lampsam.datasets.rosbag_build.increment_covariances`: the difference of
consecutive pose covariances, rotated into the earlier body frame, its negative eigenvalues clipped to zero (the
backend adds :class:`~lampsam.datasets.odometry.Pose2OdometryModel`'s per-sample
floor). Where either pose's covariance is unknown (``-1`` in ``[0]``), or every
message's covariance on the topic is zero (a driver that fills none in), the
increment's covariance is left empty: the backend's
:class:`~lampsam.datasets.odometry.Pose2OdometryModel` default applies. The report
says which was used and how many increments were clipped.

This module chooses the topics and writes the run; :mod:`~lampsam.datasets.rosbag_streams`
reads the messages, :mod:`~lampsam.datasets.rosbag_build` makes the rig and the odometry.
"""

from __future__ import annotations

import logging
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from lampsam.datasets.logrun import (
    GROUNDTRUTH_FILE,
    META_FILE,
    ODOMETRY_FILE,
    RIG_FILE,
    Trajectory,
    write_meta,
    write_odometry,
    write_tum,
)
from lampsam.datasets.odometry import (
    ODOMETRY_POSE2_FILE,
    Pose2OdometryLog,
    write_pose2_odometry,
)
from lampsam.datasets.ros_messages import DEPTH_ENCODINGS
from lampsam.datasets.rosbag_build import odometry_from_streams, rig_from_streams
from lampsam.datasets.rosbag_streams import read_streams
from lampsam.errors import DatasetError

log = logging.getLogger(__name__)

KIND_TYPES: dict[str, tuple[str, ...]] = {
    "joints": ("sensor_msgs/msg/JointState",),
    "odometry": ("nav_msgs/msg/Odometry",),
    "image": ("sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage"),
    "camera_info": ("sensor_msgs/msg/CameraInfo",),
    "tf_static": ("tf2_msgs/msg/TFMessage",),
    "depth": ("sensor_msgs/msg/Image",),
    "scan": ("sensor_msgs/msg/LaserScan",),
    "groundtruth": ("nav_msgs/msg/Odometry",),
    "rig": ("std_msgs/msg/String",),
}
"""Message types each kind reads (ROS2 spelling; ROS1 bags use the same names here)."""

_PREFERRED = {
    "joints": ("/joint_states",),
    "odometry": ("/odom", "/odometry", "/wheel_odom"),
    "image": ("/camera/image_raw", "/camera/image_raw/compressed", "/image_raw"),
    "camera_info": ("/camera/camera_info", "/camera_info"),
    "tf_static": ("/tf_static",),
    "groundtruth": ("/ground_truth", "/groundtruth"),
    "rig": ("/lampsam/rig",),
}
_TRUTH_WORDS = ("ground_truth", "groundtruth", "truth", "mocap", "vicon")


@dataclass
class ImportOptions:
    """How to read a bag (see the module docstring).

    Attributes:
        topics: kind -> topic name, overriding the automatic choice (``"none"``: skip).
        wheel_joints: ``(left, right)`` joint names: odometry from ``JointState``.
        wheel_radius: wheel radius for ``wheel_joints``, m.
        wheel_base: distance between the wheels, m (the rig's wheel odometry model).
        k_wheel: wheel slip constant ``k_r = k_l`` of the rig, m (paper 1 eq. 15).
        rig: a ``rig.yaml`` to use instead of the bag's camera_info / tf.
        base_frame: the robot body frame of the tf tree (when it has no static tf
            to the camera, the odometry messages' ``child_frame_id`` is tried, e.g.
            ``base_footprint``, and the report says so).
    """

    topics: dict[str, str] = field(default_factory=dict)
    wheel_joints: tuple[str, str] | None = None
    wheel_radius: float | None = None
    wheel_base: float | None = None
    k_wheel: float | None = None
    rig: Path | None = None
    base_frame: str = "base_link"


@dataclass
class ImportReport:
    """What was found, used and skipped.

    Attributes:
        chosen: kind -> topic.
        used: topic -> messages written.
        skipped: topic -> {reason: count}.
        ignored: topics of the bag no kind reads (topic -> type).
        notes: other remarks (e.g. lateral odometry motion dropped).
    """

    chosen: dict[str, str] = field(default_factory=dict)
    used: dict[str, int] = field(default_factory=dict)
    skipped: dict[str, dict[str, int]] = field(default_factory=dict)
    ignored: dict[str, str] = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)

    def skip(self, topic: str, reason: str) -> None:
        """Count one skipped message."""
        self.skipped.setdefault(topic, {}).setdefault(reason, 0)
        self.skipped[topic][reason] += 1

    def lines(self) -> list[str]:
        """Human-readable summary lines."""
        out = [f"{kind}: {topic} ({self.used.get(topic, 0)} messages used)"
               for kind, topic in self.chosen.items()]  # fmt: skip
        for topic, reasons in self.skipped.items():
            out += [f"skipped {n} on {topic}: {r}" for r, n in reasons.items()]
        readable = {ty for types in KIND_TYPES.values() for ty in types}
        out += [f"not used: {t} ({ty})" + ("" if ty in readable else ", a type no lampsam kind reads")
                + (": wheel angles? --wheel-joints L,R --wheel-radius R reads them as wheel travel"
                   " (export-bag writes left_wheel_joint,right_wheel_joint at radius 0.05 m)"
                   if ty.endswith("JointState") and "joints" not in self.chosen else "")
                for t, ty in self.ignored.items()]  # fmt: skip
        return out + self.notes

    def to_dict(self) -> dict[str, Any]:
        """Plain mapping for ``meta.yaml``."""
        return {"chosen": self.chosen, "used": self.used, "skipped": self.skipped,
                "ignored": self.ignored, "notes": self.notes}  # fmt: skip


def _bag_paths(bag: Path) -> list[Path]:
    """The path ``AnyReader`` takes: a ``.bag`` file or a ROS2 bag directory."""
    if bag.is_file() and bag.suffix in (".db3", ".mcap") and (bag.parent / "metadata.yaml").exists():
        return [bag.parent]
    if not bag.exists():
        raise DatasetError("bag not found", bag)
    return [bag]


def _present(topics: dict[str, str]) -> str:
    """``topic (type)`` list for error messages."""
    return ", ".join(f"{t} ({ty})" for t, ty in sorted(topics.items())) or "none"


def choose_topics(
    topics: dict[str, str], first: dict[str, Any], options: ImportOptions, bag: Path
) -> dict[str, str]:
    """Kind -> topic, by type, name and the user's choices (module docstring).

    Args:
        topics: the bag's topic -> type.
        first: topic -> its first message (tells colour images from depth).
        options: the user's ``topics`` override the automatic choice.
        bag: for error messages.

    Raises:
        DatasetError: a chosen topic is absent or of the wrong type; several candidates.
    """
    chosen: dict[str, str] = {}
    for kind, name in options.topics.items():
        if kind not in KIND_TYPES:
            raise DatasetError(f"unknown kind {kind!r} in --topic (kinds: {', '.join(KIND_TYPES)})")
        if name == "none":
            continue
        if name not in topics:
            raise DatasetError(f"--topic {kind}={name}: no such topic; present: {_present(topics)}", bag)
        if topics[name] not in KIND_TYPES[kind]:
            raise DatasetError(
                f"--topic {kind}={name}: type {topics[name]}, expected {' or '.join(KIND_TYPES[kind])}", bag)
        chosen[kind] = name

    def is_depth(topic: str) -> bool:
        msg = first.get(topic)
        enc = str(getattr(msg, "encoding", ""))
        return enc in DEPTH_ENCODINGS or "depth" in topic

    def is_truth(topic: str) -> bool:
        return any(w in topic.lower() for w in _TRUTH_WORDS)

    filters = {
        "image": lambda t: not is_depth(t), "depth": is_depth,
        "odometry": lambda t: not is_truth(t), "groundtruth": is_truth,
        "rig": lambda t: t == "/lampsam/rig",
        "tf_static": lambda t: t.rstrip("/").endswith("tf_static"),
    }  # fmt: skip
    for kind, types in KIND_TYPES.items():
        if kind in chosen or kind in options.topics:
            continue
        keep = filters.get(kind, lambda t: True)
        cands = [t for t, ty in topics.items() if ty in types and keep(t) and t not in chosen.values()]
        if len(cands) > 1:
            pref = [t for t in _PREFERRED.get(kind, ()) if t in cands]
            if not pref:
                raise DatasetError(
                    f"several topics could be {kind}: {', '.join(sorted(cands))}; "
                    f"choose one with --topic {kind}=NAME", bag)
            cands = pref[:1]
        if cands:
            chosen[kind] = cands[0]
    return chosen


def import_bag(bag: str | Path, out: str | Path, options: ImportOptions | None = None) -> ImportReport:
    """Read ``bag`` and write the logged run ``out`` (module docstring).

    Raises:
        DatasetError: no odometry topic (the message lists the bag's topics and their
            types), an unreadable bag, a missing wheel joint, an incomplete rig.
    """
    from rosbags.highlevel import AnyReader, AnyReaderError
    from rosbags.typesys import Stores, get_typestore

    opts = options or ImportOptions()
    bag, out = Path(bag), Path(out)
    report = ImportReport()
    try:
        reader = AnyReader(_bag_paths(bag), default_typestore=get_typestore(Stores.ROS2_HUMBLE))
        reader.open()
    except (AnyReaderError, FileNotFoundError) as exc:
        raise DatasetError(f"cannot read bag: {exc}", bag) from exc
    except (UnicodeDecodeError, TypeError, ValueError, KeyError) as exc:
        # rosbags reading foreign bytes: a binary file named .bag, a ROS2 metadata.yaml that
        # is not text or has a string where a number belongs (its own errors are above)
        raise DatasetError(f"cannot read bag: not a ROS1 bag or ROS2 bag folder this can read "
                           f"({type(exc).__name__}: {exc})", bag) from exc
    try:
        topics = {c.topic: c.msgtype for c in reader.connections}
        first: dict[str, Any] = {}
        for conn in reader.connections:
            if conn.msgtype == "sensor_msgs/msg/Image" and conn.topic not in first:
                for c, _, raw in reader.messages(connections=[conn]):
                    first[conn.topic] = reader.deserialize(raw, c.msgtype)
                    break
        chosen = choose_topics(topics, first, opts, bag)
        odo_kind = "joints" if opts.wheel_joints else "odometry"
        if odo_kind not in chosen:
            need = "sensor_msgs/JointState (--wheel-joints)" if opts.wheel_joints else "nav_msgs/Odometry"
            raise DatasetError(
                f"no odometry topic: need {need}; topics present: {_present(topics)}", bag)
        chosen.pop("odometry" if odo_kind == "joints" else "joints", None)
        report.chosen = chosen
        report.ignored = {t: ty for t, ty in topics.items() if t not in chosen.values()}
        out.mkdir(parents=True, exist_ok=True)
        streams = read_streams(reader, chosen, opts, report, out)
    finally:
        reader.close()
    rig = rig_from_streams(streams, opts, chosen, bag, report, need_wheels=odo_kind == "joints")
    odometry = odometry_from_streams(streams, odo_kind, opts, rig, report, chosen, bag)
    if streams["image_size"] is not None and streams["image_size"] != (rig.camera.height, rig.camera.width):
        raise DatasetError(f"images are {streams['image_size']} (h, w) but the camera is "
                           f"{rig.camera.height}x{rig.camera.width}", bag)  # fmt: skip
    rig.to_yaml(out / RIG_FILE)
    for stale in (ODOMETRY_FILE, ODOMETRY_POSE2_FILE):
        (out / stale).unlink(missing_ok=True)
    if isinstance(odometry, Pose2OdometryLog):
        write_pose2_odometry(out / ODOMETRY_POSE2_FILE, odometry)
    else:
        write_odometry(out / ODOMETRY_FILE, odometry)
    if streams["truth"]:
        t, poses, _ = zip(*streams["truth"], strict=True)
        write_tum(out / GROUNDTRUTH_FILE, Trajectory(t=np.array(t), poses=np.array(poses)))
    write_meta(out / META_FILE, {"generator": "lampsam.datasets.rosbag_import",
                                 "source": str(bag), "import": report.to_dict()})  # fmt: skip
    for line in report.lines():
        log.info("import %s: %s", bag.name, line)
    return report


def topic_counts(bag: str | Path) -> Counter[str]:
    """Messages per topic of a bag (for reports and tests)."""
    from rosbags.highlevel import AnyReader

    with AnyReader(_bag_paths(Path(bag))) as reader:
        return Counter({c.topic: c.msgcount for c in reader.connections})
