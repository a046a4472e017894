"""Occupancy grid: conversions, free/occupied logic, ROS map_server files."""

from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

from lampsam.localization.grid import (
    PGM_FREE,
    PGM_OCCUPIED,
    PGM_UNKNOWN,
    GridMapError,
    LogOddsConfig,
    OccupancyGrid,
    free_mask,
    integrate_points,
    integrate_scan,
    load_map_server,
    occupancy_probabilities,
    occupied_mask,
    save_map_server,
)


def test_world_cell_round_trip_with_yaw(rng: np.random.Generator) -> None:
    grid = OccupancyGrid(np.zeros((40, 60)), 0.1, np.array([1.0, -2.0, 0.3]))
    cells = np.stack([rng.integers(0, 60, 50), rng.integers(0, 40, 50)], axis=1)
    centres = grid.cell_to_world(cells)
    np.testing.assert_array_equal(grid.world_to_cell(centres), cells)
    # Cell (0, 0) centre sits half a cell from the origin along the rotated axes.
    c, s = math.cos(0.3), math.sin(0.3)
    expected = np.array([1.0 + 0.05 * c - 0.05 * s, -2.0 + 0.05 * s + 0.05 * c])
    np.testing.assert_allclose(grid.cell_to_world(np.array([0, 0])), expected, atol=1e-12)


def test_integrate_scan_hand_made_case() -> None:
    # 10 x 5 cells of 1 m, origin at (0, 0). Sensor at the centre of cell (0, 2)
    # looking along +x; one beam of 6.6 m ends at x = 7.1, inside cell (7, 2).
    cfg = LogOddsConfig(l_occ=0.9, l_free=-0.4, l_min=-2.0, l_max=2.0)
    grid = OccupancyGrid(np.zeros((5, 10)), 1.0)
    integrate_scan(grid, np.array([0.5, 2.5, 0.0]), np.array([6.6]), np.array([0.0]),
                   max_range=20.0, config=cfg)
    row = grid.log_odds[2]
    np.testing.assert_allclose(row[:7], -0.4)   # cells 0..6 traversed: free once each
    assert row[7] == pytest.approx(0.9)          # end cell: occupied
    np.testing.assert_allclose(row[8:], 0.0)     # behind the hit: unknown
    np.testing.assert_allclose(np.delete(grid.log_odds, 2, axis=0), 0.0)  # other rows untouched


def test_integrate_scan_vertical_beam_and_max_range() -> None:
    grid = OccupancyGrid(np.zeros((10, 3)), 1.0)
    cfg = LogOddsConfig()
    # Beam straight up (+y in world) from cell (1, 0): no return (range = max) clears 4 cells.
    integrate_scan(grid, np.array([1.5, 0.5, math.pi / 2]), np.array([np.inf, np.nan]),
                   np.array([0.0, 0.1]), max_range=4.0, config=cfg)
    col = grid.log_odds[:, 1]
    np.testing.assert_allclose(col[:5], cfg.l_free)  # y in [0.5, 4.5] -> rows 0..4
    np.testing.assert_allclose(col[5:], 0.0)
    assert not occupied_mask(grid).any()


def test_repeated_updates_clamp_and_occupied_wins() -> None:
    cfg = LogOddsConfig(l_occ=1.0, l_free=-1.0, l_min=-3.0, l_max=2.5)
    grid = OccupancyGrid(np.zeros((3, 8)), 0.5)
    sensor = np.array([0.25, 0.75])
    # Two points on one line: the nearer one's cell is both traversed (towards the farther)
    # and hit: occupied wins within one call.
    pts = np.array([[1.75, 0.75], [3.25, 0.75]])
    for _ in range(5):
        integrate_points(grid, sensor, pts, max_range=10.0, config=cfg)
    row = grid.log_odds[1]
    assert row[3] == pytest.approx(2.5)   # hit 5 times, clamped to l_max
    assert row[6] == pytest.approx(2.5)
    np.testing.assert_allclose(row[[0, 1, 2, 4, 5]], -3.0)  # free 5 times, clamped
    assert row[7] == 0.0


def test_probabilities_and_masks() -> None:
    grid = OccupancyGrid(np.array([[0.0, 2.0, -2.0]]), 1.0)
    p = occupancy_probabilities(grid)
    np.testing.assert_allclose(p, [[0.5, 1 / (1 + math.exp(-2)), 1 / (1 + math.exp(2))]])
    np.testing.assert_array_equal(occupied_mask(grid), [[False, True, False]])
    np.testing.assert_array_equal(free_mask(grid), [[False, False, True]])


def test_map_server_round_trip_and_pgm_orientation(tmp_path: Path) -> None:
    cfg = LogOddsConfig()
    grid = OccupancyGrid(np.zeros((20, 30)), 0.05, np.array([-1.0, 2.0, 0.0]))
    # An obstacle near the top-right of the map (high x, high y), free cell near bottom-left.
    obstacle = np.array([-1.0 + 0.05 * 27.5, 2.0 + 0.05 * 18.5])
    ix, iy = grid.world_to_cell(obstacle)
    assert (ix, iy) == (27, 18)
    grid.log_odds[iy, ix] = 3.0
    grid.log_odds[1, 2] = -3.0
    yaml_path = save_map_server(grid, tmp_path / "map", cfg)
    meta = yaml.safe_load(yaml_path.read_text())
    assert meta["image"] == "map.pgm" and meta["mode"] == "trinary" and meta["negate"] == 0
    assert meta["resolution"] == pytest.approx(0.05)
    assert meta["origin"] == pytest.approx([-1.0, 2.0, 0.0])
    img = cv2.imread(str(tmp_path / "map.pgm"), cv2.IMREAD_UNCHANGED)
    assert img.shape == (20, 30) and img.dtype == np.uint8
    # PGM row 0 is the TOP (max y): the obstacle in array row 18 is image row 20 - 1 - 18 = 1.
    assert img[1, 27] == PGM_OCCUPIED
    assert img[20 - 1 - 1, 2] == PGM_FREE
    assert img[0, 0] == PGM_UNKNOWN
    assert (img == PGM_OCCUPIED).sum() == 1 and (img == PGM_FREE).sum() == 1
    back = load_map_server(yaml_path, cfg)
    np.testing.assert_allclose(back.origin, grid.origin)
    assert back.resolution == pytest.approx(0.05)
    np.testing.assert_array_equal(occupied_mask(back), occupied_mask(grid))
    np.testing.assert_array_equal(free_mask(back), free_mask(grid))
    assert back.log_odds[18, 27] == cfg.l_max and back.log_odds[1, 2] == cfg.l_min


def test_load_map_server_bad_input(tmp_path: Path) -> None:
    with pytest.raises(GridMapError, match="not found"):
        load_map_server(tmp_path / "absent.yaml")
    bad = tmp_path / "bad.yaml"
    bad.write_text("image: nothere.pgm\nresolution: 0.05\norigin: [0, 0, 0]\n")
    with pytest.raises(GridMapError, match="nothere.pgm"):
        load_map_server(bad)
    bad.write_text("image: x.pgm\nresolution: 0.05\n")
    with pytest.raises(GridMapError, match="origin"):
        load_map_server(bad)


def test_integrate_scan_rejects_mismatched_shapes() -> None:
    grid = OccupancyGrid(np.zeros((4, 4)), 1.0)
    with pytest.raises(GridMapError, match="shape"):
        integrate_scan(grid, np.zeros(3), np.ones(3), np.zeros(2), max_range=5.0)
