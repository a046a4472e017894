"""Ceiling images by ray casting, and the true projections of landmarks, from geometry only.

Renderer (per image):

1. Every output pixel is split into ``S x S`` sub-pixel rays. Each ray's
   direction comes from the camera model alone: ``cv2.undistortPoints`` of the
   sub-pixel position gives the camera ray, ``body_R_camera`` turns it into body
   axes, and it is scaled to unit height, ``(u, v, 1)``. This is done once.
2. For a robot pose ``(x, y, theta)`` the optical centre is
   ``c = (x, y) + R(theta) body_t_camera[:2]`` at height ``z_cam``; a ray meets
   the horizontal plane at height ``H`` at ``c + (H - z_cam) R(theta) (u, v)``.
3. Each distinct height is a *layer*: its surfaces, texture marks and lamps are
   rasterised once, anti-aliased, into a premultiplied (grey * alpha, alpha)
   float texture of ``texel`` metres (edges get their exact sub-texel coverage
   from a signed distance). The ray's hit is looked up with bilinear
   interpolation (``cv2.remap``).
4. Layers are composited front to back (lowest, i.e. nearest, first):
   ``out += T * grey_alpha``, ``T *= 1 - alpha``; rays that hit nothing see the
   background grey. The ``S x S`` samples are averaged (box filter = pixel area).
5. Optional glare around over-exposed lamps, then seeded Gaussian sensor noise,
   then saturation to 0..255.

The truth (where each landmark projects) is computed independently of this renderer,
in :mod:`lampsam.datasets.ceiling_truth`.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from dataclasses import dataclass

import cv2
import numpy as np

from lampsam.arrays import BoolArray, FloatArray, ImageU8
from lampsam.datasets.logrun import CameraModel
from lampsam.datasets.openings import Opening
from lampsam.datasets.shapes import disc_sdf, rect_sdf
from lampsam.datasets.world import Lamp, Surface, TextureItem, World

log = logging.getLogger(__name__)

GreyField = Callable[[FloatArray, FloatArray], FloatArray]
"""A texture: grey level at world points ``(x, y)`` (arrays of one shape, m)."""


# --------------------------------------------------------------------------- rasterising
@dataclass(frozen=True, eq=False)
class Layer:
    """A rasterised horizontal layer.

    Attributes:
        height: height above the floor, m.
        x0: world x of texel column 0's centre, m.
        y0: world y of texel row 0's centre, m.
        texel: texel size, m.
        tex: (rows, cols, 2) float32 premultiplied ``(grey * alpha, alpha)``; row ``i``,
            column ``j`` is the world point ``(x0 + j texel, y0 + i texel)``.
        flat: (rows, cols) float32 ``grey * alpha + (1 - alpha) * background``: the
            layer composited over the background (used when nothing lies behind it).
    """

    height: float
    x0: float
    y0: float
    texel: float
    tex: np.ndarray
    flat: np.ndarray

    @property
    def bounds(self) -> tuple[float, float, float, float]:
        """``(xmin, ymin, xmax, ymax)`` covered, m."""
        rows, cols = self.tex.shape[:2]
        return (
            self.x0,
            self.y0,
            self.x0 + (cols - 1) * self.texel,
            self.y0 + (rows - 1) * self.texel,
        )


class _Canvas:
    """A layer being painted: premultiplied grey and alpha over a texel grid."""

    def __init__(self, bounds: tuple[float, float, float, float], texel: float, pad: int = 3):
        """Empty canvas covering ``bounds`` (m) plus ``pad`` texels."""
        x0, y0, x1, y1 = bounds
        self.texel = texel
        self.x0 = math.floor(x0 / texel) * texel - pad * texel
        self.y0 = math.floor(y0 / texel) * texel - pad * texel
        cols = int(math.ceil((x1 - self.x0) / texel)) + pad + 1
        rows = int(math.ceil((y1 - self.y0) / texel)) + pad + 1
        self.p = np.zeros((rows, cols), np.float32)
        self.a = np.zeros((rows, cols), np.float32)

    def paint(
        self,
        bbox: tuple[float, float, float, float],
        sdf: Callable[[FloatArray, FloatArray], FloatArray],
        grey: float | GreyField,
    ) -> None:
        """Paint a shape given by a signed-distance callable over its bounding box ("over").

        ``grey`` is a grey level, or a callable ``grey(x, y)`` of world points (a texture).
        """
        t = self.texel
        rows, cols = self.p.shape
        j0 = max(int(math.floor((bbox[0] - self.x0) / t)) - 2, 0)
        j1 = min(int(math.ceil((bbox[2] - self.x0) / t)) + 3, cols)
        i0 = max(int(math.floor((bbox[1] - self.y0) / t)) - 2, 0)
        i1 = min(int(math.ceil((bbox[3] - self.y0) / t)) + 3, rows)
        if j0 >= j1 or i0 >= i1:
            return
        xs = self.x0 + t * np.arange(j0, j1)
        ys = self.y0 + t * np.arange(i0, i1)
        gx, gy = np.meshgrid(xs, ys)
        d = sdf(gx, gy)
        # Coverage of a texel-sized box by a locally straight edge at distance d.
        cov = np.clip(0.5 - d / t, 0.0, 1.0).astype(np.float32)
        sl = (slice(i0, i1), slice(j0, j1))
        g = np.asarray(grey(gx, gy), dtype=np.float32) if callable(grey) else np.float32(grey)
        self.p[sl] = cov * g + (1 - cov) * self.p[sl]
        self.a[sl] = cov + (1 - cov) * self.a[sl]

    def rect(
        self, center: tuple[float, float], size: tuple[float, float], yaw: float,
        grey: float | GreyField,
    ) -> None:
        """Paint a rotated rectangle of side lengths ``size``."""
        half = (size[0] / 2, size[1] / 2)
        r = math.hypot(*half)
        bbox = (center[0] - r, center[1] - r, center[0] + r, center[1] + r)
        if abs(math.sin(2 * yaw)) < 1e-12:  # axis aligned: exact bbox (thin lines stay cheap)
            hx, hy = half if abs(math.cos(yaw)) > 0.5 else (half[1], half[0])
            bbox = (center[0] - hx, center[1] - hy, center[0] + hx, center[1] + hy)
        self.paint(bbox, lambda x, y: rect_sdf(x, y, center, half, yaw), grey)

    def disc(self, center: tuple[float, float], radius: float, grey: float) -> None:
        """Paint a disc."""
        bbox = (center[0] - radius, center[1] - radius, center[0] + radius, center[1] + radius)
        self.paint(bbox, lambda x, y: disc_sdf(x, y, center, radius), grey)

    def layer(self, height: float, box: int, background: float) -> Layer:
        """The finished layer, box-filtered over ``box`` x ``box`` texels (odd; 1 = none)."""
        tex: np.ndarray = np.ascontiguousarray(np.dstack([self.p, self.a]))
        if box > 1:
            tex = cv2.blur(tex, (box, box), borderType=cv2.BORDER_CONSTANT)
        flat = np.ascontiguousarray(tex[..., 0] + (1.0 - tex[..., 1]) * np.float32(background))
        return Layer(height, self.x0, self.y0, self.texel, tex, flat)


def _lamp_half_diag(lp: Lamp) -> float:
    """Half the diagonal of a lamp's bounding rectangle, m."""
    return 0.5 * math.hypot(lp.length, lp.width)


