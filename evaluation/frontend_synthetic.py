"""A small independent renderer of ceiling images with truth, for the frontend's tests.

Lamps (rotated rectangles and discs) and dark/bright ceiling plates (whose corners
are the corner truth) are drawn with OpenCV at :data:`SUPERSAMPLE` x resolution and
reduced with ``INTER_AREA``, so edges are area-sampled (anti-aliased) like a real
camera's. The scene is a flat ceiling in pixel units; a view is a similarity
``(o_x, o_y, psi)`` (px, px, rad). It shares no code with the frontend it tests
(:mod:`lampsam.evaluation.frontend_eval` measures the frontend on these frames).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from lampsam.angles import wrap_axis
from lampsam.arrays import BoolArray, FloatArray, ImageU8, IntArray
from lampsam.datasets.tables import lamp_mask

SUPERSAMPLE = 8
"""Supersampling factor of the synthetic renderer."""


@dataclass(frozen=True)
class FrameTruth:
    """Truth projections of one image.

    Attributes:
        ids: shape (K,) landmark ids.
        types: K type names (``lamp_rect``, ``lamp_round``, ``lamp_square``, ``corner``).
        pixel: shape (K, 2) projected ``(col, row)``, px.
        angle_px: shape (K,) projected long axis of ``lamp_rect`` lamps (rad,
            ``atan2(d_row, d_col)``, mod pi); NaN for others.
        visible: shape (K,) bool.
        fully_visible: shape (K,) bool (lamps entirely inside the image).
    """

    ids: IntArray
    types: tuple[str, ...]
    pixel: FloatArray
    angle_px: FloatArray
    visible: BoolArray
    fully_visible: BoolArray

    def is_lamp(self) -> BoolArray:
        """shape (K,) True for lamps (:func:`lampsam.datasets.tables.lamp_mask`)."""
        return lamp_mask(self.types)



@dataclass(frozen=True)
class SyntheticScene:
    """A flat ceiling in pixel units of a reference view, for :func:`synthetic_sequence`.

    Attributes:
        lamps: shape (L, 5) ``(x, y, length, width, angle)``: centre (px), size (px),
            long-axis angle (rad); ``width == length`` and ``round_lamp`` draws a disc.
        round_lamp: shape (L,) bool, draw a disc of diameter ``length``.
        plates: shape (Q, 5) ``(x, y, length, width, angle)`` rectangles of other
            grey levels (vents, panels, beams); their corners are the corner truth.
        plate_grey: shape (Q,) grey level of each plate.
        background: ceiling grey level.
        lamp_grey: lamp grey level (255 = saturated).
    """

    lamps: FloatArray
    round_lamp: BoolArray
    plates: FloatArray
    plate_grey: FloatArray
    background: float = 70.0
    lamp_grey: float = 240.0


def random_scene(rng: np.random.Generator, size: tuple[int, int] = (900, 700)) -> SyntheticScene:
    """A random ceiling: a grid of lamps (most rectangular, some round) and plates.

    Args:
        rng: random generator.
        size: ``(width, height)`` of the ceiling area, px.
    """
    w, h = size
    lamps = []
    rnd = []
    for x in np.arange(80.0, w - 50, 120.0):
        for y in np.arange(70.0, h - 50, 110.0):
            is_round = rng.random() < 0.2
            length = rng.uniform(10, 14) if is_round else rng.uniform(28, 44)
            width = length if is_round else rng.uniform(6, 10)
            lamps.append((x + rng.uniform(-15, 15), y + rng.uniform(-15, 15), length, width,
                          rng.uniform(-math.pi / 2, math.pi / 2)))  # fmt: skip
            rnd.append(is_round)
    plates: list[tuple[float, float, float, float, float]] = []
    grey: list[float] = []
    lam = np.array(lamps)
    for _ in range(5000):
        if len(plates) >= 40:
            break
        p = (rng.uniform(0, w), rng.uniform(0, h), rng.uniform(14, 40), rng.uniform(10, 30),
             rng.uniform(-math.pi / 2, math.pi / 2))  # fmt: skip
        if np.min(np.hypot(lam[:, 0] - p[0], lam[:, 1] - p[1])) < 52:
            continue
        if plates and np.min(np.hypot(*(np.array(plates)[:, :2] - p[:2]).T)) < 55:
            continue
        plates.append(p)
        grey.append(rng.choice([25.0, 40.0, 120.0, 140.0]))
    return SyntheticScene(
        lamps=lam, round_lamp=np.array(rnd), plates=np.array(plates), plate_grey=np.array(grey)
    )


def _rect_points(spec: FloatArray) -> FloatArray:
    """shape (4, 2) corners of a rotated rectangle ``(x, y, length, width, angle)``."""
    x, y, length, width, ang = spec
    c, s = math.cos(ang), math.sin(ang)
    half = np.array([[1, 1], [-1, 1], [-1, -1], [1, -1]]) * np.array([length, width]) / 2
    rot = np.array([[c, -s], [s, c]])
    return half @ rot.T + np.array([x, y])


def render_view(
    scene: SyntheticScene,
    view: tuple[float, float, float],
    size: tuple[int, int] = (320, 240),
    noise_grey: float = 2.0,
    rng: np.random.Generator | None = None,
) -> tuple[ImageU8, FrameTruth]:
    """Render the scene seen through a similarity ``view`` with truth.

    The image pixel of a scene point ``p`` is ``R(psi) (p - o)`` with
    ``view = (o_x, o_y, psi)``: the view's origin and rotation. Polygons are
    filled at :data:`SUPERSAMPLE` x and area-averaged down.

    Args:
        scene: the ceiling.
        view: ``(o_x, o_y, psi)``, px, px, rad.
        size: ``(width, height)`` of the image.
        noise_grey: sigma of additive Gaussian noise (grey levels).
        rng: generator for the noise (None: no noise).

    Returns:
        The uint8 image and its truth (lamp ids ``0..L-1``, plate corner ids
        ``1000 + 4 q + k``).
    """
    w, h = size
    ox, oy, psi = view
    c, s = math.cos(psi), math.sin(psi)
    rot = np.array([[c, -s], [s, c]])
    ss = SUPERSAMPLE

    def to_img(pts: FloatArray) -> FloatArray:
        return (pts - np.array([ox, oy])) @ rot.T

    big = np.full((h * ss, w * ss), scene.background, np.float32)

    def fill(pts_img: FloatArray, grey: float) -> None:
        big_pts = (pts_img + 0.5) * ss - 0.5
        cv2.fillPoly(big, [np.round(big_pts * 16).astype(np.int32)], float(grey), cv2.LINE_8, 4)

    ids: list[int] = []
    types: list[str] = []
    pix: list[FloatArray] = []
    ang: list[float] = []
    vis: list[bool] = []
    full: list[bool] = []
    for q, spec in enumerate(scene.plates):
        pts = to_img(_rect_points(spec))
        fill(pts, float(scene.plate_grey[q]))
        for k in range(4):
            ids.append(1000 + 4 * q + k)
            types.append("corner")
            pix.append(pts[k])
            ang.append(math.nan)
            inside = bool(0 <= pts[k, 0] <= w - 1 and 0 <= pts[k, 1] <= h - 1)
            vis.append(inside)
            full.append(inside)
    for li, spec in enumerate(scene.lamps):
        centre = to_img(spec[None, :2])[0]
        if scene.round_lamp[li]:
            r = spec[2] / 2
            big_c = (centre + 0.5) * ss - 0.5
            cv2.circle(big, tuple(int(v) for v in np.round(big_c * 16)), int(round(r * ss * 16)),
                       float(scene.lamp_grey), -1, cv2.LINE_8, 4)  # fmt: skip
            outline = centre + r * np.array([[1, 0], [-1, 0], [0, 1], [0, -1]])
            ang.append(math.nan)
            types.append("lamp_round")
        else:
            outline = to_img(_rect_points(spec))
            fill(outline, scene.lamp_grey)
            ang.append(wrap_axis(spec[4] + psi))
            types.append("lamp_rect")
        ids.append(li)
        pix.append(centre)
        inside = (
            (outline[:, 0] >= 1)
            & (outline[:, 0] <= w - 2)
            & (outline[:, 1] >= 1)
            & (outline[:, 1] <= h - 2)
        )
        vis.append(bool(0 <= centre[0] <= w - 1 and 0 <= centre[1] <= h - 1))
        full.append(bool(inside.all()))
    img = cv2.resize(big, (w, h), interpolation=cv2.INTER_AREA)
    if rng is not None and noise_grey > 0:
        img = img + rng.normal(0.0, noise_grey, img.shape)
    out = np.clip(np.round(img), 0, 255).astype(np.uint8)
    truth = FrameTruth(
        ids=np.array(ids, dtype=np.int64),
        types=tuple(types),
        pixel=np.array(pix).reshape(-1, 2),
        angle_px=np.array(ang),
        visible=np.array(vis, dtype=bool),
        fully_visible=np.array(full, dtype=bool),
    )
    return out, truth


def synthetic_sequence(
    rng: np.random.Generator,
    n_frames: int = 20,
    size: tuple[int, int] = (320, 240),
    step_px: float = 6.0,
    turn_rad: float = 0.02,
    noise_grey: float = 2.0,
) -> list[tuple[ImageU8, FrameTruth]]:
    """A short rendered run: the view slides and turns over a random ceiling.

    Args:
        rng: random generator (scene and noise).
        n_frames: number of images.
        size: image ``(width, height)``.
        step_px: translation between frames, px.
        turn_rad: rotation between frames, rad.
        noise_grey: image noise sigma, grey levels.

    Returns:
        ``(image, truth)`` pairs.
    """
    scene = random_scene(rng)
    out = []
    for k in range(n_frames):
        view = (150.0 + step_px * k, 120.0 + 0.5 * step_px * k, turn_rad * k)
        out.append(render_view(scene, view, size, noise_grey, rng))
    return out


