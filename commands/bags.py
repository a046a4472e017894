"""CLI commands between ROS bags and logged runs: ``import-bag`` and ``export-bag``.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from lampsam.commands._args import add_force, log, nonneg, output_dir, positive

#: Parts of a run that export-bag has no message for: (file or folder, what it holds).
_NOT_EXPORTED = (("kinect", "the forward RGB-D frames"),
                 ("rangebearing.csv", "the range-bearing measurements"))


# --------------------------------------------------------------------------- ROS bags
def _cmd_import_bag(args: argparse.Namespace) -> int:
    from lampsam.datasets.rosbag_import import ImportOptions, import_bag
    from lampsam.errors import DatasetError

    topics: dict[str, str] = {}
    for item in args.topic:
        kind, sep, name = item.partition("=")
        if not sep or not kind or not name:
            raise DatasetError(f"--topic expects KIND=NAME, got {item!r}")
        topics[kind.strip()] = name.strip()
    joints = None
    if args.wheel_joints:
        names = [j.strip() for j in args.wheel_joints.split(",")]
        if len(names) != 2 or not all(names):
            raise DatasetError(f"--wheel-joints expects LEFT,RIGHT, got {args.wheel_joints!r}")
        joints = (names[0], names[1])
    opts = ImportOptions(
        topics=topics, wheel_joints=joints, wheel_radius=args.wheel_radius,
        wheel_base=args.wheel_base, k_wheel=args.k_wheel,
        rig=Path(args.rig) if args.rig else None, base_frame=args.base_frame,
    )  # fmt: skip
    # a non-empty --out needs --force: a second import into the same folder left the first
    # one's odometry.csv beside the new odometry_pose2.csv, and slam read the stale one
    out = output_dir(args)
    report = import_bag(Path(args.bag), out, opts)
    for line in report.lines():
        print(line)
    print(f"logged run written to {args.out}")
    return 0


def add_import_bag(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("import-bag", help="ROS1 .bag / ROS2 bag -> logged run (docs/log-format.md)")
    p.add_argument("bag", help="ROS1 .bag file, or ROS2 bag directory (or its .db3 / .mcap file)")
    p.add_argument("--out", required=True, help="run directory to write")
    p.add_argument("--topic", action="append", default=[], metavar="KIND=NAME",
                   help="use topic NAME for KIND (joints, odometry, image, camera_info, tf_static, "
                        "depth, scan, groundtruth, rig); NAME 'none' skips the kind; repeatable")
    p.add_argument("--wheel-joints", default=None, metavar="L,R",
                   help="odometry from sensor_msgs/JointState: the left and right wheel joints")
    p.add_argument("--wheel-radius", type=positive, default=None, help="wheel radius, m (with --wheel-joints)")
    p.add_argument("--wheel-base", type=positive, default=None, help="distance between the wheels, m")
    p.add_argument("--k-wheel", type=nonneg, default=None, help="wheel slip constant k_r = k_l, m")
    p.add_argument("--rig", default=None, help="rig.yaml to use instead of the bag's camera_info / tf")
    p.add_argument("--base-frame", default="base_link", help="robot body frame in tf (default base_link)")
    add_force(p)
    p.set_defaults(func=_cmd_import_bag)


def _cmd_export_bag(args: argparse.Namespace) -> int:
    from lampsam.datasets.rosbag_export import export_bag

    summary = export_bag(Path(args.run), Path(args.out), ros1=args.ros1, compressed=args.compressed,
                         wheel_radius=args.wheel_radius, mcap=args.mcap,
                         force=args.force)  # fmt: skip
    for topic, n in summary.counts.items():
        print(f"{topic}: {n} messages")
    for name, what in _NOT_EXPORTED:
        if (Path(args.run) / name).exists():
            log.warning("%s: %s are not in the bag (export-bag writes odometry, ceiling images, "
                        "camera info, tf, ground truth and the rig; docs/log-format.md)",
                        Path(args.run) / name, what)
    print(f"bag written to {summary.path}")
    return 0


def add_export_bag(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("export-bag", help="logged run -> ROS1 .bag or ROS2 bag")
    p.add_argument("run", help="run directory")
    p.add_argument("--out", required=True, help="ROS1: the .bag file; ROS2: the bag directory")
    ver = p.add_mutually_exclusive_group()
    ver.add_argument("--ros1", action="store_true", help="ROS1 (Noetic) .bag")
    ver.add_argument("--ros2", action="store_true", help="ROS2 (Humble) bag (the default)")
    p.add_argument("--mcap", action="store_true", help="ROS2 storage MCAP instead of SQLite (.db3)")
    p.add_argument("--compressed", action="store_true",
                   help="images as sensor_msgs/CompressedImage (the run's PNG files)")
    p.add_argument("--wheel-radius", type=positive, default=0.05,
                   help="wheel radius for the joint angles, m (default 0.05)")
    add_force(p)
    p.set_defaults(func=_cmd_export_bag)
