"""The fleet engine (local pool / Dask) behind ``lampsam batch`` and ``lampsam compare``.

The Dask tests start a real scheduler with two worker processes on 127.0.0.1
(``distributed.LocalCluster``) once for the module, and check that results equal the
local process pool's and that failures stay failed rows.
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from lampsam.cli import main
from lampsam.datasets.logrun import OdometryLog, OdometryModel, RangeBearingLog, Rig, write_run
from lampsam.datasets.motion import follow_waypoints, noisy_wheel_travel
from lampsam.evaluation import fleet
from lampsam.evaluation.batch import BatchError, batch, folder_names
from lampsam.evaluation.compare import compare
from lampsam.factors.geometry import wrap_angle
from lampsam.factors.range_bearing import range_bearing

distributed = pytest.importorskip("distributed")

#: Figures that are timings or memory (differ between any two executions).
TIMING_KEYS = {"total_time_s", "frame_ms_median", "frame_ms_p95", "final_optimisation_s",
               "peak_rss_mb", "out"}
LANDMARKS = np.array([[-1.0, -1.0], [1.5, -1.2], [4.0, -1.0], [4.2, 1.0], [4.0, 3.2],
                      [1.5, 3.2], [-1.0, 3.0], [-1.2, 1.0]])


def _write_rb_run(path: Path, seed: int, duration: float = 12.0) -> Path:
    """A small range-bearing run: a loop among eight landmarks, wheel noise, truth."""
    from lampsam.datasets.logrun import Trajectory

    rng = np.random.default_rng(seed)
    k = 4e-5
    rig = Rig(odometry=OdometryModel(0.4, k, k))
    waypoints = np.array([[0.0, 0.0], [3.0, 0.0], [3.0, 2.0], [0.0, 2.0]])
    t, poses, wheel = follow_waypoints(waypoints, speed=0.4, rate_hz=20.0, wheel_base=0.4,
                                       duration=duration)
    noisy = noisy_wheel_travel(wheel, k, k, rng)
    rows = []
    for i in range(0, len(t), 5):
        for j, lm in enumerate(LANDMARKS):
            z, _, _ = range_bearing(poses[i], lm)
            if z[1] < 3.5:
                rows.append((t[i], j, z[1] + rng.normal(0, 0.05),
                             wrap_angle(z[0] + rng.normal(0, 0.02))))
    arr = np.array(rows)
    rb = RangeBearingLog(t=arr[:, 0], landmark_id=arr[:, 1].astype(np.int64), range=arr[:, 2],
                         bearing=arr[:, 3])
    odo = OdometryLog(t=t[1:], d_left=noisy[1:, 0], d_right=noisy[1:, 1])
    return write_run(path, rig, odo, groundtruth=Trajectory(t=t, poses=poses), range_bearing=rb)


@pytest.fixture(scope="module")
def runs(tmp_path_factory: pytest.TempPathFactory) -> list[str]:
    """Two good runs and a broken one (no odometry file) as the third."""
    root = tmp_path_factory.mktemp("runs")
    good = [str(_write_rb_run(root / f"loop{s}", seed=s)) for s in range(2)]
    broken = root / "broken"
    broken.mkdir()
    return [*good, str(broken)]


@pytest.fixture(scope="module")
def local_batch(runs: list[str], tmp_path_factory: pytest.TempPathFactory
                ) -> tuple[Path, list[dict]]:
    """``batch`` over the runs on the local process pool: (output folder, rows)."""
    out = tmp_path_factory.mktemp("local_batch")
    return out, batch(runs, out, workers=2, progress=False)


@pytest.fixture(scope="module")
def scheduler() -> Iterator[str]:
    """A real scheduler and two worker processes on loopback; its address."""
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                                  host="127.0.0.1", dashboard_address=":0",
                                  timeout=60) as cluster:
        with distributed.Client(cluster, timeout=60) as client:
            client.wait_for_workers(2, timeout=60)
            assert len(client.scheduler_info()["workers"]) == 2
        yield cluster.scheduler_address


def _without_timings(rows: list[dict]) -> str:
    """The rows without timing keys, as canonical JSON (NaN compares equal to NaN)."""
    return json.dumps([{k: v for k, v in r.items() if k not in TIMING_KEYS} for r in rows],
                      sort_keys=True, default=str)


def test_thread_variables_restored(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
    monkeypatch.setenv("OPENBLAS_NUM_THREADS", "4")
    with fleet.single_threaded_children():
        assert os.environ["OMP_NUM_THREADS"] == "1"
        assert os.environ["OPENBLAS_NUM_THREADS"] == "4"  # the user's choice is kept
    assert "OMP_NUM_THREADS" not in os.environ and os.environ["OPENBLAS_NUM_THREADS"] == "4"


def test_folder_names_are_unique() -> None:
    assert folder_names(["a/run", "b/run", "c/other", "d/run"]) == ["run", "run-2", "other", "run-3"]


def test_batch_local_pool_writes_folders_and_keeps_failures(
        runs: list[str], local_batch: tuple[Path, list[dict]], tmp_path: Path) -> None:
    """Two runs optimised (errors against truth below 0.1 m RMS), the broken one a failed row."""
    out, rows = local_batch
    assert [r["run"] for r in rows] == ["loop0", "loop1", "broken"]
    for r in rows[:2]:
        assert r["status"] == "ok" and r["backend"] == "batch"
        assert r["pos_rms_m"] < 0.1 and r["landmarks"] == len(LANDMARKS)
        assert (out / r["run"] / "trajectory.tum").is_file()
    assert rows[2]["status"].startswith("failed") and "broken" in rows[2]["status"]
    doc = json.loads((out / "summary.json").read_text())
    assert doc["failed"] == 1 and len(doc["runs"]) == 3 and doc["engine"].startswith("local")
    assert len((out / "summary.csv").read_text().splitlines()) == 4
    with pytest.raises(BatchError):
        batch(runs, tmp_path / "x", backend="kalman")


@pytest.mark.parametrize("engine", ["pool", "dask"])
def test_exceptions_become_failed_results_in_order(engine: str, scheduler: str) -> None:
    """A job that raises is ``failed(job, reason)`` in its place; the others are untouched."""
    out = fleet.run_jobs(math.sqrt, [4.0, -1.0, 9.0], lambda job, why: why, workers=2,
                         dask=scheduler if engine == "dask" else None, progress=False)
    assert out[0] == 2.0 and out[2] == 3.0
    assert out[1].startswith("failed: ValueError") and "math domain error" in out[1]


def test_batch_on_dask_equals_local_pool(runs: list[str], local_batch: tuple[Path, list[dict]],
                                         scheduler: str, tmp_path: Path) -> None:
    """Same rows (all but timings) and byte-identical trajectories; the failure stays a row."""
    local_out, local = local_batch
    assert main(["batch", *runs, "--out", str(tmp_path / "dask"), "--dask", scheduler,
                 "--no-progress"]) == 1  # one failed run: exit code 1
    doc = json.loads((tmp_path / "dask" / "summary.json").read_text())
    assert doc["engine"] == f"dask {scheduler}"
    assert _without_timings(doc["runs"]) == _without_timings(local)
    for r in local[:2]:
        a = (local_out / r["run"] / "trajectory.tum").read_bytes()
        b = (tmp_path / "dask" / r["run"] / "trajectory.tum").read_bytes()
        assert a == b


def test_compare_on_dask_equals_local_pool(runs: list[str], scheduler: str, tmp_path: Path) -> None:
    """``compare`` (one job): the aggregated rows agree but for timings and memory."""
    kw = {"backends": ("ekf",), "progress": False}
    local = compare(runs[:1], out=tmp_path / "local", workers=1, **kw)
    on_dask = compare(runs[:1], out=tmp_path / "dask", dask=scheduler, **kw)
    assert len(local) == 1 and local[0]["failed"] == 0 and local[0]["pos_rms_m"] < 0.2
    assert _without_timings(on_dask) == _without_timings(local)


def test_unreachable_scheduler_is_a_clear_error(runs: list[str], tmp_path: Path,
                                                monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(fleet, "CONNECT_TIMEOUT_S", 1.0)
    with pytest.raises(fleet.FleetError, match="tcp://127.0.0.1:9"):
        batch(runs[:1], tmp_path, dask="tcp://127.0.0.1:9", progress=False)
