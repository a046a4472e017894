"""The lamp detector on ceilings of other buildings: a bright window in view, a small camera.

docs/photo-labels.md, last section. Synthetic images, seeded; each test fails with
the rule before (``light_share=None``, ``thin_min_length_px=0``).
"""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np

from lampsam.frontend.lamp_config import DEFAULT_CONFIG, LampDetectorConfig
from lampsam.frontend.lamps import measure_blobs
from lampsam.frontend.threshold import auto_threshold

OLD_THRESHOLD = dataclasses.replace(DEFAULT_CONFIG, light_share=None)
OLD_THIN = dataclasses.replace(DEFAULT_CONFIG, thin_min_length_px=0.0)


def ceiling_with_window(
    rng: np.random.Generator, sky: bool = False
) -> tuple[np.ndarray, list[tuple[int, int]]]:
    """320x240 ceiling (grey 120, noise 3) with six unclipped tubes (levels 242-254; noise keeps them below 255) and a
    saturated 3x2-pane window with bars covering ~9 % of the frame (``sky``: panes 240-254
    with a gradient, never clipped); returns the tube centres."""
    img = np.full((240, 320), 120.0)
    centres = []
    for i, level in enumerate((242, 246, 249, 251, 253, 254)):
        cx, cy = 30 + 45 * i, 200
        cv2.rectangle(img, (cx - 16, cy - 4), (cx + 16, cy + 4), float(level), -1)
        centres.append((cx, cy))
    x0, y0, ww, wh = 100, 20, 120, 62  # 7440 px = 9.7 % of the frame
    img[y0:y0 + wh, x0:x0 + ww] = np.linspace(254.0, 241.0, wh)[:, None] if sky else 255.0
    for x in np.linspace(x0, x0 + ww - 3, 4).round().astype(int):
        img[y0:y0 + wh, x:x + 3] = 70.0
    for y in np.linspace(y0, y0 + wh - 3, 3).round().astype(int):
        img[y:y + 3, x0:x0 + ww] = 70.0
    noisy = np.where(img < 255, np.clip(img + rng.normal(0.0, 3.0, img.shape), 0, 254), 255)
    if sky:
        noisy[y0:y0 + wh, x0:x0 + ww] = np.minimum(noisy[y0:y0 + wh, x0:x0 + ww], 254)
    return noisy.astype(np.uint8), centres


def found(moments: list, centres: list[tuple[int, int]], tol: float = 2.0) -> int:
    """How many of ``centres`` have a detected blob centroid within ``tol`` px."""
    cen = np.array([m.centroid for m in moments]).reshape(-1, 2)
    return sum(bool(len(cen)) and float(np.min(np.hypot(*(cen - c).T))) < tol for c in centres)


def test_saturated_window_does_not_lift_the_threshold_above_the_tubes() -> None:
    img, _ = ceiling_with_window(np.random.default_rng(0))
    k_old = auto_threshold(img, OLD_THRESHOLD)
    k_new = auto_threshold(img, DEFAULT_CONFIG)
    assert k_old is not None and k_old > 245  # the failure: most tubes below k
    assert k_new is not None and 130 < k_new < 230  # above the ceiling, below every tube


def test_tubes_beside_a_saturated_window_are_all_found() -> None:
    img, centres = ceiling_with_window(np.random.default_rng(1))
    old, _, _, _ = measure_blobs(img, OLD_THRESHOLD)
    new, _, _, _ = measure_blobs(img, DEFAULT_CONFIG)
    assert found(old, centres) <= 3
    assert found(new, centres) == len(centres)


def test_unclipped_sky_window_does_not_lift_the_threshold_either() -> None:
    img, centres = ceiling_with_window(np.random.default_rng(5), sky=True)
    assert int(img.max()) == 254  # nothing clipped: the share counts light-level pixels
    k_old = auto_threshold(img, OLD_THRESHOLD)
    k_new = auto_threshold(img, DEFAULT_CONFIG)
    assert k_old is not None and k_old > 240
    assert k_new is not None and 130 < k_new < 230
    assert found(measure_blobs(img, DEFAULT_CONFIG)[0], centres) == len(centres)


