"""Conversions between ROS messages (as ``rosbags`` builds them) and lampsam arrays.

Shared by :mod:`lampsam.datasets.rosbag_import` and
:mod:`lampsam.datasets.rosbag_export`. Works on ROS1 (Noetic) and ROS2 message
classes alike: the few field names that differ (``CameraInfo.K`` / ``.k``,
``Header.seq``) are handled here. Times are seconds (float) in lampsam and
``sec, nanosec`` in ROS; quaternions are ``(x, y, z, w)``.
"""

from __future__ import annotations

import math
from typing import Any

import cv2
import numpy as np

from lampsam.arrays import FloatArray, ImageU8, ImageU16
from lampsam.errors import DatasetError

GREY_ENCODINGS = ("mono8", "8UC1", "rgb8", "bgr8", "rgba8", "bgra8", "mono16")
"""``sensor_msgs/Image`` encodings read as ceiling images (colour -> grey; mono16 -> top 8 bits)."""

DEPTH_ENCODINGS = ("16UC1", "32FC1")
"""``sensor_msgs/Image`` encodings read as depth (16UC1 in mm, 32FC1 in m)."""

_CHANNELS = {"mono8": 1, "8UC1": 1, "rgb8": 3, "bgr8": 3, "rgba8": 4, "bgra8": 4}


def stamp_seconds(stamp: Any) -> float:
    """Seconds of a ``builtin_interfaces/Time`` (ROS1 ``time`` has the same fields here)."""
    return float(stamp.sec) + 1e-9 * float(stamp.nanosec)


def stamp_ns(stamp: Any) -> int:
    """Nanoseconds of a ``builtin_interfaces/Time``."""
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def ns_from_seconds(t: float) -> int:
    """Nearest nanosecond of a time in seconds (exact for the run format's 1 us stamps)."""
    return int(round(float(t) * 1e9))


def make_time(store: Any, ns: int) -> Any:
    """A ``builtin_interfaces/Time`` of the typestore at ``ns`` nanoseconds."""
    time_cls = store.types["builtin_interfaces/msg/Time"]
    return time_cls(sec=int(ns // 1_000_000_000), nanosec=int(ns % 1_000_000_000))


def make_header(store: Any, ns: int, frame_id: str, seq: int = 0) -> Any:
    """A ``std_msgs/Header`` (with ``seq`` on ROS1)."""
    header_cls = store.types["std_msgs/msg/Header"]
    fields = header_cls.__dataclass_fields__
    if "seq" in fields:
        return header_cls(seq=seq, stamp=make_time(store, ns), frame_id=frame_id)
    return header_cls(stamp=make_time(store, ns), frame_id=frame_id)


def yaw_of(q: Any) -> float:
    """Yaw (about z, ZYX) of a ``geometry_msgs/Quaternion``, rad."""
    n = math.sqrt(q.x * q.x + q.y * q.y + q.z * q.z + q.w * q.w)
    x, y, z, w = q.x / n, q.y / n, q.z / n, q.w / n
    return math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))


def rotation_of(q: Any) -> FloatArray:
    """(3, 3) rotation matrix of a ``geometry_msgs/Quaternion`` (normalised first)."""
    from scipy.spatial.transform import Rotation

    return np.asarray(Rotation.from_quat([q.x, q.y, q.z, q.w]).as_matrix())


def quaternion_xyzw(rot: FloatArray) -> FloatArray:
    """``(x, y, z, w)`` of a (3, 3) rotation matrix."""
    from scipy.spatial.transform import Rotation

    return np.asarray(Rotation.from_matrix(np.asarray(rot, dtype=float)).as_quat())


