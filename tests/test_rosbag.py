"""ROS bags: export -> import round trip (ROS1, ROS2 SQLite, ROS2 MCAP) and import of a bag
written here with rosbags' own writer and the standard message definitions."""

from __future__ import annotations

import math
import re
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from lampsam.backend.slam import run_slam
from lampsam.cli import main
from lampsam.datasets.logrun import LoggedRun, read_run, write_run
from lampsam.datasets.odometry import (
    Pose2OdometryLog,
    Pose2OdometryModel,
    increments_from_poses,
    pose2_odometry_from_poses,
)
from lampsam.datasets.rosbag_export import export_bag, typestore_for
from lampsam.datasets.rosbag_import import ImportOptions, import_bag
from lampsam.errors import DatasetError, InputError
from tests.conftest import SimRun

JOINTS = ("left_wheel_joint", "right_wheel_joint")


@pytest.fixture(scope="module")
def lab1(sim_run: SimRun) -> Path:
    """One second of the simulated lab (31 odometry samples, 16 images)."""
    return sim_run(seed=4, duration=1.0)


def _position_rms(run_dir: Path) -> tuple[np.ndarray, float]:
    res = run_slam(run_dir, "isam2", frames="images")
    gt = read_run(run_dir).groundtruth
    assert gt is not None
    err = res.poses[:, :2] - gt.interpolate(res.times)[:, :2]
    return res.poses, float(np.sqrt(np.mean(np.sum(err**2, axis=1))))


def _same_run(a: LoggedRun, b: LoggedRun) -> None:
    """Odometry to the format's precision, images bit for bit, truth, rig."""
    np.testing.assert_array_equal(b.odometry.t, a.odometry.t)
    np.testing.assert_allclose(b.odometry.d_left, a.odometry.d_left, rtol=0, atol=1e-12)
    np.testing.assert_allclose(b.odometry.d_right, a.odometry.d_right, rtol=0, atol=1e-12)
    assert a.images is not None and b.images is not None and len(b.images) == len(a.images)
    np.testing.assert_array_equal(b.images.t, a.images.t)
    for i in range(len(a.images)):
        np.testing.assert_array_equal(b.images.load(i), a.images.load(i))
    assert a.groundtruth is not None and b.groundtruth is not None
    np.testing.assert_allclose(b.groundtruth.poses, a.groundtruth.poses, atol=1e-9)
    assert b.rig.to_dict() == a.rig.to_dict()


@pytest.mark.parametrize(
    ("ros1", "compressed", "mcap", "name"),
    [(True, False, False, "run.bag"), (False, False, False, "bag2"), (False, True, True, "bag2m")],
)
def test_round_trip_is_exact(
    lab1: Path, tmp_path: Path, ros1: bool, compressed: bool, mcap: bool, name: str
) -> None:
    """run -> bag -> run: same files' contents and the same SLAM result."""
    bag = tmp_path / name
    summary = export_bag(lab1, bag, ros1=ros1, compressed=compressed, mcap=mcap)
    assert summary.counts["/joint_states"] == 31
    back = tmp_path / "back"
    report = import_bag(bag, back, ImportOptions(wheel_joints=JOINTS, wheel_radius=0.05))
    assert report.chosen["joints"] == "/joint_states"
    _same_run(read_run(lab1), read_run(back))
    if not ros1 and not compressed:  # one SLAM comparison is enough (the inputs are equal)
        poses_a, rms_a = _position_rms(lab1)
        poses_b, rms_b = _position_rms(back)
        np.testing.assert_array_equal(poses_b, poses_a)
        assert rms_b == rms_a < 0.02


def _wheel_step_cov(dl: float, dr: float, b: float, k: float) -> np.ndarray:
    """(3, 3) covariance of one midpoint-rule increment from eq. 15's wheel noise."""
    ds, a = 0.5 * (dl + dr), (dr - dl) / (2 * b)
    c, s = math.cos(a), math.sin(a)
    jac = np.array([[0.5 * c + ds * s / (2 * b), 0.5 * c - ds * s / (2 * b)],
                    [0.5 * s - ds * c / (2 * b), 0.5 * s + ds * c / (2 * b)],
                    [-1 / b, 1 / b]])
    return jac @ np.diag([k * abs(dl), k * abs(dr)]) @ jac.T


