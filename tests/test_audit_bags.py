"""A robot's own ROS bag (audit): a TurtleBot-style ``base_footprint`` body frame, and
``mono16`` depth. Each bag is written here with ``rosbags``' own writer."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest

from lampsam.datasets.rosbag_export import typestore_for
from lampsam.datasets.rosbag_import import import_bag
from lampsam.errors import DatasetError

W, H = 32, 24


def _bag(path: Path, body: str, tf_parent: str, depth_encoding: str | None = None) -> None:
    """ROS1 bag: 6 odometry messages (child ``body``), 3 PNG images with camera_info, a
    static tf ``tf_parent -> cam_optical`` (camera looking up), optional depth."""
    from rosbags.rosbag1 import Writer

    store = typestore_for(True)
    T = store.types

    def header(ns: int, frame: str) -> Any:
        stamp = T["builtin_interfaces/msg/Time"](sec=ns // 10**9, nanosec=ns % 10**9)
        return T["std_msgs/msg/Header"](seq=0, stamp=stamp, frame_id=frame)

    def quat(x: float, y: float, z: float, w: float) -> Any:
        return T["geometry_msgs/msg/Quaternion"](x=x, y=y, z=z, w=w)

    zero = T["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0)
    msgs: list[tuple[int, str, str, Any]] = []
    t0 = 1_700_000_000 * 10**9
    for k in range(6):
        ns = t0 + k * 100_000_000
        pose = T["geometry_msgs/msg/Pose"](position=T["geometry_msgs/msg/Point"](x=0.05 * k, y=0.0, z=0.0),
                                           orientation=quat(0.0, 0.0, 0.0, 1.0))
        msgs.append((ns, "/odom", "nav_msgs/msg/Odometry", T["nav_msgs/msg/Odometry"](
            header=header(ns, "odom"), child_frame_id=body,
            pose=T["geometry_msgs/msg/PoseWithCovariance"](pose=pose, covariance=np.zeros(36)),
            twist=T["geometry_msgs/msg/TwistWithCovariance"](
                twist=T["geometry_msgs/msg/Twist"](linear=zero, angular=zero), covariance=np.zeros(36)))))
    rng = np.random.default_rng(0)
    kk = [40.0, 0.0, W / 2, 0.0, 40.0, H / 2, 0.0, 0.0, 1.0]
    for k in range(3):
        ns = t0 + k * 200_000_000 + 50_000_000
        png = cv2.imencode(".png", rng.integers(0, 255, (H, W), dtype=np.uint8))[1].ravel()
        msgs.append((ns, "/cam/image/compressed", "sensor_msgs/msg/CompressedImage",
                     T["sensor_msgs/msg/CompressedImage"](header=header(ns, "cam_optical"),
                                                          format="png", data=png)))
        msgs.append((ns, "/cam/camera_info", "sensor_msgs/msg/CameraInfo", T["sensor_msgs/msg/CameraInfo"](
            header=header(ns, "cam_optical"), height=H, width=W, distortion_model="plumb_bob",
            D=np.zeros(5), K=np.array(kk), R=np.eye(3).ravel(),
            P=np.array(kk[:3] + [0.0] + kk[3:6] + [0.0] + kk[6:] + [0.0]), binning_x=0, binning_y=0,
            roi=T["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0,
                                                      do_rectify=False))))
        if depth_encoding is not None:
            d = np.full((3, 4), 1500 + k, dtype="<u2")
            msgs.append((ns, "/camera/depth/image", "sensor_msgs/msg/Image", T["sensor_msgs/msg/Image"](
                header=header(ns, "depth_optical"), height=3, width=4, encoding=depth_encoding,
                is_bigendian=0, step=8, data=np.frombuffer(d.tobytes(), dtype=np.uint8))))
    # camera z up, x forward-ish: a rotation of pi about the body x axis
    up = quat(1.0, 0.0, 0.0, 0.0)
    tf = T["tf2_msgs/msg/TFMessage"](transforms=[T["geometry_msgs/msg/TransformStamped"](
        header=header(0, tf_parent), child_frame_id="cam_optical",
        transform=T["geometry_msgs/msg/Transform"](
            translation=T["geometry_msgs/msg/Vector3"](x=0.1, y=0.0, z=0.3), rotation=up))])
    msgs.append((t0, "/tf_static", "tf2_msgs/msg/TFMessage", tf))
    msgs.sort(key=lambda m: m[0])
    conns: dict[str, Any] = {}
    with Writer(path) as writer:
        for ns, topic, typ, msg in msgs:
            if topic not in conns:
                conns[topic] = writer.add_connection(topic, typ, typestore=store)
            writer.write(conns[topic], ns, store.serialize_ros1(msg, typ))


def test_camera_mounting_from_the_odometry_body_frame(tmp_path: Path) -> None:
    """No tf from base_link: the odometry's child frame (base_footprint) is used, and said."""
    _bag(tmp_path / "tb.bag", "base_footprint", "base_footprint")
    report = import_bag(tmp_path / "tb.bag", tmp_path / "run")
    assert any("'base_footprint', the odometry's child_frame_id" in n for n in report.notes)
    rig = (tmp_path / "run" / "rig.yaml").read_text()
    assert "0.3" in rig  # the mounting's height came from the tf
    # a tf tree with neither frame still names them, and the way out
    _bag(tmp_path / "none.bag", "base_footprint", "chassis")
    with pytest.raises(DatasetError, match=r"no static tf from 'base_link' or the odometry's "
                                           r"child frame 'base_footprint'.*--base-frame"):
        import_bag(tmp_path / "none.bag", tmp_path / "run2")


def test_mono16_depth_is_read_as_millimetres(tmp_path: Path) -> None:
    _bag(tmp_path / "d.bag", "base_link", "base_link", depth_encoding="mono16")
    import_bag(tmp_path / "d.bag", tmp_path / "run")
    files = sorted((tmp_path / "run" / "depth").glob("*.png"))
    assert len(files) == 3
    d = cv2.imread(str(files[2]), cv2.IMREAD_UNCHANGED)
    assert d.dtype == np.uint16 and np.all(d == 1502)
    assert math.isclose(float(d.mean()), 1502.0)
