"""Branch-and-bound global scan matching: finds the true pose, bounds are admissible, exact search."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from lampsam.localization.correlative import (
    CorrelativeError,
    ScorePyramid,
    SearchConfig,
    branch_and_bound,
    field_score,
    scan_points,
)
from lampsam.localization.grid import OccupancyGrid, occupied_mask
from lampsam.localization.likelihood import BeamModelConfig, LikelihoodFieldModel
from lampsam.localization.map_layers import EnvironmentMaps
from lampsam.localization.map_tables import (
    DISTANCE_FIELD_FILE,
    load_distance_field,
    load_range_table,
    range_table_file,
    save_distance_field,
)
from lampsam.localization.raycast import RangeTable, cast_rays, distance_field

ANGLES = np.linspace(-math.pi / 2, math.pi / 2, 181)


def _clutter_grid(rng: np.random.Generator, size: tuple[float, float], boxes: int) -> OccupancyGrid:
    """A walled room (5 cm cells) with random boxes inside."""
    g = OccupancyGrid.empty(0.0, 0.0, size[0], size[1], 0.05)
    lo = np.full((g.height, g.width), -4.0)
    lo[:2, :] = lo[-2:, :] = lo[:, :2] = lo[:, -2:] = 4.0
    for _ in range(boxes):
        x0, y0 = rng.uniform(1.0, size[0] - 2.0), rng.uniform(1.0, size[1] - 2.0)
        w, h = rng.uniform(0.3, 1.5, 2)
        lo[int(y0 / 0.05) : int((y0 + h) / 0.05), int(x0 / 0.05) : int((x0 + w) / 0.05)] = 4.0
    g.log_odds = lo
    return g


def _pyramid(g: OccupancyGrid, cfg: SearchConfig) -> ScorePyramid:
    score, floor = field_score(distance_field(occupied_mask(g)), g.resolution, 0.15, 0.9, 0.1,
                               cfg.max_range)  # fmt: skip
    return ScorePyramid(g, score, floor, cfg)


def _free_pose(g: OccupancyGrid, rng: np.random.Generator) -> np.ndarray:
    dist = distance_field(occupied_mask(g)) * g.resolution
    while True:
        p = np.array([rng.uniform(1, g.width * g.resolution - 1),
                      rng.uniform(1, g.height * g.resolution - 1), rng.uniform(-math.pi, math.pi)])
        if dist[int(p[1] / g.resolution), int(p[0] / g.resolution)] > 0.4:
            return p


def test_finds_the_true_pose_on_a_cluttered_map() -> None:
    rng = np.random.default_rng(3)
    g = _clutter_grid(rng, (30.0, 20.0), 14)
    cfg = SearchConfig(resolution=0.1, max_points=80, max_range=20.0)
    pyr = _pyramid(g, cfg)
    for _ in range(3):
        truth = _free_pose(g, rng)
        r = cast_rays(g, truth[None], ANGLES, 20.0)[0] + rng.normal(0.0, 0.01, ANGLES.size)
        pts = scan_points(r[None], ANGLES, np.zeros((1, 3)), 20.0, cfg.resolution, cfg.max_points)
        cands, stats = branch_and_bound(pyr, pts, cfg)
        best = cands[0].pose
        # a search cell is 10 cm and a heading step 1 deg: the best leaf is the truth's cell
        assert math.hypot(*(best[:2] - truth[:2])) < 0.1
        assert abs(math.remainder(best[2] - truth[2], 2 * math.pi)) < math.radians(1.0)
        # the bound pruned: far fewer leaves scored than the 60,000 free cells x 360 headings
        assert stats.nodes_per_level[-1] < 60_000 * 360 / 100


def test_bound_is_admissible_at_every_level() -> None:
    """B_h(node) >= the score of every leaf below it (Hess et al. eq. 15-16), checked numerically."""
    rng = np.random.default_rng(5)
    g = _clutter_grid(rng, (8.0, 6.0), 6)
    cfg = SearchConfig(resolution=0.1, depth=4, max_points=60, max_range=12.0)
    pyr = _pyramid(g, cfg)
    truth = _free_pose(g, rng)
    r = cast_rays(g, truth[None], ANGLES, 12.0)[0]
    pts = scan_points(r[None], ANGLES, np.zeros((1, 3)), 12.0, cfg.resolution, cfg.max_points)
    hs, ws = pyr.shape
    checked = 0
    for theta in rng.uniform(-math.pi, math.pi, 6):
        off = pyr.flat_offsets(*pyr.offsets(pts, float(theta)))
        leaf_y, leaf_x = np.mgrid[0:hs, 0:ws]
        leaf = pyr.score(0, leaf_x.ravel(), leaf_y.ravel(), np.broadcast_to(off, (leaf_x.size, off.size)))
        leaf = leaf.reshape(hs, ws)
        for h in range(1, cfg.depth + 1):
            n = 2**h
            for _ in range(20):
                x0, y0 = int(rng.integers(-n + 1, ws)), int(rng.integers(-n + 1, hs))
                bound = pyr.score(h, np.array([x0]), np.array([y0]), off[None])[0]
                below = leaf[max(y0, 0) : y0 + n, max(x0, 0) : x0 + n]
                if below.size:
                    assert bound >= below.max() - 1e-3
                    checked += 1
    assert checked > 400


def test_branch_and_bound_equals_exhaustive_search() -> None:
    """The best leaf of the pruned search is the best of every free leaf at every heading."""
    rng = np.random.default_rng(8)
    g = _clutter_grid(rng, (6.0, 5.0), 5)
    cfg = SearchConfig(resolution=0.1, angle_step_deg=5.0, depth=4, max_points=50, max_range=10.0,
                       top_k=3, window=50.0, min_score=-10.0)  # fmt: skip
    pyr = _pyramid(g, cfg)
    truth = _free_pose(g, rng)
    r = cast_rays(g, truth[None], ANGLES, 10.0)[0] + rng.normal(0.0, 0.03, ANGLES.size)
    pts = scan_points(r[None], ANGLES, np.zeros((1, 3)), 10.0, cfg.resolution, cfg.max_points)
    cands, _ = branch_and_bound(pyr, pts, cfg)
    hs, ws = pyr.shape
    free = pyr.free[0][pyr.pad : pyr.pad + hs, pyr.pad : pyr.pad + ws]
    fy, fx = np.nonzero(free)
    best = -math.inf
    for k in range(72):
        off = pyr.flat_offsets(*pyr.offsets(pts, k * math.radians(5.0) - math.pi))
        s = pyr.score(0, fx, fy, np.broadcast_to(off, (fx.size, off.size)))
        best = max(best, float(s.max()))
    assert cands[0].score * len(pts) == pytest.approx(best, abs=1e-3)


def test_joined_scans_and_bad_input() -> None:
    odom = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, math.pi / 2]])
    ranges = np.array([[2.0, np.nan], [3.0, 50.0]])
    pts = scan_points(ranges, np.array([0.0, 0.5]), odom, 30.0, 0.1, 10)
    # scan 1's beam at 0 rad from (1, 0) facing +y ends at (1, 3) in scan 0's frame
    assert pts.shape == (2, 2)
    assert np.allclose(pts, [[2.0, 0.0], [1.0, 3.0]])
    with pytest.raises(CorrelativeError, match="no usable return"):
        scan_points(np.full((1, 2), np.nan), np.array([0.0, 0.5]), np.zeros((1, 3)), 30.0, 0.1, 10)
    with pytest.raises(CorrelativeError, match="whole multiple"):
        _pyramid(OccupancyGrid.empty(0, 0, 2, 2, 0.05), SearchConfig(resolution=0.12))


def test_stored_fields_round_trip_in_one_store(tmp_path: Path) -> None:
    """Distance field and range table live in map_tables' files; every user reads the same ones."""
    g = _clutter_grid(np.random.default_rng(2), (4.0, 3.0), 3)
    dist = distance_field(occupied_mask(g))
    save_distance_field(tmp_path, g, dist)
    stored = load_distance_field(tmp_path, g)
    assert stored is not None and np.array_equal(stored, dist.astype(np.float32))
    beam = BeamModelConfig(sigma_hit=0.15, max_range=8.0)
    a, b = LikelihoodFieldModel(g, beam), LikelihoodFieldModel(g, beam, dist_cells=stored)
    assert np.allclose(a.field, b.field, atol=1e-6)
    maps = EnvironmentMaps.grid_only(g)
    maps = EnvironmentMaps(g, maps.spatial_xyz, maps.spatial_descriptors, maps.ceiling_xyz,
                           maps.ceiling_body_t_camera, cache_dir=tmp_path)  # fmt: skip
    built = maps.range_table(3.0)
    assert sorted(p.name for p in tmp_path.iterdir()) == [DISTANCE_FIELD_FILE, range_table_file(3.0)]
    loaded = load_range_table(tmp_path, g, 3.0)
    assert loaded is not None and np.array_equal(loaded.ranges_mm, built.ranges_mm)
    again = EnvironmentMaps(g, maps.spatial_xyz, maps.spatial_descriptors, maps.ceiling_xyz,
                            maps.ceiling_body_t_camera, cache_dir=tmp_path).range_table(3.0)  # fmt: skip
    assert np.array_equal(again.row_of_cell, built.row_of_cell)


