"""Meshes and picture textures of a :class:`~lampsam.datasets.scene3d.Scene3D` for the RGB-D renderer.

:func:`triangle_scene` turns the scene's boxes (walls, doors, furniture), floor,
ceiling and pictures into one triangle mesh with per-triangle colour, texture and
object id; :func:`picture_texture` draws a picture's seeded, feature-rich texture.
World frame of ``docs/conventions.md`` (``z`` up, metres).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from lampsam.arrays import FloatArray, ImageU8, IntArray
from lampsam.datasets.scene3d import KIND_CEILING, KIND_FLOOR, KIND_PICTURE, Picture, Scene3D

TEXTURE_PX_PER_M = 256.0
"""Texture resolution of pictures, pixels per metre."""


@dataclass(frozen=True)
class TriangleScene:
    """One triangle mesh of the whole scene with what a renderer needs per triangle.

    Attributes:
        vertices: (V, 3) float32 world metres.
        triangles: (T, 3) int32 vertex indices.
        colors: (T, 3) float32 base RGB in [0, 1].
        texture_index: (T,) int32 index into ``textures`` or -1 (plain colour).
        tex_coords: (T, 3, 2) float32 texture coordinates (column, row) in [0, 1] of the
            three vertices; barycentric ``(u, v)`` of a hit gives
            ``(1 - u - v) t0 + u t1 + v t2``.
        object_index: (T,) int32 index into ``object_ids``.
        object_ids: object id per index.
        object_kinds: object kind per index.
        textures: the picture textures, uint8 (H, W, 3) RGB.
    """

    vertices: FloatArray
    triangles: IntArray
    colors: FloatArray
    texture_index: IntArray
    tex_coords: FloatArray
    object_index: IntArray
    object_ids: tuple[str, ...]
    object_kinds: tuple[str, ...]
    textures: tuple[ImageU8, ...]


def picture_texture(picture: Picture, px_per_m: float = TEXTURE_PX_PER_M) -> ImageU8:
    """Procedural, SIFT-rich texture of a picture: seeded shapes and text-like marks.

    Args:
        picture: the picture (its ``seed`` fixes the texture).
        px_per_m: texture resolution, pixels per metre.

    Returns:
        uint8 (H, W, 3) RGB, H = height * px_per_m, W = width * px_per_m (at least 16).
    """
    rng = np.random.default_rng(picture.seed)
    w = max(16, int(round(picture.width * px_per_m)))
    h = max(16, int(round(picture.height * px_per_m)))
    img = np.empty((h, w, 3), np.uint8)
    img[:] = rng.integers(170, 250, 3)
    area = w * h
    for _ in range(int(30 + area / 2500)):
        color = tuple(int(c) for c in rng.integers(0, 256, 3))
        kind = rng.integers(0, 4)
        x, y = int(rng.integers(0, w)), int(rng.integers(0, h))
        s = int(rng.integers(4, max(6, min(w, h) // 5)))
        if kind == 0:
            cv2.rectangle(img, (x, y), (x + s, y + int(rng.integers(4, s + 5))), color, -1)
        elif kind == 1:
            cv2.circle(img, (x, y), s // 2 + 2, color, -1)
        elif kind == 2:
            pts = np.stack([x + rng.integers(-s, s, 4), y + rng.integers(-s, s, 4)], axis=1).astype(
                np.int32
            )
            cv2.fillPoly(img, [pts], color)
        else:
            cv2.line(
                img, (x, y), (x + int(rng.integers(-s, s)), y + int(rng.integers(-s, s))), color, 2
            )
    letters = "ABCDEFGHJKLMNPQRSTUVWXYZ0123456789"
    for _ in range(int(3 + h / 40)):
        text = "".join(
            letters[int(i)] for i in rng.integers(0, len(letters), int(rng.integers(3, 8)))
        )
        org = (int(rng.integers(0, max(1, w - 40))), int(rng.integers(14, h)))
        color = tuple(int(c) for c in rng.integers(0, 90, 3))
        cv2.putText(
            img,
            text,
            org,
            cv2.FONT_HERSHEY_SIMPLEX,
            float(rng.uniform(0.4, 1.0)),
            color,
            2,
            cv2.LINE_AA,
        )
    cv2.rectangle(img, (0, 0), (w - 1, h - 1), (40, 30, 20), max(2, w // 60))
    return img


# ---------------------------------------------------------------------------- meshes
_BOX_FACES = np.array(
    [
        [0, 2, 3],
        [0, 3, 1],
        [4, 5, 7],
        [4, 7, 6],
        [0, 1, 5],
        [0, 5, 4],
        [2, 6, 7],
        [2, 7, 3],
        [0, 4, 6],
        [0, 6, 2],
        [1, 3, 7],
        [1, 7, 5],
    ],
    dtype=np.int32,
)


def triangle_scene(scene: Scene3D, px_per_m: float = TEXTURE_PX_PER_M) -> TriangleScene:
    """Triangulate the scene: floor, ceiling, boxes (12 triangles each), pictures (2 each).

    Args:
        scene: the scene.
        px_per_m: picture texture resolution, pixels per metre.

    Returns:
        The :class:`TriangleScene` (world frame, metres).
    """
    verts: list[FloatArray] = []
    tris: list[IntArray] = []
    colors: list[FloatArray] = []
    tex_index: list[IntArray] = []
    tex_coords: list[FloatArray] = []
    obj_index: list[IntArray] = []
    obj_ids: list[str] = []
    obj_kinds: list[str] = []
    textures: list[ImageU8] = []

    def add(
        v: FloatArray,
        f: NDArray[np.integer],
        color: FloatArray,
        oid: str,
        kind: str,
        tex: int = -1,
        tc: FloatArray | None = None,
    ) -> None:
        base = sum(len(x) for x in verts)
        verts.append(np.asarray(v, float))
        tris.append(np.asarray(f, np.int64) + base)
        colors.append(np.tile(np.asarray(color, float), (len(f), 1)))
        tex_index.append(np.full(len(f), tex, np.int32))
        tex_coords.append(np.zeros((len(f), 3, 2)) if tc is None else tc)
        obj_index.append(np.full(len(f), len(obj_ids), np.int32))
        obj_ids.append(oid)
        obj_kinds.append(kind)

    x0, y0, x1, y1 = (float(b) for b in scene.bounds)
    pad = 0.5
    for z, color, oid, kind in (
        (0.0, scene.floor_color, "floor", KIND_FLOOR),
        (scene.height, scene.ceiling_color, "ceiling", KIND_CEILING),
    ):
        quad = np.array(
            [
                [x0 - pad, y0 - pad, z],
                [x1 + pad, y0 - pad, z],
                [x1 + pad, y1 + pad, z],
                [x0 - pad, y1 + pad, z],
            ]
        )
        add(quad, np.array([[0, 1, 2], [0, 2, 3]]), color, oid, kind)
    for box in scene.boxes:
        add(box.corners(), _BOX_FACES, box.color, box.id, box.kind)
    quad_tc = np.array([[[0.0, 0.0], [1.0, 0.0], [1.0, 1.0]], [[0.0, 0.0], [1.0, 1.0], [0.0, 1.0]]])
    for pic in scene.pictures:
        textures.append(picture_texture(pic, px_per_m))
        add(
            pic.corners(),
            np.array([[0, 1, 2], [0, 2, 3]]),
            np.ones(3),
            pic.id,
            KIND_PICTURE,
            len(textures) - 1,
            quad_tc,
        )
    return TriangleScene(
        vertices=np.concatenate(verts).astype(np.float32),
        triangles=np.concatenate(tris).astype(np.int32),
        colors=np.concatenate(colors).astype(np.float32),
        texture_index=np.concatenate(tex_index),
        tex_coords=np.concatenate(tex_coords).astype(np.float32),
        object_index=np.concatenate(obj_index),
        object_ids=tuple(obj_ids),
        object_kinds=tuple(obj_kinds),
        textures=tuple(textures),
    )