def _paint_surface(cv: _Canvas, s: Surface) -> None:
    """Paint a surface: base rectangle, tile-grid lines clipped to it, then its marks."""
    x0, y0, x1, y1 = s.extent
    cv.rect(((x0 + x1) / 2, (y0 + y1) / 2), (x1 - x0, y1 - y0), 0.0, s.grey)
    if s.tiles is not None:
        tg = s.tiles
        kx = np.arange(
            math.ceil((x0 - tg.origin[0]) / tg.pitch[0]),
            math.floor((x1 - tg.origin[0]) / tg.pitch[0]) + 1,
        )
        ky = np.arange(
            math.ceil((y0 - tg.origin[1]) / tg.pitch[1]),
            math.floor((y1 - tg.origin[1]) / tg.pitch[1]) + 1,
        )
        hw = tg.line_width / 2
        for k in kx:
            x = tg.origin[0] + k * tg.pitch[0]
            xa, xb = max(x - hw, x0), min(x + hw, x1)
            if xb > xa:
                cv.rect(((xa + xb) / 2, (y0 + y1) / 2), (xb - xa, y1 - y0), 0.0, tg.grey)
        for k in ky:
            y = tg.origin[1] + k * tg.pitch[1]
            ya, yb = max(y - hw, y0), min(y + hw, y1)
            if yb > ya:
                cv.rect(((x0 + x1) / 2, (ya + yb) / 2), (x1 - x0, yb - ya), 0.0, tg.grey)
    for it in s.items:
        _paint_item(cv, it)


