"""The printed ``lampsam slam`` summary line names iSAM2's damped steps (commands/slam.py).

iSAM2's divergence check (:meth:`lampsam.backend.isam2_update.Isam2Updates._damp_divergence`)
counts each diverging Gauss-Newton step it damps in ``extra["n_damped_rebuilds"]``
(summary.json); the one-line summary says so when the count is not zero. On a clean
simulated run nothing diverges, so the thresholds are set below any error to make the
check damp every relinearising update (its step threshold set to 0).
"""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest

from lampsam.backend import isam2_update
from lampsam.cli import main
from tests.conftest import SimRun


def _slam_line(run: Path, out: Path, capsys: pytest.CaptureFixture[str]) -> tuple[str, float]:
    """``lampsam slam RUN --backend isam2``'s summary line and summary.json's count."""
    assert main(["slam", str(run), "--backend", "isam2", "--out", str(out)]) == 0
    line = [s for s in capsys.readouterr().out.splitlines() if s.startswith("isam2: ")][-1]
    return line, json.loads((out / "summary.json").read_text())["n_damped_rebuilds"]


def test_damped_steps_are_printed_when_nonzero(sim_run: SimRun, tmp_path: Path,
                                               capsys: pytest.CaptureFixture[str],
                                               monkeypatch: pytest.MonkeyPatch) -> None:
    """Defaults on a 4 s lab run: no damping, nothing said. Forced damping: the line gives
    the same count as summary.json (measured: 3 of the 31 keyframes' updates)."""
    run = sim_run(seed=2, duration=4.0)
    line, n = _slam_line(run, tmp_path / "plain", capsys)
    assert n == 0 and "diverging" not in line
    monkeypatch.setattr(isam2_update, "DIVERGENCE_RATIO", -1.0)
    monkeypatch.setattr(isam2_update, "DIVERGENCE_MARGIN", -1.0)
    monkeypatch.setattr(isam2_update, "DIVERGENCE_MIN_STEP", 0.0)
    line, n = _slam_line(run, tmp_path / "forced", capsys)
    m = re.search(r"; (\d+) diverging iSAM2 steps? damped \(Levenberg-Marquardt solve", line)
    assert m is not None, line
    assert n >= 1 and int(m.group(1)) == n
