"""The working-resolution rule and the full-resolution second look (issue 20; docs/photo-labels.md)."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from lampsam.datasets.logrun import CameraModel
from lampsam.frontend.lamp_config import DEFAULT_CONFIG
from lampsam.frontend.lamps import measure_blobs
from lampsam.frontend.resolution import (
    ResolutionPolicy,
    detect_photo_lamps,
    lamp_config_for_width,
    resize_width,
    width_for_camera,
    width_for_lamps,
)
from lampsam.frontend.second_look import (
    SQRT12,
    SecondLookConfig,
    long_blobs,
    scale_moments,
    second_look,
)

FULL = (1600, 1200)  # full-resolution photo, px
COARSE = 320  # f = 5


def _photo(
    rng: np.random.Generator, seam_grey: float | None, gap_px: int, lengths: tuple[int, int] = (360, 360)
) -> np.ndarray:
    """A ceiling photo: two short lamps and one long row of two modules end to end.

    The row's modules are ``lengths`` x 40 px along +x from x = 400 at y = 800,
    separated by ``gap_px`` px of ceiling (``seam_grey`` None) or of a lit seam
    at ``seam_grey``. Slight blur (the lens), grey noise sigma 2.
    """
    w, h = FULL
    img = np.full((h, w), 120.0)
    img[300:340, 300:500] = 250.0  # short lamps, 200 x 40 px
    img[300:340, 1000:1200] = 250.0
    a, b = lengths
    img[780:820, 400 : 400 + a] = 250.0
    img[780:820, 400 + a + gap_px : 400 + a + gap_px + b] = 250.0
    if seam_grey is not None:
        img[780:820, 400 + a : 400 + a + gap_px] = seam_grey
    img = cv2.GaussianBlur(img, (0, 0), 1.0)
    img += rng.normal(0.0, 2.0, img.shape)
    return np.clip(np.rint(img), 0, 255).astype(np.uint8)


def _coarse(full: np.ndarray) -> tuple[list, float, np.ndarray]:
    img = resize_width(full, COARSE)
    moments, k, mask, _ = measure_blobs(img, lamp_config_for_width(DEFAULT_CONFIG, COARSE))
    assert k is not None
    return moments, k, mask


def test_two_lamps_end_to_end_merge_coarse_and_split_at_full_resolution() -> None:
    full = _photo(np.random.default_rng(1), None, gap_px=2)
    moments, k, mask = _coarse(full)
    assert len(moments) == 3  # the 2 px gap is 0.4 of a coarse px: the row is one blob
    idx, med = long_blobs(moments, 2.0)
    assert len(idx) == 1 and med == pytest.approx(40.0, rel=0.05)  # 200 px / 5
    out, n_split = second_look(
        full, 5.0, moments, mask, k, lamp_config_for_width(DEFAULT_CONFIG, FULL[0])
    )
    assert n_split == 1 and len(out) == 4
    row = sorted((m for m in out if abs(m.centroid[1] - 159.5) < 1.0), key=lambda m: m.centroid[0])
    assert len(row) == 2
    # truth: module centres at full-resolution x = 579.5 and 941.5, y = 799.5 (pixel centres),
    # coarse x = (x + 0.5) / 5 - 0.5
    for m, x_full in zip(row, (579.5, 941.5), strict=True):
        assert m.centroid[0] == pytest.approx((x_full + 0.5) / 5 - 0.5, abs=0.15)
        assert m.centroid[1] == pytest.approx(159.5, abs=0.15)
        assert SQRT12 * m.sigma1 == pytest.approx(72.0, rel=0.05)  # 360 px / 5
        assert not m.touches_border


def test_two_module_fitting_with_a_lit_seam_is_not_split() -> None:
    full = _photo(np.random.default_rng(2), seam_grey=215.0, gap_px=2)
    moments, k, mask = _coarse(full)
    assert k < 215.0 - 20  # the seam stays above the threshold at full resolution
    out, n_split = second_look(
        full, 5.0, moments, mask, k, lamp_config_for_width(DEFAULT_CONFIG, FULL[0])
    )
    assert n_split == 0 and out == moments


def test_a_lamp_fragment_does_not_split_a_blob() -> None:
    """A piece shorter than half the frame's median lamp is not a lamp of its own."""
    full = _photo(np.random.default_rng(3), None, gap_px=2, lengths=(560, 90))  # 18 px at 320
    moments, k, mask = _coarse(full)
    fine_cfg = lamp_config_for_width(DEFAULT_CONFIG, FULL[0])
    assert len(moments) == 3 and len(long_blobs(moments, 2.0)[0]) == 1
    out, n_split = second_look(full, 5.0, moments, mask, k, fine_cfg)
    assert n_split == 0 and out == moments
    # the stub is a blob at full resolution that passes the lamp tests: only its length stops it
    _, n_any = second_look(full, 5.0, moments, mask, k, fine_cfg, SecondLookConfig(min_part_ratio=0.0))
    assert n_any == 1


