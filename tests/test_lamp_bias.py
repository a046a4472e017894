"""The lamp measurement's error against the simulator's truth, and a lamp bent by lens distortion.

docs/lamp-bias.md: on the simulated lab the lamp centroid's error is mostly the pixel
phase of saturated edges (a partly covered pixel that clips reads as fully covered),
not distortion (the lab camera has none), the hung lamps' height or their sides. These
tests hold the measured figures: no bias by image region beyond a few hundredths of a
pixel, the per-sighting RMS, and that unsaturated lamps roughly halve it.
"""

from __future__ import annotations

import dataclasses
import math

import cv2
import numpy as np
import pytest

from lampsam.datasets.camera import CameraModel
from lampsam.datasets.ceiling_truth import occluders, project_landmarks
from lampsam.datasets.render_ceiling import CeilingRenderer, camera_center
from lampsam.datasets.simulator import simulate_trajectory
from lampsam.datasets.world import World, load_world
from lampsam.datasets.world_landmarks import world_landmarks
from lampsam.frontend.lamp_config import LampDetectorConfig
from lampsam.frontend.lamps import detect_lamps
from tests.test_fisheye_lamps import _draw_lamp


def _lamp_errors(
    world: World, every: int, configs: tuple[LampDetectorConfig, ...] = (LampDetectorConfig(),)
) -> tuple[list[np.ndarray], np.ndarray]:
    """Observation errors ``m - m*`` in px (N, 2), one array per detector setting, and the true
    pixels (N, 2) of every fully visible lamp detected with every setting, on every
    ``every``-th image pose of the path (seed 0)."""
    cam = world.rig.camera
    f = math.sqrt(cam.fx * cam.fy)
    renderer = CeilingRenderer(world)
    lms = world_landmarks(world)
    occ = occluders(world)
    _, poses, _, _ = simulate_trajectory(world, 0)
    errs: list[list[np.ndarray]] = [[] for _ in configs]
    pix = []
    for k, pose in enumerate(poses[:: 2 * every]):
        img = renderer.render(pose, np.random.default_rng([0, k]))
        truth = project_landmarks(cam, pose, lms, occ, renderer.m_max)
        rows = [r for r, t in enumerate(truth.types) if t.startswith("lamp") and truth.fully_visible[r]]
        if not rows:
            continue
        found: list[dict[int, np.ndarray]] = []
        for config in configs:
            seen = {}
            for ob in detect_lamps(img, cam, config).lamps:
                d = np.hypot(*(truth.pixel[rows] - ob.pixel).T)
                if not ob.touches_border and d.min() <= 4.0:
                    seen[rows[int(np.argmin(d))]] = ob.m
            found.append(seen)
        for r in set.intersection(*(set(sn) for sn in found)):
            xyz = lms.xyz[lms.index_of(int(truth.ids[r]))]
            rel = xyz[:2] - camera_center(cam, pose)
            c, s = math.cos(pose[2]), math.sin(pose[2])
            m_true = np.array([c * rel[0] + s * rel[1], -s * rel[0] + c * rel[1]]) / (xyz[2] - cam.z_cam)
            for out, seen in zip(errs, found, strict=True):
                out.append(f * (seen[r] - m_true))
            pix.append(truth.pixel[r])
    return [np.array(e) for e in errs], np.array(pix)


