"""What the run prints agrees with what it writes: pruned landmarks and keyframes."""

from __future__ import annotations

import json
import logging
import re
from pathlib import Path

import pytest

from lampsam.backend.slam import run_slam
from tests.conftest import SimRun


@pytest.fixture(scope="module")
def lab_run(sim_run: SimRun) -> Path:
    """5 s of the simulated lab, seed 0."""
    return sim_run(seed=0, duration=5.0)


@pytest.mark.parametrize("backend", ["ekf", "isam2"])
def test_pruned_and_keyframe_counts_agree(lab_run: Path, tmp_path: Path, backend: str,
                                          caplog: pytest.LogCaptureFixture) -> None:
    """The one pruning warning gives summary.json's count and its breakdown sums to it;
    summary.json has one keyframe count, the number of steps flagged as keyframes."""
    with caplog.at_level(logging.WARNING):
        result = run_slam(lab_run, backend, ("lamps", "corners"), tmp_path, frames="truth")
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["landmarks_pruned"] == result.n_pruned
    assert sum(summary["landmarks_pruned_by_reason"].values()) == result.n_pruned
    said = [int(m.group(1)) for r in caplog.records
            if (m := re.match(r"(\d+) landmarks pruned", r.getMessage()))]
    if result.n_pruned:
        assert said == [result.n_pruned]
    assert summary["keyframes"] == int(result.keyframes.sum()) and "n_keyframes" not in summary
