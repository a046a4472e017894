"""A new user's CARMEN logs (audit): a log cut off mid-line, raw laser messages."""

from __future__ import annotations

import logging
from pathlib import Path

import pytest

from lampsam.datasets.carmen import read_carmen
from lampsam.errors import DatasetError


def _flaser(k: int) -> str:
    return (f"FLASER 4 1.0 2.0 3.0 4.0 {0.5 * k} 0 0 {0.5 * k} 0 0 {10.0 + k} host "
            f"{10.0 + k}\n")


def test_a_cut_last_line_is_skipped_with_a_warning(
        tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    text = "".join(_flaser(k) for k in range(5))
    path = tmp_path / "cut.log"
    path.write_text(text + _flaser(5)[:25])  # the logger stopped mid-line
    with caplog.at_level(logging.WARNING):
        log = read_carmen(path)
    assert len(log.scans) == 5
    assert "cut.log:6" in caplog.text and "cut off without its newline" in caplog.text
    # the same line with its newline is malformed, not cut off: an error naming it
    path.write_text(text + _flaser(5)[:25] + "\n")
    with pytest.raises(DatasetError, match=r"cut.log:6: FLASER with 4 beams needs 13 fields"):
        read_carmen(path)
    # a bad line with records after it is still an error naming its line
    path.write_text(text[:len(_flaser(0))] + _flaser(1)[:25] + "\n" + text)
    with pytest.raises(DatasetError, match=r"cut.log:2: FLASER with 4 beams needs 13 fields"):
        read_carmen(path)


def test_raw_laser_messages_are_named_in_the_error(tmp_path: Path) -> None:
    path = tmp_path / "raw.log"
    path.write_text("ODOM 0 0 0 0 0 0 1.0 host 1.0\n"
                    "RAWLASER1 0 -1.57 3.14 0.0175 81.9 0.01 0 4 1 2 3 4 0 1.0 host 1.0\n"
                    "RLASER 4 1 2 3 4 0 0 0 0 0 0 1.0 host 1.0\n")
    with pytest.raises(DatasetError) as err:
        read_carmen(path)
    msg = str(err.value)
    assert "no FLASER or ROBOTLASER1 scans in the log" in msg
    assert "1 RAWLASER1 (no pose)" in msg and "1 RLASER (the rear laser)" in msg
    assert "1 ODOM" in msg


def test_the_front_laser_params_give_the_flaser_geometry(tmp_path: Path) -> None:
    """A 240-deg Hokuyo logged as FLASER: the log's PARAM lines say so (they were ignored,
    so its scans were read over 180 deg and every wall bent)."""
    import math

    import numpy as np

    scans = "".join(_flaser(k).replace("FLASER 4 1.0 2.0 3.0 4.0", "FLASER 5 1 2 3 4 5")
                    for k in range(3))
    path = tmp_path / "urg.log"
    path.write_text("PARAM laser_front_laser_fov 240 host 0\n" + scans)
    a = read_carmen(path).scans.angles
    np.testing.assert_allclose(np.degrees(a), [-120, -60, 0, 60, 120], atol=1e-9)
    path.write_text("PARAM laser_front_laser_fov 240.0 host 0\n"
                    "PARAM laser_front_laser_flipped 1 host 0\n" + scans)
    np.testing.assert_allclose(np.degrees(read_carmen(path).scans.angles),
                               [120, 60, 0, -60, -120], atol=1e-9)
    path.write_text(scans)  # no PARAM: a SICK over 180 deg, as before
    assert math.isclose(float(np.degrees(read_carmen(path).scans.angles[0])), -90.0)
    path.write_text("PARAM laser_front_laser_fov wide host 0\n" + scans)
    with pytest.raises(DatasetError, match=r"urg.log:1: PARAM laser_front_laser_fov 'wide'"):
        read_carmen(path)
