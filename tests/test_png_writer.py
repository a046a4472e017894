"""The image writer's PNG level changes the file size, never the pixels read back."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from lampsam.datasets.logrun import read_run
from lampsam.datasets.simulator import simulate_world
from lampsam.datasets.tables import ImageWriter, encode_png, png_params
from lampsam.errors import DatasetError


def test_every_level_decodes_to_the_same_pixels(rng: np.random.Generator, tmp_path: Path) -> None:
    """Levels 0-9 (bytes and ImageWriter files) decode to the written image; level 0
    (stored) is at least 1.3x the size of level 6 on a noisy ceiling-like image."""
    img = np.clip(rng.normal(90, 3, (240, 320)), 0, 255).astype(np.uint8)
    img[100:120, 50:150] = 250
    sizes = {}
    for level in range(10):
        png = encode_png(img, level)
        sizes[level] = len(png)
        back = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_UNCHANGED)
        np.testing.assert_array_equal(back, img)
        w = ImageWriter(tmp_path / str(level), png_compression=level)
        path = w.write(0.0, img)
        w.close()
        np.testing.assert_array_equal(cv2.imread(str(path), cv2.IMREAD_UNCHANGED), img)
    assert sizes[0] > 1.3 * sizes[6]
    assert sizes[0] >= img.size  # stored: every pixel byte is in the file


def test_bad_level_is_refused(tmp_path: Path) -> None:
    """A level outside 0-9 is refused with the value named (writer and simulator)."""
    with pytest.raises(ValueError, match="got 10"):
        png_params(10)
    with pytest.raises(DatasetError, match="got -1"):
        simulate_world("lab", tmp_path / "r", duration=0.5, workers=1, png_compression=-1)


def test_simulated_run_pixels_do_not_depend_on_the_level(tmp_path: Path) -> None:
    """The same seeded lab run written at level 0 and level 6: same images, level 0 larger."""
    runs = [read_run(simulate_world("lab", tmp_path / f"l{lv}", seed=1, duration=0.6,
                                    workers=1, png_compression=lv)) for lv in (0, 6)]
    a, b = (r.images for r in runs)
    assert a is not None and b is not None and len(a) == len(b) >= 8
    for i in range(len(a)):
        np.testing.assert_array_equal(a.load(i), b.load(i))
    assert sum(p.stat().st_size for p in a.files) > 1.3 * sum(p.stat().st_size for p in b.files)
