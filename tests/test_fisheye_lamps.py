"""Lamps seen through a fisheye: centre and axis taken on the ceiling (issue 16).

A rectangular lamp is drawn on the ceiling plane (normalised coordinates ``m``)
and imaged through an equidistant fisheye by area sampling (8 x 8 sub-pixels
per pixel, each mapped to ``m`` by the camera model): the detected centre and
axis are compared with the rectangle's, and with what the pixel centroid
mapped through the camera gives (the bent image's centroid, off the lamp).
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from lampsam.angles import wrap_axis
from lampsam.datasets.camera import CameraModel
from lampsam.frontend.ceiling_grid import build_ceiling_grid, ceiling_grid
from lampsam.frontend.lamps import detect_lamps

SUB = 8
FISHEYE = CameraModel.from_fov(320, 240, 150.0, model="fisheye")
"""150 deg equidistant fisheye, f = 122 px (one object: its table is built once)."""


def _draw_lamp(
    cam: CameraModel, centre: tuple[float, float], size: tuple[float, float], yaw: float,
    rng: np.random.Generator,
) -> np.ndarray:
    """Grey image (background 60, lamp 250, noise 1 grey) of a ceiling rectangle, area-sampled."""
    # Only the pixels near the lamp's image are sampled finely (the rest is background).
    corners = np.array([[sx, sy] for sx in (-0.5, 0.5) for sy in (-0.5, 0.5)]) * size
    rot = np.array([[math.cos(yaw), -math.sin(yaw)], [math.sin(yaw), math.cos(yaw)]])
    px = cam.pixels_from_normalized(corners @ rot.T + centre)
    c0, r0 = np.floor(px.min(axis=0)).astype(int) - 4
    c1, r1 = np.ceil(px.max(axis=0)).astype(int) + 4
    offs = (np.arange(SUB) + 0.5) / SUB - 0.5
    cols = np.arange(c0, c1)[None, :, None, None] + offs[None, None, None, :]
    rows = np.arange(r0, r1)[:, None, None, None] + offs[None, None, :, None]
    cols, rows = np.broadcast_arrays(cols, rows)
    m = cam.normalized_from_pixels(np.column_stack([cols.ravel(), rows.ravel()]))
    local = (m - centre) @ rot  # in the lamp's axes
    inside = (np.abs(local[:, 0]) <= size[0] / 2) & (np.abs(local[:, 1]) <= size[1] / 2)
    cover = inside.reshape(r1 - r0, c1 - c0, SUB * SUB).mean(axis=2)
    img = np.full((cam.height, cam.width), 60.0)
    img[r0:r1, c0:c1] += 190.0 * cover
    img += rng.normal(0.0, 1.0, img.shape)
    return np.clip(np.rint(img), 0, 255).astype(np.uint8)


@pytest.mark.parametrize(
    ("centre", "yaw_deg"), [((0.9, 0.6), 20.0), ((-0.2, 1.3), -65.0), ((0.05, -0.1), 40.0)]
)
def test_fisheye_lamp_centre_and_axis_on_the_ceiling(
    centre: tuple[float, float], yaw_deg: float, rng: np.random.Generator
) -> None:
    """A 0.48 x 0.12 lamp (1.2 m x 0.3 m at 2.5 m) 50-55 deg off the optical axis: the centre
    within 0.001 of truth (about 0.1 px there) and the axis within 0.3 deg; the pixel centroid
    mapped through the camera is off by more (curvature), so the test tells them apart."""
    cam = FISHEYE
    size = (0.48, 0.12)
    yaw = math.radians(yaw_deg)
    img = _draw_lamp(cam, centre, size, yaw, rng)
    det = detect_lamps(img, cam)
    assert len(det.lamps) == 1
    (lamp,), (mom,) = det.lamps, det.moments
    assert mom.ceiling is not None
    err = float(np.hypot(*(lamp.m - centre)))
    assert err < 1e-3
    assert lamp.axis is not None
    assert abs(wrap_axis(lamp.axis - yaw)) < math.radians(0.3)
    # The face's elongation, measured on the ceiling: 4 (a uniform 4:1 rectangle).
    assert lamp.ratio == pytest.approx(4.0, rel=0.05)
    # The area on the ceiling is the face's.
    assert mom.ceiling.area == pytest.approx(size[0] * size[1], rel=0.03)
    if np.hypot(*centre) > 1.0:  # far off axis: the bent image's pixel centroid is off the lamp
        naive = cam.normalized_from_pixels(lamp.pixel[None])[0]
        assert float(np.hypot(*(naive - centre))) > 3 * err


def test_ceiling_grid_table() -> None:
    """The table holds m at every pixel centre (as the camera computes it), NaN beyond 90 deg,
    and |det dm/dpx| against central differences; an upward pinhole needs no table."""
    cam = FISHEYE
    grid = build_ceiling_grid(cam)
    assert not grid.affine and grid.u.shape == (320 * 240,)
    probe = np.array([[40.0, 30.0], [159.0, 119.0], [280.0, 200.0], [0.0, 0.0]])
    m = cam.normalized_from_pixels(probe)
    flat = (probe[:, 1] * 320 + probe[:, 0]).astype(int)
    np.testing.assert_allclose(np.column_stack([grid.u[flat], grid.v[flat]])[:3], m[:3], atol=1e-12)
    assert np.isnan(grid.u[0])  # the image corner sees beyond 90 deg (r = 200 px, f = 122 px)
    step = 1e-3
    for x, y in probe[:3]:
        d = cam.normalized_from_pixels(
            np.array([[x + step, y], [x - step, y], [x, y + step], [x, y - step]])
        )
        jac = np.column_stack([(d[0] - d[1]) / (2 * step), (d[2] - d[3]) / (2 * step)])
        assert grid.g[round(y) * 320 + round(x)] == pytest.approx(abs(np.linalg.det(jac)), rel=1e-3)
    assert build_ceiling_grid(CameraModel()).affine
    assert ceiling_grid(cam) is ceiling_grid(cam)  # built once per camera
