"""KITTI odometry stereo sequence reader (rectified grey pairs, calib.txt, poses.txt).

Layout (as in the shared folder ``kitti_stereo_seq1``)::

    calib.txt        one 3x4 projection matrix per line (12 numbers, optional "P0:" label);
                     unlabelled: line 1 = left camera, line 2 = right camera; labelled
                     as the KITTI odometry benchmark's (P0..P3, Tr): P0/P1 for grey
                     images, P2/P3 for colour ones; or, instead of calib.txt, the KITTI
                     raw ``calib_cam_to_cam.txt`` (P_rect_00/01 grey, P_rect_02/03
                     colour; S_rect_xx, the rectified size, checked against the images)
    poses.txt        one 3x4 [R | t] per frame: the left camera in the frame of the
                     left camera at frame 0 (KITTI camera axes: x right, y down, z forward);
                     in the benchmark's own layout (dataset/sequences/NN/) the ground truth
                     dataset/poses/NN.txt is found without copying
    image_l/*.png    left images, sorted by name (or the KITTI odometry benchmark's
    image_r/*.png    image_0/image_1 grey, image_2/image_3 colour); right images, same names

A calibration whose principal point lies outside the middle half of the images (made for
another image size) is warned about: the answer would be wrong without a word.

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


# calib_cam_to_cam.txt keys that are not 3x4 matrices (skipped by name)
_RAW_OTHER = re.compile(r"^(calib_time|corner_dist|[SKDRT]_\d\d|[SR]_rect_\d\d)$")


def _read_matrices(path: Path, expect: int | None = None,
                   labels: list[str] | None = None) -> FloatArray:
    """Lines of 12 numbers (optionally ``label:`` first) -> (N, 3, 4).

    When ``labels`` is a list, each matrix's label (``""`` when none) is appended to it;
    the KITTI raw calibration's other keys (``calib_time``, ``S_00``, ``K_00``, ...) are
    skipped.
    """
    mats = []
    with open_text(path) as fh:
        for i, line in enumerate(fh, start=1):
            s = line.strip()
            if not s:
                continue
            m = re.match(r"^([A-Za-z_][A-Za-z0-9_]*):\s*", s)
            label = m.group(1) if m else ""
            if _RAW_OTHER.match(label):
                continue
            s = s[m.end():] if m else s
            if labels is not None:
                labels.append(label)
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
    calib_path = path / "calib.txt"
    if not calib_path.is_file() and (path / "calib_cam_to_cam.txt").is_file():
        calib_path = path / "calib_cam_to_cam.txt"
    labels: list[str] = []
    calib = _read_matrices(calib_path, expect=2, labels=labels)
    left_dir, right_dir = _image_folders(path)
    left = tuple(sorted(left_dir.glob("*.png")))
    right = tuple(sorted(right_dir.glob("*.png")))
    if not left:
        raise KittiError(f"no left images ({left_dir.name}/*.png)", path)
    names_l, names_r = {f.name for f in left}, {f.name for f in right}
    if names_l != names_r:
        only_l, only_r = sorted(names_l - names_r), sorted(names_r - names_l)
        what = (f"{len(only_l)} left images have no right image (first {only_l[0]})" if only_l
                else f"{len(only_r)} right images have no left image (first {only_r[0]})")
        raise KittiError(f"left and right image names differ: {what}", right_dir)
    first = cv2.imread(str(left[0]), cv2.IMREAD_UNCHANGED)
    if first is None:
        raise KittiError("cannot read image", left[0])
    h, w = first.shape[:2]
    colour = first.ndim == 3 and not (np.array_equal(first[..., 0], first[..., 1])
                                      and np.array_equal(first[..., 1], first[..., 2]))
    p_left, p_right = _pair(calib_path, calib, labels, left_dir.name, colour, (w, h))
    if not np.allclose(p_left[:, :3], p_right[:, :3]) or p_right[0, 3] >= p_left[0, 3]:
        raise KittiError("left/right projection matrices are not a rectified pair "
                         "(same K, right camera to the right)", calib_path)
    cx, cy = p_left[0, 2], p_left[1, 2]
    if abs(cx - w / 2) > w / 4 or abs(cy - h / 2) > h / 4:
        log.warning("%s: the principal point (%.1f, %.1f) px lies outside the middle half of "
                    "the %dx%d images: a calibration for another image size (another "
                    "sequence, or images resized)? The poses will be wrong", calib_path, cx, cy,
                    w, h)
    pose_path = _pose_file(path)
    poses = _read_matrices(pose_path)
    if len(poses) != len(left):
        raise KittiError(f"{len(poses)} poses for {len(left)} image pairs", pose_path)
    log.info("KITTI sequence %s: %d pairs %dx%d", path, len(left), w, h)
    return KittiStereoSequence(path, p_left, p_right, poses, left, right, w, h)


def _pose_file(path: Path) -> Path:
    """``poses.txt`` in the folder, else the odometry benchmark's ``../../poses/NN.txt``.

    The benchmark keeps the ground truth apart (``dataset/sequences/NN/`` and
    ``dataset/poses/NN.txt``), and only for sequences 00-10.
    """
    own = path / "poses.txt"
    if own.exists():
        return own
    shared = path.parent.parent / "poses" / f"{path.name}.txt"
    if path.parent.name == "sequences" and shared.is_file():
        log.info("%s: ground truth from %s", path, shared)
        return shared
    raise KittiError("no poses.txt: the check scores against ground-truth poses (the odometry "
                     "benchmark has them for sequences 00-10 only, as dataset/poses/NN.txt; "
                     "copy it here as poses.txt)", own)


def _image_folders(path: Path) -> tuple[Path, Path]:
    """The left and right image folders: image_l/image_r, image_0/image_1 or image_2/image_3."""
    for left, right in (("image_l", "image_r"), ("image_0", "image_1"), ("image_2", "image_3")):
        if (path / left).is_dir():
            return path / left, path / right
    raise KittiError("no left images (image_l/*.png, or the KITTI odometry benchmark's "
                     "image_0/ or image_2/)", path)


def _pair(calib_path: Path, calib: FloatArray, labels: list[str], left_dir: str, colour: bool,
          size: tuple[int, int]) -> tuple[FloatArray, FloatArray]:
    """The pair's (3, 4) projection matrices among the calibration's (module docstring)."""
    cams = "23" if left_dir == "image_2" or (left_dir == "image_l" and colour) else "01"
    for lbl in (f"P{cams[0]}", f"P_rect_0{cams[0]}"):
        right = lbl[:-1] + cams[1]
        if lbl in labels and right in labels:
            _check_rect_size(calib_path, f"S_rect_0{cams[0]}", size)
            if cams == "23" and left_dir == "image_l":
                log.info("%s: colour images: the colour cameras' %s/%s used", calib_path, lbl,
                         right)
            return calib[labels.index(lbl)], calib[labels.index(right)]
    if any(labels) and cams == "23":
        raise KittiError(f"colour images ({left_dir}) need the colour cameras' P2/P3 (or "
                         f"P_rect_02/03); found {', '.join(lb for lb in labels if lb)}",
                         calib_path)
    return calib[0], calib[1]


def _check_rect_size(calib_path: Path, key: str, size: tuple[int, int]) -> None:
    """Refuse images whose size differs from the raw calibration's ``S_rect_xx``."""
    if calib_path.name != "calib_cam_to_cam.txt":
        return
    with open_text(calib_path) as fh:
        for i, line in enumerate(fh, start=1):
            if line.startswith(key + ":"):
                try:
                    w, h = (round(float(v)) for v in line.split(":", 1)[1].split())
                except ValueError as exc:
                    raise KittiError(f"{key}: expected 'width height'", calib_path, i) from exc
                if (w, h) != size:
                    raise KittiError(f"{key} is {w}x{h} but the images are {size[0]}x{size[1]}",
                                     calib_path, i)
