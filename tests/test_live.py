"""The Rerun live view: a SLAM run and a stereo run write .rrd files that read back.

Skipped with a reason when rerun-sdk (the ``lampsam[viz]`` extra) is not installed.
"""

from __future__ import annotations

from collections import Counter
from pathlib import Path

import numpy as np
import pytest

from lampsam.observe import emit, listening, observing
from tests.conftest import SimRun

rr = pytest.importorskip("rerun", reason="rerun-sdk not installed (pip install 'lampsam[viz]')")


def _rows(path: Path) -> Counter[str]:
    """Rows logged per entity path in an .rrd file, read with Rerun's own reader."""
    from rerun.chunk import RrdReader

    rows: Counter[str] = Counter()
    for chunk in RrdReader(path).stream().to_chunks():
        rows[str(chunk.entity_path)] += chunk.num_rows
    return rows


def test_observer_is_scoped_to_the_block() -> None:
    seen: list[tuple[str, dict[str, object]]] = []
    assert not listening()
    with observing(lambda e, f: seen.append((e, dict(f)))):
        assert listening()
        emit("x.y", a=1)
    emit("x.y", a=2)  # nobody listens: dropped
    assert seen == [("x.y", {"a": 1})] and not listening()


def test_slam_run_to_rrd_and_back(tmp_path: Path, sim_run: SimRun) -> None:
    """EKF on 4 s of the simulated lab (truth frames): every step's pose, image and
    detections are in the recording, the map is logged, and the path ends at the result."""
    from lampsam.backend.slam import run_slam
    from lampsam.datasets.logrun import read_run
    from lampsam.evaluation.live import live_view

    run_dir = sim_run(seed=1, duration=4.0)
    run = read_run(run_dir)
    rrd = tmp_path / "live" / "slam.rrd"
    with live_view(str(rrd), "test slam", run=run):
        result = run_slam(run_dir, "ekf", ("lamps", "corners"), None, frames="truth", run=run)
    rows = _rows(rrd)
    n = len(result.times)
    assert rows["/world/estimate/pose"] == n and rows["/timing/step_ms"] == n
    assert rows["/camera/image"] == len(run.images)
    assert rows["/camera/image/lamps"] == len(run.images)
    assert rows["/world/truth/path"] == 1 and rows["/world/map/landmarks"] >= 1
    assert rows["/camera/image/associations"] > 0


def test_stereo_run_to_rrd(tmp_path: Path) -> None:
    from lampsam.cli import main

    run_dir, out = tmp_path / "run", tmp_path / "ekf"
    assert main(["stereo-sim", "--scenario", "turn", "--out", str(run_dir), "--seed", "4"]) == 0
    assert main(["stereo", str(run_dir), "--estimator", "ekf", "--out", str(out), "--rerun"]) == 0
    rows = _rows(out / "live.rrd")
    assert rows["/timing/ekf_ms"] == 161  # every frame of the turn scenario
    assert rows["/target/ekf/pose"] == 161 and rows["/target/truth"] == 1


def test_weight_colours_order_by_weight() -> None:
    from lampsam.evaluation.live import weight_colors

    c = weight_colors(np.log(np.array([0.1, 0.5, 0.4])))
    assert c.dtype == np.uint8 and c.shape == (3, 3)
    assert c[1, 0] > c[2, 0] > c[0, 0]  # heavier: nearer yellow


def test_localization_events_to_rrd(tmp_path: Path) -> None:
    """Particles (coloured by weight), candidate discs and estimates, one update per particle event."""
    from lampsam.evaluation.live import live_view
    from lampsam.localization.candidates import PoseCandidate

    rng = np.random.default_rng(5)
    rrd = tmp_path / "loc.rrd"
    with live_view(str(rrd), "test localize"):
        emit("localize.candidates",
             candidates=[PoseCandidate(np.array([1.0, 2.0, 0.3]), 0.5, 0.05, 12, 0.0)])
        for k in range(3):
            emit("localize.particles", particles=rng.normal(size=(200, 3)),
                 log_weights=rng.normal(size=200), update=k + 1)
        emit("localize.estimate", pose=np.array([1.0, 2.0, 0.3]), attempt=0)
    rows = _rows(rrd)
    assert rows["/world/particles"] == 3 and rows["/localize/effective_n"] == 3
    assert rows["/world/candidates/discs"] == 1 and rows["/world/estimate/pose"] == 1
