"""Bad input to ``lampsam import-bag``: foreign bytes where a bag belongs.

rosbags raises UnicodeDecodeError for a binary file named ``.bag`` and for a ROS2 bag
folder whose ``metadata.yaml`` is not text (and TypeError for a string where its
metadata has a number); these reached the user as "internal error". Now they are one
error naming the bag (exit 2), like rosbags' own errors (``cannot read bag: ...``).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from lampsam.cli import main


def _import(bag: Path, out: Path, capsys: pytest.CaptureFixture[str]) -> str:
    assert main(["import-bag", str(bag), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "internal error" not in err and "Traceback" not in err
    assert len([ln for ln in err.splitlines() if ln.strip()]) == 1
    assert not out.exists() or not any(out.iterdir())  # nothing written
    return err


def test_binary_file_named_bag(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    bag = tmp_path / "run.bag"
    bag.write_bytes(np.random.default_rng(2).bytes(4000))
    err = _import(bag, tmp_path / "RUN", capsys)
    assert f"{bag}: cannot read bag: not a ROS1 bag or ROS2 bag folder" in err


def test_ros2_folder_with_binary_metadata(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    folder = tmp_path / "bag2"
    folder.mkdir()
    (folder / "metadata.yaml").write_bytes(b"\xff\xfe" + np.random.default_rng(4).bytes(600))
    (folder / "bag2.db3").write_bytes(b"")
    err = _import(folder, tmp_path / "RUN", capsys)
    assert f"{folder}: cannot read bag:" in err and "UnicodeDecodeError" in err


def test_export_warns_what_the_bag_leaves_out(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                              caplog: pytest.LogCaptureFixture) -> None:
    """A run's range-bearing measurements (and kinect/ frames) have no message in export-bag;
    the bag used to be written without a word about them."""
    from lampsam.datasets.logrun import write_run
    from lampsam.datasets.rig import Rig
    from lampsam.datasets.tables import OdometryLog, RangeBearingLog

    n = 10
    odo = OdometryLog(t=np.arange(n) * 0.1, d_left=np.full(n, 0.01), d_right=np.full(n, 0.01))
    rb = RangeBearingLog(t=np.arange(n) * 0.1, landmark_id=np.full(n, 2), range=np.full(n, 2.0),
                         bearing=np.zeros(n))
    run = tmp_path / "run"
    write_run(run, Rig(), odo, range_bearing=rb)
    assert main(["export-bag", str(run), "--out", str(tmp_path / "r.bag"), "--ros1"]) == 0
    assert (tmp_path / "r.bag").is_file()
    assert "rangebearing.csv: the range-bearing measurements are not in the bag" in caplog.text
    assert "kinect" not in caplog.text