@pytest.fixture(scope="module")
def lab_errors() -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Errors on the lab as simulated (with and without the saturated-edge model), and on the
    lab with its lamps below saturation (grey 250)."""
    lab = load_world("lab")
    unsat = dataclasses.replace(
        lab, lamps=tuple(dataclasses.replace(lp, brightness=250.0) for lp in lab.lamps)
    )
    (e, e_read), px = _lamp_errors(lab, 20, (LampDetectorConfig(), LampDetectorConfig(saturated_edges=False)))
    (e_unsat,), _ = _lamp_errors(unsat, 20)
    return e, px, e_unsat, e_read


def _rms(e: np.ndarray) -> float:
    """RMS length of the rows of ``e`` (N, 2)."""
    return float(np.sqrt(np.mean(np.sum(e * e, axis=1))))


def test_lamp_error_has_no_bias_by_image_region(lab_errors: tuple) -> None:
    """Lab, every 20th image of the path (130 images, seed 0): the mean lamp error in each
    band of distance from the image centre is under 0.03 px per axis (about 0.7 mm at lamp
    height; measured 0.002-0.010 px on 484 sightings), and the per-sighting RMS is 0.04-0.08
    px (measured 0.069 px; 0.088 px without the saturated-edge model, docs/lamp-bias.md)."""
    e, px, _, _ = lab_errors
    assert len(e) > 250
    centre = np.array([159.5, 119.5])
    r = np.hypot(*(px - centre).T)
    for lo, hi in ((0.0, 60.0), (60.0, 110.0), (110.0, 200.0)):
        sel = (r >= lo) & (r < hi)
        assert sel.sum() > 40
        assert np.all(np.abs(e[sel].mean(axis=0)) < 0.03)
    assert 0.04 < _rms(e) < 0.08


def test_saturation_is_the_main_cause_and_the_edge_model_removes_a_quarter(lab_errors: tuple) -> None:
    """The same poses with lamps at grey 250 (no clipping of partly covered pixels): the RMS
    error is under 0.65 of the saturated lamps' as read (measured 0.048 against 0.088 px):
    saturation, not the lamp's height or sides, is the main cause. The saturated-edge model
    (:mod:`lampsam.frontend.saturated_edges`) takes the saturated lamps' RMS under 0.8 of the
    weights as read (measured 0.069 against 0.088 px)."""
    e, _, e_unsat, e_read = lab_errors
    assert _rms(e_unsat) < 0.65 * _rms(e_read)
    assert _rms(e) < 0.8 * _rms(e_read)


def test_distorted_pinhole_lamp_centre_recovered(rng: np.random.Generator) -> None:
    """A 0.48 x 0.12 lamp drawn on the ceiling and imaged through a pinhole with strong barrel
    distortion (k1 = -0.3, k2 = 0.08; 110 deg) near the image corner: the detector's centre
    (coverage moments taken on the ceiling) is within 1e-4 of the truth (measured 2.8e-5,
    0.003 px), where the pixel centroid undistorted as a point is off by over 0.01 (measured
    0.036, 3 px: the bent image's centroid is not the lamp centre's image)."""
    cam = CameraModel.from_fov(320, 240, 110.0, dist=np.array([-0.3, 0.08, 0.0, 0.0, 0.0]))
    centre, size, yaw = (0.55, 0.45), (0.48, 0.12), math.radians(30.0)
    img = _draw_lamp(cam, centre, size, yaw, rng)
    det = detect_lamps(img, cam)
    assert len(det.lamps) == 1
    (lamp,), (mom,) = det.lamps, det.moments
    assert mom.ceiling is not None
    err = float(np.hypot(*(lamp.m - centre)))
    assert err < 1e-4
    naive = cam.normalized_from_pixels(lamp.pixel[None])[0]
    assert float(np.hypot(*(naive - centre))) > 0.01


def _bright_rects(rng: np.random.Generator, blur_px: float) -> tuple[np.ndarray, np.ndarray]:
    """Four 30-31 x 8-9 px rectangles at grey 400 (clipped to 255) on a ceiling at 100, axis-aligned
    at random sub-pixel positions, exact area coverage, optionally blurred before clipping.

    Returns:
        ``(image (240, 320) uint8, true centres (4, 2) (col, row))``.
    """
    img = np.full((240, 320), 100.0)
    centres = np.array([[70.0, 60.0], [230.0, 60.0], [70.0, 180.0], [230.0, 180.0]])
    centres += rng.uniform(-0.5, 0.5, centres.shape)
    cols, rows = np.arange(320.0), np.arange(240.0)
    for k, (c, r) in enumerate(centres):
        w, h = rng.uniform(30.0, 31.0), rng.uniform(8.0, 9.0)
        w, h = (w, h) if k % 2 == 0 else (h, w)
        # Pixel i covers [i - 0.5, i + 0.5]: its overlap with the rectangle, per axis.
        ox = np.clip(np.minimum(cols + 0.5, c + w / 2) - np.maximum(cols - 0.5, c - w / 2), 0.0, 1.0)
        oy = np.clip(np.minimum(rows + 0.5, r + h / 2) - np.maximum(rows - 0.5, r - h / 2), 0.0, 1.0)
        img += 300.0 * np.outer(oy, ox)
    if blur_px > 0:
        img = cv2.GaussianBlur(img, (0, 0), blur_px)
    img += rng.normal(0.0, 1.0, img.shape)
    return np.clip(np.rint(img), 0, 255).astype(np.uint8), centres


def _centroid_errors(blur_px: float, saturated_edges: bool, n: int = 20) -> np.ndarray:
    """Pixel centroid errors (N, 2) of :func:`_bright_rects` over ``n`` seeded images."""
    rng = np.random.default_rng(7)
    config = LampDetectorConfig(saturated_edges=saturated_edges)
    errs = []
    for _ in range(n):
        img, centres = _bright_rects(rng, blur_px)
        det = detect_lamps(img, CameraModel(), config)
        assert len(det.lamps) == 4
        for mom in det.moments:
            errs.append(mom.centroid - centres[np.argmin(np.hypot(*(centres - mom.centroid).T))])
    return np.array(errs)


def test_saturated_edge_model_on_sharp_and_blurred_edges() -> None:
    """Sharp saturated rectangles (clip coverage c_s = 155 / 300 = 0.52) at random sub-pixel
    positions and sizes, 20 images: the centroid error RMS with the edge model is under 0.85 of
    the weights as read (measured 0.095 against 0.130 px; the information left in a clipped
    edge pixel bounds the gain, docs/lamp-bias.md); blurred by a lens (sigma 1 px before
    clipping) the model measures no sharp clipped edges and changes nothing (errors identical)."""
    sharp_model, sharp_read = _centroid_errors(0.0, True), _centroid_errors(0.0, False)
    assert _rms(sharp_model) < 0.85 * _rms(sharp_read)
    np.testing.assert_array_equal(_centroid_errors(1.0, True), _centroid_errors(1.0, False))