def grey_from_image(msg: Any, where: str) -> ImageU8:
    """uint8 (H, W) grey image of a ``sensor_msgs/Image`` (encodings :data:`GREY_ENCODINGS`).

    Raises:
        DatasetError: an unsupported encoding or a data size that does not match.
    """
    enc = str(msg.encoding)
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    data = np.frombuffer(bytes(msg.data), dtype=np.uint8)
    if enc == "mono16":
        dt = np.dtype(">u2" if msg.is_bigendian else "<u2")
        if len(data) < h * step:
            raise DatasetError(f"{where}: image data has {len(data)} bytes, expected {h * step}")
        img16 = np.frombuffer(data[: h * step].tobytes(), dtype=dt).reshape(h, step // 2)[:, :w]
        return (img16 >> 8).astype(np.uint8)
    if enc not in _CHANNELS:
        raise DatasetError(
            f"{where}: image encoding {enc!r} is not supported; use one of {GREY_ENCODINGS}"
        )
    c = _CHANNELS[enc]
    if len(data) < h * step or step < w * c:
        raise DatasetError(f"{where}: image data has {len(data)} bytes for {w}x{h} {enc}")
    img = data[: h * step].reshape(h, step)[:, : w * c].reshape(h, w, c)
    if c == 1:
        return np.ascontiguousarray(img[:, :, 0])
    code = {
        "rgb8": cv2.COLOR_RGB2GRAY, "bgr8": cv2.COLOR_BGR2GRAY,
        "rgba8": cv2.COLOR_RGBA2GRAY, "bgra8": cv2.COLOR_BGRA2GRAY,
    }[enc]  # fmt: skip
    return np.asarray(cv2.cvtColor(np.ascontiguousarray(img), code), dtype=np.uint8)


def grey_from_compressed(msg: Any, where: str) -> ImageU8:
    """uint8 (H, W) grey image of a ``sensor_msgs/CompressedImage`` (PNG, JPEG, ...).

    Raises:
        DatasetError: the bytes do not decode.
    """
    img = cv2.imdecode(np.frombuffer(bytes(msg.data), dtype=np.uint8), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise DatasetError(f"{where}: compressed image ({msg.format!r}) does not decode")
    if img.dtype == np.uint16:
        img = (np.asarray(img, dtype=np.uint16) >> 8).astype(np.uint8)
    if img.ndim == 3:
        code = cv2.COLOR_BGRA2GRAY if img.shape[2] == 4 else cv2.COLOR_BGR2GRAY
        img = cv2.cvtColor(img, code)
    return np.asarray(img, dtype=np.uint8)


def depth_mm_from_image(msg: Any, where: str) -> ImageU16:
    """uint16 (H, W) depth in millimetres (0 = none) of a ``16UC1`` or ``32FC1`` image.

    ``mono16`` on a depth topic (older OpenNI drivers) is read as ``16UC1`` (mm); a
    ``mono16`` topic is taken for depth only by its name (``is_depth`` in
    ``rosbag_import``), never by its encoding, as cameras use it for grey images.

    Raises:
        DatasetError: another encoding, or a data size that does not match.
    """
    enc = str(msg.encoding)
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    data = bytes(msg.data)
    if enc == "mono16":
        enc = "16UC1"
    if enc not in DEPTH_ENCODINGS or len(data) < h * step:
        raise DatasetError(f"{where}: depth encoding {enc!r} ({len(data)} bytes) not supported")
    order = ">" if msg.is_bigendian else "<"
    if enc == "16UC1":
        a = np.frombuffer(data[: h * step], dtype=order + "u2").reshape(h, step // 2)[:, :w]
        return np.ascontiguousarray(a.astype(np.uint16))
    f = np.frombuffer(data[: h * step], dtype=order + "f4").reshape(h, step // 4)[:, :w]
    mm = np.where(np.isfinite(f) & (f > 0), np.round(f * 1000.0), 0.0)
    return np.clip(mm, 0, 65535).astype(np.uint16)


def image_message(store: Any, ns: int, frame_id: str, img: ImageU8, seq: int = 0) -> Any:
    """A ``sensor_msgs/Image`` (``mono8``) of a uint8 (H, W) image."""
    cls = store.types["sensor_msgs/msg/Image"]
    h, w = img.shape
    return cls(
        header=make_header(store, ns, frame_id, seq), height=h, width=w, encoding="mono8",
        is_bigendian=0, step=w, data=np.ascontiguousarray(img).reshape(-1).copy(),
    )  # fmt: skip


def compressed_message(store: Any, ns: int, frame_id: str, png: bytes, seq: int = 0) -> Any:
    """A ``sensor_msgs/CompressedImage`` holding PNG bytes."""
    cls = store.types["sensor_msgs/msg/CompressedImage"]
    return cls(
        header=make_header(store, ns, frame_id, seq), format="mono8; png compressed",
        data=np.frombuffer(png, dtype=np.uint8).copy(),
    )  # fmt: skip


def camera_info_fields(msg: Any) -> tuple[int, int, FloatArray, FloatArray, str]:
    """``(width, height, K (9,), D, distortion_model)`` of a ``CameraInfo`` (ROS1 or ROS2)."""
    k = getattr(msg, "k", None)
    if k is None:
        k = msg.K
    d = getattr(msg, "d", None)
    if d is None:
        d = msg.D
    return (
        int(msg.width), int(msg.height), np.asarray(k, dtype=float),
        np.asarray(d, dtype=float), str(msg.distortion_model),
    )  # fmt: skip
