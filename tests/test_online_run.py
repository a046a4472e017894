"""``lampsam slam RUN --online decoupled`` (lampsam.backend.online_run): the backend in a
worker process gives the same result as in one process; tracked poses near the backend's;
a real SIGTERM / SIGINT writes what both processes finished."""

from __future__ import annotations

import json
import signal
import time
from pathlib import Path

import numpy as np
import pytest

from lampsam.backend.config import SlamConfig
from lampsam.backend.online_run import run_slam_decoupled
from lampsam.backend.slam import iter_steps, run_slam, start_pose_of
from lampsam.backend.tracking import run_decoupled
from lampsam.datasets.logrun import LoggedRun, read_run
from lampsam.datasets.tum import read_tum
from lampsam.frontend.pipeline import iter_run
from tests.conftest import SimRun, interrupted_summary, start_lampsam, wait_for_line


@pytest.fixture(scope="module")
def lab_dir(sim_run: SimRun) -> Path:
    """4 s of the simulated lab (61 frames), seed 2."""
    return sim_run(seed=2, duration=4.0)


@pytest.fixture(scope="module")
def lab_run(lab_dir: Path) -> LoggedRun:
    return read_run(lab_dir)


@pytest.fixture(scope="module")
def lab10(sim_run: SimRun) -> Path:
    """10 s of the simulated lab (151 frames), seed 1: long enough to be stopped mid-run."""
    return sim_run(seed=1, duration=10.0)


def test_decoupled_result_equals_sequential(lab_run: LoggedRun, tmp_path: Path) -> None:
    """Same frames, same backend in a worker: trajectory, covariances and map bit for bit,
    the written trajectory.tum / landmarks.csv byte-equal; tracked.tum has every step and
    the summary both latencies."""
    seq = run_slam(lab_run.path, "isam2", out=tmp_path / "seq", run=lab_run)
    dec, tm = run_slam_decoupled(lab_run, "isam2", tmp_path / "dec")
    assert dec.status == "ok" and len(dec.times) == len(seq.times) > 50
    np.testing.assert_array_equal(dec.poses, seq.poses)
    np.testing.assert_array_equal(dec.pose_covs, seq.pose_covs)
    assert [lm.id for lm in dec.landmarks] == [lm.id for lm in seq.landmarks]
    np.testing.assert_array_equal([lm.position for lm in dec.landmarks],
                                  [lm.position for lm in seq.landmarks])
    for name in ("trajectory.tum", "landmarks.csv"):
        assert (tmp_path / "dec" / name).read_bytes() == (tmp_path / "seq" / name).read_bytes()
    tracked = read_tum(tmp_path / "dec" / "tracked.tum")
    np.testing.assert_allclose(tracked.t, seq.times, atol=1e-6)
    summary = json.loads((tmp_path / "dec" / "summary.json").read_text())
    for key in ("online_tracked_latency_ms_p95", "online_keyframe_latency_ms_p95",
                "online_x_real_time", "online_backend_cpu_s"):
        assert summary[key] > 0.0
    # the default back-pressure (15): step i + 1's pose is given before the wait for i - 15
    assert summary["online_anchor_lag_p95_steps"] <= 16


def test_tracked_poses_near_backend_at_keyframes(lab_run: LoggedRun) -> None:
    """max_lag 0 (the worker finishes each step before the next is read): every tracked
    pose is the previous step's estimate plus one step of odometry (or the step's own
    estimate, when it is back before the pose is given); at keyframes it is
    within 5 mm and 1 deg of the backend's estimate after the keyframe's update (the
    update's correction; largest early in a run, when the heading is least known:
    measured 0.58 deg, seed 2). The backend's estimates are those of max_lag None."""
    steps = list(iter_steps(lab_run.odometry, list(iter_run(lab_run))))
    args = ("isam2", lab_run.rig.odometry, SlamConfig(), start_pose_of(lab_run),
            lab_run.rig.camera)
    tm = run_decoupled(iter(steps), *args, max_lag=0)
    assert all(i - 1 <= a <= i for i, a in enumerate(tm.anchor))
    free = run_decoupled(iter(steps), *args, max_lag=None)
    np.testing.assert_array_equal(np.array(tm.backend_pose), np.array(free.backend_pose))
    kf = np.array(tm.keyframe, bool)
    assert kf.sum() > 20
    d = np.array(tm.pose)[kf] - np.array(tm.backend_pose)[kf]
    assert np.hypot(d[:, 0], d[:, 1]).max() < 5e-3, np.hypot(d[:, 0], d[:, 1]).max()
    assert np.degrees(np.abs(np.angle(np.exp(1j * d[:, 2])))).max() < 1.0


def _children(pid: int) -> list[int]:
    """Child process ids of ``pid`` (Linux /proc)."""
    kids: list[int] = []
    for task in Path(f"/proc/{pid}/task").iterdir():
        text = (task / "children").read_text().split()
        kids.extend(int(k) for k in text)
    return kids


def _gone(pid: int, wait_s: float = 60.0) -> bool:
    """Whether process ``pid`` has ended (or is a zombie) within ``wait_s``."""
    t_end = time.monotonic() + wait_s
    while time.monotonic() < t_end:
        try:
            stat = Path(f"/proc/{pid}/stat").read_text()
        except FileNotFoundError:
            return True
        if stat.split(")")[-1].split()[0] == "Z":  # finished, not yet reaped
            return True
        time.sleep(0.05)
    return False


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT], ids=["SIGTERM", "SIGINT"])
def test_signal_mid_decoupled_run(lab10: Path, tmp_path: Path, sig: signal.Signals,
                                  cli_env: dict[str, str]) -> None:
    """A real signal to ``lampsam slam --online decoupled`` mid-run: exit 3, no traceback,
    the worker's finished steps written (status interrupted, fewer than the run's 151,
    finite), tracked.tum at least as long, no temporary files, the worker processes
    (the mapping worker, multiprocessing's resource tracker) ended."""
    out = tmp_path / "out"
    proc = start_lampsam(cli_env, "slam", str(lab10), "--out", str(out), "--online", "decoupled",
                         "--max-lag", "0")
    # the worker has finished steps (a signal before its first would leave 0 on a loaded machine)
    lines = wait_for_line(proc, "first estimates back from the mapping worker")
    workers = _children(proc.pid)
    assert workers
    proc.send_signal(sig)
    summary = interrupted_summary(proc, out, 151, lines, sig.name)
    tracked = np.loadtxt(out / "tracked.tum", ndmin=2)
    assert len(tracked) >= summary["steps"] and np.all(np.isfinite(tracked))
    assert all(_gone(w) for w in workers)
