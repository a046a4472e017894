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
:func:`increment_covariances`: the difference of consecutive pose covariances,
rotated into the earlier body frame, its negative eigenvalues clipped to zero (the
backend adds :class:`~lampsam.datasets.odometry.Pose2OdometryModel`'s per-sample
floor). Where either pose's covariance is unknown (``-1`` in ``[0]``), or every
message's covariance on the topic is zero (a driver that fills none in), the
increment's covariance is left empty: the backend's
:class:`~lampsam.datasets.odometry.Pose2OdometryModel` default applies. The report
says which was used and how many increments were clipped.
"""

from __future__ import annotations

import logging
import math
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from lampsam.datasets.calibration import intrinsics_from_k
from lampsam.datasets.logrun import (
    GROUNDTRUTH_FILE,
    META_FILE,
    ODOMETRY_FILE,
    RIG_FILE,
    ImageWriter,
    OdometryLog,
    Trajectory,
    write_meta,
    write_odometry,
    write_tum,
)
from lampsam.datasets.odometry import (
    ODOMETRY_POSE2_FILE,
    Pose2OdometryLog,
    increments_from_poses,
    write_pose2_odometry,
)
from lampsam.datasets.rig import Rig
from lampsam.datasets.ros_messages import (
    DEPTH_ENCODINGS,
    camera_info_fields,
    depth_mm_from_image,
    grey_from_compressed,
    grey_from_image,
    rotation_of,
    stamp_seconds,
    yaw_of,
)
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
_XYYAW = [0, 1, 5]
"""Rows/cols of x, y, yaw in a ROS 6x6 pose covariance (x, y, z, roll, pitch, yaw)."""
DEPTH_FILE = "depth.csv"
DEPTH_DIR = "depth"
SCANS_FILE = "scans.csv"


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


def _tf_chain(transforms: list[Any], base: str, child: str) -> tuple[np.ndarray, np.ndarray] | None:
    """``base_R_child, base_t_child`` through static transforms, or None (no path)."""
    edges: dict[str, list[tuple[str, np.ndarray, np.ndarray, bool]]] = {}
    for tr in transforms:
        parent, kid = tr.header.frame_id.lstrip("/"), tr.child_frame_id.lstrip("/")
        r = rotation_of(tr.transform.rotation)
        v = tr.transform.translation
        t = np.array([v.x, v.y, v.z])
        edges.setdefault(parent, []).append((kid, r, t, False))
        edges.setdefault(kid, []).append((parent, r, t, True))
    stack = [(base.lstrip("/"), np.eye(3), np.zeros(3))]
    seen = {base.lstrip("/")}
    while stack:
        frame, rot, trans = stack.pop()
        if frame == child.lstrip("/"):
            return rot, trans
        for nxt, r, t, inverse in edges.get(frame, []):
            if nxt in seen:
                continue
            seen.add(nxt)
            if inverse:  # edge stored as nxt -> frame: invert it
                r, t = r.T, -r.T @ t
            stack.append((nxt, rot @ r, trans + rot @ t))
    return None


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
        streams = _read_streams(reader, chosen, opts, report, out)
    finally:
        reader.close()
    rig = _rig(streams, opts, chosen, bag, report, need_wheels=odo_kind == "joints")
    odometry = _odometry(streams, odo_kind, opts, rig, report, chosen, bag)
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


def _increasing(stream: list[Any], topic: str, t: float, report: ImportReport) -> bool:
    """True when ``t`` is after the stream's last time; else count a skip."""
    if stream and not t > stream[-1][0]:
        report.skip(topic, "time stamp does not increase")
        return False
    return True