def test_range_tables_of_two_max_ranges_live_side_by_side(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Two localizers with different beam ranges on one map each build their table once, then load it."""
    import lampsam.localization.map_tables as mt

    g = _clutter_grid(np.random.default_rng(3), (4.0, 3.0), 3)
    base = EnvironmentMaps.grid_only(g)

    def fresh_maps() -> EnvironmentMaps:  # a new localize process on the same map directory
        return EnvironmentMaps(g, base.spatial_xyz, base.spatial_descriptors, base.ceiling_xyz,
                               base.ceiling_body_t_camera, cache_dir=tmp_path)  # fmt: skip

    built: list[float] = []
    real_build = mt.build_range_table

    def counting_build(grid: OccupancyGrid, max_range: float, n_angles: int = 360) -> RangeTable:
        built.append(max_range)
        return real_build(grid, max_range, n_angles)

    monkeypatch.setattr(mt, "build_range_table", counting_build)
    t3 = fresh_maps().range_table(3.0)
    t2 = fresh_maps().range_table(2.0)
    assert built == [3.0, 2.0]
    again3, again2 = fresh_maps().range_table(3.0), fresh_maps().range_table(2.0)
    assert built == [3.0, 2.0]  # both loaded, neither rebuilt
    assert np.array_equal(again3.ranges_mm, t3.ranges_mm) and np.array_equal(again2.ranges_mm, t2.ranges_mm)
    assert int(t2.ranges_mm.max()) <= 2000 < int(t3.ranges_mm.max())  # truly different tables
    assert {p.name for p in tmp_path.glob("range_table*")} == {range_table_file(3.0), range_table_file(2.0)}
    # a map written before the tables were keyed: its range_table.npz is read when it matches
    (tmp_path / range_table_file(3.0)).rename(tmp_path / mt.RANGE_TABLE_FILE)
    legacy = fresh_maps().range_table(3.0)
    assert built == [3.0, 2.0] and np.array_equal(legacy.ranges_mm, t3.ranges_mm)