def test_scaled_moments_match_the_coarse_measurement() -> None:
    """A blob measured at full resolution and scaled by 1/5 agrees with the coarse image's own."""
    full = _photo(np.random.default_rng(4), None, gap_px=2)
    fine, _, _, _ = measure_blobs(full, lamp_config_for_width(DEFAULT_CONFIG, FULL[0]))
    coarse, _, _ = _coarse(full)
    a = min(fine, key=lambda m: m.centroid[0] + m.centroid[1])  # the short lamp at (400, 320)
    b = min(coarse, key=lambda m: m.centroid[0] + m.centroid[1])
    s = scale_moments(a, 5.0, False)
    assert np.allclose(s.centroid, b.centroid, atol=0.05)
    assert s.sigma1 == pytest.approx(b.sigma1, rel=0.02)
    assert s.sigma2 == pytest.approx(b.sigma2, rel=0.1)  # 8 px wide at 320: the edges' blur matters
    assert s.theta == pytest.approx(a.theta)


def test_width_rules() -> None:
    # the camera form: W = n F d / g
    assert width_for_camera(70.0, 6.0, 0.02) == math.ceil(2 * math.radians(70) * 6 / 0.02) == 734
    assert width_for_camera(70.0, 2.4, 0.02) == 294  # the robot's upward camera: 320 px suffice
    with pytest.raises(ValueError):
        width_for_camera(70.0, 0.0, 0.02)
    # the image form: the median lamp must be min_gap_px / gap_to_width = 10 px wide
    p = ResolutionPolicy()
    assert width_for_lamps(np.array([4.0, 5.0, 9.0]), 320, 4000, p) == 640
    assert width_for_lamps(np.array([4.4]), 320, 4000, p) == 736  # 727.3 rounded up to 16
    assert width_for_lamps(np.array([20.0]), 320, 4000, p) == 320  # never below the first pass
    assert width_for_lamps(np.array([0.5]), 320, 4000, p) == 4000  # nor above the photo
    assert width_for_lamps(np.array([]), 320, 4000, p) == 320
    # the detector's pixel settings at 640 px: area x4, reach x2 (or area only)
    c = lamp_config_for_width(DEFAULT_CONFIG, 640)
    assert (c.min_area_px, c.support_px, c.ring_px) == (24, 4, 6)
    c = lamp_config_for_width(DEFAULT_CONFIG, 640, scale_reach=False)
    assert (c.min_area_px, c.support_px, c.ring_px) == (24, 2, 3)
    assert lamp_config_for_width(DEFAULT_CONFIG, 320) is DEFAULT_CONFIG


def test_detect_photo_lamps_policy_end_to_end() -> None:
    """320 px alone merges the row; the full-resolution look splits it; the rule picks the width."""
    full = _photo(np.random.default_rng(5), None, gap_px=2)

    def cam(w: int, h: int) -> CameraModel:
        return CameraModel.from_fov(w, h, 70.0)

    off = ResolutionPolicy(auto=False, second_look=False)
    plain, _ = detect_photo_lamps(full, cam, DEFAULT_CONFIG, off)
    full_look = ResolutionPolicy(auto=False, look_factor=5.0)
    looked, _ = detect_photo_lamps(full, cam, DEFAULT_CONFIG, full_look)
    assert len(plain.lamps) == 3 and len(looked.lamps) == 4
    auto, _ = detect_photo_lamps(full, cam, DEFAULT_CONFIG, ResolutionPolicy(second_look=False))
    # lamps 40 px wide at full resolution are 8 px at 320: the rule asks for 10 px -> 400 px
    assert auto.mask.shape == (300, 400)


def _border_row(rng: np.random.Generator, stub: tuple[int, int]) -> np.ndarray:
    """Two short lamps, and a 360 x 40 px lamp 2 px from a neighbour that the left border cuts.

    ``stub``: ``(visible length, height)`` px of the cut neighbour at x = 0 (rows centred
    on the row's 800).
    """
    w, h = FULL
    img = np.full((h, w), 120.0)
    img[300:340, 300:500] = 250.0
    img[300:340, 1000:1200] = 250.0
    ln, ht = stub
    img[800 - ht // 2 : 800 + ht // 2, 0:ln] = 250.0
    img[780:820, ln + 2 : ln + 362] = 250.0
    img = cv2.GaussianBlur(img, (0, 0), 1.0) + rng.normal(0.0, 2.0, img.shape)
    return np.clip(np.rint(img), 0, 255).astype(np.uint8)


@pytest.mark.parametrize("stub", [(60, 40), (4, 30)])
def test_a_lamp_merged_with_a_border_cut_neighbour_is_kept(stub: tuple[int, int]) -> None:
    """The border blob (cut neighbour + lamp) is dropped at 320 px; the look keeps the lamp.

    (60, 40): the cut piece is found at full resolution but is shorter than half a lamp
    (the border cut it); (4, 30): it is below the minimum area at full resolution. Either
    way the lamp is the one whole part clear of the border, and it replaces the cut blob.
    """
    full = _border_row(np.random.default_rng(6), stub)
    moments, k, mask = _coarse(full)
    assert len(moments) == 3 and sum(m.touches_border for m in moments) == 1  # merged, cut
    out, n_split = second_look(
        full, 5.0, moments, mask, k, lamp_config_for_width(DEFAULT_CONFIG, FULL[0])
    )
    assert n_split == 1
    inner = [m for m in out if not m.touches_border]
    assert len(inner) == 3
    lamp = max(inner, key=lambda m: m.sigma1)
    x_full = stub[0] + 2 + 179.5  # the lamp's centre, full-resolution px
    assert lamp.centroid[0] == pytest.approx((x_full + 0.5) / 5 - 0.5, abs=0.2)
    assert SQRT12 * lamp.sigma1 == pytest.approx(72.0, rel=0.05)
