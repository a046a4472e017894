"""Lamps under their own symbol with their own iSAM2 relinearisation threshold (issue 19).

- the ceiling handler keys lamps ``L(j)`` and corners ``C(j)``, and readers that know
  only an id find the one in the graph;
- ``[isam2] lamp_relinearize_threshold`` relinearises a lamp whose pending correction
  is under the common threshold, and leaves a corner with the same correction alone.
"""

from __future__ import annotations

import gtsam
import numpy as np
import pytest
from gtsam.symbol_shorthand import C, L, X

from lampsam.backend.ceiling_graph import CEILING_SYMBOLS, find_point_key, point_key
from lampsam.backend.config import Isam2Config
from lampsam.backend.interface import LandmarkKind


def test_point_keys_of_lamps_and_corners() -> None:
    assert point_key(LandmarkKind.LAMP, 7) == L(7)
    assert point_key(LandmarkKind.CORNER, 7) == C(7)
    assert find_point_key(7, {int(C(7)), int(X(7))}) == C(7)
    assert find_point_key(7, {int(L(7))}) == L(7)
    assert find_point_key(7, {int(L(8)), int(C(6))}) is None


def _pending_correction_graph() -> tuple[gtsam.NonlinearFactorGraph, gtsam.Values, np.ndarray]:
    """A pose, a lamp and a corner, each held by a prior; both points start 5 cm off."""
    truth = np.array([1.0, 2.0, 2.5])
    graph = gtsam.NonlinearFactorGraph()
    graph.add(gtsam.PriorFactorPose2(X(0), gtsam.Pose2(), gtsam.noiseModel.Isotropic.Sigma(3, 1e-3)))
    values = gtsam.Values()
    values.insert(X(0), gtsam.Pose2())
    for key in (L(0), C(1)):
        graph.add(gtsam.PriorFactorPoint3(key, truth, gtsam.noiseModel.Isotropic.Sigma(3, 1e-3)))
        values.insert(key, truth + np.array([0.0, 0.0, -0.05]))
    return graph, values, truth


@pytest.mark.parametrize("lamp_threshold", [None, 0.01])
def test_lamp_threshold_relinearises_lamps_only(lamp_threshold: float | None) -> None:
    cfg = Isam2Config(relinearize_threshold=0.1, relinearize_skip=1,
                      lamp_relinearize_threshold=lamp_threshold)
    isam = gtsam.ISAM2(cfg.to_gtsam(CEILING_SYMBOLS))
    graph, values, truth = _pending_correction_graph()
    isam.update(graph, values)  # linearised at the start: a pending correction of 5 cm each
    isam.update()  # the relinearisation check
    lin = isam.getLinearizationPoint()
    lamp_moved = abs(float(lin.atPoint3(L(0))[2]) - truth[2]) < 1e-6
    corner_moved = abs(float(lin.atPoint3(C(1))[2]) - truth[2]) < 1e-6
    assert not corner_moved  # 0.05 < 0.1: the corner keeps its linearisation point
    assert lamp_moved == (lamp_threshold is not None)  # 0.05 > 0.01: the lamp is relinearised
    # the estimate is the same either way (one Gauss-Newton step of a linear prior)
    np.testing.assert_allclose(isam.calculateEstimatePoint3(L(0)), truth, atol=1e-9)


def test_threshold_map_only_with_symbols_and_a_different_lamp_threshold() -> None:
    def printed(params: gtsam.ISAM2Params) -> str:
        return " ".join(str(params).split())

    scalar = "relinearizeThreshold: 0.1"
    assert scalar in printed(Isam2Config(lamp_relinearize_threshold=0.01).to_gtsam())
    assert scalar in printed(Isam2Config(lamp_relinearize_threshold=0.1).to_gtsam(CEILING_SYMBOLS))
    mapped = printed(Isam2Config(lamp_relinearize_threshold=0.01).to_gtsam(CEILING_SYMBOLS))
    assert "{mapped}" in mapped and "'c' -> [0.1 0.1 0.1 ]" in mapped
    assert "'l' -> [0.01 0.01 0.01 ]" in mapped and "'a' -> [0.01 0.01 0.01 ]" in mapped


def test_factor_cache_and_slot_settings_reach_gtsam() -> None:
    params = Isam2Config(cache_linearized_factors=False, find_unused_factor_slots=True).to_gtsam()
    assert params.cacheLinearizedFactors is False and params.findUnusedFactorSlots is True
    params = Isam2Config().to_gtsam()  # GTSAM's defaults
    assert params.cacheLinearizedFactors is True and params.findUnusedFactorSlots is False
