"""Audit 2: a stereo run whose coordinates lie off the image (docs/failures.md, "audit 2").

``measurements.csv`` holds coordinates from the principal point; a run written with
pixel columns (or any coordinate off the image) used to run to a wrong answer without
a word (batch smoother 3.9 m RMS lateral error on the simulated straight run shifted by
700 px, raw triangulation 7.5 m, against 0.015 m and 1.2 m).
"""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np
import pytest

from lampsam.datasets.stereo_sim import read_stereo_run, simulate_stereo_run
from lampsam.errors import DatasetError


def rewrite(path: Path, change) -> None:  # noqa: ANN001 - a small row function
    rows = list(csv.reader(path.open()))
    rows = [rows[0]] + [change(r) for r in rows[1:]]
    with path.open("w") as fh:
        csv.writer(fh, lineterminator="\n").writerows(rows)


@pytest.fixture()
def run_dir(tmp_path: Path) -> Path:
    return Path(simulate_stereo_run("straight", tmp_path / "run", seed=0))


def test_clean_run_reads(run_dir: Path) -> None:
    run = read_stereo_run(run_dir)
    assert run.seen.sum() > 50
    assert np.abs(run.z[run.seen]).max() <= run.rig.half_width_px()


def test_coordinates_off_the_image_are_refused_naming_line_and_column(run_dir: Path) -> None:
    # pixel columns of a target in the image's right half (u = cu - x with x < -324 ...),
    # or coordinates in another origin: here every seen coordinate moved by 700 px
    rewrite(run_dir / "measurements.csv",
            lambda r: r if r[1] == "0" else r[:2] + [f"{float(v) + 700:.1f}" for v in r[2:]])
    with pytest.raises(DatasetError, match=r"measurements.csv:\d+: column 'xl1': .* px lies "
                                           r"off the 648-px image .*not pixel columns"):
        read_stereo_run(run_dir)


def test_unseen_rows_are_not_checked(run_dir: Path) -> None:
    rewrite(run_dir / "measurements.csv",
            lambda r: r if r[1] == "1" else [r[0], "0", "9999", "9999", "9999", "9999"])
    assert read_stereo_run(run_dir).seen.sum() > 50
