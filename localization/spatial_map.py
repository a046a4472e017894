"""The spatial feature map: SIFT keypoints with 3-D world positions (paper 2, sec. 2.3).

For each Kinect colour image, SIFT keypoints (``cv2.SIFT_create``) are detected;
each keypoint with a valid depth is back-projected to the camera frame
(``p = z ((u - cx)/fx, (v - cy)/fy, 1)``) and placed in the world with the
mapping pose. The map keeps, per point: the world position, the 128-D
descriptor, the keypoint's size (``r`` in the paper's Fig. 5(c)) and orientation
(``theta``), and how many frames saw it.

One physical point is seen in many frames. Duplicates are merged when they lie
within ``merge_radius`` of each other in 3-D *and* their descriptors are within
``merge_descriptor_dist`` (L2); connected groups become one map point with the
mean position and mean descriptor (:func:`merge_duplicates`).

On disk: ``spatial_features.npz`` with arrays ``xyz`` (N, 3) float64 world m,
``descriptors`` (N, 128) float32, ``size_px`` (N,), ``angle_deg`` (N,),
``n_obs`` (N,) int.
"""

from __future__ import annotations

import logging
import zipfile
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from numpy.typing import NDArray

from lampsam.arrays import FloatArray, ImageU8, ImageU16, IntArray
from lampsam.datasets.rgbd import RgbdCamera
from lampsam.errors import LocalizationError
from lampsam.localization.pointcloud import backproject_pixels, check_pose, transform_points
from lampsam.safe_io import atomic_path

log = logging.getLogger(__name__)

#: (N, 128) float32 SIFT descriptors (OpenCV's type).
DescriptorArray = NDArray[np.float32]

SPATIAL_FILE = "spatial_features.npz"


class SpatialMapError(LocalizationError):
    """A spatial feature map could not be built or read."""


@dataclass(frozen=True)
class SpatialMapConfig:
    """Feature extraction and duplicate merging.

    Attributes:
        n_features: SIFT's ``nfeatures`` per image (default 0 = all).
        contrast_threshold: SIFT's ``contrastThreshold`` (default 0.04, OpenCV's).
        merge_radius: 3-D distance within which two observations may be one point,
            metres (default 0.05).
        merge_descriptor_dist: L2 descriptor distance below which they are (default 250;
            OpenCV SIFT descriptors have norm 512).
        min_observations: drop merged points seen fewer times (default 1: keep all).
    """

    n_features: int = 0
    contrast_threshold: float = 0.04
    merge_radius: float = 0.05
    merge_descriptor_dist: float = 250.0
    min_observations: int = 1


@dataclass(frozen=True, eq=False)
class SpatialFeatureMap:
    """SIFT features with world positions.

    Attributes:
        xyz: (N, 3) world positions, metres.
        descriptors: (N, 128) float32 SIFT descriptors.
        size_px: (N,) keypoint diameter, pixels (mean over observations).
        angle_deg: (N,) keypoint orientation, degrees (OpenCV, of the first observation).
        n_obs: (N,) number of frames merged into each point.
    """

    xyz: FloatArray
    descriptors: DescriptorArray
    size_px: FloatArray
    angle_deg: FloatArray
    n_obs: IntArray

    def __len__(self) -> int:
        """Number of map points."""
        return int(len(self.xyz))

    def save(self, path: str | Path) -> Path:
        """Write ``.npz`` (module docstring); returns the path."""
        path = Path(path)
        with atomic_path(path) as tmp, open(tmp, "wb") as fh:
            np.savez_compressed(fh, xyz=self.xyz, descriptors=self.descriptors,
                                size_px=self.size_px, angle_deg=self.angle_deg, n_obs=self.n_obs)
        return path

    @classmethod
    def load(cls, path: str | Path) -> SpatialFeatureMap:
        """Read a map written by :meth:`save`.

        Raises:
            SpatialMapError: missing file or array, inconsistent lengths.
        """
        path = Path(path)
        if not path.is_file():
            raise SpatialMapError(f"{path}: spatial feature map not found")
        try:
            with np.load(path, allow_pickle=False) as data:
                out = cls(
                    np.asarray(data["xyz"], float),
                    np.asarray(data["descriptors"], np.float32),
                    np.asarray(data["size_px"], float),
                    np.asarray(data["angle_deg"], float),
                    np.asarray(data["n_obs"], np.int64),
                )
        except KeyError as exc:
            raise SpatialMapError(f"{path}: missing array {exc}") from exc
        except (OSError, ValueError, EOFError, zipfile.BadZipFile) as exc:
            raise SpatialMapError(f"{path}: unreadable, not a NumPy .npz archive (empty, cut "
                                  f"short or another file: {type(exc).__name__})") from exc
        n = len(out.xyz)
        if any(len(a) != n for a in (out.descriptors, out.size_px, out.angle_deg, out.n_obs)):
            raise SpatialMapError(f"{path}: arrays of different lengths")
        return out