def _read_streams(reader: Any, chosen: dict[str, str], opts: ImportOptions,
                  report: ImportReport, out: Path) -> dict[str, Any]:
    """One pass over the chosen topics; images and depth are written as they come."""
    by_topic = {topic: kind for kind, topic in chosen.items()}
    conns = [c for c in reader.connections if c.topic in by_topic]
    s: dict[str, Any] = {"joints": [], "odometry": [], "truth": [], "tf": [], "info": None,
                         "rig": None, "image_size": None, "camera_frame": None,
                         "odom_child": None}  # fmt: skip
    images = ImageWriter(out) if "image" in chosen else None
    depth_fh = scans_fh = None
    depth_last = scan_last = -math.inf
    img_last = -math.inf
    try:
        for conn, bag_ns, raw in reader.messages(connections=conns):
            kind = by_topic[conn.topic]
            msg = reader.deserialize(raw, conn.msgtype)
            header = getattr(msg, "header", None)
            t = stamp_seconds(header.stamp) if header is not None else bag_ns * 1e-9
            where = f"{conn.topic} at {t:.6f} s"
            report.used.setdefault(conn.topic, 0)
            if kind == "joints":
                names = list(msg.name)
                assert opts.wheel_joints is not None
                missing = [j for j in opts.wheel_joints if j not in names]
                if missing:
                    if not s["joints"] and report.used[conn.topic] == 0 and len(names) >= 2:
                        raise DatasetError(f"wheel joint {missing[0]!r} not in {conn.topic} "
                                           f"(joints: {', '.join(names)})")  # fmt: skip
                    report.skip(conn.topic, "wheel joints absent")
                    continue
                if not _increasing(s["joints"], conn.topic, t, report):
                    continue
                pos = [float(msg.position[names.index(j)]) for j in opts.wheel_joints]
                s["joints"].append((t, pos[0], pos[1]))
            elif kind in ("odometry", "groundtruth"):
                key = "odometry" if kind == "odometry" else "truth"
                if kind == "odometry" and s["odom_child"] is None:
                    s["odom_child"] = str(getattr(msg, "child_frame_id", "")).lstrip("/") or None
                if not _increasing(s[key], conn.topic, t, report):
                    continue
                p = msg.pose.pose
                cov = np.asarray(msg.pose.covariance, dtype=float).reshape(6, 6)[np.ix_(_XYYAW, _XYYAW)]
                if float(msg.pose.covariance[0]) == -1.0:
                    cov = np.full((3, 3), np.nan)
                s[key].append((t, np.array([p.position.x, p.position.y, yaw_of(p.orientation)]), cov))
            elif kind == "image":
                if not t > img_last:
                    report.skip(conn.topic, "time stamp does not increase")
                    continue
                img = (grey_from_compressed(msg, where) if "Compressed" in conn.msgtype
                       else grey_from_image(msg, where))  # fmt: skip
                if s["image_size"] is None:
                    s["image_size"] = img.shape
                    s["camera_frame"] = header.frame_id if header is not None else None
                elif img.shape != s["image_size"]:
                    report.skip(conn.topic, f"size {img.shape} differs from the first image")
                    continue
                assert images is not None
                images.write(t, img)
                img_last = t
            elif kind == "camera_info":
                if s["info"] is None:
                    s["info"] = camera_info_fields(msg)
            elif kind == "tf_static":
                s["tf"].extend(msg.transforms)
            elif kind == "rig":
                s["rig"] = str(msg.data)
            elif kind == "depth":
                if not t > depth_last:
                    report.skip(conn.topic, "time stamp does not increase")
                    continue
                depth_fh = depth_fh or _table(out / DEPTH_FILE, "t,file")
                (out / DEPTH_DIR).mkdir(exist_ok=True)
                rel = f"{DEPTH_DIR}/{report.used[conn.topic]:06d}.png"
                import cv2

                cv2.imwrite(str(out / rel), depth_mm_from_image(msg, where))
                depth_fh.write(f"{t:.6f},{rel}\n")
                depth_last = t
            elif kind == "scan":
                if not t > scan_last:
                    report.skip(conn.topic, "time stamp does not increase")
                    continue
                scans_fh = scans_fh or _table(
                    out / SCANS_FILE, "t,angle_min,angle_increment,range_min,range_max,ranges")
                ranges = " ".join(f"{r:.4f}" if math.isfinite(r) else "nan" for r in msg.ranges)
                scans_fh.write(f"{t:.6f},{msg.angle_min:.9f},{msg.angle_increment:.9f},"
                               f"{msg.range_min:.4f},{msg.range_max:.4f},{ranges}\n")  # fmt: skip
                scan_last = t
            report.used[conn.topic] += 1
    finally:
        if images is not None:
            images.close()
        for fh in (depth_fh, scans_fh):
            if fh is not None:
                fh.close()
    return s


