"""True motion of a differential-drive robot along waypoints, and wheel-slip noise.

Pure numpy, no estimator code: the simulators (ceiling world, office world) use
these to make the truth that the estimators are tested against.

The true robot moves on exact arcs between samples (constant linear and angular
speed over each step), so its poses are not the output of the paper's eq. 13
(which is the midpoint approximation of the same arc); dead reckoning with eq. 13
from noiseless wheel travel differs from the truth only by that approximation.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import numpy as np

from lampsam.arrays import FloatArray

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class DriveLimits:
    """How the simulated robot steers to waypoints.

    Attributes:
        max_turn_rate: largest angular speed, rad/s (default 0.8).
        heading_gain: angular speed per rad of heading error, 1/s (default 2.0).
        turn_in_place: heading error above which the robot stops and turns in place,
            rad (default 0.6, about 34 deg).
        reach_tolerance: distance at which an intermediate waypoint counts as reached,
            m (default 0.15).
        final_tolerance: distance at which the last waypoint counts as reached, m
            (default 0.02).
        approach_gain: speed per metre of distance near the last waypoint, 1/s (default 1.0).
        max_duration: safety stop, s (default 3600).
    """

    max_turn_rate: float = 0.8
    heading_gain: float = 2.0
    turn_in_place: float = 0.6
    reach_tolerance: float = 0.15
    final_tolerance: float = 0.02
    approach_gain: float = 1.0
    max_duration: float = 3600.0


def _wrap(a: float) -> float:
    """Wrap an angle to (-pi, pi]."""
    w = math.fmod(a + math.pi, 2.0 * math.pi)
    if w <= 0.0:
        w += 2.0 * math.pi
    return w - math.pi


def arc_step(pose: FloatArray, ds: float, dth: float) -> FloatArray:
    """Exact planar motion over one step at constant speed and turn rate.

    Args:
        pose: (3,) ``(x, y, theta)`` before the step, m and rad.
        ds: distance travelled by the axle midpoint, m.
        dth: heading change, rad.

    Returns:
        (3,) the pose after the step: the chord of the arc has length
        ``ds * sinc(dth / 2)`` in direction ``theta + dth / 2`` (eq. 13 without the
        small-angle approximation).
    """
    half = 0.5 * dth
    chord = ds * (math.sin(half) / half if abs(half) > 1e-9 else 1.0 - half * half / 6.0)
    x, y, th = float(pose[0]), float(pose[1]), float(pose[2])
    return np.array(
        [x + chord * math.cos(th + half), y + chord * math.sin(th + half), _wrap(th + dth)]
    )


def follow_waypoints(
    waypoints: FloatArray,
    speed: float = 0.4,
    rate_hz: float = 30.0,
    wheel_base: float = 0.4,
    start_heading: float | None = None,
    limits: DriveLimits | None = None,
    duration: float | None = None,
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Drive a differential-drive robot through waypoints.

    The robot starts at ``waypoints[0]``; at each step it steers towards the next
    waypoint with a proportional heading controller (angular speed clipped to
    ``limits.max_turn_rate``), slows with ``cos`` of the heading error, and turns
    in place when the error exceeds ``limits.turn_in_place``. It stops at the last
    waypoint.

    Args:
        waypoints: (K, 2) world ``(x, y)`` to visit in order, m; K >= 2.
        speed: cruise speed of the axle midpoint, m/s (paper: about 0.4).
        rate_hz: sample rate, Hz.
        wheel_base: distance between the wheels, m.
        start_heading: initial heading, rad; default: facing the second waypoint.
        limits: steering parameters (default :class:`DriveLimits`).
        duration: stop after this many seconds (default: when the path is done).

    Returns:
        ``(t, poses, wheel)``: ``t`` (N,) time stamps from 0, s; ``poses`` (N, 3) true
        ``world_T_body = (x, y, theta)``; ``wheel`` (N, 2) true travel of the
        ``(left, right)`` wheels since the previous sample, m (row 0 is zero).
        ``ds_r - ds_l = b * dth`` and ``(ds_r + ds_l) / 2 = ds`` per step.

    Raises:
        ValueError: fewer than two waypoints, non-finite values or non-positive speed/rate.
    """
    wp = np.asarray(waypoints, dtype=np.float64)
    if wp.ndim != 2 or wp.shape[1] != 2 or len(wp) < 2 or not np.all(np.isfinite(wp)):
        raise ValueError("waypoints must be a finite (K, 2) array with K >= 2")
    if speed <= 0 or rate_hz <= 0 or wheel_base <= 0:
        raise ValueError("speed, rate_hz and wheel_base must be positive")
    lim = limits or DriveLimits()
    dt = 1.0 / rate_hz
    if start_heading is None:
        d0 = wp[1] - wp[0]
        start_heading = math.atan2(d0[1], d0[0])
    pose = np.array([wp[0, 0], wp[0, 1], _wrap(start_heading)])
    t_end = lim.max_duration if duration is None else min(duration, lim.max_duration)
    poses = [pose]
    wheel = [np.zeros(2)]
    target = 1
    n_steps_max = int(math.floor(t_end * rate_hz + 1e-9))
    for _ in range(n_steps_max):
        # Skip reached waypoints.
        while target < len(wp):
            last = target == len(wp) - 1
            tol = lim.final_tolerance if last else lim.reach_tolerance
            if np.hypot(*(wp[target] - pose[:2])) > tol:
                break
            target += 1
        if target >= len(wp):
            break
        delta = wp[target] - pose[:2]
        dist = float(np.hypot(*delta))
        err = _wrap(math.atan2(delta[1], delta[0]) - pose[2])
        w = float(np.clip(lim.heading_gain * err, -lim.max_turn_rate, lim.max_turn_rate))
        if abs(err) > lim.turn_in_place:
            v = 0.0
        else:
            v = speed * max(math.cos(err), 0.0)
            if target == len(wp) - 1:
                v = min(v, lim.approach_gain * dist)
            v = min(v, dist / dt)
        ds, dth = v * dt, w * dt
        pose = arc_step(pose, ds, dth)
        poses.append(pose)
        half = 0.5 * wheel_base * dth
        wheel.append(np.array([ds - half, ds + half]))
    else:
        if duration is None:
            log.warning("follow_waypoints stopped at max_duration %.0f s", t_end)
    t = np.arange(len(poses), dtype=np.float64) * dt
    return t, np.array(poses), np.array(wheel)