def test_frames_without_a_bright_majority_keep_their_threshold() -> None:
    """A noisy bright frame whose upper classes are never mostly at the peak's level: the old rule."""
    rng = np.random.default_rng(2)
    img = np.clip(rng.normal(150, 40, (120, 160)), 0, 255).astype(np.uint8)
    assert auto_threshold(img, DEFAULT_CONFIG) == auto_threshold(img, OLD_THRESHOLD)


# Frame 28 of a 160x120 `lab` run (seed 0), 9x9 px around the white disc (grey 235,
# 14 cm across at 2.4 m: 2.7 px) that passed as a lamp; a tile line crosses row 4.
DISC_PATCH = np.array([
    [172, 172, 176, 177, 173, 176, 171, 163, 170],
    [173, 178, 172, 177, 172, 171, 175, 161, 166],
    [178, 175, 173, 177, 173, 174, 178, 166, 171],
    [175, 172, 176, 212, 221, 180, 174, 161, 168],
    [155, 157, 173, 238, 231, 188, 157, 149, 152],
    [176, 176, 175, 217, 219, 182, 173, 166, 170],
    [177, 173, 175, 175, 172, 175, 174, 162, 168],
    [174, 177, 174, 176, 173, 174, 178, 164, 167],
    [174, 175, 175, 174, 172, 173, 177, 158, 168],
], dtype=np.uint8)


def small_frame(rng: np.random.Generator, disc_gain: float = 0.0) -> np.ndarray:
    """160x120 frame: ceiling 175 (noise 2; grey 65 left of column 90), a saturated lamp (12x6 px) and the disc patch
    at (106..114, 66..74); ``disc_gain`` grey added to the disc's pixels above 200."""
    img = np.clip(rng.normal(175.0, 2.0, (120, 160)), 0, 255)
    img[:, :90] -= 110.0  # dark beyond the ceiling's edge: the run's frame has median 65
    img[50:56, 100:112] = 255.0
    patch = DISC_PATCH.astype(np.float64)
    patch[patch > 200] += disc_gain
    img[66:75, 106:115] = np.clip(patch, 0, 255)
    return img.astype(np.uint8)


def near_disc(moments: list) -> bool:
    """A blob centred on the disc (column 110.5, row 70)."""
    return any(abs(m.centroid[0] - 110.5) < 2 and abs(m.centroid[1] - 70) < 2 for m in moments)


K_FRAME = 210  # the automatic threshold of that frame


def test_small_white_disc_is_not_a_lamp_in_a_small_frame() -> None:
    img = small_frame(np.random.default_rng(3))
    old = dataclasses.replace(OLD_THIN, threshold=K_FRAME)
    new = dataclasses.replace(DEFAULT_CONFIG, threshold=K_FRAME)
    assert near_disc(measure_blobs(img, old)[0])  # the failure: judged as a thin line
    assert not near_disc(measure_blobs(img, new)[0])


def test_small_light_source_is_still_a_lamp() -> None:
    """The same disc with its centre saturating (a light source) is kept, and so is the lamp."""
    img = small_frame(np.random.default_rng(4), disc_gain=40.0)
    moments, _, _, _ = measure_blobs(img, dataclasses.replace(DEFAULT_CONFIG, threshold=K_FRAME))
    assert near_disc(moments)
    assert found(moments, [(105.5, 52.5)], tol=1.0) == 1


def test_dim_thin_line_keeps_the_line_margin() -> None:
    """A thin line (a lamp seen edge-on, 2 px wide, 14 px long) 20 below the peak is kept."""
    img = np.full((120, 160), 175.0)
    img[50:56, 40:52] = 255.0
    img[80:82, 60:74] = 235.0
    img = np.clip(img + np.random.default_rng(5).normal(0, 2.0, img.shape), 0, 255).astype(np.uint8)
    moments, _, _, _ = measure_blobs(img, LampDetectorConfig())
    assert found(moments, [(66, 80)], tol=1.5) == 1