def _independent_bag(run: LoggedRun, path: Path, ros1: bool,
                     unknown_cov: tuple[int, ...] = ()) -> tuple[np.ndarray, np.ndarray]:
    """A bag made with rosbags' writer and stock message classes, not by export_bag.

    Odometry as nav_msgs/Odometry (poses integrated here with the midpoint rule; the
    pose covariance a dead-reckoning filter reports, ``S_i = S_{i-1} + R Q_i R^T`` with
    ``Q_i`` eq. 15's wheel noise through the midpoint step; messages ``unknown_cov``
    have ``-1`` in covariance[0]),
    CompressedImage PNG, CameraInfo (plumb_bob), a static tf with the camera one
    frame below an intermediate ``camera_link``, and a LaserScan.

    Returns:
        (N, 3) the odometry poses and (N, 3, 3) the step covariances ``Q_i`` (Q_0 = 0).
    """
    from rosbags.rosbag1 import Writer as Writer1
    from rosbags.rosbag2 import Writer as Writer2

    store = typestore_for(ros1)
    T = store.types
    ser = store.serialize_ros1 if ros1 else store.serialize_cdr

    def header(ns: int, frame: str) -> Any:
        stamp = T["builtin_interfaces/msg/Time"](sec=ns // 10**9, nanosec=ns % 10**9)
        if ros1:
            return T["std_msgs/msg/Header"](seq=0, stamp=stamp, frame_id=frame)
        return T["std_msgs/msg/Header"](stamp=stamp, frame_id=frame)

    def quat(yaw: float) -> Any:
        return T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=math.sin(yaw / 2), w=math.cos(yaw / 2))

    def vec(x: float, y: float, z: float) -> Any:
        return T["geometry_msgs/msg/Vector3"](x=x, y=y, z=z)

    def transform(parent: str, child: str, t: list[float], q: Any) -> Any:
        return T["geometry_msgs/msg/TransformStamped"](
            header=header(0, parent), child_frame_id=child,
            transform=T["geometry_msgs/msg/Transform"](translation=vec(*t), rotation=q))

    cam = run.rig.camera
    offset = 1_700_000_000 * 10**9  # a wall-clock epoch, as a robot's bag has
    b = run.rig.odometry.wheel_base
    x = y = th = 0.0
    acc = np.zeros((3, 3))
    poses, qs = [], []
    msgs: list[tuple[int, str, str, Any]] = []
    for k, t in enumerate(run.odometry.t):
        dl, dr = run.odometry.d_left[k], run.odometry.d_right[k]
        ds, dth = 0.5 * (dl + dr), (dr - dl) / b
        q = _wheel_step_cov(dl, dr, b, run.rig.odometry.k_r)
        rot = np.array([[math.cos(th), -math.sin(th), 0], [math.sin(th), math.cos(th), 0], [0, 0, 1]])
        acc = acc + rot @ q @ rot.T
        qs.append(q)
        cov6 = np.zeros((6, 6))
        cov6[np.ix_([0, 1, 5], [0, 1, 5])] = acc
        cov6[2, 2] = cov6[3, 3] = cov6[4, 4] = 1e6  # z, roll, pitch: not estimated
        if k in unknown_cov:
            cov6[0, 0] = -1.0
        x += ds * math.cos(th + dth / 2)
        y += ds * math.sin(th + dth / 2)
        th += dth
        poses.append((x, y, th))
        pose = T["geometry_msgs/msg/Pose"](position=T["geometry_msgs/msg/Point"](x=x, y=y, z=0.0),
                                           orientation=quat(th))
        twist = T["geometry_msgs/msg/Twist"](linear=vec(0, 0, 0), angular=vec(0, 0, 0))
        ns = offset + round(t * 1e9)
        msgs.append((ns, "/wheel/odometry", "nav_msgs/msg/Odometry", T["nav_msgs/msg/Odometry"](
            header=header(ns, "odom"), child_frame_id="base_link",
            pose=T["geometry_msgs/msg/PoseWithCovariance"](pose=pose, covariance=cov6.ravel()),
            twist=T["geometry_msgs/msg/TwistWithCovariance"](twist=twist, covariance=np.zeros(36)))))
        scan = T["sensor_msgs/msg/LaserScan"](
            header=header(ns, "laser"), angle_min=-1.5, angle_max=1.5, angle_increment=0.5,
            time_increment=0.0, scan_time=0.1, range_min=0.1, range_max=10.0,
            ranges=np.array([1.0, 2.0, 3.0, np.inf, 5.0, 6.0, 7.0], dtype=np.float32),
            intensities=np.zeros(0, dtype=np.float32))
        msgs.append((ns, "/scan", "sensor_msgs/msg/LaserScan", scan))
    assert run.images is not None
    kk = [cam.fx, 0.0, cam.cx, 0.0, cam.fy, cam.cy, 0.0, 0.0, 1.0]
    info_fields = ("D", "K", "R", "P") if ros1 else ("d", "k", "r", "p")
    for k, t in enumerate(run.images.t):
        ns = offset + round(t * 1e9)
        msgs.append((ns, "/ceiling/image/compressed", "sensor_msgs/msg/CompressedImage",
                     T["sensor_msgs/msg/CompressedImage"](
                         header=header(ns, "ceiling_optical"), format="png",
                         data=np.frombuffer(run.images.files[k].read_bytes(), dtype=np.uint8))))
        depth = (1000 + 10 * k + np.arange(12, dtype=np.uint16).reshape(3, 4)).astype("<u2")
        msgs.append((ns, "/camera/depth/image_raw", "sensor_msgs/msg/Image", T["sensor_msgs/msg/Image"](
            header=header(ns, "depth_optical"), height=3, width=4, encoding="16UC1", is_bigendian=0,
            step=8, data=np.frombuffer(depth.tobytes(), dtype=np.uint8))))
        arrays = dict(zip(info_fields, (np.zeros(5), np.array(kk), np.eye(3).ravel(),
                                        np.array(kk[:3] + [0.0] + kk[3:6] + [0.0] + kk[6:] + [0.0])),
                          strict=True))
        msgs.append((ns, "/ceiling/camera_info", "sensor_msgs/msg/CameraInfo",
                     T["sensor_msgs/msg/CameraInfo"](
                         header=header(ns, "ceiling_optical"), height=cam.height, width=cam.width,
                         distortion_model="plumb_bob", binning_x=0, binning_y=0,
                         roi=T["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0,
                                                                    width=0, do_rectify=False),
                         **arrays)))
    # base_link -> camera_link (translation) -> ceiling_optical (rotation)
    from scipy.spatial.transform import Rotation

    qr = Rotation.from_matrix(cam.body_R_camera).as_quat()
    tf = T["tf2_msgs/msg/TFMessage"](transforms=[
        transform("base_link", "camera_link", list(cam.body_t_camera), quat(0.0)),
        transform("camera_link", "ceiling_optical", [0.0, 0.0, 0.0],
                  T["geometry_msgs/msg/Quaternion"](x=qr[0], y=qr[1], z=qr[2], w=qr[3])),
    ])
    msgs.append((offset, "/tf_static", "tf2_msgs/msg/TFMessage", tf))
    msgs.sort(key=lambda m: m[0])
    writer: Any = Writer1(path) if ros1 else Writer2(path, version=9)
    conns: dict[str, Any] = {}
    with writer:
        for ns, topic, typ, msg in msgs:
            if topic not in conns:
                conns[topic] = writer.add_connection(topic, typ, typestore=store)
            writer.write(conns[topic], ns, ser(msg, typ))
    return np.array(poses), np.array(qs)


