"""The working resolution of a high-resolution photo, chosen from what the lamp detector must resolve.

The detector (paper 1, eqs. 1-7) separates two lamps only when the gap
between them spans pixels below the threshold ``k``: a gap of ``g`` m seen at
``d`` m by a camera of horizontal field of view ``F`` rad over ``W`` px spans
``g W / (F d)`` px, so resolving it with ``n`` px (``min_gap_px``, ~2: one
pixel below ``k`` whatever the sampling phase) needs

    ``W >= n F d / g``                                          (:func:`width_for_camera`)

(a 70 deg camera, ``g`` = 2 cm between two fittings' end caps: 293 px for a
robot's upward camera 2.4 m under the lamps, 733 px for lamps 6 m away in an
oblique photo). The distance is rarely known for a photo, but the lamps
themselves measure it: a fitting ``b`` m wide spans ``b W / (F d)`` px, so a
gap ``g = rho b`` spans ``n`` px once the lamp spans ``n / rho`` px. The rule
from the image (:func:`width_for_lamps`): detect at a coarse width first,
take the median short-axis width of the frame's lamps, and work at the width
that makes it ``min_gap_px / gap_to_width`` px (10 px for ``rho`` = 0.2, a
2 cm gap beside a 10 cm fitting), never below the coarse width nor above the
photo's. Gaps narrower than ``rho`` of the lamp width (connectors between LED
modules) are left to the second look, at ``look_factor`` (2) times the working
width or full resolution (:mod:`lampsam.frontend.second_look`), inside the
blobs that are long for the frame or cut by the border.

Pixel sizes of :class:`~lampsam.frontend.lamp_config.LampDetectorConfig` are
for 320 px wide frames; :func:`lamp_config_for_width` scales them.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, replace

import cv2
import numpy as np

from lampsam.arrays import ImageU8
from lampsam.frontend.ceiling_coords import PixelToCeiling
from lampsam.frontend.ceiling_grid import ceiling_grid
from lampsam.frontend.lamp_config import LampDetectorConfig
from lampsam.frontend.lamps import LampDetections, lamps_from_moments, measure_blobs
from lampsam.frontend.second_look import SQRT12, SecondLookConfig, second_look

REFERENCE_WIDTH = 320  # px: the width the detector's pixel settings are given for

# Narrowest photo the lamp detector is trusted on, px. Measured on the labelled ceiling
# photos reduced before detection (tests/data/ceiling_photo_labels.json; chosen on the two
# "tune" photos: fitting recall 0.94 at 320 px and 640 px, 0.89 at 200-240, 0.71 at 160,
# 0.42 at 64; the three "report" photos, held out: 1.0 down to 160, 0.95 at 128, 0.54 at
# 64; precision stayed 0.93-1.0 at every width). Narrower photos are read with a warning.
MIN_PHOTO_WIDTH = 200


def small_photo_warning(width: int, height: int) -> str | None:
    """The warning for a ``width`` x ``height`` px photo narrower than :data:`MIN_PHOTO_WIDTH`.

    Returns:
        The message (without the file name), or None when the photo is wide enough.
    """
    if width >= MIN_PHOTO_WIDTH:
        return None
    return (f"the photo is {width}x{height} px, narrower than the {MIN_PHOTO_WIDTH} px the "
            "lamp detector is checked down to: lamps are missed (on the labelled photos, "
            "fitting recall 0.94 at 320 px, 0.71 at 160, 0.42 at 64) and the counts are not "
            "reliable; use the camera's full-resolution image")


@dataclass(frozen=True)
class ResolutionPolicy:
    """How a photo larger than the robot's frames is processed.

    Attributes:
        width: working width, px, when ``auto`` is off (default 320).
        auto: choose the working width with :func:`width_for_lamps` from a
            first pass at ``coarse_width`` (default True).
        coarse_width: width of that first pass, px (default 320).
        min_gap_px: pixels the smallest gap must span (default 2).
        gap_to_width: the smallest gap between two fittings end to end as a
            fraction of a fitting's width (default 0.2).
        step_px: the working width is rounded up to a multiple of this (default 16).
        second_look: look again at full resolution inside the blobs long for
            their frame or cut by the border (default True;
            :mod:`lampsam.frontend.second_look`).
        look_factor: the second look is at this many times the working width,
            or at full resolution if less (default 2: a gap half the smallest
            the working width resolves, 0.1 of a lamp's width, spans 2 px; the
            detector's reach scales with the width, so the look's cost grows
            with about the cube of the factor).
        look: second-look settings.
    """

    width: int = REFERENCE_WIDTH
    auto: bool = True
    coarse_width: int = REFERENCE_WIDTH
    min_gap_px: float = 2.0
    gap_to_width: float = 0.2
    step_px: int = 16
    second_look: bool = True
    look_factor: float = 2.0
    look: SecondLookConfig = SecondLookConfig()


def lamp_config_for_width(
    config: LampDetectorConfig, width: int, scale_reach: bool = True
) -> LampDetectorConfig:
    """Scale the detector's pixel settings from 320 px wide frames to ``width`` (``s = width / 320``).

    The minimum area scales with ``s^2``; the blob's reach (``support_px``, the
    dilation that collects its blurred edge, and ``ring_px``, the background
    ring that the contrast and crowding tests read) with ``s``, so that both
    look at the same ceiling around a lamp at any width. ``thin_width_px``
    stays: it is about sampling (a blob 1-2 px wide at any width), not the ceiling.
    ``scale_reach=False`` scales the area only (the dilations' cost grows with
    the reach: a whole 12 Mpx photo takes ~1.7x the CPU with it scaled).
    """
    s = width / REFERENCE_WIDTH
    if abs(s - 1.0) < 1e-9:
        return config
    area = replace(config, min_area_px=max(int(round(config.min_area_px * s * s)), 1))
    if not scale_reach:
        return area
    return replace(
        area,
        support_px=max(int(round(config.support_px * s)), 1),
        ring_px=max(int(round(config.ring_px * s)), 1),
    )


def width_for_camera(fov_deg: float, range_m: float, gap_m: float, min_gap_px: float = 2.0) -> int:
    """Image width (px) at which a gap of ``gap_m`` seen at ``range_m`` spans ``min_gap_px``.

    ``W = n F d / g`` (module docstring), ``F`` the horizontal field of view in rad;
    small angles (``g << d``).
    """
    if fov_deg <= 0 or range_m <= 0 or gap_m <= 0 or min_gap_px <= 0:
        raise ValueError("width_for_camera: every argument must be positive")
    return math.ceil(min_gap_px * math.radians(fov_deg) * range_m / gap_m)


def width_for_lamps(
    lamp_widths_px: np.ndarray, coarse_width: int, full_width: int, policy: ResolutionPolicy
) -> int:
    """Working width making the frame's median lamp ``min_gap_px / gap_to_width`` px wide.

    Args:
        lamp_widths_px: shape (N,) short-axis widths ``sqrt(12) sigma2`` of the
            lamps found at ``coarse_width`` (border lamps left out), px.
        coarse_width: width of the image they were measured in, px.
        full_width: the photo's width, px (the largest width returned).
        policy: the rule's settings.

    Returns:
        The width, px, rounded up to ``step_px``, in ``[coarse_width, full_width]``;
        ``coarse_width`` when no lamp was found.
    """
    widths = np.asarray(lamp_widths_px, dtype=np.float64)
    widths = widths[np.isfinite(widths) & (widths > 0)]
    if widths.size == 0:
        return min(coarse_width, full_width)
    need = policy.min_gap_px / policy.gap_to_width  # lamp width, px
    w = coarse_width * need / float(np.median(widths))
    w = policy.step_px * math.ceil(w / policy.step_px)
    return int(min(max(w, coarse_width), full_width))


def resize_width(image: ImageU8, width: int) -> ImageU8:
    """The image resized to ``width`` px (height keeps the aspect ratio) with area averaging."""
    h, w = image.shape
    if width == w:
        return image
    size = (width, max(1, round(width * h / w)))
    return np.asarray(cv2.resize(image, size, interpolation=cv2.INTER_AREA), dtype=np.uint8)


def detect_photo_lamps(
    full: ImageU8,
    camera_for: Callable[[int, int], PixelToCeiling],
    config: LampDetectorConfig,
    policy: ResolutionPolicy | None = None,
) -> tuple[LampDetections, LampDetectorConfig]:
    """Lamps of a high-resolution photo at the working width the policy chooses.

    Args:
        full: shape (H, W) uint8 grey photo at full resolution.
        camera_for: the camera model for an image of ``(width, height)`` px.
        config: detector settings at 320 px (scaled here).
        policy: resolution policy (defaults if None).

    Returns:
        ``(detections in working-width pixels, the scaled settings used)``; the
        working size is ``detections.mask.shape``.
    """
    policy = policy or ResolutionPolicy()
    full_w = full.shape[1]
    width = min(policy.width, full_w)
    if policy.auto:
        cw = min(policy.coarse_width, full_w)
        coarse = resize_width(full, cw)
        moments, _, _, _ = measure_blobs(coarse, lamp_config_for_width(config, cw))
        widths = np.array([SQRT12 * m.sigma2 for m in moments if not m.touches_border])
        width = width_for_lamps(widths, cw, full_w, policy)
    img = resize_width(full, width)
    h = img.shape[0]
    cfg = lamp_config_for_width(config, width)
    camera = camera_for(width, h)
    moments, k, mask, n_rej = measure_blobs(img, cfg, ceiling_grid(camera))
    look_w = min(full_w, int(policy.look_factor * width))
    if policy.second_look and k is not None and look_w > width:
        fine = resize_width(full, look_w)
        moments, _ = second_look(
            fine, look_w / width, moments, mask, k, lamp_config_for_width(config, look_w), policy.look
        )
    return lamps_from_moments(moments, k, mask, n_rej, camera, cfg), cfg