@dataclass(frozen=True, eq=False)
class FrameFeatures:
    """SIFT features of one RGB-D frame with valid depth.

    Attributes:
        pixels: (K, 2) keypoint ``(col, row)``.
        camera_xyz: (K, 3) points in the camera frame, metres.
        descriptors: (K, 128) float32.
        size_px: (K,) keypoint diameters, pixels.
        angle_deg: (K,) orientations, degrees.
    """

    pixels: FloatArray
    camera_xyz: FloatArray
    descriptors: DescriptorArray
    size_px: FloatArray
    angle_deg: FloatArray


def make_sift(config: SpatialMapConfig = SpatialMapConfig()) -> cv2.SIFT:
    """An OpenCV SIFT detector for the config."""
    # SIFT_create is missing from OpenCV's type stubs
    return cv2.SIFT_create(  # type: ignore[attr-defined]
        nfeatures=config.n_features, contrastThreshold=config.contrast_threshold
    )


def frame_features(
    rgb: ImageU8, depth: ImageU16, camera: RgbdCamera, sift: cv2.SIFT
) -> FrameFeatures:
    """Detect SIFT keypoints and give each a 3-D camera-frame position from depth.

    Args:
        rgb: uint8 (H, W, 3) RGB (or (H, W) grey).
        depth: uint16 (H, W) (value / ``camera.depth_scale`` = metres).
        camera: the camera.
        sift: the detector (:func:`make_sift`).

    Returns:
        Features whose depth is valid (``backproject_pixels``).
    """
    grey = rgb if rgb.ndim == 2 else cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)
    kps, desc = sift.detectAndCompute(grey, None)
    if not kps:
        return FrameFeatures(
            np.zeros((0, 2)),
            np.zeros((0, 3)),
            np.zeros((0, 128), np.float32),
            np.zeros(0),
            np.zeros(0),
        )
    px = np.array([k.pt for k in kps], dtype=np.float64)
    pts, valid = backproject_pixels(depth, camera, px)
    return FrameFeatures(
        px[valid],
        pts[valid],
        np.asarray(desc, np.float32)[valid],
        np.array([k.size for k in kps])[valid],
        np.array([k.angle for k in kps])[valid],
    )