def _paint_item(cv: _Canvas, it: TextureItem) -> None:
    """Paint one texture mark."""
    if it.kind == "disc":
        cv.disc(it.center, it.size[0] / 2, it.grey)
    else:
        cv.rect(it.center, it.size, it.yaw, it.grey)


def _paint_lamp(cv: _Canvas, lp: Lamp) -> None:
    """Paint a lamp at its (possibly > 255) brightness."""
    if lp.shape == "round":
        cv.disc(lp.center, lp.length / 2, lp.brightness)
    else:
        cv.rect(lp.center, (lp.length, lp.width), lp.yaw, lp.brightness)


def _paint_opening(cv: _Canvas, op: Opening) -> None:
    """Paint a daylight opening: textured sky, then its glazing bars."""
    cv.rect(op.center, op.size, op.yaw, op.daylight())
    for centre, size in op.bars():
        cv.rect(centre, size, op.yaw, op.bar_grey)


def prefilter_size(
    height_above_camera: float, camera: CameraModel, supersample: int, texel: float
) -> int:
    """Odd box-filter width (texels) matching one sub-pixel sample's footprint on a plane.

    For an upward pinhole the footprint of a ray sample on a horizontal plane at
    ``h`` above the camera is ``h / (f S)`` metres wide everywhere in the image.
    """
    spacing = height_above_camera / (math.sqrt(camera.fx * camera.fy) * supersample)
    return max(1, 2 * int(round((spacing / texel - 1.0) / 2.0)) + 1)


def build_layers(world: World, camera: CameraModel | None = None) -> tuple[Layer, ...]:
    """Rasterise the world's ceiling into layers, nearest (lowest) first.

    One layer per height that has surfaces: its surfaces in file order (base, tile
    lines, items), then the daylight openings, then the lamps at that height.
    Lamps and openings at a height without a surface (hung lamps, raised
    skylights) get one small layer each, so that the renderer only
    samples them inside their own image window. Each texture is box-filtered to
    the footprint of a sub-pixel sample (:func:`prefilter_size`), so that the S x S
    samples of a pixel add up to its area coverage without quantisation.

    Args:
        world: the world.
        camera: camera used to size the prefilter (default ``world.rig.camera``).
    """
    cam = camera or world.rig.camera
    st = world.render
    texel = st.texel
    heights = sorted(
        {round(s.height, 6) for s in world.surfaces}
        | {round(lp.height, 6) for lp in world.lamps}
        | {round(op.height, 6) for op in world.openings}
    )
    layers = []
    for h in heights:
        surfs = [s for s in world.surfaces if round(s.height, 6) == h]
        lamps = [lp for lp in world.lamps if round(lp.height, 6) == h]
        opens = [op for op in world.openings if round(op.height, 6) == h]
        groups: list[tuple[list[Surface], list[Opening], list[Lamp]]] = (
            [(surfs, opens, lamps)]
            if surfs
            else [([], [op], []) for op in opens] + [([], [], [lp]) for lp in lamps]
        )
        box = prefilter_size(h - cam.z_cam, cam, st.supersample, texel)
        for g_surfs, g_opens, g_lamps in groups:
            boxes = [s.extent for s in g_surfs]
            for op in g_opens:
                r = 0.5 * math.hypot(*op.size)
                boxes.append((op.center[0] - r, op.center[1] - r, op.center[0] + r, op.center[1] + r))
            for lp in g_lamps:
                r = _lamp_half_diag(lp)
                boxes.append(
                    (lp.center[0] - r, lp.center[1] - r, lp.center[0] + r, lp.center[1] + r)
                )
            b = np.array(boxes)
            cv = _Canvas(
                (b[:, 0].min(), b[:, 1].min(), b[:, 2].max(), b[:, 3].max()), texel, pad=3 + box
            )
            for s in g_surfs:
                _paint_surface(cv, s)
            for op in g_opens:
                _paint_opening(cv, op)
            for lp in g_lamps:
                _paint_lamp(cv, lp)
            layers.append(cv.layer(float(h), box, st.background))
            log.debug("layer at %.3f m: %s texels, prefilter %d", h, layers[-1].tex.shape[:2], box)
    return tuple(layers)


