"""True landmarks of a ceiling world: its lamps and the corners derived from its surfaces.

Corners are tile-grid intersections inside a surface (except those under an item or
lamp of that surface), the four corners of ``rect`` items and, when asked, of the
surface's extent (the world schema: :mod:`lampsam.datasets.world`). World frame,
metres, ``z`` above the floor.
"""

from __future__ import annotations

import math

import numpy as np

from lampsam.arrays import FloatArray
from lampsam.datasets.logrun import LandmarkTable
from lampsam.datasets.world import LAMP_TYPES, Surface, TextureItem, World


def _grid_intersections(s: Surface) -> FloatArray:
    """(N, 2) tile-grid intersections strictly inside a surface (a line width from the edge)."""
    assert s.tiles is not None
    tg = s.tiles
    x0, y0, x1, y1 = s.extent
    m = 2 * tg.line_width
    xs = tg.origin[0] + tg.pitch[0] * np.arange(
        math.ceil((x0 + m - tg.origin[0]) / tg.pitch[0]),
        math.floor((x1 - m - tg.origin[0]) / tg.pitch[0]) + 1,
    )
    ys = tg.origin[1] + tg.pitch[1] * np.arange(
        math.ceil((y0 + m - tg.origin[1]) / tg.pitch[1]),
        math.floor((y1 - m - tg.origin[1]) / tg.pitch[1]) + 1,
    )
    gx, gy = np.meshgrid(xs, ys)
    return np.column_stack([gx.ravel(), gy.ravel()])


def _item_contains(item: TextureItem, xy: FloatArray, margin: float) -> np.ndarray:
    """(N,) bool: points on a texture item grown by ``margin``."""
    d = np.asarray(xy).reshape(-1, 2) - np.asarray(item.center)
    if item.kind == "disc":
        return np.hypot(d[:, 0], d[:, 1]) <= item.size[0] / 2 + margin
    c, s = math.cos(item.yaw), math.sin(item.yaw)
    lx = c * d[:, 0] + s * d[:, 1]
    ly = -s * d[:, 0] + c * d[:, 1]
    return (np.abs(lx) <= item.size[0] / 2 + margin) & (np.abs(ly) <= item.size[1] / 2 + margin)


def world_landmarks(world: World) -> LandmarkTable:
    """True landmarks of a world: its lamps, then the derived corners.

    Corner ids start at ``world.corner_id_start`` and follow the order: for each
    surface, tile intersections (row-major in y then x), rect item corners, extent
    corners. Tile intersections lying on an item or a lamp at the surface's height
    (grown by 5 cm) are left out.

    Returns:
        The table; lamps' ``xyz`` is the centre of the lamp face, ``phi`` the yaw
        (rect lamps wrapped to (-pi/2, pi/2]; round 0), length/width as in :class:`Lamp`.
    """
    ids: list[int] = []
    types: list[str] = []
    xyz: list[tuple[float, float, float]] = []
    phi: list[float] = []
    length: list[float] = []
    width: list[float] = []
    for lp in world.lamps:
        ids.append(lp.id)
        types.append(LAMP_TYPES[lp.shape])
        xyz.append((lp.center[0], lp.center[1], lp.height))
        if lp.shape == "rect":
            a = (lp.yaw + math.pi / 2) % math.pi - math.pi / 2
            phi.append(math.pi / 2 if a == -math.pi / 2 else a)
        elif lp.shape == "square":
            phi.append(lp.yaw)
        else:
            phi.append(0.0)
        length.append(lp.length)
        width.append(lp.width)
    next_id = world.corner_id_start
    for s in world.surfaces:
        pts: list[FloatArray] = []
        if s.tiles is not None and s.tiles.corners:
            g = _grid_intersections(s)
            keep = np.ones(len(g), dtype=bool)
            for it in s.items:
                keep &= ~_item_contains(it, g, 0.05)
            for lp in world.lamps:
                if abs(lp.height - s.height) < 1e-6:
                    keep &= ~lp.contains(g, 0.05)
            for op in world.openings:  # no tile grid across the sky
                keep &= ~op.contains(g, 0.05)
            pts.append(g[keep])
        for it in s.items:
            if it.kind == "rect" and it.corners:
                pts.append(it.corner_points())
        if s.corners:
            x0, y0, x1, y1 = s.extent
            pts.append(np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]]))
        for p in pts:
            for x, y in p:
                ids.append(next_id)
                next_id += 1
                types.append("corner")
                xyz.append((float(x), float(y), s.height))
                phi.append(0.0)
                length.append(0.0)
                width.append(0.0)
    return LandmarkTable(
        ids=np.array(ids, dtype=np.int64),
        types=tuple(types),
        xyz=np.array(xyz, dtype=np.float64).reshape(-1, 3),
        phi=np.array(phi),
        length=np.array(length),
        width=np.array(width),
    )
