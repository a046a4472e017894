"""A logged run replayed in time order as a robot, and global localization of a run.

A log cannot be steered: the recorded motion decides where the robot went, and
the localizer (:func:`~lampsam.localization.localizer.localize`) reads the
frames recorded while the log turned and drove. Used by ``lampsam localize RUN``.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Iterator
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import cv2
import numpy as np

from lampsam.arrays import Float32Array, FloatArray, ImageU8, ImageU16
from lampsam.datasets.rgbd import RgbdCamera
from lampsam.localization.filter_config import GlobalLocalizerConfig
from lampsam.localization.localizer import localize
from lampsam.localization.map_layers import EnvironmentMaps
from lampsam.localization.result import LocalizationResult, is_correct, summarize, write_result
from lampsam.localization.robot import DriveFrame, GlobalLocalizationError, TurnFrame

if TYPE_CHECKING:
    from lampsam.frontend.measurements import CeilingFrame

log = logging.getLogger(__name__)


def kinect_turn_data(
    rgb: ImageU8, depth: ImageU16, camera: RgbdCamera, sift: cv2.SIFT
) -> tuple[FloatArray, Float32Array, FloatArray]:
    """What the turn stage needs of one Kinect frame, in the body frame.

    Args:
        rgb: (H, W, 3) colour image.
        depth: (H, W) depth image (``camera.depth_scale`` units per metre).
        camera: the Kinect, with its mounting ``body_T_camera``.
        sift: the SIFT detector (:func:`~lampsam.localization.spatial_map.make_sift`).

    Returns:
        SIFT keypoints with valid depth (N, 3) (m), their descriptors (N, 128),
        and the depth points (P, 3) (m, every 4th pixel), all in the body frame.
    """
    from lampsam.localization.pointcloud import depth_to_points
    from lampsam.localization.spatial_map import frame_features

    R, t = camera.body_T_camera[:3, :3], camera.body_T_camera[:3, 3]
    ff = frame_features(rgb, depth, camera, sift)
    pts = depth_to_points(depth, camera, stride=4)
    return ff.camera_xyz @ R.T + t, ff.descriptors, pts @ R.T + t


class ReplayRobot:
    """A logged run replayed in time order as a :class:`~lampsam.localization.robot.Robot`.

    The run (``docs/log-format.md``) must hold wheel odometry and the Kinect
    frames under ``kinect/`` (TUM RGB-D layout with ``kinect.yaml``, whose
    ``body_T_camera`` places the Kinect on the robot); ceiling features come
    from the run's ceiling images through the frontend when it has images.
    ``turn`` returns the Kinect frames from the current time until the odometry
    heading has turned by ``angle``; ``drive`` the ceiling frames until the
    odometry has covered ``distance``. The recorded motion decides what the
    robot did: the requested rate is not enforced. An exhausted log returns no
    frame.

    Args:
        run_dir: the run directory.
    """

    def __init__(self, run_dir: str | Path) -> None:
        from lampsam.datasets.logrun import read_run
        from lampsam.datasets.motion import dead_reckoning
        from lampsam.datasets.rgbd import read_tum_rgbd
        from lampsam.localization.spatial_map import make_sift

        self.run = read_run(run_dir)
        odo = self.run.odometry
        from lampsam.datasets.odometry import Pose2OdometryLog

        if isinstance(odo, Pose2OdometryLog):  # no wheel travel to replay
            raise GlobalLocalizationError(f"{run_dir}: laser replay needs wheel odometry "
                                          "(odometry.csv), not Pose2 increments")
        if len(odo.t) == 0:
            raise GlobalLocalizationError(f"{run_dir}: the run has no odometry")
        wheel = np.column_stack([odo.d_left, odo.d_right])
        self.t_odom = np.asarray(odo.t, dtype=float)
        self.odom = dead_reckoning(wheel, self.run.rig.odometry.wheel_base, np.zeros(3))
        self.heading = np.unwrap(self.odom[:, 2])
        self.path = np.cumsum(np.abs(0.5 * (wheel[:, 0] + wheel[:, 1])))
        kdir = Path(run_dir) / "kinect"
        if not kdir.is_dir():
            raise GlobalLocalizationError(f"{kdir}: the run has no Kinect frames")
        self.kinect = read_tum_rgbd(kdir)
        self.sift = make_sift()
        self.cursor = float(min(self.t_odom[0], self.kinect.t[0]))
        self._ceiling: list[DriveFrame] = []
        self._ceiling_source: Iterator[CeilingFrame] | None = None
        if self.run.images is not None:
            from lampsam.frontend.pipeline import iter_run

            self._ceiling_source = iter_run(self.run)

    def _odom_at(self, t: float) -> FloatArray:
        i = int(np.clip(np.searchsorted(self.t_odom, t, side="right") - 1, 0, len(self.t_odom) - 1))
        return self.odom[i].copy()

    def _index_at(self, t: float) -> int:
        return int(
            np.clip(np.searchsorted(self.t_odom, t, side="right") - 1, 0, len(self.t_odom) - 1)
        )

    def turn(self, angle: float, rate: float) -> list[TurnFrame]:
        """Kinect frames until the recorded heading has changed by ``|angle|``."""
        cam = self.kinect.camera
        h0 = self.heading[self._index_at(self.cursor)]
        frames: list[TurnFrame] = []
        for i in np.nonzero(self.kinect.t >= self.cursor)[0]:
            ti = float(self.kinect.t[i])
            rgb, depth = self.kinect.load_rgb(int(i)), self.kinect.load_depth(int(i))
            frames.append(TurnFrame(ti, self._odom_at(ti), *kinect_turn_data(rgb, depth, cam,
                                                                            self.sift)))
            self.cursor = ti + 1e-6
            if abs(self.heading[self._index_at(ti)] - h0) >= abs(angle) - 1e-3:
                break
        return frames

    def _ceiling_frames(self) -> Iterator[DriveFrame]:
        """The run's ceiling frames in time order, each through the frontend once, when first needed.

        The frontend processes every image on its own, so running it lazily (only
        up to the last frame a drive asks for) gives the same frames as running
        it over the whole run first, at the cost of the frames read.
        """
        k = 0
        while True:
            while k >= len(self._ceiling) and self._ceiling_source is not None:
                f = next(self._ceiling_source, None)
                if f is None:
                    self._ceiling_source = None
                    break
                m = [o.m for o in f.lamps] + [o.m for o in f.corners]
                kinds = [True] * len(f.lamps) + [False] * len(f.corners)
                axis = [np.nan if o.axis is None else o.axis for o in f.lamps]
                axis += [np.nan] * len(f.corners)
                self._ceiling.append(DriveFrame(
                    f.t, self._odom_at(f.t), np.array(m, dtype=float).reshape(-1, 2),
                    np.array(kinds, bool), np.array(axis, dtype=float),
                ))  # fmt: skip
            if k >= len(self._ceiling):
                return
            yield self._ceiling[k]
            k += 1

    def drive(self, distance: float) -> list[DriveFrame]:
        """Ceiling frames until the recorded path has grown by ``distance``."""
        s0 = self.path[self._index_at(self.cursor)]
        frames: list[DriveFrame] = []
        for f in self._ceiling_frames():
            if f.t < self.cursor:
                continue
            frames.append(f)
            self.cursor = f.t + 1e-6
            if self.path[self._index_at(f.t)] - s0 >= distance - 1e-9:
                break
        return frames


def localize_run(
    run_dir: str | Path,
    map_dir: str | Path,
    out_dir: str | Path,
    config: GlobalLocalizerConfig,
    seed: int = 0,
) -> LocalizationResult:
    """Global localization of a logged run against a map directory; writes ``result.json``.

    Args:
        run_dir: the run (see :class:`ReplayRobot`).
        map_dir: the environment map (``lampsam.localization.map_store``).
        out_dir: where ``result.json`` goes.
        config: the pipeline configuration.
        seed: seed of RANSAC and the particle filter.
            ``config.head_for_open_space`` is switched off: a replayed log
            cannot turn where the localizer asks.

    Returns:
        The result (also written).

    Raises:
        LampsamError subclasses: unreadable run or map, no usable data.
    """
    from lampsam.localization.map_store import load_env_map

    env = load_env_map(map_dir)
    # a log cannot be steered: the recorded drive decides where the robot went
    config = replace(config, head_for_open_space=False)
    robot = ReplayRobot(run_dir)
    cam = robot.run.rig.camera
    maps = EnvironmentMaps.from_env_map(env, cam.body_t_camera, cam, cache_dir=Path(map_dir))
    result = localize(robot, maps, config, np.random.default_rng(seed))
    path = write_result(result, out_dir, score_run(robot, result))
    log.info("localization %s: result in %s", "succeeded" if result.success else "failed", path)
    return result


def score_run(robot: ReplayRobot, result: LocalizationResult) -> dict[str, Any]:
    """The run as one trial: truth at the time of the answer when the run has it, and the summary.

    The answer's pose goes with the last frame replayed (``robot.cursor``); the
    run's ``groundtruth.tum`` there is the truth.
    """
    trial: dict[str, Any] = {
        "status": result.status,
        "compute_s": float(sum(result.compute_time.values())),
        "robot_s": float(sum(result.robot_time.values())),
        "t": robot.cursor,
        "correct": None,
    }
    gt = robot.run.groundtruth
    if gt is not None and len(gt.t):
        i = int(np.clip(np.searchsorted(gt.t, robot.cursor), 0, len(gt.t) - 1))
        truth = np.asarray(gt.poses[i], dtype=float)
        d = result.pose - truth
        trial.update(
            truth=truth.tolist(),
            error_m=float(np.hypot(d[0], d[1])),
            error_deg=float(np.degrees(abs(math.remainder(float(d[2]), 2 * math.pi)))),
            correct=is_correct(result.pose, truth),
        )
    return {"trial": trial, "summary": summarize([trial])}