# --------------------------------------------------------------------------- rays
def sample_rays(camera: CameraModel, supersample: int) -> tuple[np.ndarray, np.ndarray, BoolArray]:
    """Normalised ceiling coordinates of every sub-pixel sample.

    Args:
        camera: the camera (distortion included via ``cv2.undistortPoints``).
        supersample: ``S``; samples sit at ``col + (i + 0.5) / S - 0.5``, ``i < S``.

    Returns:
        ``(U, V, valid)``: (S H, S W) float32 forward/left per metre of height
        (body axes), and where the ray points upwards.
    """
    s = int(supersample)
    cols = (np.arange(camera.width * s) + 0.5) / s - 0.5
    rows = (np.arange(camera.height * s) + 0.5) / s - 0.5
    gc, gr = np.meshgrid(cols, rows)
    m = camera.normalized_from_pixels(np.column_stack([gc.ravel(), gr.ravel()]))
    valid = np.all(np.isfinite(m), axis=1).reshape(gc.shape)
    m = np.nan_to_num(m, nan=0.0)
    u = m[:, 0].reshape(gc.shape).astype(np.float32)
    v = m[:, 1].reshape(gc.shape).astype(np.float32)
    return u, v, valid


def camera_center(camera: CameraModel, pose: FloatArray) -> FloatArray:
    """World ``(x, y)`` of the optical centre for a body pose ``(x, y, theta)``."""
    c, s = math.cos(pose[2]), math.sin(pose[2])
    bx, by = camera.body_t_camera[:2]
    return np.array([pose[0] + c * bx - s * by, pose[1] + s * bx + c * by])


