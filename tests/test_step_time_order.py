"""Every backend refuses a step whose time goes back (``interface.check_step_time``), with
the same message, and keeps running from the last good step."""

from __future__ import annotations

import numpy as np
import pytest

from lampsam.backend.config import SlamConfig
from lampsam.backend.interface import check_step_time
from lampsam.backend.slam import make_backend
from lampsam.datasets.odometry import Pose2OdometryModel
from lampsam.errors import EstimationError


def test_check_step_time() -> None:
    assert check_step_time(2.0, 1.0) == 2.0 and check_step_time(1.0, 1.0) == 1.0
    with pytest.raises(EstimationError, match=r"t=0\.500 s: time goes backwards \(previous 1\.000\)"):
        check_step_time(0.5, 1.0)


@pytest.mark.parametrize("backend", ["ekf", "isam2", "batch"])
def test_backends_refuse_time_going_back(backend: str) -> None:
    """Two steps forward (Pose2 increments of 0.5 m), one back: refused naming both times;
    the next step forward is taken from the last good pose."""
    be = make_backend(backend, Pose2OdometryModel(), SlamConfig(), np.zeros(3))
    inc = np.r_[0.5, 0.0, 0.0, np.full(9, np.nan)][None]  # (1, 12): no covariance, the default
    be.step(1.0, inc, None)
    be.step(2.0, inc, None)
    with pytest.raises(EstimationError, match=r"t=1\.500 s: time goes backwards \(previous 2\.000\)"):
        be.step(1.5, inc, None)
    est = be.step(3.0, inc, None)
    assert est.pose[0] == pytest.approx(1.5, abs=1e-6)
