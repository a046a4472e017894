"""The pass-split test of a batch map's landmark covariances (backend/map_calibration.py).

A small ceiling graph with the real projection factors: a drive that passes twice
under a row of landmarks (a loop away between the passes), sightings with Gaussian
pixel noise. With the noise as stated the split NEES per dof averages 1; with twice the
stated noise it averages 4; with an offset repeated at every sighting of one pass (what
no sighting count averages out) the landmarks fail the test and are inflated to their
real error.
"""

from __future__ import annotations

import math
from pathlib import Path

import gtsam
import numpy as np
import pytest
from gtsam.symbol_shorthand import L, X

from lampsam.backend.ceiling_map_io import CeilingMap, MapLandmark, read_map, write_map
from lampsam.backend.map_calibration import (
    MapCalibrationConfig,
    calibrate_map,
    pass_split_tests,
    split_passes,
)
from lampsam.datasets.logrun import Rig
from lampsam.factors.gtsam_factors import projection_factor

BODY_T_CAMERA = np.array([0.1, 0.0, 0.3])
SIGMA = 0.005  # stated noise of the normalised image coordinates (about 0.5 px at f = 92 px)


def _path() -> np.ndarray:
    """(K, 3) poses: east along y = 0, a loop away to the north, east again along y = 0.3."""
    first = [(0.1 * k, 0.0, 0.0) for k in range(40)]
    away = [(4.0 - 0.1 * k, 4.0, math.pi) for k in range(40)]
    second = [(0.1 * k, 0.3, 0.0) for k in range(40)]
    return np.array(first + away + second)


def _graph(rng: np.random.Generator, noise: float, pass_bias: float
           ) -> tuple[gtsam.NonlinearFactorGraph, gtsam.Values, dict[int, np.ndarray]]:
    """The drive's ceiling graph solved by Levenberg-Marquardt; the true landmarks.

    ``noise``: the sightings' real noise (the factors state :data:`SIGMA`);
    ``pass_bias``: a per-landmark offset (normalised units, random direction) added to
    every sighting of the second pass.
    """
    poses = _path()
    pts = {j: np.array([0.2 + 0.25 * j, 0.15 + 0.3 * (-1) ** j, 2.5]) for j in range(15)}
    bias = {j: pass_bias * rng.normal(size=2) / math.sqrt(2) for j in pts}
    graph = gtsam.NonlinearFactorGraph()
    truth = gtsam.Values()
    graph.add(gtsam.PriorFactorPose2(X(0), gtsam.Pose2(*poses[0]), gtsam.noiseModel.Isotropic.Sigma(3, 1e-4)))
    odo = gtsam.noiseModel.Diagonal.Sigmas(np.array([0.002, 0.002, 0.001]))
    for k, p in enumerate(poses):
        truth.insert(X(k), gtsam.Pose2(*p))
        if k:
            rel = gtsam.Pose2(*poses[k - 1]).between(gtsam.Pose2(*p))
            noisy = rel.compose(gtsam.Pose2(*(rng.normal(size=3) * [0.002, 0.002, 0.001])))
            graph.add(gtsam.BetweenFactorPose2(X(k - 1), X(k), noisy, odo))
    cov = SIGMA**2 * np.eye(2)
    for j, p in pts.items():
        truth.insert(L(j), p)
        graph.add(gtsam.PriorFactorPoint3(L(j), p + [0.0, 0.0, 0.0],
                                          gtsam.noiseModel.Diagonal.Sigmas(np.array([10.0, 10.0, 0.5]))))
        for k, q in enumerate(poses):
            if np.hypot(*(p[:2] - q[:2])) > 1.2:
                continue
            predicted = projection_factor(X(k), L(j), np.zeros(2), cov, BODY_T_CAMERA
                                          ).unwhitenedError(truth)
            z = predicted + noise * rng.normal(size=2) + (bias[j] if k >= 80 else 0.0)
            graph.add(projection_factor(X(k), L(j), z, cov, BODY_T_CAMERA))
    start = gtsam.Values()
    for k in range(len(poses)):
        start.insert(X(k), truth.atPose2(X(k)).compose(gtsam.Pose2(*(rng.normal(size=3) * 1e-3))))
    for j, p in pts.items():
        start.insert(L(j), p + rng.normal(size=3) * 1e-3)
    values = gtsam.LevenbergMarquardtOptimizer(graph, start).optimize()
    return graph, values, pts


