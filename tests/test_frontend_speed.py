"""The frontend's shortcuts give the same frames as the straightforward paths they skip.

Each shortcut is exact by construction (e.g. no second dilation when no two blobs
can share a pixel of their reach); these tests run the pipeline on seeded rendered
frames with and without the shortcut and compare every field of every lamp and
corner (1e-9, most are bit-identical).
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import fields

import cv2
import numpy as np
import pytest

import lampsam.frontend.lamps as lamps_module
from lampsam.datasets.logrun import CameraModel
from lampsam.evaluation.frontend_synthetic import synthetic_sequence
from lampsam.frontend.blob_reach import gather_reach, reaches_may_overlap
from lampsam.frontend.dilation import dilate_disk
from lampsam.frontend.lamp_config import LampDetectorConfig
from lampsam.frontend.measurements import CeilingFrame, CornerObservation, LampObservation
from lampsam.frontend.pipeline import process_image


def _values(frame: CeilingFrame) -> Iterator[tuple[str, object]]:
    items: list[LampObservation | CornerObservation] = [*frame.lamps, *frame.corners]
    for i, item in enumerate(items):
        for f in fields(item):
            yield f"{type(item).__name__} {i} {f.name}", getattr(item, f.name)


def assert_same_frame(a: CeilingFrame, b: CeilingFrame) -> None:
    """Same lamps and corners, in the same order, every field to 1e-9."""
    assert (len(a.lamps), len(a.corners)) == (len(b.lamps), len(b.corners))
    for (name, va), (_, vb) in zip(_values(a), _values(b), strict=True):
        if isinstance(va, (float, np.ndarray)) or hasattr(va, "__array__"):
            np.testing.assert_allclose(np.asarray(va, dtype=float), np.asarray(vb, dtype=float),
                                       rtol=1e-9, atol=1e-12, err_msg=name)
        else:
            assert va == vb, name


def _crowded_image(rng: np.random.Generator) -> np.ndarray:
    """Lamps close enough for their reaches to overlap (panes of a skylight), and apart."""
    img = np.full((240, 320), 90.0)
    for c0 in (40, 52, 64):  # three panes 4 px apart: reaches (5 px) overlap
        img[60:80, c0 : c0 + 8] = 240.0
    img[150:160, 200:240] = 235.0  # a lone lamp
    img[30:36, 260:300] = 238.0
    img = cv2.GaussianBlur(img, (0, 0), 0.7)
    return np.clip(img + rng.normal(0.0, 2.0, img.shape), 0, 255).astype(np.uint8)


def test_reach_overlap_test_never_misses(rng: np.random.Generator) -> None:
    """``reaches_may_overlap`` is True whenever two blobs' dilated reaches share a pixel
    (brute force: one dilation per blob), on random blob layouts."""
    cfg = LampDetectorConfig()
    reach = cfg.support_px + cfg.ring_px
    said_apart = 0
    for _ in range(200):
        img = np.zeros((60, 80), np.uint8)
        for _ in range(int(rng.integers(2, 5))):
            r, c = int(rng.integers(0, 55)), int(rng.integers(0, 75))
            img[r : r + int(rng.integers(1, 6)), c : c + int(rng.integers(1, 6))] = 1
        n, labels, stats, _ = cv2.connectedComponentsWithStats(img, connectivity=8)
        lo, hi = stats[1:, :2], stats[1:, :2] + stats[1:, 2:4]
        cover = sum(
            (dilate_disk((labels == i).astype(np.uint8), reach) > 0).astype(int)
            for i in range(1, n)
        )
        shared = bool((np.asarray(cover) > 1).any())
        apart = not reaches_may_overlap(lo, hi, reach)
        assert not (shared and apart)
        said_apart += apart
    assert 20 <= said_apart <= 180  # both answers exercised


def test_crowding_without_second_dilation_is_the_same(rng: np.random.Generator) -> None:
    """``gather_reach`` without the reversed-label dilation gives the same crowding
    labels when the reaches are apart, and the test sees the skylight panes' overlap."""
    cfg = LampDetectorConfig()
    img = np.zeros((50, 90), np.uint8)
    img[10:15, 10:16] = 1
    img[30:40, 60:64] = 1
    img[31:33, 70:72] = 1  # 6 px from the blob above: reaches overlap
    n, labels, stats, _ = cv2.connectedComponentsWithStats(img, connectivity=8)
    comp = labels.astype(np.uint8)
    grey = (rng.integers(0, 60, img.shape) + 180 * img).astype(np.uint8)
    lo, hi = stats[1:, :2], stats[1:, :2] + stats[1:, 2:4]
    assert reaches_may_overlap(lo, hi, cfg.support_px + cfg.ring_px)
    assert not reaches_may_overlap(lo[:2], hi[:2], cfg.support_px + cfg.ring_px)
    two = np.where(comp == 3, 0, comp).astype(np.uint8)  # the first two blobs only
    binary = (two > 0).astype(np.uint8)
    sub = (0, 50, 0, 90)
    full = gather_reach(two, sub, (0, 0), binary, grey, cfg, True)
    fast = gather_reach(two, sub, (0, 0), binary, grey, cfg, False)
    for a, b in zip(full, fast, strict=True):
        np.testing.assert_array_equal(np.sort(a), np.sort(b))


@pytest.mark.parametrize("crowded", [False, True])
def test_frames_match_the_full_path(rng: np.random.Generator, crowded: bool,
                                    monkeypatch: pytest.MonkeyPatch) -> None:
    """Whole frames (lamps and corners) with the shortcuts equal those without them,
    on 6 rendered frames of a moving view and on a crowded ceiling."""
    camera = CameraModel()
    if crowded:
        images = [_crowded_image(rng) for _ in range(2)]
    else:
        images = [img for img, _ in synthetic_sequence(rng, n_frames=6)]
    decisions: list[bool] = []
    real = lamps_module.reaches_may_overlap

    def spy(lo: np.ndarray, hi: np.ndarray, reach: int) -> bool:
        decisions.append(real(lo, hi, reach))
        return decisions[-1]

    monkeypatch.setattr(lamps_module, "reaches_may_overlap", spy)
    fast = [process_image(img, 0.1 * i, i, camera) for i, img in enumerate(images)]
    monkeypatch.setattr(lamps_module, "reaches_may_overlap", lambda lo, hi, reach: True)
    full = [process_image(img, 0.1 * i, i, camera) for i, img in enumerate(images)]
    assert sum(len(f.lamps) for f in fast) >= (6 if crowded else 10)
    assert any(decisions) if crowded else not all(decisions)
    for a, b in zip(fast, full, strict=True):
        assert_same_frame(a, b)
