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