@pytest.mark.parametrize("ros1", [True, False])
def test_import_of_an_independent_bag(lab1: Path, tmp_path: Path, ros1: bool,
                                      capsys: pytest.CaptureFixture[str]) -> None:
    """Odometry poses with covariance, compressed images, camera_info, a two-step static
    tf and a laser: the imported run has Pose2 increments of the odometry poses (1e-9)
    with the step covariances the poses' covariances were summed from (1e-12), the
    original's images and camera, and the same SLAM accuracy (``lampsam slam``, iSAM2)."""
    run = read_run(lab1)
    bag = tmp_path / ("indep.bag" if ros1 else "indep")
    poses, qs = _independent_bag(run, bag, ros1)
    out = tmp_path / "imported"
    report = import_bag(bag, out)  # Pose2 odometry: no wheel constants needed
    assert report.chosen["odometry"] == "/wheel/odometry"
    assert report.chosen["image"] == "/ceiling/image/compressed"
    assert report.chosen["scan"] == "/scan"
    assert report.chosen["depth"] == "/camera/depth/image_raw"
    assert any("covariance from the pose covariances" in n and f"for {len(poses) - 1} of "
               f"{len(poses) - 1} increments" in n for n in report.notes)
    assert (out / "odometry_pose2.csv").exists() and not (out / "odometry.csv").exists()
    import cv2

    depth_rows = (out / "depth.csv").read_text().splitlines()
    assert len(depth_rows) == 1 + len(run.images.t)  # type: ignore[union-attr]
    d5 = cv2.imread(str(out / depth_rows[6].split(",")[1]), cv2.IMREAD_UNCHANGED)
    np.testing.assert_array_equal(d5, 1050 + np.arange(12).reshape(3, 4))
    got = read_run(out)
    assert isinstance(got.odometry, Pose2OdometryLog)
    np.testing.assert_allclose(got.odometry.t, run.odometry.t + 1.7e9, rtol=0, atol=2e-6)
    np.testing.assert_allclose(got.odometry.delta, increments_from_poses(poses), rtol=0, atol=1e-9)
    np.testing.assert_allclose(got.odometry.cov, qs, rtol=0, atol=1e-12)
    assert got.images is not None and run.images is not None
    for i in range(len(run.images)):
        np.testing.assert_array_equal(got.images.load(i), run.images.load(i))
    assert got.rig.camera.fx == run.rig.camera.fx and got.rig.camera.cy == run.rig.camera.cy
    np.testing.assert_allclose(got.rig.camera.body_t_camera, run.rig.camera.body_t_camera, atol=1e-12)
    np.testing.assert_allclose(got.rig.camera.body_R_camera, run.rig.camera.body_R_camera, atol=1e-12)
    scans = (out / "scans.csv").read_text().splitlines()
    assert len(scans) == 1 + len(run.odometry) and scans[1].endswith("3.0000 nan 5.0000 6.0000 7.0000")
    if ros1:  # one SLAM comparison is enough (both bags hold the same messages)
        return
    # same accuracy: SLAM over the imported run (with the original's truth) vs the original
    import shutil

    shutil.copy(lab1 / "groundtruth.tum", out / "groundtruth.tum")
    text = (out / "groundtruth.tum").read_text().splitlines()
    shifted = [text[0]] + [f"{float(ln.split()[0]) + 1.7e9:.6f} " + ln.split(" ", 1)[1] for ln in text[1:]]
    (out / "groundtruth.tum").write_text("\n".join(shifted) + "\n")
    _, rms_orig = _position_rms(lab1)
    capsys.readouterr()
    assert main(["slam", str(out), "--out", str(tmp_path / "slam"), "--frames", "images"]) == 0
    printed = re.search(r"isam2: .*position error RMS ([0-9.]+) m", capsys.readouterr().out)
    assert printed is not None
    assert float(printed.group(1)) == pytest.approx(rms_orig, abs=1.5e-3)


