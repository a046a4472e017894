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


def test_save_map_of_a_range_bearing_run_is_refused(tmp_path: Path,
                                                    capsys: pytest.CaptureFixture[str]) -> None:
    """``--save-map`` on a run used through rangebearing.csv (MRCLAM) used to write an empty
    ceiling map ("0 lamps, 0 corners", exit 0); it is refused before computing."""
    from lampsam.cli import main
    from lampsam.datasets.tables import RangeBearingLog

    rng = np.random.default_rng(9)
    n = 20
    odo = OdometryLog(t=np.arange(n) * 0.1, d_left=np.full(n, 0.01), d_right=np.full(n, 0.011))
    rb = RangeBearingLog(t=np.arange(n) * 0.1, landmark_id=np.full(n, 3),
                         range=2.0 + rng.normal(0, 0.01, n), bearing=rng.normal(0, 0.01, n))
    run = tmp_path / "rb_run"
    write_run(run, Rig(), odo, range_bearing=rb)
    cmap = tmp_path / "MAP"
    assert main(["slam", str(run), "--backend", "batch", "--save-map", str(cmap),
                 "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert "--save-map writes a ceiling map" in err and "range-bearing" in err
    assert not cmap.exists()
    assert not (tmp_path / "o" / "trajectory.tum").exists()
