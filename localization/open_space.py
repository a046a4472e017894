"""Facing open space before the verification drive, from the robot's own virtual scan.

The paper (2, sec. 4.2) only says the robot drives on to verify; driving
straight ahead into a wall makes it follow the wall, where the Kinect sees
little. :func:`open_heading` picks a heading with enough free space using the
scan alone (no map: the pose is not trusted yet).
"""

from __future__ import annotations

import logging

import numpy as np

from lampsam.arrays import FloatArray
from lampsam.factors.geometry import between, compose, wrap_angle
from lampsam.localization.filter_config import GlobalLocalizerConfig
from lampsam.localization.robot import Robot

log = logging.getLogger(__name__)


def open_heading(
    scan: FloatArray,
    need: float,
    half_width: float = float(np.deg2rad(15.0)),
    near_border: float = 1.5,
    far: float = 4.5,
) -> float:
    """Where to turn to drive into open space, from the robot's own virtual scan.

    A beam without a return (NaN) is either beyond the sensor's range or
    nearer than its minimum depth; it counts as ``far`` metres free when the
    returns on both sides of its run of NaN beams are at least ``near_border``
    away, else as blocked (0 m). The free distance of a heading is the
    smallest filled range within ``half_width`` of it (the robot's width at a
    few metres). When straight ahead has ``need`` metres free the robot goes
    on (0 is returned); otherwise it turns to the heading whose sector is
    freest on average among those with ``need`` metres free (the most open
    one when none has).

    Args:
        scan: (360,) ranges at :func:`beam_angles` (m, NaN = no return), body
            frame at the end of the turn.
        need: free distance wanted ahead (m).
        half_width: half the angular width of a drive corridor (rad).
        near_border: NaN runs bordered by returns nearer than this are blocked (m).
        far: free distance credited to a NaN beam of an open run (m): the
            sensor's range.

    Returns:
        The turn (rad, in ``(-pi, pi]``, counter-clockwise positive), 0 when
        ahead is free or the scan has no return at all.
    """
    r = np.asarray(scan, dtype=float).reshape(-1)
    n = len(r)
    finite = np.isfinite(r)
    if not finite.any():
        return 0.0
    filled = np.where(finite, np.minimum(r, far), 0.0)
    # each NaN beam's nearest returns clockwise and counter-clockwise
    idx = np.arange(n)
    fin_idx = np.nonzero(finite)[0]
    ext = np.concatenate([fin_idx - n, fin_idx, fin_idx + n])
    nxt = ext[np.searchsorted(ext, idx, side="left")] % n
    prv = ext[np.searchsorted(ext, idx, side="right") - 1] % n
    open_nan = ~finite & (np.minimum(r[nxt], r[prv]) >= near_border)
    filled[open_nan] = far
    k = max(int(round(np.rad2deg(half_width))), 0)
    window = np.stack([np.roll(filled, -j) for j in range(-k, k + 1)])
    free = window.min(axis=0)
    if free[0] >= need:
        return 0.0
    mean = window.mean(axis=0)
    ok = free >= need
    score = np.where(ok, mean, -np.inf) if ok.any() else free
    best = int(np.argmax(score))
    return float(wrap_angle(np.deg2rad(float(best))))

def face_open_space(
    robot: Robot,
    scan: FloatArray,
    pose: FloatArray,
    odom: FloatArray,
    config: GlobalLocalizerConfig,
    robot_time: dict[str, float],
) -> tuple[FloatArray, FloatArray]:
    """Turn in place towards open space (:func:`open_heading`) before driving on.

    The estimate follows the turn by odometry; the turn's robot seconds are
    added to ``robot_time["turn"]``.

    Returns:
        The pose estimate (3,) and the odometry (3,) after the turn.
    """
    angle = open_heading(scan, config.open_space_need)
    if abs(angle) < 1e-9:
        return pose, odom
    frames = robot.turn(angle, config.turn_rate)
    if not frames:
        return pose, odom
    robot_time["turn"] += float(frames[-1].t - frames[0].t)
    new_odom = np.asarray(frames[-1].odom, dtype=float)
    log.info("turned %.0f deg towards open space before driving on", np.rad2deg(angle))
    return compose(pose, between(np.asarray(odom, dtype=float), new_odom)), new_odom

