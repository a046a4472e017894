"""KITTI odometry stereo sequence reader (rectified grey pairs, calib.txt, poses.txt).

Layout (as in the shared folder ``kitti_stereo_seq1``)::

    calib.txt        one 3x4 projection matrix per line (12 numbers, optional "P0:" label);
                     line 1 = left camera, line 2 = right camera
    poses.txt        one 3x4 [R | t] per frame: the left camera in the frame of the
                     left camera at frame 0 (KITTI camera axes: x right, y down, z forward)
    image_l/*.png    left images, sorted by name
    image_r/*.png    right images, same names

Planar mapping to the stereo two-point frame (docs/stereo.md): the rig origin is
the midpoint of the two optical centres (left centre + B/2 along camera x);
paper ``x`` = KITTI ``z`` (forward), paper ``y`` = -KITTI ``x`` (left), heading
``theta`` = rotation about the up axis (-KITTI ``y``), counter-clockwise positive:
``theta = atan2(-R[0, 2], R[2, 2])`` of the camera's rotation.
"""

from __future__ import annotations

import logging
import math
import re
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from lampsam.arrays import FloatArray, ImageU8
from lampsam.datasets.stereo_types import StereoRig
from lampsam.datasets.textio import open_text
from lampsam.errors import DatasetError

log = logging.getLogger(__name__)


class KittiError(DatasetError):
    """A KITTI sequence folder is missing a file or holds a malformed one."""


def _read_matrices(path: Path, expect: int | None = None) -> FloatArray:
    """Lines of 12 numbers (optionally ``label:`` first) -> (N, 3, 4)."""
    mats = []
    with open_text(path) as fh:
        for i, line in enumerate(fh, start=1):
            s = line.strip()
            if not s:
                continue
            s = re.sub(r"^[A-Za-z_][A-Za-z0-9_]*:\s*", "", s)
            parts = s.split()
            if len(parts) != 12:
                raise KittiError(f"expected 12 numbers, got {len(parts)}", path, i)
            try:
                vals = np.array([float(p) for p in parts])
            except ValueError as exc:
                raise KittiError(f"not a number: {exc}", path, i) from exc
            if not np.all(np.isfinite(vals)):
                raise KittiError("non-finite value", path, i)
            mats.append(vals.reshape(3, 4))
    if not mats:
        raise KittiError("no matrices", path)
    if expect is not None and len(mats) < expect:
        raise KittiError(f"expected at least {expect} matrices, got {len(mats)}", path)
    return np.array(mats)


@dataclass(frozen=True)
class KittiStereoSequence:
    """A rectified KITTI stereo sequence.

    Attributes:
        path: the sequence folder.
        P_left, P_right: (3, 4) projection matrices, px.
        poses: (N, 3, 4) left-camera poses ``[R | t]`` in the frame-0 left camera, m.
        left_files, right_files: N image paths each.
        width, height: image size, px (from the first left image).
    """

    path: Path
    P_left: FloatArray
    P_right: FloatArray
    poses: FloatArray
    left_files: tuple[Path, ...]
    right_files: tuple[Path, ...]
    width: int
    height: int

    def __len__(self) -> int:
        return len(self.left_files)

    @property
    def fx(self) -> float:
        """Focal length, px (``f / p`` of eq. 2)."""
        return float(self.P_left[0, 0])

    @property
    def cx(self) -> float:
        """Principal point column, px."""
        return float(self.P_left[0, 2])

    @property
    def baseline(self) -> float:
        """Stereo baseline ``B``, m: ``-(P_right[0, 3] - P_left[0, 3]) / fx``."""
        return float(-(self.P_right[0, 3] - self.P_left[0, 3]) / self.fx)

    def stereo_rig(self) -> StereoRig:
        """The calibrated pair as a :class:`StereoRig` (baseline, ``fx`` and width in px)."""
        return StereoRig.from_pixels(baseline=self.baseline, f_px=self.fx, width_px=self.width)

    def load_pair(self, i: int) -> tuple[ImageU8, ImageU8]:
        """Left and right grey images of frame ``i``, uint8 (H, W) each.

        Raises:
            KittiError: unreadable image or a size differing from the first frame.
        """
        out = []
        for f in (self.left_files[i], self.right_files[i]):
            img = cv2.imread(str(f), cv2.IMREAD_GRAYSCALE)
            if img is None:
                raise KittiError("cannot read image", f)
            if img.shape != (self.height, self.width):
                raise KittiError(f"image size {img.shape[::-1]} differs from "
                                 f"{(self.width, self.height)}", f)
            out.append(np.asarray(img, dtype=np.uint8))
        return out[0], out[1]

    def planar_rig_poses(self) -> FloatArray:
        """(N, 3) rig (mid-baseline) poses ``(x, y, theta)`` in the paper frame of frame 0.

        See the module docstring for the axis mapping.
        """
        half = np.array([0.5 * self.baseline, 0.0, 0.0])
        r0, t0 = self.poses[0, :, :3], self.poses[0, :, 3]
        mid0 = t0 + r0 @ half
        out = np.zeros((len(self.poses), 3))
        for k, m in enumerate(self.poses):
            r, t = r0.T @ m[:, :3], r0.T @ (m[:, 3] + m[:, :3] @ half - mid0)
            out[k] = (t[2], -t[0], math.atan2(-r[0, 2], r[2, 2]))
        return out


def read_kitti_sequence(path: Path) -> KittiStereoSequence:
    """Read a sequence folder (layout in the module docstring).

    Raises:
        KittiError: missing folder/file, malformed calibration or pose line (file
            and line named), left/right image lists that differ, pose count not
            matching the image count, non-rectified calibration.
    """
    path = Path(path)
    if not path.is_dir():
        raise KittiError("sequence folder not found", path)
    calib = _read_matrices(path / "calib.txt", expect=2)
    p_left, p_right = calib[0], calib[1]
    if not np.allclose(p_left[:, :3], p_right[:, :3]) or p_right[0, 3] >= p_left[0, 3]:
        raise KittiError("left/right projection matrices are not a rectified pair "
                         "(same K, right camera to the right)", path / "calib.txt")
    poses = _read_matrices(path / "poses.txt")
    left = tuple(sorted((path / "image_l").glob("*.png")))
    right = tuple(sorted((path / "image_r").glob("*.png")))
    if not left:
        raise KittiError("no left images (image_l/*.png)", path)
    if [f.name for f in left] != [f.name for f in right]:
        raise KittiError("left and right image names differ", path / "image_r")
    if len(poses) != len(left):
        raise KittiError(f"{len(poses)} poses for {len(left)} image pairs", path / "poses.txt")
    first = cv2.imread(str(left[0]), cv2.IMREAD_GRAYSCALE)
    if first is None:
        raise KittiError("cannot read image", left[0])
    h, w = first.shape
    log.info("KITTI sequence %s: %d pairs %dx%d", path, len(left), w, h)
    return KittiStereoSequence(path, p_left, p_right, poses, left, right, w, h)
