"""Signals and failing final optimisations never lose finished work.

SIGTERM and SIGINT are sent to real ``lampsam`` subprocesses mid-run; what they
wrote is checked. The final-optimisation cases run in-process with a backend
whose ``finish`` fails.
"""

from __future__ import annotations

import json
import signal
import time
from pathlib import Path

import numpy as np
import pytest

from lampsam.backend.interface import SlamBackend, SlamResult, StepEstimate
from lampsam.backend.slam import drive
from lampsam.interrupt import EXIT_INTERRUPTED, clear_stop, interruptible, request_stop
from tests.conftest import SimRun, interrupted_summary, start_lampsam, wait_for_line


@pytest.fixture(scope="module")
def run6(sim_run: SimRun) -> Path:
    """6 s of the lab world (91 images), seed 1."""
    return sim_run(seed=1, duration=6.0)


@pytest.fixture(scope="module")
def run15(sim_run: SimRun) -> Path:
    """15 s of the lab world (226 images), seed 1: long enough that a signal sent when the
    first step is done lands mid-run on a fast machine (the smoothers read keyframes only)."""
    return sim_run(seed=1, duration=15.0)


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT], ids=["SIGTERM", "SIGINT"])
def test_signal_mid_slam_writes_finished_steps(run15: Path, tmp_path: Path,
                                               sig: signal.Signals,
                                               cli_env: dict[str, str]) -> None:
    """A signal mid-run: exit 3, the finished steps written (status interrupted, fewer
    than the run's 226 frames, all finite), no traceback, no temporary files left."""
    out = tmp_path / "out"
    proc = start_lampsam(cli_env, "slam", str(run15), "--out", str(out), "--backend", "batch")
    wait_for_line(proc, "first step done")  # a step finished: not 0 steps on a loaded machine
    proc.send_signal(sig)
    interrupted_summary(proc, out, 226, signal_name=sig.name)


@pytest.mark.slow
def test_compare_interrupted_then_resumed(run6: Path, tmp_path: Path,
                                          cli_env: dict[str, str]) -> None:
    """SIGTERM to ``compare`` after its first job: the report of the finished jobs is
    written (complete: false, the rest named), exit 3; ``--resume`` then runs only the
    unfinished jobs and leaves the finished ones untouched."""
    out = tmp_path / "cmp"
    args = ["compare", str(run6), "--backends", "ekf,isam2,batch", "--workers", "1",
            "--frames", "truth", "--out", str(out), "--no-progress"]
    proc = start_lampsam(cli_env, *args)
    first = out / "jobs" / "run-ekf" / "job_result.json"
    t_end = time.monotonic() + 180
    while not first.exists() and time.monotonic() < t_end and proc.poll() is None:
        time.sleep(0.05)
    assert first.exists()
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=180)
    assert proc.returncode == EXIT_INTERRUPTED, err
    assert "Traceback" not in err
    summary = json.loads((out / "summary.json").read_text())
    assert summary["complete"] is False
    done = {j["backend"] for j in summary["jobs"]}
    missing = {u["backend"] for u in summary["unfinished"]}
    assert "ekf" in done and missing and done | missing == {"ekf", "isam2", "batch"}
    assert "Interrupted" in (out / "report.md").read_text()
    stamp = first.stat().st_mtime_ns

    proc = start_lampsam(cli_env, *args, "--resume")
    _, err = proc.communicate(timeout=300)
    assert proc.returncode == 0, err
    summary = json.loads((out / "summary.json").read_text())
    assert summary["complete"] is True
    assert sorted(j["backend"] for j in summary["jobs"]) == ["batch", "ekf", "isam2"]
    assert first.stat().st_mtime_ns == stamp  # the finished job was not run again


# --------------------------------------------------------------------------- final optimisation
class _FailingFinish(SlamBackend):
    """Steps return a straight-line pose; ``finish`` raises the given exception."""

    name = "ekf"

    def __init__(self, exc: BaseException) -> None:
        self.exc = exc
        self.n = 0

    def step(self, t: float, wheel: np.ndarray, frame: object) -> StepEstimate:
        self.n += 1
        return StepEstimate(t, np.array([0.1 * self.n, 0.0, 0.0]), 1e-4 * np.eye(3),
                            keyframe=True, time_s=1e-3)

    def finish(self, status: str = "ok") -> SlamResult:
        raise self.exc


@pytest.mark.parametrize("exc", [KeyboardInterrupt(), RuntimeError("Indeterminant system")],
                         ids=["interrupt", "failure"])
def test_final_optimisation_failure_keeps_online_estimate(exc: BaseException) -> None:
    """An interrupt or failure inside ``finish``: the online per-step estimates are
    returned under the estimator's name, status 'final optimisation failed: ...'."""
    steps = [(0.1 * k, np.zeros((1, 2)), None) for k in range(1, 6)]
    result = drive(_FailingFinish(exc), steps)  # type: ignore[arg-type]
    assert result.status.startswith("final optimisation failed: ")
    assert ("interrupted" in result.status) == isinstance(exc, KeyboardInterrupt)
    assert result.backend == "ekf"
    np.testing.assert_allclose(result.poses[:, 0], [0.1, 0.2, 0.3, 0.4, 0.5])
    np.testing.assert_allclose(result.times, [0.1, 0.2, 0.3, 0.4, 0.5])
    assert result.landmarks == []


def test_stop_request_stops_between_steps() -> None:
    """A stop requested during a step lets that step finish, then ends the loop."""
    seen: list[int] = []
    clear_stop()
    try:
        with pytest.raises(KeyboardInterrupt, match="stopped by test"):
            for k in interruptible(range(10)):
                seen.append(k)
                if k == 3:
                    request_stop("test")
    finally:
        clear_stop()
    assert seen == [0, 1, 2, 3]
