"""The synthetic corridor of ``scripts/bench/bench_scaling.py``: world, run, dead reckoning.

A straight corridor along world x with a landmark every ``spacing`` m on both walls, a
robot weaving gently along it with noisy wheel odometry (paper 1 eq. 15) and noisy
range-bearing frames (:class:`CorridorConfig`). Imported as a sibling module.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from lampsam.arrays import FloatArray, IntArray
from lampsam.datasets.logrun import (
    LoggedRun,
    OdometryLog,
    OdometryModel,
    RangeBearingLog,
    Rig,
    Trajectory,
)
from lampsam.factors.geometry import wrap_angle
from lampsam.factors.motion import diff_drive_step


@dataclass(frozen=True)
class CorridorConfig:
    """The synthetic corridor world and its sensors.

    Attributes:
        spacing: distance between landmarks along each wall, m (default 0.5).
        half_width: distance from the centre line to each wall, m (default 1.5).
        speed: forward speed, m/s (default 0.5).
        odo_rate: odometry rate, Hz (default 20).
        frame_every: a range-bearing frame every this many odometry samples
            (default 10: 2 Hz, one every 0.25 m).
        weave_rate: amplitude of the weaving yaw rate, rad/s (default 0.05).
        weave_period: its period, s (default 20).
        wheel_base: m (default 0.4); k_wheel: eq. 15 slip constant, m (default 2e-5).
        max_range: sensor range, m (default 3.0).
        half_fov: half field of view about body x, rad (default pi/2).
        sigma_range: range noise, m (default 0.03); sigma_bearing: rad (default 0.01).
    """

    spacing: float = 0.5
    half_width: float = 1.5
    speed: float = 0.5
    odo_rate: float = 20.0
    frame_every: int = 10
    weave_rate: float = 0.05
    weave_period: float = 20.0
    wheel_base: float = 0.4
    k_wheel: float = 2e-5
    max_range: float = 3.0
    half_fov: float = math.pi / 2
    sigma_range: float = 0.03
    sigma_bearing: float = 0.01


def corridor_landmarks(length: float, cfg: CorridorConfig) -> FloatArray:
    """Landmarks on both walls of a corridor along world x from 0 to ``length``.

    Returns:
        (L, 2) world positions (x, y), m; ids are the row indices.
    """
    xs = np.arange(0.0, length + 1e-9, cfg.spacing)
    left = np.column_stack([xs, np.full_like(xs, cfg.half_width)])
    right = np.column_stack([xs, np.full_like(xs, -cfg.half_width)])
    return np.vstack([left, right])


def simulate_corridor(length: float, cfg: CorridorConfig, rng: np.random.Generator,
                      known_ids: bool = True) -> tuple[LoggedRun, FloatArray]:
    """A run along the corridor: noisy wheel odometry and range-bearing frames.

    The true wheel travels follow ``v`` and a weaving yaw rate
    ``w(t) = weave_rate cos(2 pi t / weave_period)`` (``d_r,l = v dt +- b w dt / 2``);
    the logged travels add ``N(0, k |d|)`` per wheel (paper 1, eq. 15).

    Args:
        length: corridor length, m.
        cfg: world and sensor parameters.
        rng: the random generator (all noise).
        known_ids: log the true landmark ids (else -1: association by the gate).

    Returns:
        ``(run, landmarks (L, 2))``; the run has odometry, range-bearing frames and
        the true trajectory at the odometry times.
    """
    lms = corridor_landmarks(length, cfg)
    dt = 1.0 / cfg.odo_rate
    n_max = int(math.ceil(1.5 * length / (cfg.speed * dt)))  # weaving lengthens the path
    t = np.arange(n_max + 1) * dt
    w = cfg.weave_rate * np.cos(2.0 * math.pi * t / cfg.weave_period)
    ds = np.full(n_max + 1, cfg.speed * dt)
    d_right = ds + 0.5 * cfg.wheel_base * w * dt
    d_left = ds - 0.5 * cfg.wheel_base * w * dt
    d_right[0] = d_left[0] = 0.0
    poses = np.zeros((n_max + 1, 3))
    n = n_max
    for i in range(1, n_max + 1):
        poses[i] = diff_drive_step(poses[i - 1], float(d_left[i]), float(d_right[i]),
                                   cfg.wheel_base)[0]
        if poses[i, 0] >= length:  # the end of the corridor
            n = i
            break
    t, d_left, d_right, poses = t[: n + 1], d_left[: n + 1], d_right[: n + 1], poses[: n + 1]
    meas_left = d_left + rng.normal(0.0, 1.0, n + 1) * np.sqrt(cfg.k_wheel * np.abs(d_left))
    meas_right = d_right + rng.normal(0.0, 1.0, n + 1) * np.sqrt(cfg.k_wheel * np.abs(d_right))
    rb_t: list[FloatArray] = []
    rb_id: list[IntArray] = []
    rb_r: list[FloatArray] = []
    rb_b: list[FloatArray] = []
    for i in range(cfg.frame_every, n + 1, cfg.frame_every):
        x, y, th = poses[i]
        dx, dy = lms[:, 0] - x, lms[:, 1] - y
        rng_true = np.hypot(dx, dy)
        bearing = np.asarray(wrap_angle(np.arctan2(dy, dx) - th), float)
        seen = np.flatnonzero((rng_true <= cfg.max_range) & (np.abs(bearing) <= cfg.half_fov))
        k = len(seen)
        rb_t.append(np.full(k, t[i]))
        rb_id.append(seen.astype(np.int64) if known_ids else np.full(k, -1, np.int64))
        rb_r.append(rng_true[seen] + rng.normal(0.0, cfg.sigma_range, k))
        rb_b.append(np.asarray(wrap_angle(bearing[seen] + rng.normal(0.0, cfg.sigma_bearing, k)),
                               float))
    rig = Rig(odometry=OdometryModel(wheel_base=cfg.wheel_base, k_r=cfg.k_wheel, k_l=cfg.k_wheel))
    run = LoggedRun(
        path=Path(f"<corridor {length:g} m>"),
        rig=rig,
        odometry=OdometryLog(t=t, d_left=meas_left, d_right=meas_right),
        groundtruth=Trajectory(t=t, poses=poses),
        range_bearing=RangeBearingLog(t=np.concatenate(rb_t), landmark_id=np.concatenate(rb_id),
                                      range=np.concatenate(rb_r), bearing=np.concatenate(rb_b)),
        meta={"source": "bench_scaling corridor", "length_m": length},
    )
    return run, lms


def dead_reckoning_error(run: LoggedRun) -> float:
    """End position error of the logged (noisy) odometry alone, m (a reference)."""
    assert run.groundtruth is not None
    pose = run.groundtruth.poses[0].copy()
    b = run.rig.odometry.wheel_base
    for d_l, d_r in zip(run.odometry.d_left, run.odometry.d_right, strict=True):
        pose = diff_drive_step(pose, float(d_l), float(d_r), b)[0]
    return float(np.hypot(*(pose[:2] - run.groundtruth.poses[-1, :2])))
