"""What a bag's streams become (:mod:`lampsam.datasets.rosbag_import`): the rig and the odometry.

The rig comes from ``--rig``, else the bag's ``/lampsam/rig``, else ``camera_info`` and the
static tf chain from the body frame to the camera (:func:`tf_chain`). Wheel odometry is
joint angles times the wheel radius; ``nav_msgs/Odometry`` poses become Pose2 increments
whose covariance :func:`increment_covariances` approximates from the poses' covariances
(the import module's docstring has the model).
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import yaml

from lampsam.datasets.calibration import intrinsics_from_k
from lampsam.datasets.logrun import OdometryLog
from lampsam.datasets.odometry import Pose2OdometryLog, increments_from_poses
from lampsam.datasets.rig import Rig
from lampsam.datasets.ros_messages import rotation_of
from lampsam.errors import DatasetError

if TYPE_CHECKING:
    from lampsam.datasets.rosbag_import import ImportOptions, ImportReport


def tf_chain(transforms: list[Any], base: str, child: str) -> tuple[np.ndarray, np.ndarray] | None:
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


def rig_from_streams(s: dict[str, Any], opts: ImportOptions, chosen: dict[str, str],
                     bag: Path, report: ImportReport, need_wheels: bool) -> Rig:
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
    mount = tf_chain(s["tf"], opts.base_frame, s["camera_frame"] or "")
    child = s.get("odom_child")
    if mount is None and child and child != opts.base_frame:
        # the odometry's body frame (base_footprint on many robots) when base_link has no tf
        mount = tf_chain(s["tf"], child, s["camera_frame"] or "")
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


def odometry_from_streams(s: dict[str, Any], kind: str, opts: ImportOptions, rig: Rig,
                          report: ImportReport, chosen: dict[str, str], bag: Path
                          ) -> OdometryLog | Pose2OdometryLog:
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
