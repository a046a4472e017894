"""Daylight is not a lamp (issue 20): simulated openings, the crowding test, the lamp-model gate."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from lampsam.datasets.logrun import CameraModel
from lampsam.datasets.render_ceiling import CeilingRenderer
from lampsam.datasets.world import load_world, world_from_dict
from lampsam.errors import DatasetError
from lampsam.frontend.lamp_config import LampDetectorConfig
from lampsam.frontend.lamp_models import size_gate_from_models, within_size_gate
from lampsam.frontend.lamps import detect_lamps


def test_lab_daylight_world_has_textured_openings_that_are_not_landmarks() -> None:
    world = load_world("lab_daylight")
    lab = load_world("lab")
    assert len(world.openings) == 4
    assert {op.kind for op in world.openings} == {"skylight", "window"}
    assert len(world.lamps) == len(lab.lamps)
    # The skylight's daylight seen from below it: bright, textured, saturated in part only.
    op = world.openings[0]
    img = CeilingRenderer(world).render(np.array([op.center[0], op.center[1] + 0.4, 0.0]), None)
    cam = world.rig.camera
    px = cam.pixels_from_normalized(
        (np.array([[op.center[0], op.center[1]]]) - [op.center[0], op.center[1] + 0.4] - cam.body_t_camera[:2])
        / (op.height - cam.z_cam)
    )[0]
    c, r = int(px[0]), int(px[1])
    patch = img[r - 8 : r + 8, c - 8 : c + 8].astype(float)
    assert patch.mean() > 150
    assert patch.std() > 20
    assert 0.02 < np.mean(patch >= 250) < 0.9


def test_opening_keys_are_checked() -> None:
    doc = {
        "rig": {"camera": {"width": 320, "height": 240, "hfov_deg": 120}},
        "ceiling": {"openings": [{"kind": "skylight", "center": [0, 0], "size": [1, 1], "height": 2.7, "brightnes": 2}]},
    }
    with pytest.raises(DatasetError, match=r"ceiling\.openings\[0\]\.brightnes: unknown key \(did you mean 'brightness'\?\)"):
        world_from_dict(doc)
    doc["ceiling"]["openings"][0] = {"kind": "door", "center": [0, 0], "size": [1, 1], "height": 2.7}
    with pytest.raises(DatasetError, match="skylight or window"):
        world_from_dict(doc)


def _grid_image(bar_px: int) -> np.ndarray:
    """A 4x3 grid of saturated 14 px panes separated by ``bar_px`` dark bars, and one lone lamp."""
    img = np.full((240, 320), 150, np.uint8)
    for i in range(4):
        for j in range(3):
            x0, y0 = 40 + i * (14 + bar_px), 40 + j * (14 + bar_px)
            img[y0 : y0 + 14, x0 : x0 + 14] = 255
    img[150:164, 220:234] = 255  # a square lamp of the same size, alone
    return cv2.GaussianBlur(img, (3, 3), 0.7)


def test_crowded_panes_are_rejected_a_lone_lamp_is_kept() -> None:
    cam = CameraModel.from_fov(320, 240, 70.0)
    det = detect_lamps(_grid_image(2), cam)
    assert [tuple(np.round(mo.centroid)) for mo in det.moments] == [(226.0, 156.0)]
    off = detect_lamps(_grid_image(2), cam, LampDetectorConfig(max_crowding=None))
    assert len(off.moments) == 13  # without the test every pane is a "lamp"


def test_size_gate_from_lamp_models() -> None:
    gate = size_gate_from_models(
        ["lamp_rect", "lamp_round"], np.array([1.2, 0.4]), np.array([0.3, 0.4]), np.array([2.0, 2.5])
    )
    assert gate[0] == pytest.approx((0.36 / 4 / 1.5, 0.36 / 4 * 1.5, 4.0))
    assert gate[1][2] == 1.0
    assert gate[1][0] == pytest.approx(math.pi * 0.04 / 6.25 / 1.5)
    # A 4:1 blob of the rect lamp's area passes, a square of that area and a tiny blob do not.
    cam = CameraModel.from_fov(320, 240, 70.0)
    img = np.full((240, 320), 120, np.uint8)
    f = cam.fx
    ln, wd = 1.2 / 2.0 * f, 0.3 / 2.0 * f  # px at 2 m
    cv2.rectangle(img, (40, 40), (40 + round(ln) - 1, 40 + round(wd) - 1), 255, -1)
    s = round(math.sqrt(ln * wd))
    cv2.rectangle(img, (200, 150), (200 + s - 1, 150 + s - 1), 255, -1)
    cv2.rectangle(img, (100, 200), (103, 203), 255, -1)
    det = detect_lamps(img, cam, LampDetectorConfig(max_crowding=None))
    assert len(det.moments) == 3
    from lampsam.frontend.ceiling_coords import ceiling_jacobians, ceiling_shapes

    m, jac = ceiling_jacobians(cam, np.array([mo.centroid for mo in det.moments]), 0.5)
    keep = within_size_gate(ceiling_shapes(det.moments, m, jac), gate)
    kept = [tuple(np.round(mo.centroid)) for mo, k in zip(det.moments, keep, strict=True) if k]
    assert len(kept) == 1 and kept[0][1] < 100
    gated = detect_lamps(img, cam, LampDetectorConfig(max_crowding=None, size_gate=gate))
    assert len(gated.moments) == 1 and gated.n_rejected >= 2