def test_pose2_covariance_unknown_or_absent(lab1: Path, tmp_path: Path) -> None:
    """``-1`` in covariance[0] leaves the increments on either side of that message
    without a covariance (NaN: the model default), the others are the step covariances;
    a topic whose covariances are all zero gives no covariance at all."""
    run = read_run(lab1)
    poses, qs = _independent_bag(run, tmp_path / "b1", ros1=False, unknown_cov=(5,))
    report = import_bag(tmp_path / "b1", tmp_path / "r1")
    cov = read_run(tmp_path / "r1").odometry.cov  # type: ignore[union-attr]
    nan = ~np.all(np.isfinite(cov), axis=(1, 2))
    assert np.flatnonzero(nan).tolist() == [5, 6]
    np.testing.assert_allclose(cov[~nan], qs[~nan], rtol=0, atol=1e-12)
    n = len(poses) - 1
    assert any(f"for {n - 2} of {n} increments" in s and "Pose2OdometryModel default" in s
               for s in report.notes)
    # export_bag of a wheel run writes zero covariances: the import reads them as unknown
    export_bag(lab1, tmp_path / "b2")
    import_bag(tmp_path / "b2", tmp_path / "r2", ImportOptions(topics={"joints": "none"}))
    assert np.all(np.isnan(read_run(tmp_path / "r2").odometry.cov))  # type: ignore[union-attr]


