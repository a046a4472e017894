"""The overlapped frontend (backend/pipelined.py) gives the sequential run's frames and results.

Frames are compared as pickled bytes (every float bit for bit); the SLAM runs by
their trajectories and maps (exactly equal).
"""

from __future__ import annotations

import dataclasses
import pickle
from pathlib import Path

import numpy as np
import pytest

from lampsam.backend.pipelined import FrameTimes, frame_source, pack_frame, unpack_frame
from lampsam.backend.slam import run_slam
from lampsam.datasets.logrun import LoggedRun, read_run
from lampsam.errors import FrontendError
from lampsam.frontend.measurements import CeilingFrame
from lampsam.frontend.pipeline import iter_run
from tests.conftest import SimRun


@pytest.fixture(scope="module")
def lab_run(sim_run: SimRun) -> LoggedRun:
    """4 s of the simulated lab (60 frames)."""
    return read_run(sim_run(seed=3, duration=4.0))


def _bytes(frames: list[CeilingFrame]) -> list[bytes]:
    return [pickle.dumps(f, pickle.HIGHEST_PROTOCOL) for f in frames]


def test_pack_round_trip_is_bit_identical(lab_run: LoggedRun) -> None:
    """pack_frame / unpack_frame keep every field (frames with and without corners)."""
    frames = list(iter_run(lab_run))[:20]
    assert sum(len(f.corners) for f in frames) > 100
    empty = CeilingFrame(t=1.0, index=3)
    for f in [*frames, empty]:
        back = unpack_frame(pickle.loads(pickle.dumps(pack_frame(f))))
        assert _bytes([back]) == _bytes([f])


@pytest.mark.parametrize("mode", ["thread", "process"])
def test_worker_frames_equal_sequential(lab_run: LoggedRun, mode: str) -> None:
    """A worker (queue of 3) gives the same frames, in order, as the frontend run in turn;
    each frame's arrival precedes its ready time."""
    assert lab_run.images is not None
    ref = list(iter_run(lab_run))
    times = FrameTimes()
    got = list(frame_source(lab_run.images, lab_run.rig.camera, mode=mode,  # type: ignore[arg-type]
                            depth=3, times=times))
    assert len(got) == len(ref) == len(lab_run.images)
    assert _bytes(got) == _bytes(ref)
    assert len(times.arrival) == len(times.ready) == len(ref)
    assert all(r >= a for a, r in zip(times.arrival, times.ready, strict=True))
    assert times.worker_cpu_s > 0.0


def test_slam_with_frontend_process_is_identical(lab_run: LoggedRun, tmp_path: Path) -> None:
    """iSAM2 over the run: the same trajectory, covariances and map with the frontend
    in a worker process as in turn."""
    seq = run_slam(lab_run.path, "isam2", run=lab_run)
    par = run_slam(lab_run.path, "isam2", run=lab_run, frontend="process")
    assert seq.status == par.status == "ok"
    np.testing.assert_array_equal(par.times, seq.times)
    np.testing.assert_array_equal(par.poses, seq.poses)
    np.testing.assert_array_equal(par.pose_covs, seq.pose_covs)
    assert len(par.landmarks) == len(seq.landmarks) > 3
    for a, b in zip(par.landmarks, seq.landmarks, strict=True):
        np.testing.assert_array_equal(np.asarray(a.position), np.asarray(b.position))


@pytest.mark.parametrize("mode", ["thread", "process"])
def test_worker_error_names_the_image(lab_run: LoggedRun, tmp_path: Path, mode: str) -> None:
    """A corrupt image stops the run with a FrontendError naming the file, raised when
    its frame is due (the frames before it are delivered)."""
    assert lab_run.images is not None
    bad = tmp_path / "000005.png"
    bad.write_bytes(b"not a png")
    files = list(lab_run.images.files[:8])
    files[5] = bad
    images = dataclasses.replace(lab_run.images, t=lab_run.images.t[:8], files=files)
    got = []
    with pytest.raises(FrontendError, match="000005.png"):
        for f in frame_source(images, lab_run.rig.camera, mode=mode):  # type: ignore[arg-type]
            got.append(f)
    assert [f.index for f in got] == [0, 1, 2, 3, 4]


def test_bad_arguments_are_named(lab_run: LoggedRun) -> None:
    """An unknown mode or an empty queue is refused with the value named."""
    assert lab_run.images is not None
    with pytest.raises(ValueError, match="'gpu'"):
        next(frame_source(lab_run.images, lab_run.rig.camera, mode="gpu"))  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="depth"):
        next(frame_source(lab_run.images, lab_run.rig.camera, depth=0))


def test_cli_frontend_option_same_trajectory(lab_run: LoggedRun, tmp_path: Path) -> None:
    """``lampsam --cv-threads 1 slam --frontend thread`` writes the sequential run's trajectory
    byte for byte, and OpenCV runs with the thread count asked."""
    import cv2

    from lampsam.cli import main

    for name, extra in (("seq", []), ("thr", ["--frontend", "thread"])):
        argv = ["--cv-threads", "1", "slam", str(lab_run.path), "--backend", "ekf",
                "--out", str(tmp_path / name), *extra]
        assert main(argv) == 0
    assert cv2.getNumThreads() == 1
    seq, thr = (sorted((tmp_path / n).glob("*.tum")) for n in ("seq", "thr"))
    assert seq and [p.name for p in seq] == [p.name for p in thr]
    for a, b in zip(seq, thr, strict=True):
        assert a.read_bytes() == b.read_bytes()


@pytest.mark.parametrize("mode", ["thread", "process"])
def test_stopping_early_ends_the_worker(lab_run: LoggedRun, mode: str) -> None:
    """A consumer that stops after 3 frames (queue of 2, the worker blocked on a full
    queue) leaves no worker thread or process behind once the source is closed."""
    import multiprocessing
    import threading

    assert lab_run.images is not None
    source = frame_source(lab_run.images, lab_run.rig.camera, mode=mode,  # type: ignore[arg-type]
                          depth=2)
    got = [next(source) for _ in range(3)]
    assert [f.index for f in got] == [0, 1, 2]
    source.close()
    assert not [t for t in threading.enumerate() if t.name == "lampsam-frontend"]
    assert not [p for p in multiprocessing.active_children() if p.name == "lampsam-frontend"]
