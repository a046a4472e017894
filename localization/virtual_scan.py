"""The paper's "virtual map": a 360-degree scan assembled while turning in place.

Paper 2, sec. 4.1: the Kinect's field of view is narrow (about 57 deg), so the
depth seen during the turn is accumulated, compensated by the odometry
rotation, into one range per degree around the robot; the particle filter
compares it with the ranges ray-cast in the grid map (eq. 8).

Points are given in the body frame (``docs/conventions.md``: ``x`` forward,
``y`` left, ``z`` up from the floor). Those between ``z_min`` and ``z_max``
(obstacles, not floor or ceiling: the same band the grid map is built from)
are projected onto the floor plane, reduced to the nearest point per 1-degree
bin, and stored in the odometry frame. :meth:`VirtualScan.scan` returns, for the
robot's current odometry pose, the minimum range in each of the 360 beams;
beam ``k`` points at bearing ``k`` degrees (counter-clockwise from forward,
wrapped to ``(-pi, pi]``) and covers ``[k - 0.5, k + 0.5)`` degrees. A beam
nothing was seen in is NaN (no return).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from lampsam.arrays import FloatArray, IntArray
from lampsam.errors import LocalizationError
from lampsam.factors.geometry import wrap_angle

log = logging.getLogger(__name__)

N_BEAMS = 360


class VirtualScanError(LocalizationError):
    """Malformed depth points or odometry for the virtual scan."""


@dataclass(frozen=True)
class VirtualScanConfig:
    """Which depth points make up the virtual scan.

    Attributes:
        z_min: lowest point height kept (m above the floor). Default 0.08 m,
            the grid map's band (``envmap.DepthGridConfig.height_band``).
        z_max: highest point height kept (m). Default 1.8 m (same band).
        min_range: nearer points are dropped (m); the Kinect's minimum depth
            is about 0.5 m along the optical axis. Default 0.3 m.
        max_range: farther points are dropped (m). Default 4.5 m.
    """

    z_min: float = 0.08
    z_max: float = 1.8
    min_range: float = 0.3
    max_range: float = 4.5


def beam_angles() -> FloatArray:
    """Bearings of the 360 beams (rad, body frame, wrapped to ``(-pi, pi]``).

    Returns:
        (360,) ``wrap_angle(k deg)`` for ``k = 0 .. 359``.
    """
    return np.asarray(wrap_angle(np.deg2rad(np.arange(N_BEAMS, dtype=float))))


def beam_index(bearing: FloatArray) -> IntArray:
    """Beam of each bearing: ``round(bearing in degrees) mod 360``.

    Args:
        bearing: (N,) rad, body frame.

    Returns:
        (N,) int64 in ``[0, 360)``.
    """
    return np.mod(np.rint(np.rad2deg(bearing)).astype(np.int64), N_BEAMS)


def min_range_scan(points_xy: FloatArray) -> FloatArray:
    """360-beam scan from floor-projected points around the origin.

    Args:
        points_xy: (N, 2) points in the frame the scan is taken in (m).

    Returns:
        (360,) minimum range per 1-degree beam (m), NaN where the beam is empty.
    """
    ranges = np.full(N_BEAMS, np.inf)
    if len(points_xy):
        r = np.hypot(points_xy[:, 0], points_xy[:, 1])
        k = beam_index(np.arctan2(points_xy[:, 1], points_xy[:, 0]))
        np.minimum.at(ranges, k, r)
    ranges[~np.isfinite(ranges)] = np.nan
    return ranges


def _to_frame(pose: FloatArray, xy: FloatArray) -> FloatArray:
    """World (odometry) points into the frame of ``pose``: ``R^T (p - t)``."""
    c, s = np.cos(pose[2]), np.sin(pose[2])
    d = xy - pose[:2]
    return np.column_stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1]])


def _from_frame(pose: FloatArray, xy: FloatArray) -> FloatArray:
    """Points in the frame of ``pose`` into the odometry frame: ``t + R p``."""
    c, s = np.cos(pose[2]), np.sin(pose[2])
    return np.column_stack(
        [pose[0] + c * xy[:, 0] - s * xy[:, 1], pose[1] + s * xy[:, 0] + c * xy[:, 1]]
    )


class VirtualScan:
    """Accumulates depth points during the turn into a 360-beam scan.

    Args:
        config: the height and range band of the points kept.
    """

    def __init__(self, config: VirtualScanConfig) -> None:
        self.config = config
        self._odom_xy: list[FloatArray] = []
        self.n_frames = 0

    def add(self, odom_pose: FloatArray, body_points: FloatArray) -> int:
        """Add one depth frame.

        Args:
            odom_pose: (3,) ``odom_T_body`` of the frame (m, m, rad).
            body_points: (N, 3) depth points, body frame (m); rows with NaN are
                skipped (invalid depth).

        Returns:
            The number of points kept (after the height/range band and the
            per-beam reduction).

        Raises:
            VirtualScanError: wrong shapes or a non-finite pose.
        """
        odom_pose = np.asarray(odom_pose, dtype=float)
        pts = np.asarray(body_points, dtype=float)
        if odom_pose.shape != (3,) or not np.all(np.isfinite(odom_pose)):
            raise VirtualScanError(f"odometry pose must be a finite (3,), got {odom_pose}")
        if pts.ndim != 2 or pts.shape[1] != 3:
            raise VirtualScanError(f"depth points must be (N, 3), got {pts.shape}")
        cfg = self.config
        pts = pts[np.all(np.isfinite(pts), axis=1)]
        r = np.hypot(pts[:, 0], pts[:, 1])
        keep = (pts[:, 2] >= cfg.z_min) & (pts[:, 2] <= cfg.z_max)
        keep &= (r >= cfg.min_range) & (r <= cfg.max_range)
        xy = pts[keep, :2]
        # reduce to the nearest point per beam of this frame (bounded memory)
        if len(xy):
            k = beam_index(np.arctan2(xy[:, 1], xy[:, 0]))
            rr = r[keep]
            order = np.lexsort((rr, k))
            first = np.ones(len(order), dtype=bool)
            first[1:] = k[order][1:] != k[order][:-1]
            xy = xy[order[first]]
            self._odom_xy.append(_from_frame(odom_pose, xy))
        self.n_frames += 1
        return len(xy)

    def points(self) -> FloatArray:
        """All kept points in the odometry frame, (N, 2) m."""
        if not self._odom_xy:
            return np.zeros((0, 2))
        return np.vstack(self._odom_xy)

    def scan(self, odom_pose: FloatArray) -> FloatArray:
        """The 360-beam scan seen from ``odom_pose``.

        Args:
            odom_pose: (3,) ``odom_T_body`` now (usually the end of the turn).

        Returns:
            (360,) ranges (m) at :func:`beam_angles`, NaN = no return.
        """
        xy = _to_frame(np.asarray(odom_pose, dtype=float), self.points())
        r = np.hypot(xy[:, 0], xy[:, 1]) if len(xy) else np.zeros(0)
        ranges = min_range_scan(xy[r <= self.config.max_range])
        log.debug(
            "virtual scan: %d frames, %d beams with a return",
            self.n_frames,
            int(np.count_nonzero(np.isfinite(ranges))),
        )
        return ranges
