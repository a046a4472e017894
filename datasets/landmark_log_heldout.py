"""Held-out synthetic landmark logs: layouts and noise unlike the tuning logs, with truth.

The online no-ids association was tuned on Victoria Park's first 3,500 poses, MRCLAM
and :mod:`lampsam.datasets.landmark_log_sim`'s uniform field (docs/failures.md). These
logs are for checking its defaults on what those logs do not have; their parameters
(:data:`HELD_OUT`) were fixed before any option was run on them:

- ``grid``: trees on a square grid (6 m, 0.3 m jitter): every tree has look-alike
  neighbours at the same spacing (aliasing), the robot wanders as in the uniform log;
- ``loop``: three laps of a 160 m x 60 m rectangle with 50 trees along it (few in
  view at once, long stretches with one or none) and a heading noise that closes each
  lap metres off;
- ``odo2x``: a uniform field, but the odometry's true noise is twice the stated
  sigma (the file understates it), denser trees and a longer range than the tuning log;
- ``loop2``, ``sparse`` (added later, fixed before any run on them): a 120 m x 90 m
  loop with 60 trees, and 150 uniform trees in 140 m with odometry 1.5x noisier
  than stated.

The log is written as ``ODOMETRY`` and ``BR`` records and the truth as ``VERTEX2``
(:mod:`lampsam.datasets.graph_text` reads both), as
:func:`lampsam.datasets.landmark_log_sim.write_landmark_log` does. Imports no
estimator code.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from lampsam.arrays import FloatArray
from lampsam.datasets.landmark_log_sim import odometry_record, sighting_records, write_log_and_truth


@dataclass(frozen=True)
class HeldOutSpec:
    """One held-out log.

    Attributes:
        layout: ``"grid"`` (square grid of side ``extent``, ``spacing`` apart, jittered
            by ``jitter`` m), ``"uniform"`` (``n_landmarks`` uniform in the square of
            side ``extent``) or ``"loop"`` (``n_landmarks`` within ``corridor`` m of a
            ``loop_size`` rectangle, driven ``laps`` times).
        n_poses: poses for ``grid`` and ``uniform`` (``loop``: as the laps take).
        step: forward motion per pose, m.
        sigma_fwd, sigma_side, sigma_theta: *stated* odometry sigma per pose (m, m, rad).
        true_noise: the odometry's true sigma over the stated one.
        max_range: sighting range, m; sigma_range: range noise, m.
        sigma_bearing0, sigma_bearing_per_m: bearing noise ``s0 + s1 * range``, rad.
    """

    layout: str = "uniform"
    n_poses: int = 2000
    n_landmarks: int = 300
    extent: float = 120.0
    spacing: float = 6.0
    jitter: float = 0.3
    loop_size: tuple[float, float] = (160.0, 60.0)
    corridor: float = 12.0
    laps: int = 3
    step: float = 0.5
    sigma_fwd: float = 0.01
    sigma_side: float = 0.03
    sigma_theta: float = 0.004
    true_noise: float = 1.0
    max_range: float = 12.0
    sigma_range: float = 0.1
    sigma_bearing0: float = 0.005
    sigma_bearing_per_m: float = 0.001


#: The held-out logs (fixed 2026-11-24 before any association option ran on them) and
#: their seeds.
HELD_OUT: dict[str, tuple[HeldOutSpec, int]] = {
    "grid": (HeldOutSpec(layout="grid", n_poses=2000, extent=120.0, spacing=6.0,
                         max_range=12.0), 101),
    "loop": (HeldOutSpec(layout="loop", n_landmarks=50, loop_size=(160.0, 60.0),
                         corridor=12.0, laps=3, sigma_theta=0.006, max_range=15.0), 102),
    "odo2x": (HeldOutSpec(layout="uniform", n_poses=2500, n_landmarks=400, extent=150.0,
                          true_noise=2.0, max_range=20.0, sigma_bearing0=0.01,
                          sigma_bearing_per_m=0.002), 103),
    # two more, fixed 2026-11-24 23:30 UTC before any run on them (session revisitloop):
    # a squarer loop with more trees, and a sparse uniform field with odometry 1.5x noisier
    # than stated
    "loop2": (HeldOutSpec(layout="loop", n_landmarks=60, loop_size=(120.0, 90.0),
                          corridor=10.0, laps=3, sigma_theta=0.005, max_range=15.0), 201),
    "sparse": (HeldOutSpec(layout="uniform", n_poses=2500, n_landmarks=150, extent=140.0,
                           true_noise=1.5, max_range=15.0), 202),
}


def _landmarks(spec: HeldOutSpec, rng: np.random.Generator) -> FloatArray:
    """(N, 2) tree positions, m."""
    if spec.layout == "grid":
        half = spec.extent / 2
        ax = np.arange(-half, half + 1e-9, spec.spacing)
        gx, gy = np.meshgrid(ax, ax)
        marks = np.column_stack([gx.ravel(), gy.ravel()])
        return marks + rng.normal(0.0, spec.jitter, marks.shape)
    if spec.layout == "loop":
        w, h = spec.loop_size
        # points spread along the rectangle's perimeter, pushed sideways
        s = rng.uniform(0.0, 2 * (w + h), spec.n_landmarks)
        on = np.array([_perimeter(x, w, h) for x in s])
        off = rng.uniform(2.0, spec.corridor, spec.n_landmarks) * rng.choice([-1.0, 1.0],
                                                                            spec.n_landmarks)
        normal = np.array([_perimeter_normal(x, w, h) for x in s])
        return on + off[:, None] * normal
    if spec.layout == "uniform":
        half = spec.extent / 2
        return rng.uniform(-half, half, (spec.n_landmarks, 2))
    raise ValueError(f"HeldOutSpec.layout: unknown {spec.layout!r} (grid, loop, uniform)")


def _perimeter(s: float, w: float, h: float) -> FloatArray:
    """The point at arc length ``s`` on the ``w`` x ``h`` rectangle from (0, 0), counter-clockwise."""
    s = s % (2 * (w + h))
    if s < w:
        return np.array([s, 0.0])
    if s < w + h:
        return np.array([w, s - w])
    if s < 2 * w + h:
        return np.array([w - (s - w - h), h])
    return np.array([0.0, h - (s - 2 * w - h)])


def _perimeter_normal(s: float, w: float, h: float) -> FloatArray:
    """The outward unit normal of the rectangle at arc length ``s``."""
    s = s % (2 * (w + h))
    if s < w:
        return np.array([0.0, -1.0])
    if s < w + h:
        return np.array([1.0, 0.0])
    if s < 2 * w + h:
        return np.array([0.0, 1.0])
    return np.array([-1.0, 0.0])


def _controls(spec: HeldOutSpec, rng: np.random.Generator) -> list[FloatArray]:
    """The true relative motions ``(dx, 0, dtheta)`` per pose."""
    out: list[FloatArray] = []
    pose = np.zeros(3)
    if spec.layout == "loop":
        w, h = spec.loop_size
        n = int(round(spec.laps * 2 * (w + h) / spec.step))
        for k in range(n):
            target = _perimeter((k + 8) * spec.step, w, h)  # a point ahead on the loop
            err = math.atan2(target[1] - pose[1], target[0] - pose[0]) - pose[2]
            turn = float(np.clip(math.remainder(err, math.tau), -0.15, 0.15))
            d = np.array([spec.step, 0.0, turn])
            out.append(d)
            pose = _compose(pose, d)
        return out
    half = spec.extent / 2
    turn = 0.0
    for _ in range(spec.n_poses - 1):
        to_c = math.remainder(math.atan2(-pose[1], -pose[0]) - pose[2], math.tau)
        turn = 0.9 * turn + 0.1 * rng.normal(0, 0.05)
        if math.hypot(pose[0], pose[1]) > 0.8 * half:
            turn = 0.2 * to_c
        d = np.array([spec.step, 0.0, turn])
        out.append(d)
        pose = _compose(pose, d)
    return out


def _compose(pose: FloatArray, d: FloatArray) -> FloatArray:
    c, s = math.cos(pose[2]), math.sin(pose[2])
    return np.array([pose[0] + c * d[0] - s * d[1], pose[1] + s * d[0] + c * d[1],
                     math.remainder(pose[2] + d[2], math.tau)])


def simulate_held_out(spec: HeldOutSpec, rng: np.random.Generator
                      ) -> tuple[list[str], FloatArray, FloatArray]:
    """Simulate a held-out log.

    Returns:
        ``(lines, truth (n, 3), landmarks (N, 2))``: the iSAM text records (the stated
        covariance on every ``ODOMETRY``), the true poses ``world_T_body`` (m, rad) and
        the tree positions (m). Landmark ids in the records are ``n + j``.
    """
    marks = _landmarks(spec, rng)
    controls = _controls(spec, rng)
    n = len(controls) + 1
    cov = np.diag([spec.sigma_fwd**2, spec.sigma_side**2, spec.sigma_theta**2])
    pose = np.zeros(3)
    truth = [pose.copy()]
    lines: list[str] = []
    for k, d in enumerate(controls, start=1):
        pose = _compose(pose, d)
        truth.append(pose.copy())
        meas = d + spec.true_noise * rng.multivariate_normal(np.zeros(3), cov)
        lines.append(odometry_record(k, meas, cov))
        lines += sighting_records(k, pose, marks, n, spec, rng, _wrap_remainder)
    return lines, np.array(truth), marks


def _wrap_remainder(angle: float) -> float:
    """``angle`` wrapped to [-pi, pi] by ``math.remainder`` (these logs' wrap)."""
    return math.remainder(angle, math.tau)


def write_held_out(path: str | Path, name: str) -> tuple[Path, Path]:
    """Write held-out log ``name`` (:data:`HELD_OUT`, its own seed) to ``path`` and its
    truth to ``<stem>_truth.txt`` (``VERTEX2``). Returns ``(log path, truth path)``."""
    if name not in HELD_OUT:
        raise ValueError(f"held-out log {name!r}: one of {', '.join(HELD_OUT)}")
    spec, seed = HELD_OUT[name]
    lines, truth, _ = simulate_held_out(spec, np.random.default_rng(seed))
    return write_log_and_truth(path, lines, truth)
