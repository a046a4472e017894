"""Map-to-world alignment (evaluation/map_alignment.py): exact recovery and robustness."""

from __future__ import annotations

import math

import numpy as np
import pytest

from lampsam.evaluation.map_alignment import (
    AlignmentInputError,
    fit_se2,
    map_to_truth,
    pair_with_truth,
    transform_poses,
)


def _world(rng: np.random.Generator) -> tuple[np.ndarray, list[str]]:
    """11 lamps and 120 corners over a 10 x 7 m ceiling."""
    xy = rng.uniform([0.0, 0.0], [10.0, 7.0], size=(131, 2))
    return xy, ["lamp_rect"] * 11 + ["corner"] * 120


def _inverse(T: np.ndarray) -> np.ndarray:
    c, s = math.cos(T[2]), math.sin(T[2])
    return np.array([-(c * T[0] + s * T[1]), s * T[0] - c * T[1], -T[2]])


def test_rotated_shifted_map_is_recovered_exactly() -> None:
    rng = np.random.default_rng(3)
    true_xy, true_kinds = _world(rng)
    truth_T_map = np.array([0.0042, -0.0031, math.radians(0.02)])
    map_xy = transform_poses(_inverse(truth_T_map), np.column_stack([true_xy, np.zeros(len(true_xy))]))[:, :2]
    kinds = ["lamp" if k.startswith("lamp") else "corner" for k in true_kinds]
    fit = map_to_truth(map_xy, kinds, true_xy, true_kinds)
    assert fit is not None
    np.testing.assert_allclose(fit.truth_T_map, truth_T_map, atol=1e-9)
    assert fit.residual_rms_m < 1e-9
    assert fit.n_pairs == 131 and fit.n_lamps == 11
    # a large turn and shift (fit_se2 has no small-angle assumption)
    big = np.array([3.0, -2.0, 2.5])
    np.testing.assert_allclose(fit_se2(true_xy, transform_poses(big, np.column_stack(
        [true_xy, np.zeros(len(true_xy))]))[:, :2]), big, atol=1e-9)


def test_noise_and_wrong_corners_leave_the_frame_close() -> None:
    """Lamps 1 mm, corners 5 mm noise, 10 corners 3 cm off: the 10 are dropped and the frame
    is within 1.5 mm / 0.01 deg (lamp noise over a 5 m lever gives about 0.5 mm per axis)."""
    rng = np.random.default_rng(4)
    true_xy, true_kinds = _world(rng)
    truth_T_map = np.array([-0.003, 0.002, math.radians(-0.015)])
    map_xy = transform_poses(_inverse(truth_T_map), np.column_stack([true_xy, np.zeros(len(true_xy))]))[:, :2]
    map_xy[:11] += rng.normal(0.0, 0.001, (11, 2))
    map_xy[11:] += rng.normal(0.0, 0.005, (120, 2))
    map_xy[11:21] += 0.03
    kinds = ["lamp"] * 11 + ["corner"] * 120
    fit = map_to_truth(map_xy, kinds, true_xy, true_kinds)
    assert fit is not None
    assert np.linalg.norm(fit.truth_T_map[:2] - truth_T_map[:2]) < 1.5e-3
    assert abs(fit.truth_T_map[2] - truth_T_map[2]) < math.radians(0.01)
    assert fit.n_lamps == 11 and fit.n_pairs == 121
    unweighted = fit_se2(map_xy, true_xy)  # every pair, equal weights: pulled by the 10
    assert np.linalg.norm(unweighted[:2] - truth_T_map[:2]) > np.linalg.norm(fit.truth_T_map[:2] - truth_T_map[:2])


def test_pairs_are_mutual_nearest_of_one_kind() -> None:
    true_xy = np.array([[0.0, 0.0], [1.0, 0.0], [1.01, 0.0]])
    im, it = pair_with_truth(np.array([[0.0, 0.01], [1.004, 0.0], [5.0, 5.0]]), ["corner", "corner", "lamp"],
                             true_xy, ["lamp_round", "corner", "corner"], 0.05)
    assert im.tolist() == [1] and it.tolist() == [1]  # not the lamp at 1 cm, not the farther corner


def test_bad_input_is_a_clear_error() -> None:
    with pytest.raises(AlignmentInputError, match="same shape"):
        fit_se2(np.zeros((3, 2)), np.zeros((4, 2)))
    with pytest.raises(AlignmentInputError, match="at least 2"):
        fit_se2(np.zeros((1, 2)), np.zeros((1, 2)))
    assert map_to_truth(np.zeros((2, 2)), ["lamp", "lamp"], np.zeros((2, 2)), ["lamp", "lamp"]) is None