class CeilingRenderer:
    """Renders a world's ceiling as seen by its camera (see the module docstring).

    Args:
        world: the world (its ``render`` settings and ``rig.camera`` are used).
        camera: another camera to render with (default ``world.rig.camera``).
    """

    def __init__(self, world: World, camera: CameraModel | None = None):
        """Rasterise the layers and precompute the sub-pixel rays."""
        self.world = world
        self.camera = camera or world.rig.camera
        self.settings = world.render
        self.layers = build_layers(world, self.camera)
        self.u, self.v, self.valid = sample_rays(self.camera, self.settings.supersample)
        self.all_valid = bool(self.valid.all())
        self.m_max = float(np.sqrt(self.u**2 + self.v**2)[self.valid].max())
        b = np.array([lay.bounds for lay in self.layers]).reshape(-1, 4)
        self._corners = np.stack(
            [b[:, [0, 1]], b[:, [2, 1]], b[:, [2, 3]], b[:, [0, 3]]], axis=1
        )  # (L, 4, 2)
        self._h = np.array([lay.height for lay in self.layers]) - self.camera.z_cam
        self._exact_windows = not self.camera.has_distortion and self.all_valid

    def _windows(self, pose: FloatArray, cxy: FloatArray) -> list[tuple[slice, slice] | None]:
        """Per layer, the sample-grid window that can see it (None: out of view)."""
        cam = self.camera
        rows, cols = self.u.shape
        full = (slice(0, rows), slice(0, cols))
        reach = self._h * self.m_max
        lo = self._corners.min(axis=1)
        hi = self._corners.max(axis=1)
        in_view = (cxy + reach[:, None] >= lo).all(axis=1) & (cxy - reach[:, None] <= hi).all(
            axis=1
        )
        if not self._exact_windows:
            return [full if k else None for k in in_view]
        # Pinhole, every ray upwards: a layer's rectangle images to the convex hull of
        # its corners' images, so their bounding box (padded) is a safe window.
        c, s = math.cos(pose[2]), math.sin(pose[2])
        d = self._corners - cxy  # (L, 4, 2)
        m = np.stack(
            [
                c * d[..., 0] + s * d[..., 1],
                -s * d[..., 0] + c * d[..., 1],
                self._h[:, None] * np.ones(4),
            ],
            -1,
        )
        cam_pts = m @ cam.body_R_camera  # body -> camera axes, (L, 4, 3)
        col = cam.fx * cam_pts[..., 0] / cam_pts[..., 2] + cam.cx
        row = cam.fy * cam_pts[..., 1] / cam_pts[..., 2] + cam.cy
        ss = self.settings.supersample
        out: list[tuple[slice, slice] | None] = []
        for k in range(len(self.layers)):
            if not in_view[k]:
                out.append(None)
                continue
            c0 = max(int(math.floor((col[k].min() + 0.5) * ss - 0.5)) - 2, 0)
            c1 = min(int(math.ceil((col[k].max() + 0.5) * ss - 0.5)) + 3, cols)
            r0 = max(int(math.floor((row[k].min() + 0.5) * ss - 0.5)) - 2, 0)
            r1 = min(int(math.ceil((row[k].max() + 0.5) * ss - 0.5)) + 3, rows)
            out.append((slice(r0, r1), slice(c0, c1)) if (r0 < r1 and c0 < c1) else None)
        return out

    def render_linear(self, pose: FloatArray) -> np.ndarray:
        """Noise-free radiance image before saturation.

        Args:
            pose: (3,) body pose ``(x, y, theta)``, world m and rad.

        Returns:
            (H, W) float32 grey levels (lamps may exceed 255).
        """
        cam = self.camera
        bg = np.float32(self.settings.background)
        c, s = np.float32(math.cos(pose[2])), np.float32(math.sin(pose[2]))
        a = c * self.u - s * self.v  # world-x offset per metre of height
        b = s * self.u + c * self.v
        cxy = camera_center(cam, pose)
        wins = self._windows(pose, cxy)
        acc = np.zeros_like(a)
        trans = np.ones_like(a)
        last = len(self.layers) - 1
        for k, layer in enumerate(self.layers):
            win = wins[k]
            if win is None:
                continue
            scale = np.float32((layer.height - cam.z_cam) / layer.texel)
            ox = np.float32((cxy[0] - layer.x0) / layer.texel)
            oy = np.float32((cxy[1] - layer.y0) / layer.texel)
            if k == last:
                # Nothing lies behind the highest layer: sample it composited over the
                # background, one channel, over the whole grid.
                flat = cv2.remap(layer.flat, a * scale + ox, b * scale + oy, cv2.INTER_LINEAR,
                                 borderMode=cv2.BORDER_CONSTANT, borderValue=float(bg))  # fmt: skip
                acc += trans * flat
                trans = None  # type: ignore[assignment]
                break
            samp = cv2.remap(layer.tex, a[win] * scale + ox, b[win] * scale + oy, cv2.INTER_LINEAR,
                             borderMode=cv2.BORDER_CONSTANT, borderValue=0)  # fmt: skip
            acc[win] += trans[win] * samp[..., 0]
            trans[win] *= 1.0 - samp[..., 1]
        if trans is not None:
            acc += trans * bg
        if not self.all_valid:
            acc[~self.valid] = bg
        return cv2.resize(acc, (cam.width, cam.height), interpolation=cv2.INTER_AREA)

    def render(self, pose: FloatArray, rng: np.random.Generator | None) -> ImageU8:
        """A ceiling image: radiance, glare, sensor noise, saturation.

        Args:
            pose: (3,) body pose ``(x, y, theta)``.
            rng: generator for the sensor noise; None renders without noise.

        Returns:
            (H, W) uint8.
        """
        img = self.render_linear(pose)
        st = self.settings
        if st.bloom > 0:
            excess = np.maximum(img - 255.0, 0.0)
            img = img + np.float32(st.bloom) * cv2.GaussianBlur(excess, (0, 0), st.bloom_sigma)
        if rng is not None and st.noise_sigma > 0:
            img = img + rng.normal(0.0, st.noise_sigma, img.shape).astype(np.float32)
        return np.clip(np.rint(img), 0, 255).astype(np.uint8)
