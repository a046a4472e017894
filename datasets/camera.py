"""The ceiling camera: intrinsics, lens model and mounting on the robot body.

:class:`CameraModel` converts between pixels and the normalised ceiling
coordinates ``m = (u, v)`` of ``docs/conventions.md`` (body forward and left per
metre of height above the camera). Pixel convention: OpenCV, ``(col, row)`` with
the origin at the centre of the top-left pixel.

Two lens models, both OpenCV's:

- ``pinhole``: ``cv2.undistortPoints`` / ``cv2.projectPoints`` with 4, 5
  (ROS ``plumb_bob``: ``k1 k2 p1 p2 k3``), 8 (ROS ``rational_polynomial``:
  ``... k4 k5 k6``), 12 or 14 coefficients.
- ``fisheye``: the equidistant model of ``cv2.fisheye`` (ROS ``equidistant``):
  a ray at angle ``theta`` from the optical axis lands at radius
  ``r = f theta_d``, ``theta_d = theta (1 + k1 theta^2 + k2 theta^4 + k3 theta^6 + k4 theta^8)``;
  4 coefficients. It images rays up to and beyond 90 deg, which a pinhole cannot.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np

from lampsam.arrays import FloatArray

DEFAULT_BODY_R_CAMERA = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
"""Upward camera, image top = robot forward (conventions.md)."""


def _frozen_array(a: Any, shape: tuple[int, ...], name: str) -> FloatArray:
    """A read-only float64 copy of ``a`` with the given shape, or ValueError."""
    arr = np.array(a, dtype=np.float64)
    if arr.shape != shape:
        raise ValueError(f"{name} must have shape {shape}, got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} must be finite")
    arr.setflags(write=False)
    return arr


CAMERA_MODELS = ("pinhole", "fisheye")
"""Lens models of :class:`CameraModel` (module docstring)."""

PINHOLE_DIST_SIZES = (4, 5, 8, 12, 14)
"""Numbers of OpenCV pinhole distortion coefficients accepted."""

_UNDISTORT_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-12)


@dataclass(frozen=True, eq=False)
class CameraModel:
    """Camera with an OpenCV lens model, mounted on the robot body.

    Attributes:
        width: image width, px (default 320).
        height: image height, px (default 240).
        fx: focal length along columns, px (default 92.376 = 120 deg horizontal field of view).
        fy: focal length along rows, px.
        cx: principal point column, px (OpenCV: origin at the centre of the top-left pixel).
        cy: principal point row, px.
        dist: OpenCV distortion coefficients: pinhole (4,), (5,) ``(k1, k2, p1, p2, k3)``,
            (8,), (12,) or (14,); fisheye (4,) ``(k1, k2, k3, k4)`` (default: five zeros,
            no distortion; a fisheye given no coefficients gets four zeros).
        body_t_camera: (3,) optical centre in the body frame, m; ``z`` is its height
            above the floor (default ``(0.1, 0, 0.3)``).
        body_R_camera: (3, 3) columns = camera ``x, y, z`` axes in body coordinates
            (default: optical axis up, image top = robot forward).
        model: ``"pinhole"`` (default) or ``"fisheye"`` (equidistant; module docstring).
    """

    width: int = 320
    height: int = 240
    fx: float = 160.0 / math.tan(math.radians(60.0))
    fy: float = 160.0 / math.tan(math.radians(60.0))
    cx: float = 159.5
    cy: float = 119.5
    dist: FloatArray = field(default_factory=lambda: np.zeros(5))
    body_t_camera: FloatArray = field(default_factory=lambda: np.array([0.1, 0.0, 0.3]))
    body_R_camera: FloatArray = field(default_factory=lambda: DEFAULT_BODY_R_CAMERA.copy())
    model: str = "pinhole"

    def __post_init__(self) -> None:
        """Validate and freeze the arrays (ValueError on bad values)."""
        if self.model not in CAMERA_MODELS:
            raise ValueError(f"model must be one of {CAMERA_MODELS}, got {self.model!r}")
        dist = np.array(self.dist, dtype=np.float64).ravel()
        if self.model == "fisheye" and dist.shape == (5,) and not np.any(dist):
            dist = np.zeros(4)  # the default: no distortion, in the fisheye's length
        sizes = (4,) if self.model == "fisheye" else PINHOLE_DIST_SIZES
        if len(dist) not in sizes:
            raise ValueError(
                f"dist of a {self.model} camera must have {' or '.join(map(str, sizes))} "
                f"coefficients, got {len(dist)}"
            )
        object.__setattr__(self, "dist", _frozen_array(dist, dist.shape, "dist"))
        object.__setattr__(
            self, "body_t_camera", _frozen_array(self.body_t_camera, (3,), "body_t_camera")
        )
        rot = _frozen_array(self.body_R_camera, (3, 3), "body_R_camera")
        if not np.allclose(rot.T @ rot, np.eye(3), atol=1e-6) or np.linalg.det(rot) < 0:
            raise ValueError("body_R_camera must be a rotation matrix")
        object.__setattr__(self, "body_R_camera", rot)
        if self.width <= 0 or self.height <= 0 or self.fx <= 0 or self.fy <= 0:
            raise ValueError("image size and focal lengths must be positive")

    @classmethod
    def from_fov(
        cls, width: int = 320, height: int = 240, hfov_deg: float = 120.0, **kwargs: Any
    ) -> CameraModel:
        """A camera with square pixels, centred principal point and the given horizontal FOV.

        Args:
            width: image width, px.
            height: image height, px.
            hfov_deg: horizontal field of view without distortion, degrees: of the
                pinhole (``f = (W/2) / tan(hfov/2)``) or of the equidistant fisheye
                (``f = (W/2) / (hfov/2)``, hfov may exceed 180 deg).
            **kwargs: other :class:`CameraModel` fields (``dist``, ``model``, ...).
        """
        half = math.radians(hfov_deg) / 2.0
        if kwargs.get("model", "pinhole") == "fisheye":
            f = (width / 2.0) / half
        else:
            f = (width / 2.0) / math.tan(half)
        return cls(
            width=width, height=height, fx=f, fy=f,
            cx=(width - 1) / 2.0, cy=(height - 1) / 2.0, **kwargs,
        )  # fmt: skip

    def K(self) -> FloatArray:  # noqa: N802 (the usual name of the intrinsic matrix)
        """The (3, 3) intrinsic matrix."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def z_cam(self) -> float:
        """Height of the optical centre above the floor, m."""
        return float(self.body_t_camera[2])

    @property
    def has_distortion(self) -> bool:
        """False only for a pinhole without distortion (pixels map linearly to rays)."""
        return self.model != "pinhole" or bool(np.any(self.dist))

    def undistort_points(self, px: FloatArray) -> FloatArray:
        """Undistorted camera rays ``(x_n, y_n)`` (z = 1) of pixels, with the camera's lens model.

        Pinhole: ``cv2.undistortPoints``; fisheye: ``cv2.fisheye.undistortPoints``.

        Args:
            px: (N, 2) pixels ``(col, row)``.

        Returns:
            (N, 2) normalised camera coordinates (camera frame, OpenCV axes); NaN rows
            for fisheye pixels whose ray is 90 deg or more off the optical axis (they
            have no ``z = 1`` point) or where the iteration does not converge.
        """
        pts = np.ascontiguousarray(np.asarray(px, dtype=np.float64).reshape(-1, 1, 2))
        if pts.shape[0] == 0:
            return np.zeros((0, 2))
        if not self.has_distortion:
            out = np.empty((pts.shape[0], 2))
            out[:, 0] = (pts[:, 0, 0] - self.cx) / self.fx
            out[:, 1] = (pts[:, 0, 1] - self.cy) / self.fy
            return out
        if self.model == "pinhole":
            und = cv2.undistortPoints(pts, self.K(), self.dist, criteria=_UNDISTORT_CRITERIA)
            return np.asarray(und, dtype=np.float64).reshape(-1, 2)
        und = cv2.fisheye.undistortPoints(
            pts, self.K(), self.dist.reshape(4, 1), criteria=_UNDISTORT_CRITERIA
        )
        rays = np.asarray(und, dtype=np.float64).reshape(-1, 2)
        # Check by re-projection: beyond 90 deg the equidistant inverse folds back and
        # non-converged points come back as large sentinels; both fail this test.
        back, ok = self.project_camera_points(np.column_stack([rays, np.ones(len(rays))]))
        bad = ~ok | ~np.all(np.abs(back - pts.reshape(-1, 2)) < 1e-3, axis=1)
        rays[bad] = np.nan
        return rays

    def camera_rays(self, px: FloatArray) -> FloatArray:
        """Same as :meth:`undistort_points` (the name the renderer and frontend use)."""
        return self.undistort_points(px)

    def project_camera_points(self, pc: FloatArray) -> tuple[FloatArray, np.ndarray]:
        """Pixels of points given in the camera frame, with the lens model.

        Args:
            pc: (N, 3) points in the camera frame (OpenCV axes), any scale.

        Returns:
            ``px`` (N, 2) pixels ``(col, row)`` and ``ok`` (N,) bool: the point is in
            front of the lens plane (``z > 0``). A fisheye also images rays beyond
            90 deg, but no ceiling coordinate ``m`` describes them, so they count as
            not imaged here.
        """
        pc = np.asarray(pc, dtype=np.float64).reshape(-1, 3)
        if len(pc) == 0:
            return np.zeros((0, 2)), np.zeros(0, dtype=bool)
        ok = pc[:, 2] > 1e-12
        obj = np.ascontiguousarray(pc.reshape(-1, 1, 3))
        if self.model == "pinhole":
            px, _ = cv2.projectPoints(obj, np.zeros(3), np.zeros(3), self.K(), self.dist)
        else:
            px, _ = cv2.fisheye.projectPoints(
                obj, np.zeros((3, 1)), np.zeros((3, 1)), self.K(), self.dist.reshape(4, 1)
            )
        return np.asarray(px, dtype=np.float64).reshape(-1, 2), ok

    def normalized_from_pixels(self, px: FloatArray) -> FloatArray:
        """Normalised ceiling coordinates ``m = (u, v)`` of pixels (conventions.md).

        Undistorts each pixel to the camera ray ``(x_n, y_n, 1)``, rotates it into
        body axes ``b = body_R_camera @ ray`` and returns ``(b_x / b_z, b_y / b_z)``:
        forward and left per metre of height above the camera.

        Args:
            px: (N, 2) pixels ``(col, row)``.

        Returns:
            (N, 2) ``(u, v)``; rows whose ray does not point upwards are NaN.
        """
        rays = self.camera_rays(px)
        cam = np.column_stack([rays, np.ones(len(rays))])
        body = cam @ self.body_R_camera.T
        with np.errstate(divide="ignore", invalid="ignore"):
            m = body[:, :2] / body[:, 2:3]
        m[body[:, 2] <= 1e-12] = np.nan
        return m

    def pixels_from_normalized(self, m: FloatArray) -> FloatArray:
        """Pixels of normalised ceiling coordinates (inverse of :meth:`normalized_from_pixels`).

        Args:
            m: (N, 2) ``(u, v)`` (body forward, left per metre of height).

        Returns:
            (N, 2) pixels ``(col, row)`` via :meth:`project_camera_points` (with distortion);
            rows whose ray is behind the camera are NaN.
        """
        m = np.asarray(m, dtype=np.float64).reshape(-1, 2)
        if len(m) == 0:
            return np.zeros((0, 2))
        body = np.column_stack([m, np.ones(len(m))])
        cam = body @ self.body_R_camera  # = (body_R_camera.T @ b.T).T
        px, ok = self.project_camera_points(cam)
        px[~ok] = np.nan
        return px

    def to_dict(self) -> dict[str, Any]:
        """Plain-Python mapping for YAML."""
        return {
            "width": int(self.width),
            "height": int(self.height),
            "fx": float(self.fx),
            "fy": float(self.fy),
            "cx": float(self.cx),
            "cy": float(self.cy),
            "dist": [float(x) for x in self.dist],
            "body_t_camera": [float(x) for x in self.body_t_camera],
            "body_R_camera": [[float(x) for x in row] for row in self.body_R_camera],
            "model": self.model,
        }
