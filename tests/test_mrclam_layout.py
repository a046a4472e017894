"""MRCLAM as distributed (``MRCLAM_DatasetN/Robot1_Odometry.dat`` ...) reads like the resampled
``ds0_RS_`` copy in ``../shared/data``; before, ``lampsam slam MRCLAM_Dataset1 --mrclam`` said
``ds0_RS_Control.dat: file not found``.

Synthetic tables (seeded), written in both layouts; the dataset's own files carry ``#``
header lines and Unix times.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from lampsam.cli import main
from lampsam.datasets.mrclam import read_mrclam
from lampsam.errors import DatasetError

HEADER = ("# UTIAS Multi-Robot Cooperative Localization and Mapping Dataset\n"
          "# produced by Keith Leung (keith.leung@robotics.utias.utoronto.ca) 2009\n")


def _tables(rng: np.random.Generator, t0: float) -> dict[str, np.ndarray]:
    n = 200
    t = t0 + np.arange(n) * 0.02
    control = np.column_stack([t, np.full(n, 0.1), np.full(n, 0.05)])
    meas = np.column_stack([t[::10], np.full(20, 27.0), 2.0 + rng.normal(0, 0.01, 20),
                            rng.normal(0, 0.01, 20)])
    gt = np.column_stack([t, 0.002 * np.arange(n), np.zeros(n), 0.001 * np.arange(n)])
    lms = np.array([[6.0, 2.0, 0.0, 0.001, 0.001]])
    codes = np.array([[1.0, 5.0], [6.0, 27.0]])
    return {"control": control, "meas": meas, "gt": gt, "lms": lms, "codes": codes}


def _write(path: Path, a: np.ndarray, header: str = "") -> None:
    path.write_text(header + "".join(" ".join(f"{v:.6f}" for v in row) + "\n" for row in a))


@pytest.fixture()
def layouts(tmp_path: Path) -> tuple[Path, Path]:
    a = _tables(np.random.default_rng(4), 0.0)
    b = _tables(np.random.default_rng(4), 1248297567.0)
    ds0, orig = tmp_path / "mrclam_ds0", tmp_path / "MRCLAM_Dataset1"
    ds0.mkdir()
    orig.mkdir()
    for key, name in [("control", "Control"), ("meas", "Measurement"), ("gt", "Groundtruth"),
                      ("lms", "Landmark_Groundtruth"), ("codes", "Barcodes")]:
        _write(ds0 / f"ds0_RS_{name}.dat", a[key])
    _write(orig / "Robot1_Odometry.dat", b["control"], HEADER)
    _write(orig / "Robot1_Measurement.dat", b["meas"], HEADER)
    _write(orig / "Robot1_Groundtruth.dat", b["gt"], HEADER)
    _write(orig / "Landmark_Groundtruth.dat", b["lms"], HEADER)
    _write(orig / "Barcodes.dat", b["codes"], HEADER)
    return ds0, orig


def test_dataset_layout_reads_like_the_resampled_copy(layouts: tuple[Path, Path]) -> None:
    ds0, orig = layouts
    a, b = read_mrclam(ds0), read_mrclam(orig)
    np.testing.assert_allclose(b.control_t - b.control_t[0], a.control_t - a.control_t[0], atol=1e-6)
    np.testing.assert_allclose(b.v, a.v, atol=0)
    np.testing.assert_array_equal(b.meas_id, a.meas_id)
    np.testing.assert_allclose(b.meas_range, a.meas_range, atol=0)
    np.testing.assert_allclose(b.gt_poses, a.gt_poses, atol=0)
    assert list(b.meas_id) == [6] * 20


def test_cli_slam_on_the_dataset_layout(layouts: tuple[Path, Path], tmp_path: Path) -> None:
    _, orig = layouts
    assert main(["slam", str(orig), "--mrclam", "--backend", "ekf", "--duration", "3",
                 "--out", str(tmp_path / "o")]) == 0
    assert (tmp_path / "o" / "trajectory.tum").is_file()


def test_neither_layout_names_both(tmp_path: Path) -> None:
    with pytest.raises(DatasetError, match=r"not an MRCLAM folder: no ds0_RS_Control.dat .* and "
                       r"no Robot1_Odometry.dat"):
        read_mrclam(tmp_path)
