"""Fixed-lag option of the online iSAM2 backend (``[isam2] fixed_lag``, lampsam.backend.fixed_lag)."""

from __future__ import annotations

import dataclasses

import gtsam
import numpy as np
import pytest
from gtsam.symbol_shorthand import L, X

from lampsam.backend.config import SlamConfig
from lampsam.backend.fixed_lag import keyframe_stamps
from lampsam.backend.graph import Isam2Slam
from lampsam.backend.slam import iter_steps, make_backend, start_pose_of
from lampsam.datasets.logrun import LoggedRun, read_run
from lampsam.frontend.pipeline import iter_run
from tests.conftest import SimRun


def test_keyframe_stamps_new_touched_and_lamps() -> None:
    """New variables, every key of a new factor and the given lamp keys get the keyframe."""
    noise = gtsam.noiseModel.Isotropic.Sigma(3, 0.1)
    graph = gtsam.NonlinearFactorGraph()
    graph.add(gtsam.BetweenFactorPose2(X(3), X(4), gtsam.Pose2(), noise))
    values = gtsam.Values()
    values.insert(X(4), gtsam.Pose2())
    values.insert(L(9), np.zeros(3))
    stamps = keyframe_stamps(4, values, graph, [L(1)])
    assert stamps == {X(3): 4.0, X(4): 4.0, L(9): 4.0, L(1): 4.0}


@pytest.fixture(scope="module")
def lab_run(sim_run: SimRun) -> LoggedRun:
    """6 s of the simulated lab (90 frames)."""
    return read_run(sim_run(seed=3, duration=6.0))


def test_fixed_lag_bounds_the_window_and_keeps_lamps(lab_run: LoggedRun) -> None:
    """With a 10-keyframe lag, poses and corners leave the window (the smoother holds a
    bounded number of keys), every lamp stays, the run finishes, and its trajectory is
    within 2 mm RMS of full iSAM2's on the same frames."""
    frames = list(iter_run(lab_run))
    steps = list(iter_steps(lab_run.odometry, frames))
    base = SlamConfig()
    cfg = dataclasses.replace(base, isam2=dataclasses.replace(base.isam2, fixed_lag=10))
    start = start_pose_of(lab_run)
    full = make_backend("isam2", lab_run.rig.odometry, base, start, lab_run.rig.camera)
    lag = make_backend("isam2", lab_run.rig.odometry, cfg, start, lab_run.rig.camera)
    assert isinstance(lag, Isam2Slam) and lag.smoother is not None
    window = []
    for t, u, f in steps:
        full.step(t, u, f)
        lag.step(t, u, f)
        window.append(len(lag.smoother.timestamps()))
    assert lag._k > 30 and len(lag._left_poses) > 15
    lamps = [lm for lm in lag._landmarks.values() if lm.kind == "lamp" and lm.in_graph]
    assert lamps and all(lag.isam.valueExists(L(lm.id)) for lm in lamps)
    n_keys_full = full.isam.calculateEstimate().size()
    assert max(window) < 0.8 * n_keys_full
    a, b = full.finish(), lag.finish()
    assert b.status == "ok" and len(b.poses) == len(a.poses)
    assert not np.isnan(b.poses).any()
    d = np.hypot(*(b.poses[:, :2] - a.poses[:, :2]).T)
    assert float(np.sqrt(np.mean(d**2))) < 2e-3
