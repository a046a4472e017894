"""Bad input to the logged-run reader that the fuzz suite (tests/test_fuzz_inputs.py) does not
cover: a run with no odometry file at all.

Before: ``RUN/odometry.csv: file not found`` even when the run was imported with Pose2
odometry and only its ``odometry_pose2.csv`` was lost; the message now names the three
odometry files a run may hold.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from lampsam.datasets.logrun import read_run, write_run
from lampsam.datasets.rig import Rig
from lampsam.datasets.tables import OdometryLog
from lampsam.errors import DatasetError


@pytest.fixture()
def run_dir(tmp_path: Path) -> Path:
    rng = np.random.default_rng(8)
    n = 5
    odo = OdometryLog(t=np.arange(n) * 0.1, d_left=rng.uniform(0, 0.01, n),
                      d_right=rng.uniform(0, 0.01, n))
    out = tmp_path / "run"
    write_run(out, Rig(), odo)
    return out


def test_run_reads(run_dir: Path) -> None:
    assert len(read_run(run_dir).odometry) == 5


def test_no_odometry_file_names_all_three(run_dir: Path) -> None:
    (run_dir / "odometry.csv").unlink()
    with pytest.raises(DatasetError, match=r"odometry.csv: file not found \(a run needs its "
                       r"odometry: odometry.csv .* odometry_pose2.csv / odometry_poses.tum"):
        read_run(run_dir)
