"""One pass over a bag's chosen topics (:mod:`lampsam.datasets.rosbag_import`).

Odometry, ground truth, joints, ``camera_info``, ``tf_static`` and the ``/lampsam/rig``
string are collected in memory; images, depth images and laser scans are written to
the run folder as they come (``images/``, ``depth/`` + ``depth.csv``, ``scans.csv``).
Times are the messages' header stamps, s; a message whose stamp does not increase on
its topic is skipped and counted in the report.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from lampsam.datasets.logrun import ImageWriter
from lampsam.datasets.ros_messages import (
    camera_info_fields,
    depth_mm_from_image,
    grey_from_compressed,
    grey_from_image,
    stamp_seconds,
    yaw_of,
)
from lampsam.errors import DatasetError

if TYPE_CHECKING:
    from lampsam.datasets.rosbag_import import ImportOptions, ImportReport

_XYYAW = [0, 1, 5]
"""Rows/cols of x, y, yaw in a ROS 6x6 pose covariance (x, y, z, roll, pitch, yaw)."""
DEPTH_FILE = "depth.csv"
DEPTH_DIR = "depth"
SCANS_FILE = "scans.csv"


def _increasing(stream: list[Any], topic: str, t: float, report: ImportReport) -> bool:
    """True when ``t`` is after the stream's last time; else count a skip."""
    if stream and not t > stream[-1][0]:
        report.skip(topic, "time stamp does not increase")
        return False
    return True


def read_streams(reader: Any, chosen: dict[str, str], opts: ImportOptions,
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
