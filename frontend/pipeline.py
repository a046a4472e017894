"""The ceiling frontend: one grey image in, one :class:`CeilingFrame` out.

Bad images, decided once here:

* not a numpy array, empty, not 2-D (colour or extra channels), not ``uint8``,
  or not the camera's ``width x height`` -> :class:`lampsam.errors.FrontendError`
  naming the frame and what is wrong (these are bugs or the wrong camera);
* all black, all white, or flat (no grey-level contrast) -> an **empty frame**
  (no lamps, no corners) and a debug message: this happens on a real robot
  (lens cap, over-exposure) and the estimators just predict through it.
"""

from __future__ import annotations

import logging
from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np

from lampsam.arrays import ImageU8
from lampsam.datasets.tables import ImageIndex
from lampsam.errors import FrontendError
from lampsam.frontend.ceiling_coords import (
    PixelToCeiling,
    ceiling_jacobians,
    ceiling_shapes,
    to_observations,
)
from lampsam.frontend.ceiling_grid import ceiling_grid
from lampsam.frontend.corners import (
    CornerDetectorConfig,
    corner_observations,
    detect_corner_pixels,
    detect_corners,
)
from lampsam.frontend.lamp_config import LampDetectorConfig
from lampsam.frontend.lamp_models import within_size_gate
from lampsam.frontend.lamps import detect_lamps, measure_blobs
from lampsam.frontend.measurements import CeilingFrame, CornerObservation, LampObservation

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class FrontendConfig:
    """Settings of the ceiling frontend.

    Attributes:
        lamps: lamp detector settings.
        corners: corner detector settings.
        detect_corners: run the corner detector (default True).
        keep_border_lamps: keep lamps touching the image border in the frame,
            flagged ``touches_border`` (default False: they are dropped).
        min_contrast_grey: images whose grey levels span less than this are
            empty frames (default 8).
    """

    lamps: LampDetectorConfig = field(default_factory=LampDetectorConfig)
    corners: CornerDetectorConfig = field(default_factory=CornerDetectorConfig)
    detect_corners: bool = True
    keep_border_lamps: bool = False
    min_contrast_grey: float = 8.0


_DEFAULT_CONFIG = FrontendConfig()  # frozen: one shared instance (building one costs ~20 us)


def check_image(image: Any, camera: PixelToCeiling | None, where: str = "image") -> ImageU8:
    """Validate a grey ceiling image.

    Args:
        image: the candidate image.
        camera: its camera model (size check), or None to skip the size check.
        where: how to name the image in messages (e.g. ``"frame 12 (img/000012.png)"``).

    Returns:
        The same array, C-contiguous, shape (H, W) uint8.

    Raises:
        FrontendError: not an array, empty, not 2-D, not uint8, or the wrong size.
    """
    if not isinstance(image, np.ndarray):
        raise FrontendError(f"{where}: expected a numpy array, got {type(image).__name__}")
    if image.size == 0:
        raise FrontendError(f"{where}: empty image (shape {image.shape})")
    if image.ndim != 2:
        raise FrontendError(
            f"{where}: expected a grey image of shape (H, W), got shape {image.shape} "
            "(convert colour images with cv2.cvtColor(..., cv2.COLOR_BGR2GRAY))"
        )
    if image.dtype != np.uint8:
        raise FrontendError(f"{where}: expected dtype uint8, got {image.dtype}")
    if camera is not None and (image.shape[1], image.shape[0]) != (camera.width, camera.height):
        raise FrontendError(
            f"{where}: image is {image.shape[1]}x{image.shape[0]} but the camera model is "
            f"{camera.width}x{camera.height}"
        )
    return np.ascontiguousarray(image)