def test_split_passes_deals_passes_alternately() -> None:
    """Sightings at keyframes 0-9, 50-59 and 100-104 (in any order): three passes, the
    first and third in group 0; one pass gives None."""
    k = np.r_[np.arange(100, 105), np.arange(10), np.arange(50, 60)]
    labels = split_passes(k, gap=30)
    assert labels is not None
    assert np.array_equal(labels, np.r_[np.zeros(5), np.zeros(10), np.ones(10)])
    assert split_passes(np.arange(20), gap=30) is None


@pytest.mark.parametrize(("noise", "low", "high"), [(SIGMA, 0.6, 1.5), (2 * SIGMA, 2.6, 6.0)])
def test_split_nees_measures_the_real_noise(rng: np.random.Generator, noise: float,
                                            low: float, high: float) -> None:
    """Mean split NEES per dof over 15 landmarks x 4 seeds: about 1 with the noise as
    stated, about 4 with twice the stated noise (bounds: the chi-square(2) mean of 60
    draws, +-4 standard deviations); the projection residuals' chi-square per row says
    the same (0.75-1.1 and 3-5)."""
    nees, chi2 = [], []
    for _ in range(4):
        graph, values, _ = _graph(rng, noise, 0.0)
        tests, res = pass_split_tests(graph, values)
        nees += [t.nees for t in tests.values() if math.isfinite(t.nees)]
        chi2 += res["lamp"]
    assert len(nees) == 60
    assert low < np.mean(nees) < high
    per_row = np.sum(chi2) / (2 * len(chi2))
    assert (0.75 < per_row < 1.1) if noise == SIGMA else (3.0 < per_row < 5.0)


def test_a_bias_repeated_in_one_pass_is_found_and_inflated(rng: np.random.Generator,
                                                            tmp_path: Path) -> None:
    """A 3-sigma offset repeated at every second-pass sighting: most landmarks fail the
    test and their inflated covariance brings the NEES of their error against the truth
    from far above 1 to at most about 1 (the median); the figures survive the map file."""
    graph, values, pts = _graph(rng, SIGMA, 3 * SIGMA)
    marg = gtsam.Marginals(graph, values)
    lms = [MapLandmark(j, "lamp", np.asarray(values.atPoint3(L(j))), None,
                       np.pad(marg.marginalCovariance(L(j)), ((0, 1), (0, 1))), 50)
           for j in pts]
    cmap, figs = calibrate_map(CeilingMap(lms, Rig()), graph, values, MapCalibrationConfig())
    assert figs["lamp"].landmarks_split == 15
    assert figs["lamp"].inflated == figs["lamp"].failed >= 10
    assert figs["lamp"].nees_mean > 10.0

    def nees(m: CeilingMap) -> np.ndarray:
        out = []
        for lm in m.landmarks:
            e = lm.position[:2] - pts[lm.id][:2]
            out.append(e @ np.linalg.solve(lm.cov[:2, :2], e) / 2)
        return np.array(out)

    before, after = nees(CeilingMap(lms, Rig())), nees(cmap)
    assert np.median(before) > 3.0
    assert np.median(after) < 1.2
    assert all(np.all(np.linalg.eigvalsh(lm.cov[:3, :3]) >= np.linalg.eigvalsh(lm0.cov[:3, :3]) - 1e-15)
               for lm, lm0 in zip(cmap.landmarks, lms, strict=True))
    same, report = calibrate_map(CeilingMap(lms, Rig()), graph, values, inflate=False)
    assert report["lamp"].inflated == 0 and report["lamp"].failed == figs["lamp"].failed
    assert all(a.cov is b.cov for a, b in zip(same.landmarks, lms, strict=True))
    write_map(tmp_path / "m", cmap)
    back = read_map(tmp_path / "m")
    assert back.calibration is not None
    assert back.calibration["lamp"]["inflated"] == figs["lamp"].inflated
    assert back.calibration["lamp"]["nees_mean"] == figs["lamp"].nees_mean
    assert np.array_equal(back.landmarks[0].cov, cmap.landmarks[0].cov)
