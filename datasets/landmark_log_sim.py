"""Synthetic planar landmark-SLAM logs in the iSAM text format, with ground truth.

For testing and benchmarking the backends on what real outdoor logs have and the
ceiling simulator does not: Pose2 odometry whose sideways noise is larger than a
two-wheel model can give, long stops (hundreds of poses at rest), bearing noise
that grows with range, thousands of poses and hundreds of landmarks. The robot
drives a random smooth path through a field of point landmarks ("trees").

The log is written as ``ODOMETRY`` and ``BR`` records (the latter with each
sighting's own sigmas), the truth as ``VERTEX2`` records
(:mod:`lampsam.datasets.graph_text` reads both). Imports no estimator code.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

import numpy as np

from lampsam.arrays import FloatArray
from lampsam.safe_io import write_text_atomic


@dataclass(frozen=True)
class LandmarkLogSpec:
    """What to simulate.

    Attributes:
        n_poses: poses (one odometry record each).
        n_landmarks: point landmarks, uniform in a square of side ``extent``, m.
        extent: side of the landmark field, m.
        step: forward motion per pose while moving, m.
        sigma_fwd, sigma_side, sigma_theta: odometry noise per pose (m, m, rad);
            ``sigma_side`` 3x ``sigma_fwd`` by default.
        stop_every, stop_length: a stop of ``stop_length`` poses every ``stop_every``.
        max_range: sighting range, m.
        sigma_range: range noise, m.
        sigma_bearing0, sigma_bearing_per_m: bearing noise ``s0 + s1 * range``, rad.
        pose_lines: write ``ODOMETRY`` with the covariance (True) as iSAM does.
    """

    n_poses: int = 3000
    n_landmarks: int = 500
    extent: float = 200.0
    step: float = 0.5
    sigma_fwd: float = 0.01
    sigma_side: float = 0.03
    sigma_theta: float = 0.004
    stop_every: int = 700
    stop_length: int = 200
    max_range: float = 15.0
    sigma_range: float = 0.1
    sigma_bearing0: float = 0.005
    sigma_bearing_per_m: float = 0.001


def simulate_landmark_log(spec: LandmarkLogSpec, rng: np.random.Generator
                          ) -> tuple[list[str], FloatArray, FloatArray]:
    """Simulate a log.

    Returns:
        ``(lines, truth (n_poses, 3), landmarks (n_landmarks, 2))``: the iSAM text
        records, the true poses ``world_T_body`` and the landmark positions, m.
    """
    half = spec.extent / 2
    marks = rng.uniform(-half, half, (spec.n_landmarks, 2))
    cov = np.diag([spec.sigma_fwd**2, spec.sigma_side**2, spec.sigma_theta**2])
    pose = np.zeros(3)
    truth = [pose.copy()]
    lines: list[str] = []
    turn = 0.0
    for k in range(1, spec.n_poses):
        stopped = spec.stop_every > 0 and (k % spec.stop_every) < spec.stop_length and k > spec.stop_length
        if stopped:
            d = np.zeros(3)
        else:
            # steer back towards the field when near its edge, else wander
            to_c = math.atan2(-pose[1], -pose[0]) - pose[2]
            to_c = math.atan2(math.sin(to_c), math.cos(to_c))
            turn = 0.9 * turn + 0.1 * rng.normal(0, 0.05)
            if math.hypot(pose[0], pose[1]) > 0.8 * half:
                turn = 0.2 * to_c
            d = np.array([spec.step, 0.0, turn])
        c, s = math.cos(pose[2]), math.sin(pose[2])
        pose = np.array([pose[0] + c * d[0] - s * d[1], pose[1] + s * d[0] + c * d[1],
                         math.atan2(math.sin(pose[2] + d[2]), math.cos(pose[2] + d[2]))])
        truth.append(pose.copy())
        meas = d + rng.multivariate_normal(np.zeros(3), cov)
        lines.append(odometry_record(k, meas, cov))
        lines += sighting_records(k, pose, marks, spec.n_poses, spec, rng, _wrap_atan2)
    return lines, np.array(truth), marks


class SightingNoise(Protocol):
    """The sighting model of a simulated log (:class:`LandmarkLogSpec`, ``HeldOutSpec``)."""

    @property
    def max_range(self) -> float:
        """Sighting range, m."""
        ...

    @property
    def sigma_range(self) -> float:
        """Range noise, m."""
        ...

    @property
    def sigma_bearing0(self) -> float:
        """Bearing noise at zero range, rad."""
        ...

    @property
    def sigma_bearing_per_m(self) -> float:
        """Bearing noise growth with range, rad/m."""
        ...


def _wrap_atan2(angle: float) -> float:
    """``angle`` wrapped to (-pi, pi] through ``atan2(sin, cos)`` (this simulator's logs)."""
    return math.atan2(math.sin(angle), math.cos(angle))


def odometry_record(k: int, meas: FloatArray, cov: FloatArray) -> str:
    """The ``ODOMETRY k-1 k dx dy dtheta`` record with the stated covariance's upper triangle.

    Args:
        k: the pose the odometry leads to.
        meas: (3,) measured increment ``(dx, dy, dtheta)`` in the earlier body frame (m, rad).
        cov: (3, 3) diagonal covariance of it.
    """
    return (f"ODOMETRY {k - 1} {k} {meas[0]:.9g} {meas[1]:.9g} {meas[2]:.9g} "
            f"{cov[0, 0]:.9g} 0 0 {cov[1, 1]:.9g} 0 {cov[2, 2]:.9g}")


def sighting_records(k: int, pose: FloatArray, marks: FloatArray, first_id: int,
                     noise: SightingNoise, rng: np.random.Generator,
                     wrap: Callable[[float], float]) -> list[str]:
    """``BR`` records of pose ``k``: every landmark between 1 m and ``max_range``, in index order.

    Bearing noise ``sigma_bearing0 + sigma_bearing_per_m * range`` (rad), range noise
    ``sigma_range`` (m); per landmark one bearing then one range draw from ``rng``.

    Args:
        k: pose index.
        pose: (3,) true ``world_T_body`` (m, rad).
        marks: (L, 2) landmark positions, m; landmark ``j`` is written as ``first_id + j``.
        first_id: the id of landmark 0.
        noise: the sighting noise.
        rng: the generator.
        wrap: the true bearing's wrap to (-pi, pi] (each simulator keeps its own, so that
            its logs stay the same to the last digit).
    """
    rel = marks - pose[:2]
    rng_ = np.hypot(rel[:, 0], rel[:, 1])
    out = []
    for j in np.flatnonzero((rng_ < noise.max_range) & (rng_ > 1.0)):
        sb = noise.sigma_bearing0 + noise.sigma_bearing_per_m * rng_[j]
        b = wrap(math.atan2(rel[j, 1], rel[j, 0]) - pose[2]) + rng.normal(0, sb)
        r = rng_[j] + rng.normal(0, noise.sigma_range)
        out.append(f"BR {k} {first_id + j} {b:.9g} {r:.9g} {sb:.9g} {noise.sigma_range:.9g}")
    return out


def write_log_and_truth(path: str | Path, lines: list[str], truth: FloatArray) -> tuple[Path, Path]:
    """Write the records to ``path`` and the true poses (N, 3) to ``<stem>_truth.txt``
    (``VERTEX2``). Returns ``(log path, truth path)``."""
    path = Path(path)
    write_text_atomic(path, "\n".join(lines) + "\n")
    tpath = path.with_name(path.stem + "_truth.txt")
    write_text_atomic(tpath, "".join(f"VERTEX2 {k} {p[0]:.9g} {p[1]:.9g} {p[2]:.9g}\n"
                                     for k, p in enumerate(truth)))
    return path, tpath


def write_landmark_log(path: str | Path, spec: LandmarkLogSpec, rng: np.random.Generator
                       ) -> tuple[Path, Path]:
    """Simulate and write ``path`` (iSAM text) and ``<stem>_truth.txt`` (``VERTEX2``).

    Returns:
        ``(log path, truth path)``.
    """
    lines, truth, _ = simulate_landmark_log(spec, rng)
    return write_log_and_truth(path, lines, truth)
