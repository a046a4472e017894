"""The occupied / free rule of grid maps in one form (``grid.occupied_cells`` /
``free_cells``, on log-odds) against map_server's probability form."""

from __future__ import annotations

import math

import numpy as np
import pytest

from lampsam.localization.grid import (
    LogOddsConfig,
    OccupancyGrid,
    free_cells,
    free_mask,
    logit,
    occupancy_probabilities,
    occupied_cells,
    occupied_mask,
)


@pytest.mark.parametrize(("occ", "free"), [(0.65, 0.196), (0.6, 0.2), (0.9, 0.05)])
def test_log_odds_rule_equals_probability_rule(rng: np.random.Generator, occ: float,
                                               free: float) -> None:
    """On uniform log-odds, on the sums of ``l_occ`` / ``l_free`` a grid holds, and on values
    1e-9 either side of each threshold, ``l > logit(t)`` selects exactly the cells
    ``p > t`` does (and ``<`` likewise)."""
    cfg = LogOddsConfig(occupied_thresh=occ, free_thresh=free)
    sums = (cfg.l_occ * rng.integers(0, 8, 4000) + cfg.l_free * rng.integers(0, 12, 4000))
    near = np.array([logit(t) + d for t in (occ, free) for d in (-1e-9, 1e-9)])
    lo = np.concatenate([rng.uniform(-6.0, 6.0, 20000), np.clip(sums, cfg.l_min, cfg.l_max), near])
    grid = OccupancyGrid(lo[None, :], 0.05)
    p = occupancy_probabilities(grid)
    np.testing.assert_array_equal(occupied_cells(lo, cfg), (p > occ)[0])
    np.testing.assert_array_equal(free_cells(lo, cfg), (p < free)[0])
    np.testing.assert_array_equal(occupied_mask(grid, cfg), p > occ)
    np.testing.assert_array_equal(free_mask(grid, cfg), p < free)
    assert occupied_cells(near[:2], cfg).tolist() == [False, True]
    assert free_cells(near[2:], cfg).tolist() == [True, False]


def test_a_cell_on_the_threshold_is_neither() -> None:
    """map_server's strict rule: exactly ``logit(t)`` is not occupied (``>``), exactly
    ``logit(free)`` is not free (``<``); one ulp beyond is."""
    cfg = LogOddsConfig()
    occ_l, free_l = logit(cfg.occupied_thresh), logit(cfg.free_thresh)
    assert occ_l == pytest.approx(math.log(0.65 / 0.35), abs=1e-15)
    assert not occupied_cells(np.array([occ_l]), cfg)[0]
    assert occupied_cells(np.array([np.nextafter(occ_l, 1.0)]), cfg)[0]
    assert not free_cells(np.array([free_l]), cfg)[0]
    assert free_cells(np.array([np.nextafter(free_l, -2.0)]), cfg)[0]
