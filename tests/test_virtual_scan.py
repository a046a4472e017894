"""The 360-beam virtual scan assembled while turning in place."""

from __future__ import annotations

import numpy as np
import pytest

from lampsam.localization.virtual_scan import (
    VirtualScan,
    VirtualScanConfig,
    VirtualScanError,
    beam_angles,
    min_range_scan,
)


def _square_room_points(half: float, n: int = 4000) -> np.ndarray:
    """Points on the walls of a square room centred on the origin, odometry frame, z = 1 m."""
    s = np.linspace(-half, half, n // 4, endpoint=False)
    walls = [
        np.column_stack([np.full_like(s, half), s]),
        np.column_stack([np.full_like(s, -half), s]),
        np.column_stack([s, np.full_like(s, half)]),
        np.column_stack([s, np.full_like(s, -half)]),
    ]
    return np.vstack(walls)


def _kinect_frame(world_xy: np.ndarray, pose: np.ndarray, fov_deg: float = 57.0) -> np.ndarray:
    """Body-frame 3-D points the forward Kinect sees at ``pose`` (plus floor and ceiling points)."""
    c, s = np.cos(pose[2]), np.sin(pose[2])
    d = world_xy - pose[:2]
    b = np.column_stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1]])
    vis = (b[:, 0] > 0) & (np.abs(np.arctan2(b[:, 1], b[:, 0])) < np.deg2rad(fov_deg / 2))
    wall = np.column_stack([b[vis], np.ones(int(vis.sum()))])
    floor = np.column_stack([b[vis] * 0.5, np.zeros(int(vis.sum()))])  # z = 0: dropped
    ceiling = np.column_stack([b[vis] * 0.7, np.full(int(vis.sum()), 2.6)])  # dropped
    return np.vstack([wall, floor, ceiling])


def test_beam_convention() -> None:
    a = beam_angles()
    assert a.shape == (360,)
    assert a[0] == 0.0 and a[90] == pytest.approx(np.pi / 2) and a[180] == pytest.approx(np.pi)
    assert a[270] == pytest.approx(-np.pi / 2)
    # a point 2 m to the left (+y) and 1 m behind-right
    r = min_range_scan(np.array([[0.0, 2.0], [0.0, 3.0], [-1.0, -1.0]]))
    assert r[90] == pytest.approx(2.0)  # the nearer of two points in the beam
    assert r[225] == pytest.approx(np.sqrt(2))
    assert np.count_nonzero(np.isfinite(r)) == 2


def test_turn_in_place_gives_the_room_scan() -> None:
    room = _square_room_points(2.0)
    start = np.array([0.0, 0.0, 0.4])  # true heading; the odometry frame starts at 0
    vs = VirtualScan(VirtualScanConfig())
    for k in range(13):  # 12 s at 30 deg/s, a frame per second
        dth = np.deg2rad(30.0 * k)
        pose = start + np.array([0.0, 0.0, dth])
        vs.add(np.array([0.0, 0.0, dth]), _kinect_frame(room, pose))
    final_odom = np.array([0.0, 0.0, np.deg2rad(360.0)])
    scan = vs.scan(final_odom)
    # expected: the square room seen from the centre, robot heading 0.4 rad
    world_bearing = beam_angles() + start[2]
    expected = 2.0 / np.maximum(np.abs(np.cos(world_bearing)), np.abs(np.sin(world_bearing)))
    ok = np.isfinite(scan)
    assert ok.all()  # 12 x 57 deg covers the full circle
    # per-beam error: beam width 1 deg at <= 2.83 m gives <= 2.5 cm along a wall
    np.testing.assert_allclose(scan, expected, atol=0.06)
    assert np.median(np.abs(scan - expected)) < 0.02


def test_partial_turn_leaves_nan_and_compensates_translation() -> None:
    room = _square_room_points(2.0)
    vs = VirtualScan(VirtualScanConfig())
    vs.add(np.array([0.5, 0.0, 0.0]), _kinect_frame(room, np.array([0.5, 0.0, 0.0])))
    scan = vs.scan(np.array([0.0, 0.0, np.pi / 2]))  # moved back 0.5 m and turned left
    # the wall x = 2 is now to the right (beam 270 = -90 deg) at 2 m
    assert scan[270] == pytest.approx(2.0, abs=0.03)
    assert np.isnan(scan[90])  # never seen
    assert np.count_nonzero(np.isfinite(scan)) < 90


def test_bad_input() -> None:
    vs = VirtualScan(VirtualScanConfig())
    with pytest.raises(VirtualScanError):
        vs.add(np.zeros(3), np.zeros((5, 2)))
    with pytest.raises(VirtualScanError):
        vs.add(np.array([0.0, np.nan, 0.0]), np.zeros((5, 3)))
    pts = np.array([[1.0, 0.0, 1.0], [np.nan, 0.0, 1.0]])
    assert vs.add(np.zeros(3), pts) == 1  # the NaN row (invalid depth) is skipped
    assert np.all(np.isnan(VirtualScan(VirtualScanConfig()).scan(np.zeros(3))))