@pytest.mark.parametrize("ros1", [True, False])
def test_pose2_run_round_trip(lab1: Path, tmp_path: Path, ros1: bool) -> None:
    """A Pose2 run (increments with covariances, one without) -> bag -> run: the same
    increments and covariances to float precision (the one without: the model's default
    noise without its floor, what the backend would have used)."""
    run = read_run(lab1)
    rng = np.random.default_rng(3)
    poses, qs = _independent_bag(run, tmp_path / "src", ros1=False)
    cov = qs + np.einsum("nij,nkj->nik", a := rng.normal(0, 1e-3, (len(qs), 3, 3)), a)
    cov[7] = np.nan
    odo = pose2_odometry_from_poses(run.odometry.t, poses, cov)
    write_run(tmp_path / "p2", rig=run.rig, odometry=odo, groundtruth=run.groundtruth)
    bag = tmp_path / ("p2.bag" if ros1 else "p2bag")
    summary = export_bag(tmp_path / "p2", bag, ros1=ros1)
    assert "/joint_states" not in summary.counts and summary.counts["/odom"] == len(odo)
    import_bag(bag, tmp_path / "back")
    back = read_run(tmp_path / "back").odometry
    assert isinstance(back, Pose2OdometryLog)
    np.testing.assert_array_equal(back.t, odo.t)
    np.testing.assert_allclose(back.delta, odo.delta, rtol=0, atol=1e-12)
    want = cov.copy()
    want[0] = 0.0  # the first increment: the run starts at the first pose
    model = Pose2OdometryModel()
    want[7] = model.sample_cov(odo.delta[7], cov[7]) - np.diag(
        [model.var_floor_xy, model.var_floor_xy, model.var_floor_theta])
    np.testing.assert_allclose(back.cov, want, rtol=0, atol=1e-15)


def test_errors_list_topics(lab1: Path, tmp_path: Path) -> None:
    bag = tmp_path / "b"
    export_bag(lab1, bag)
    with pytest.raises(DatasetError, match=r"no odometry topic.*JointState.*/camera/image_raw \(sensor_msgs/msg/Image\)"):
        import_bag(bag, tmp_path / "o1", ImportOptions(topics={"joints": "none"},
                                                       wheel_joints=JOINTS, wheel_radius=0.05))
    with pytest.raises(DatasetError, match=r"wheel joint 'left' not in /joint_states"):
        import_bag(bag, tmp_path / "o2", ImportOptions(wheel_joints=("left", "right"), wheel_radius=0.05))
    with pytest.raises(DatasetError, match=r"--topic image=/odom: type nav_msgs/msg/Odometry"):
        import_bag(bag, tmp_path / "o3", ImportOptions(topics={"image": "/odom"}))
    with pytest.raises(DatasetError, match=r"no such topic; present: .*/tf_static \(tf2_msgs/msg/TFMessage\)"):
        import_bag(bag, tmp_path / "o4", ImportOptions(topics={"image": "/nope"}))
    with pytest.raises(DatasetError, match=r"give --wheel-base and --k-wheel"):
        import_bag(bag, tmp_path / "o5", ImportOptions(topics={"rig": "none"}, wheel_joints=JOINTS,
                                                       wheel_radius=0.05))
    with pytest.raises(DatasetError, match="bag not found"):
        import_bag(tmp_path / "absent.bag", tmp_path / "o6")
    with pytest.raises(InputError, match=r"--out: the output directory is not empty \(use --force"):
        export_bag(lab1, bag)


