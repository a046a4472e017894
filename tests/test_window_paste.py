"""The pasted window of :func:`lampsam.evaluation.photo_augment.paste_window` (docs/photo-labels.md)."""

from __future__ import annotations

import numpy as np
import pytest

from lampsam.evaluation.photo_augment import paste_window
from lampsam.evaluation.photo_labels import PhotoLabels, Region


def labels() -> PhotoLabels:
    """A 1000x750 photo with lamps along the left and bottom; the top right is free."""
    lamps = tuple(Region("lamp", np.array([x, 700.0]), 0.0, 80.0, 20.0) for x in (100, 400, 700))
    lamps += tuple(Region("lamp", np.array([60.0, y]), 90.0, 80.0, 20.0) for y in (100, 300))
    return PhotoLabels("x.jpg", 1000, 750, "tune", lamps)


def test_flat_window_is_saturated_barred_and_labelled_away_from_the_lamps() -> None:
    grey = np.full((750, 1000), 120, dtype=np.uint8)
    out, lab = paste_window(grey, labels())
    panes = [r for r in lab.regions if r.kind == "window"]
    assert len(panes) == 6
    assert not any(r.occluded for r in lab.regions if r.kind == "lamp")  # room left for it
    frac = np.count_nonzero(out == 255) / out.size
    assert 0.07 < frac < 0.105  # the audit's ~10 % of the frame, less the bars (7.5 %)
    for p in panes:  # each pane's centre is saturated and inside the bright area
        c, r = np.round(p.centre).astype(int)
        assert out[r, c] == 255
    assert np.count_nonzero(out == 70) > 0  # the bars


def test_textured_window_needs_a_generator_and_is_reproducible() -> None:
    grey = np.full((750, 1000), 120, dtype=np.uint8)
    with pytest.raises(ValueError, match="generator"):
        paste_window(grey, labels(), textured=True)
    a, _ = paste_window(grey, labels(), textured=True, rng=np.random.default_rng(0))
    b, _ = paste_window(grey, labels(), textured=True, rng=np.random.default_rng(0))
    assert np.array_equal(a, b)
    sky = a[a > 200]
    assert 225 < float(np.median(sky)) < 255 and np.count_nonzero(a == 255) < 0.5 * sky.size


def test_lamps_under_the_window_are_marked_occluded() -> None:
    grey = np.full((750, 1000), 120, dtype=np.uint8)
    many = labels()
    grid = tuple(Region("lamp", np.array([x, y]), 0.0, 40.0, 10.0)
                 for x in range(50, 1000, 100) for y in range(50, 750, 100))
    crowded = PhotoLabels("y.jpg", 1000, 750, "tune", many.regions + grid)
    _, lab = paste_window(grey, crowded)
    assert any(r.occluded for r in lab.regions if r.kind == "lamp")
