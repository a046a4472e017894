"""What the run prints agrees with what it writes: pruned landmarks and keyframes."""

from __future__ import annotations

import json
import logging
import re
from pathlib import Path

import pytest

from lampsam.backend.slam import run_slam
from lampsam.datasets.simulator import simulate_world


@pytest.fixture(scope="module")
def lab_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return simulate_world("lab", tmp_path_factory.mktemp("lab") / "run", seed=0, duration=5.0)


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