def noisy_wheel_travel(
    true_travel: FloatArray, k_r: float, k_l: float, rng: np.random.Generator
) -> FloatArray:
    """Wheel travel with slip noise (paper 1, eq. 15).

    Each wheel's travel per sample gets independent zero-mean Gaussian noise of
    variance ``k |ds|``: ``var(ds_l) = k_l |ds_l|``, ``var(ds_r) = k_r |ds_r|``.

    Args:
        true_travel: (N, 2) true ``(left, right)`` travel per sample, m.
        k_r: right-wheel constant, m.
        k_l: left-wheel constant, m.
        rng: random generator.

    Returns:
        (N, 2) noisy ``(left, right)`` travel, m.
    """
    d = np.asarray(true_travel, dtype=np.float64)
    if d.ndim != 2 or d.shape[1] != 2:
        raise ValueError("true_travel must have shape (N, 2)")
    sigma = np.sqrt(np.abs(d) * np.array([k_l, k_r]))
    return d + sigma * rng.standard_normal(d.shape)


def dead_reckoning(wheel: FloatArray, wheel_base: float, start: FloatArray) -> FloatArray:
    """Integrate wheel travel with the paper's eq. 13 (midpoint heading).

    For simulator checks and drift figures only; the estimators use
    :mod:`lampsam.factors`.

    Args:
        wheel: (N, 2) ``(left, right)`` travel per sample, m (row 0 is travel before
            the first pose and is applied too).
        wheel_base: m.
        start: (3,) pose before the first row.

    Returns:
        (N, 3) poses after each row.
    """
    w = np.asarray(wheel, dtype=np.float64)
    ds = 0.5 * (w[:, 0] + w[:, 1])
    dth = (w[:, 1] - w[:, 0]) / wheel_base
    th_after = float(start[2]) + np.cumsum(dth)
    th_mid = th_after - 0.5 * dth
    x = float(start[0]) + np.cumsum(ds * np.cos(th_mid))
    y = float(start[1]) + np.cumsum(ds * np.sin(th_mid))
    th = np.mod(th_after + np.pi, 2 * np.pi) - np.pi
    return np.column_stack([x, y, th])