def _table(path: Path, header: str) -> Any:
    """Open a CSV table for writing with its header line."""
    fh = open(path, "w", encoding="utf-8")  # noqa: SIM115 (closed by the caller)
    fh.write(header + "\n")
    return fh


def _rig(s: dict[str, Any], opts: ImportOptions, chosen: dict[str, str], bag: Path,
         report: ImportReport, need_wheels: bool) -> Rig:
    """The rig: ``opts.rig``, the bag's ``/lampsam/rig``, or camera_info + tf + options.

    ``need_wheels``: the odometry is wheel travel, so ``wheel_base`` and ``k_wheel``
    must be given; else (Pose2 odometry) the rig's wheel model is unused and absent
    values take :class:`~lampsam.datasets.rig.OdometryModel`'s defaults.
    """
    if opts.rig is not None:
        return Rig.from_yaml(opts.rig)
    if s["rig"] is not None:
        rig = Rig.from_dict(yaml.safe_load(s["rig"]), Path(f"{bag}:{chosen['rig']}"), strict=True)
        report.notes.append(f"rig from {chosen['rig']}")
        return rig
    from lampsam.datasets.rig import OdometryModel

    dflt = OdometryModel()
    odometry = {"wheel_base": dflt.wheel_base if opts.wheel_base is None else opts.wheel_base,
                "k_r": dflt.k_r if opts.k_wheel is None else opts.k_wheel,
                "k_l": dflt.k_l if opts.k_wheel is None else opts.k_wheel}  # fmt: skip
    missing = [k for k, v in (("--wheel-base", opts.wheel_base), ("--k-wheel", opts.k_wheel)) if v is None]
    if missing and need_wheels:
        raise DatasetError(f"the bag has no /lampsam/rig: give {' and '.join(missing)} (or --rig RIG.yaml)", bag)
    if s["image_size"] is None:
        from lampsam.datasets.camera import CameraModel

        cam = CameraModel()  # no images: the camera is unused
        return Rig.from_dict({"camera": cam.to_dict(), "odometry": odometry}, None, strict=True)
    if s["info"] is None:
        raise DatasetError("images but no sensor_msgs/CameraInfo topic (or give --rig RIG.yaml)", bag)
    width, height, k, d, model = s["info"]
    intr = intrinsics_from_k(width, height, k, d, model, f"{bag}:{chosen['camera_info']}")
    mount = _tf_chain(s["tf"], opts.base_frame, s["camera_frame"] or "")
    child = s.get("odom_child")
    if mount is None and child and child != opts.base_frame:
        # the odometry's body frame (base_footprint on many robots) when base_link has no tf
        mount = _tf_chain(s["tf"], child, s["camera_frame"] or "")
        if mount is not None:
            report.notes.append(
                f"camera mounting from the static tf of {child!r}, the odometry's "
                f"child_frame_id ({opts.base_frame!r} has none to the camera; --base-frame "
                "chooses)")
    if mount is None:
        frames = sorted({f for tr in s["tf"] for f in (tr.header.frame_id, tr.child_frame_id)})
        raise DatasetError(
            f"no static tf from {opts.base_frame!r}"
            + (f" or the odometry's child frame {child!r}" if child and child != opts.base_frame
               else "")
            + f" to the camera frame {s['camera_frame']!r} (frames: "
            f"{', '.join(frames) or 'none'}); give --base-frame FRAME or --rig RIG.yaml", bag)
    rot, trans = mount
    try:
        camera = intr.camera(body_t_camera=trans, body_R_camera=rot)
    except ValueError as exc:
        raise DatasetError(f"camera from the bag: {exc}", bag) from exc
    return Rig.from_dict({"camera": camera.to_dict(), "odometry": odometry}, None, strict=True)