class SpatialMapBuilder:
    """Accumulates frames' features in the world frame; :meth:`finish` merges duplicates.

    Args:
        config: extraction and merging parameters.
    """

    def __init__(self, config: SpatialMapConfig = SpatialMapConfig()) -> None:
        self.config = config
        self.sift = make_sift(config)
        self._xyz: list[FloatArray] = []
        self._desc: list[DescriptorArray] = []
        self._size: list[FloatArray] = []
        self._angle: list[FloatArray] = []

    def add_frame(
        self, rgb: ImageU8, depth: ImageU16, camera: RgbdCamera, world_T_camera: FloatArray
    ) -> int:  # noqa: N803
        """Extract one frame's features and place them with the camera pose (4, 4).

        Returns:
            The number of features with depth added.
        """
        T = check_pose(world_T_camera)
        f = frame_features(rgb, depth, camera, self.sift)
        self.add_features(transform_points(T, f.camera_xyz), f.descriptors, f.size_px, f.angle_deg)
        return len(f.descriptors)

    def add_features(
        self,
        world_xyz: FloatArray,
        descriptors: DescriptorArray,
        size_px: FloatArray,
        angle_deg: FloatArray,
    ) -> None:
        """Add already placed features: (K, 3) world metres, (K, 128), (K,), (K,)."""
        self._xyz.append(np.asarray(world_xyz, float).reshape(-1, 3))
        self._desc.append(np.asarray(descriptors, np.float32).reshape(-1, 128))
        self._size.append(np.asarray(size_px, float).reshape(-1))
        self._angle.append(np.asarray(angle_deg, float).reshape(-1))

    def finish(self) -> SpatialFeatureMap:
        """Merge duplicates (:func:`merge_duplicates`) and return the map."""
        if not self._xyz:
            return SpatialFeatureMap(
                np.zeros((0, 3)),
                np.zeros((0, 128), np.float32),
                np.zeros(0),
                np.zeros(0),
                np.zeros(0, np.int64),
            )
        return merge_duplicates(
            np.concatenate(self._xyz),
            np.concatenate(self._desc),
            np.concatenate(self._size),
            np.concatenate(self._angle),
            self.config,
        )


def merge_duplicates(
    xyz: FloatArray,
    descriptors: DescriptorArray,
    size_px: FloatArray,
    angle_deg: FloatArray,
    config: SpatialMapConfig,
) -> SpatialFeatureMap:
    """Merge observations of one physical point.

    Two observations are linked when ``|x_i - x_j| < merge_radius`` and
    ``|d_i - d_j| < merge_descriptor_dist``; each connected component of the
    links becomes one map point (mean position, mean descriptor, mean size, the
    first orientation, ``n_obs`` = component size).

    Args:
        xyz: (N, 3) world positions, metres.
        descriptors: (N, 128) descriptors.
        size_px: (N,) sizes.
        angle_deg: (N,) orientations.
        config: thresholds.

    Returns:
        The merged map (points with ``n_obs < min_observations`` dropped).
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    n = len(xyz)
    pairs = cKDTree(xyz).query_pairs(config.merge_radius, output_type="ndarray")
    if len(pairs):
        dd = np.linalg.norm(descriptors[pairs[:, 0]] - descriptors[pairs[:, 1]], axis=1)
        pairs = pairs[dd < config.merge_descriptor_dist]
    graph = (
        coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
        if len(pairs)
        else coo_matrix((n, n))
    )
    n_comp, label = connected_components(graph, directed=False)
    counts = np.bincount(label, minlength=n_comp)

    # (n_comp, n) membership matrix: one sparse product sums each component
    member = coo_matrix((np.ones(n), (label, np.arange(n))), shape=(n_comp, n)).tocsr()

    def mean_by(values: np.ndarray) -> np.ndarray:
        flat = values.reshape(n, -1).astype(np.float64)
        out = np.asarray(member @ flat) / counts[:, None]
        return out.reshape((n_comp,) + values.shape[1:])

    first = np.full(n_comp, n, np.int64)
    np.minimum.at(first, label, np.arange(n))
    keep = counts >= config.min_observations
    merged = SpatialFeatureMap(
        mean_by(xyz)[keep],
        mean_by(descriptors.astype(np.float64)).astype(np.float32)[keep],
        mean_by(size_px)[keep],
        angle_deg[first][keep],
        counts[keep].astype(np.int64),
    )
    log.info(
        "spatial map: %d observations -> %d points (%d seen more than once)",
        n,
        len(merged),
        int((counts > 1).sum()),
    )
    return merged
