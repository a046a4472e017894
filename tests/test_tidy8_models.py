"""backend.models.try_initialize: the one place the EKF and the smoothers start a landmark
from an observation that may not start one."""

from __future__ import annotations

import logging

import numpy as np
import pytest

from lampsam.backend.config import AssociationConfig
from lampsam.backend.models import Obs, initialize, try_initialize


def test_try_initialize_is_initialize_when_it_succeeds(rng: np.random.Generator) -> None:
    """A range-bearing sighting: the same state, Jacobians and covariance, bit for bit."""
    for _ in range(5):
        pose = np.array([*rng.uniform(-5, 5, 2), rng.uniform(-3, 3)])
        obs = Obs("point2", np.array([rng.uniform(1, 10), rng.uniform(-3, 3)]), 0.01 * np.eye(2))
        got = try_initialize(pose, obs, AssociationConfig())
        assert got is not None
        for a, b in zip(got, initialize(pose, obs, AssociationConfig()), strict=True):
            np.testing.assert_array_equal(a, b)


def test_try_initialize_gives_none_and_logs_when_it_cannot(caplog: pytest.LogCaptureFixture) -> None:
    """A lamp sighting with no ceiling model cannot start a landmark: None, one debug line."""
    obs = Obs("lamp", np.array([0.1, 0.2]), 1e-4 * np.eye(2))
    with caplog.at_level(logging.DEBUG, logger="lampsam.backend.models"):
        assert try_initialize(np.zeros(3), obs, AssociationConfig()) is None
    assert [r.getMessage() for r in caplog.records] == [
        "cannot initialise a landmark: ceiling landmark kind 'lamp' needs a CeilingModel"]
