"""A SLAM result as a g2o graph file (``lampsam slam ... --g2o OUT.g2o``).

g2o's planar types: ``VERTEX_SE2`` per keyframe pose, ``VERTEX_XY`` per landmark (its
height and lamp axis in a comment), ``EDGE_SE2`` odometry factors between consecutive
keyframes with their information matrices. The odometry factors are re-derived from
the run's odometry between keyframes: wheel travel through the wheel model (paper 1,
eqs. 13-15), or Pose2 increments composed with their covariances.
Landmark observation factors are not part of :class:`SlamResult`, so none are written.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from lampsam.backend.interface import SlamResult
from lampsam.backend.odometry import Pose2Motion
from lampsam.datasets.g2o_writer import write_g2o
from lampsam.datasets.logrun import LoggedRun
from lampsam.datasets.odometry import Pose2OdometryLog, Pose2OdometryModel
from lampsam.factors.motion import DEFAULT_FLOOR_VAR, accumulate_odometry


def write_result_g2o(path: str | Path, result: SlamResult, run: LoggedRun) -> tuple[int, int, int]:
    """Write ``result`` as g2o to ``path``.

    Args:
        path: the ``.g2o`` file to write.
        result: the finished SLAM result (keyframe flags select the poses written).
        run: the run it came from (its odometry and wheel model give the factors).

    Returns:
        ``(poses, odometry factors, landmarks)`` written.
    """
    kf = np.flatnonzero(result.keyframes) if np.any(result.keyframes) else np.arange(len(result.times))
    odo, wheel = run.odometry, run.rig.odometry
    edges = []
    for i in range(len(kf) - 1):
        ta, tb = result.times[kf[i]], result.times[kf[i + 1]]
        sel = (odo.t > ta) & (odo.t <= tb)
        if isinstance(odo, Pose2OdometryLog):
            delta, cov = Pose2Motion(Pose2OdometryModel()).relative(odo.samples()[sel],
                                                                    DEFAULT_FLOOR_VAR)
        else:
            delta, cov = accumulate_odometry(odo.d_left[sel], odo.d_right[sel],
                                             wheel.wheel_base, wheel.k_r, wheel.k_l)
        edges.append((i, i + 1, delta, np.linalg.inv(cov)))
    lms = result.landmarks
    notes = [f"{lm.type} id {lm.id} z {lm.position[2]:.4f} m"
             + (f" phi {lm.orientation:.6f} rad" if lm.orientation is not None else "") for lm in lms]
    write_g2o(path, np.arange(len(kf)), result.poses[kf], edges,
              landmark_ids=len(kf) + np.arange(len(lms)),
              landmarks=np.array([lm.position[:2] for lm in lms]).reshape(-1, 2),
              fixed=(0,) if len(kf) else (), landmark_notes=notes)
    return len(kf), len(edges), len(lms)