def process_image(
    image: Any,
    t: float,
    index: int,
    camera: PixelToCeiling,
    config: FrontendConfig | None = None,
) -> CeilingFrame:
    """Lamps and corners of one ceiling image (paper 1, sec. II).

    Args:
        image: shape (H, W) uint8 grey image of size ``camera.width x camera.height``.
        t: time stamp, s.
        index: image index in the run.
        camera: pixel -> normalised ceiling coordinates (``CameraModel``).
        config: frontend settings (defaults if None).

    Returns:
        The frame; empty for all-black, all-white or flat images.

    Raises:
        FrontendError: see :func:`check_image`.
    """
    config = config or _DEFAULT_CONFIG
    if (
        type(image) is np.ndarray
        and image.dtype == np.uint8
        and image.shape == (camera.height, camera.width)
        and image.flags.c_contiguous
    ):
        img = image  # already valid: skip building the error context
    else:
        img = check_image(image, camera, where=f"frame {index} (t={t:.3f} s)")
    lo, hi, _, _ = cv2.minMaxLoc(img)
    if hi - lo < config.min_contrast_grey:
        log.debug("frame %d: flat image (grey %d..%d): no detections", index, int(lo), int(hi))
        return CeilingFrame(t=float(t), index=int(index))
    if config.lamps.jacobian_step_px != config.corners.jacobian_step_px:
        det = detect_lamps(img, camera, config.lamps)
        all_lamps = det.lamps
        corners = (
            detect_corners(img, camera, det.mask, config.corners) if config.detect_corners else ()
        )
    else:
        all_lamps, corners = _lamps_and_corners(img, camera, config)
    lamps = (
        all_lamps
        if config.keep_border_lamps
        else tuple(lm for lm in all_lamps if not lm.touches_border)
    )
    return CeilingFrame(t=float(t), index=int(index), lamps=lamps, corners=corners)


def _lamps_and_corners(
    img: ImageU8, camera: PixelToCeiling, config: FrontendConfig
) -> tuple[tuple[LampObservation, ...], tuple[CornerObservation, ...]]:
    """Lamps (border ones included) and corners with one camera conversion for both.

    The same as :func:`detect_lamps` then :func:`detect_corners`, but the
    pixel -> ``m`` map and its Jacobians (:func:`ceiling_jacobians`) are
    evaluated once on the lamp centroids and corner pixels together (both
    configs must use the same Jacobian step).
    """
    moments, _, mask, _ = measure_blobs(img, config.lamps, ceiling_grid(camera))
    det = detect_corner_pixels(img, mask, config.corners) if config.detect_corners else None
    n_lamps = len(moments)
    px = np.zeros((0, 2))
    if n_lamps:
        px = np.array([mo.centroid for mo in moments])
    if det is not None and det.pixels.shape[0]:
        px = np.concatenate([px, det.pixels])
    if px.shape[0] == 0:
        return (), ()
    m, jac = ceiling_jacobians(camera, px, config.lamps.jacobian_step_px)
    jac_l = jac[:n_lamps]
    lamps: tuple[LampObservation, ...] = ()
    if n_lamps:
        shapes = ceiling_shapes(moments, m[:n_lamps], jac_l)
        if config.lamps.size_gate is not None:
            keep = within_size_gate(shapes, config.lamps.size_gate)
            moments = [mo for mo, ok in zip(moments, keep, strict=True) if ok]
            shapes, jac_l = shapes.select(keep), jac_l[keep]
        if moments:
            lamps = to_observations(moments, shapes, jac_l, config.lamps)
    corners: tuple[CornerObservation, ...] = ()
    if det is not None and det.pixels.shape[0]:
        corners = corner_observations(det, m[n_lamps:], jac[n_lamps:], config.corners)
    return lamps, corners


def iter_run(run: Any, config: FrontendConfig | None = None) -> Iterator[CeilingFrame]:
    """Process the images of a logged run one by one.

    Args:
        run: a ``lampsam.datasets.logrun.LoggedRun`` (``run.rig.camera``,
            ``run.images.t``, ``run.images.load(i)``).
        config: frontend settings.

    Yields:
        One :class:`CeilingFrame` per image, in time order.

    Raises:
        FrontendError: the run has no images, or an image is unusable (named by
            index and file).
    """
    camera = run.rig.camera
    images = run.images
    if images is None:
        raise FrontendError(f"{run.path}: the run has no ceiling images")
    for i in range(len(images.t)):
        yield process_indexed_image(images, i, camera, config)


def process_indexed_image(images: ImageIndex, i: int, camera: PixelToCeiling,
                          config: FrontendConfig | None = None) -> CeilingFrame:
    """Load image ``i`` of a run's image index and process it (:func:`process_image`,
    stamped ``images.t[i]``).

    Raises:
        FrontendError: the image is unusable, naming its file.
    """
    img = images.load(i)
    try:
        return process_image(img, float(images.t[i]), i, camera, config)
    except FrontendError as exc:
        raise FrontendError(f"{images.files[i]}: {exc}") from exc


def process_run(run: Any, config: FrontendConfig | None = None) -> list[CeilingFrame]:
    """All frames of a logged run (see :func:`iter_run`)."""
    return list(iter_run(run, config))