def increment_covariances(poses: np.ndarray, pose_cov: np.ndarray) -> tuple[np.ndarray, int]:
    """Approximate increment covariances from absolute pose covariances.

    ``C_i = R_{i-1}^T (S_i - S_{i-1}) R_{i-1}`` with ``R_{i-1} = diag(Rot(theta_{i-1}), 1)``
    (the earlier body frame), symmetrised, negative eigenvalues clipped to zero. This
    treats the odometry's pose covariance as a sum of independent per-step
    contributions expressed in the odometry frame (what a dead-reckoning filter that
    adds ``R Q R^T`` per step reports) and ignores the coupling of the earlier yaw
    error into the translation (the adjoint term), so it is exact for that model when
    the heading variance is small.

    Args:
        poses: (N, 3) ``odom_T_body`` x, y (m), yaw (rad).
        pose_cov: (N, 3, 3) covariance of each pose in the odometry frame (x, y, yaw);
            NaN: unknown.

    Returns:
        (N, 3, 3) right-tangent covariances of the increments (the first: zero, or NaN
        if its pose's covariance is unknown; NaN where either pose's is unknown), and
        how many increments had a negative eigenvalue clipped.
    """
    n = len(poses)
    out = np.full((n, 3, 3), np.nan)
    if n and np.all(np.isfinite(pose_cov[0])):
        out[0] = 0.0
    clipped = 0
    for i in range(1, n):
        diff = pose_cov[i] - pose_cov[i - 1]
        if not np.all(np.isfinite(diff)):
            continue
        c, sn = math.cos(poses[i - 1, 2]), math.sin(poses[i - 1, 2])
        rot = np.array([[c, -sn, 0.0], [sn, c, 0.0], [0.0, 0.0, 1.0]])
        m = rot.T @ diff @ rot
        m = 0.5 * (m + m.T)
        w, v = np.linalg.eigh(m)
        if w.min() < 0:
            clipped += 1
            m = (v * np.maximum(w, 0.0)) @ v.T
        out[i] = m
    return out, clipped


def _odometry(s: dict[str, Any], kind: str, opts: ImportOptions, rig: Rig,
              report: ImportReport, chosen: dict[str, str], bag: Path) -> OdometryLog | Pose2OdometryLog:
    """Wheel travel per sample (first: 0) from joints, or Pose2 increments from odometry poses."""
    if kind == "joints":
        if opts.wheel_radius is None or not opts.wheel_radius > 0:
            raise DatasetError("--wheel-joints needs a positive --wheel-radius", bag)
        if len(s["joints"]) < 2:
            raise DatasetError(f"{chosen['joints']}: fewer than 2 usable messages", bag)
        a = np.array(s["joints"])
        travel = np.vstack([np.zeros((1, 2)), np.diff(a[:, 1:3], axis=0)]) * opts.wheel_radius
        return OdometryLog(t=a[:, 0], d_left=travel[:, 0], d_right=travel[:, 1])
    if len(s["odometry"]) < 2:
        raise DatasetError(f"{chosen['odometry']}: fewer than 2 usable messages", bag)
    t = np.array([x[0] for x in s["odometry"]])
    p = np.array([x[1] for x in s["odometry"]])
    pose_cov = np.array([x[2] for x in s["odometry"]])
    if not np.any(np.nan_to_num(pose_cov)):  # all zero (or unknown): no covariance given
        pose_cov[:] = np.nan
    cov, clipped = increment_covariances(p, pose_cov)
    known = int(np.all(np.isfinite(cov[1:]), axis=(1, 2)).sum())
    steps = len(t) - 1
    report.notes.append(
        f"odometry: Pose2 increments; covariance from the pose covariances (difference of "
        f"consecutive poses' x/y/yaw covariance rotated into the earlier body frame) for "
        f"{known} of {steps} increments"
        + (f", {clipped} with negative eigenvalues clipped to 0" if clipped else "")
        + (f"; {steps - known} with zero/unknown covariance use the Pose2OdometryModel default"
           if known < steps else ""))  # fmt: skip
    return Pose2OdometryLog(t=t, delta=increments_from_poses(p), cov=cov)


def topic_counts(bag: str | Path) -> Counter[str]:
    """Messages per topic of a bag (for reports and tests)."""
    from rosbags.highlevel import AnyReader

    with AnyReader(_bag_paths(Path(bag))) as reader:
        return Counter({c.topic: c.msgcount for c in reader.connections})