def test_cli_export_then_import(lab1: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    bag = tmp_path / "cli.bag"
    assert main(["export-bag", str(lab1), "--out", str(bag), "--ros1"]) == 0
    assert "/camera/image_raw: 16 messages" in capsys.readouterr().out
    out = tmp_path / "cli_run"
    assert main(["import-bag", str(bag), "--out", str(out), "--wheel-joints", ",".join(JOINTS),
                 "--wheel-radius", "0.05"]) == 0
    printed = capsys.readouterr().out
    assert "joints: /joint_states (31 messages used)" in printed
    assert main(["import-bag", str(bag), "--out", str(out), "--topic", "image"]) == 2
    assert "--topic expects KIND=NAME" in capsys.readouterr().err


@pytest.mark.parametrize("ros1", [True, False])
def test_cli_export_over_a_bag_needs_force(lab1: Path, tmp_path: Path, ros1: bool,
                                           capsys: pytest.CaptureFixture[str]) -> None:
    """``export-bag`` over an existing bag: exit 2 with the other writers' message and the
    old bag untouched; with ``--force`` the new bag replaces it (ROS1: the file; ROS2: the
    files of the same names, a stranger file kept) and reads back as the run."""
    bag = tmp_path / ("b.bag" if ros1 else "b")
    argv = ["export-bag", str(lab1), "--out", str(bag)] + (["--ros1"] if ros1 else [])
    assert main(argv) == 0
    if ros1:
        bag.write_bytes(b"old bag")
    else:
        (bag / "metadata.yaml").write_text("old: true\n")
        (bag / "notes.txt").write_text("mine\n")
    capsys.readouterr()
    assert main(argv) == 2
    err = capsys.readouterr().err
    what = "the output file exists (use --force to overwrite it)" if ros1 else (
        "the output directory is not empty (use --force to overwrite its files)")
    assert f"{bag}: --out: {what}" in err, err
    assert (bag.read_bytes() == b"old bag" if ros1
            else (bag / "metadata.yaml").read_text() == "old: true\n")
    assert main([*argv, "--force"]) == 0
    assert f"bag written to {bag}" in capsys.readouterr().out
    if not ros1:
        assert (bag / "notes.txt").read_text() == "mine\n"
        assert not [f for f in tmp_path.iterdir() if f.name.startswith(".")]  # no temporary left
    import_bag(bag, tmp_path / "back", ImportOptions(wheel_joints=JOINTS, wheel_radius=0.05))
    _same_run(read_run(lab1), read_run(tmp_path / "back"))


def test_slam_writes_its_graph_as_g2o(lab1: Path, tmp_path: Path) -> None:
    """``lampsam slam --g2o``: GTSAM reads the poses (start + one per keyframe), the
    landmarks and the odometry factors; the last pose is the result's last keyframe."""
    import gtsam

    g2o = tmp_path / "graph.g2o"
    assert main(["slam", str(lab1), "--out", str(tmp_path / "s"), "--g2o", str(g2o)]) == 0
    graph, values = gtsam.readG2o(str(g2o), False)
    res = run_slam(lab1, "isam2", frames="images")
    kf = np.flatnonzero(res.keyframes)
    n_pose = len(kf) + 1  # X(0) is the start pose
    n_xy = sum(ln.startswith("VERTEX_XY ") for ln in g2o.read_text().splitlines())
    assert graph.size() == n_pose - 1
    assert values.size() == n_pose + n_xy and n_xy >= len(res.landmarks)
    np.testing.assert_allclose([values.atPose2(n_pose - 1).x(), values.atPose2(n_pose - 1).y()],
                               res.poses[kf[-1], :2], atol=1e-8)
