"""Ray casting (marching and range table) against a hand-made box room."""

from __future__ import annotations

import math

import numpy as np
import pytest

from lampsam.localization.grid import LogOddsConfig, OccupancyGrid
from lampsam.localization.raycast import RangeTable, RaycastError, cast_rays, distance_field

RES = 0.1


def box_room(origin: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> OccupancyGrid:
    """A 4 m x 3 m room (40 x 30 cells of 0.1 m), one-cell walls, a pillar.

    Free interior in map coordinates: x in [0.1, 3.9], y in [0.1, 2.9]; the
    pillar occupies cells ix 30..31, iy 10..11, i.e. x in [3.0, 3.2], y in [1.0, 1.2].
    """
    lo = np.full((30, 40), -LogOddsConfig().l_max)
    lo[0, :] = lo[-1, :] = lo[:, 0] = lo[:, -1] = 4.0
    lo[10:12, 30:32] = 4.0
    return OccupancyGrid(lo, RES, np.array(origin))


def _room_range(x: float, y: float, phi: float) -> float:
    """Exact distance from (x, y) along heading phi to the room's walls or the pillar."""
    c, s = math.cos(phi), math.sin(phi)
    best = math.inf
    # Axis-aligned boxes (x0, x1, y0, y1): slab test for the nearest entry.
    boxes = [(-1.0, 0.1, -1.0, 4.0), (3.9, 5.0, -1.0, 4.0), (-1.0, 5.0, -1.0, 0.1),
             (-1.0, 5.0, 2.9, 4.0), (3.0, 3.2, 1.0, 1.2)]
    for x0, x1, y0, y1 in boxes:
        tx = sorted(((x0 - x) / c, (x1 - x) / c)) if abs(c) > 1e-12 else (
            (-math.inf, math.inf) if x0 <= x <= x1 else (math.inf, -math.inf))
        ty = sorted(((y0 - y) / s, (y1 - y) / s)) if abs(s) > 1e-12 else (
            (-math.inf, math.inf) if y0 <= y <= y1 else (math.inf, -math.inf))
        t0, t1 = max(tx[0], ty[0]), min(tx[1], ty[1])
        if t0 <= t1 and t1 >= 0:
            best = min(best, max(t0, 0.0))
    return best


def test_distance_field_in_cells() -> None:
    occ = np.zeros((5, 7), dtype=bool)
    occ[2, 3] = True
    d = distance_field(occ)
    assert d[2, 3] == 0 and d[2, 5] == pytest.approx(2.0)
    assert d[0, 0] == pytest.approx(math.sqrt(13))
    assert np.isinf(distance_field(np.zeros((2, 2), dtype=bool))).all()


def test_cast_rays_box_room_exact_to_one_cell() -> None:
    grid = box_room()
    angles = np.radians(np.arange(360.0))
    poses = np.array([[2.0, 1.5, 0.0], [0.55, 0.45, 0.7], [2.6, 1.1, -2.0], [3.5, 2.5, 3.0]])
    r = cast_rays(grid, poses, angles, max_range=10.0)
    assert r.shape == (4, 360)
    truth = np.array([[_room_range(p[0], p[1], p[2] + a) for a in angles] for p in poses])
    err = r - truth
    # Exact cell traversal near walls: the entry distance into the first occupied
    # cell, up to the 1e-6-cell nudge across boundaries (the issue asks for one cell).
    assert np.abs(err).max() <= 1e-5, np.abs(err).max()
    # Straight hand-checked beams: from (2.0, 1.5) heading 0 the wall face is at x = 3.9.
    assert r[0, 0] == pytest.approx(1.9, abs=RES)
    assert r[0, 90] == pytest.approx(1.4, abs=RES)   # +y wall at y = 2.9
    assert r[0, 180] == pytest.approx(1.9, abs=RES)  # -x wall at x = 0.1


def test_cast_rays_rotated_origin_and_max_range() -> None:
    # The same room with a map origin rotated by 90 deg: map x = world y.
    grid = box_room((5.0, -1.0, math.pi / 2))
    # World point of map coordinates (2.0, 1.5): origin + R(90 deg) (2.0, 1.5) = (3.5, 1.0).
    pose_world = np.array([[3.5, 1.0, math.pi / 2]])  # facing map +x
    r = cast_rays(grid, pose_world, np.array([0.0, math.pi / 2]), max_range=10.0)
    np.testing.assert_allclose(r[0], [1.9, 1.4], atol=1e-5)
    short = cast_rays(grid, pose_world, np.array([0.0]), max_range=1.0)
    assert short[0, 0] == pytest.approx(1.0)
    outside = cast_rays(grid, np.array([[100.0, 100.0, 0.0]]), np.array([0.0]), max_range=3.0)
    assert outside[0, 0] == pytest.approx(3.0)


def test_range_table_matches_marching(rng: np.random.Generator) -> None:
    grid = box_room()
    table = RangeTable.build(grid, n_angles=360, max_range=8.0)
    assert table.n_angles == 360
    n = 200
    poses = np.column_stack([rng.uniform(0.3, 2.8, n), rng.uniform(0.3, 2.7, n),
                             rng.uniform(-math.pi, math.pi, n)])
    angles = np.radians(np.arange(0.0, 360.0, 10.0))
    # The table uses the cell centre and the nearest 1-deg bin: compare with marching from there.
    centres = grid.cell_to_world(grid.world_to_cell(poses[:, :2]))
    bins = np.rint(np.degrees(poses[:, 2])) * math.pi / 180
    exact = cast_rays(grid, np.column_stack([centres, bins]), angles, 8.0)
    np.testing.assert_allclose(table.lookup(poses, angles), exact, atol=1e-3)
    # And the truth from the true pose, within the quantisation (half a cell + 0.5 deg at <= 4 m).
    truth = np.array([[_room_range(p[0], p[1], p[2] + a) for a in angles] for p in poses])
    assert np.median(np.abs(table.lookup(poses, angles) - truth)) < RES
    # Poses in a wall or outside the map get range 0.
    np.testing.assert_allclose(table.lookup(np.array([[0.05, 1.0, 0.0], [-9, 0, 0]]), angles), 0.0)
    with pytest.raises(RaycastError, match="uint16"):
        RangeTable.build(grid, max_range=100.0)
