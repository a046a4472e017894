"""Lazy frames (#19): the smoothers read only the frames that can become keyframes.

A :class:`~lampsam.backend.pipelined.LazyFrame` reads and processes its image on
first access. ``run_slam`` (isam2, batch) and ``--online decoupled``
(:class:`~lampsam.backend.keyframes.KeyframeMirror`) then run the frontend only on
the frames the backend reads; the written results are byte for byte those of a run
fed every frame made ahead (main's behaviour), and the frontend runs on exactly the
frames the backend's keyframe rule reads.
"""

from __future__ import annotations

import dataclasses
import json
import pickle
from pathlib import Path

import numpy as np
import pytest

import lampsam.frontend.pipeline as frontend_pipeline
from lampsam.backend.config import SlamConfig
from lampsam.backend.keyframes import KeyframeMirror
from lampsam.backend.odometry import motion_model
from lampsam.backend.online_run import run_slam_decoupled
from lampsam.backend.pipelined import FrameTimes, LazyFrame, frame_source
from lampsam.backend.slam import (
    drive,
    iter_steps,
    make_backend,
    make_frames,
    run_slam,
    start_pose_of,
    write_results,
)
from lampsam.datasets.logrun import LoggedRun, read_run
from lampsam.errors import EstimationError, LampsamError
from lampsam.frontend.measurements import CeilingFrame
from lampsam.frontend.pipeline import iter_run
from tests.conftest import SimRun

#: summary.json keys that are timings (differ run to run)
TIMING_KEYS = {"time_per_frame_ms", "final_optimisation_s", "total_time_s", "update_median_ms",
               "update_p95_ms", "estimate_median_ms"}


@pytest.fixture(scope="module")
def lab_run(sim_run: SimRun) -> LoggedRun:
    """6 s of the simulated lab (91 frames), seed 4."""
    return read_run(sim_run(seed=4, duration=6.0))


@pytest.fixture(scope="module")
def eager(lab_run: LoggedRun, tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """Each smoother's results written from frames all made ahead (no lazy frame)."""
    frames = list(iter_run(lab_run))
    out = {}
    for backend in ("isam2", "batch"):
        be = make_backend(backend, lab_run.rig.odometry, SlamConfig(), start_pose_of(lab_run),
                          lab_run.rig.camera)
        result = drive(be, iter_steps(lab_run.odometry, frames))
        assert result.status == "ok"
        out[backend] = tmp_path_factory.mktemp(f"eager_{backend}")
        write_results(out[backend], result, lab_run)
    return out


def _same_files(a: Path, b: Path) -> None:
    """trajectory.tum and landmarks.csv byte-equal; summary.json equal but for timings."""
    for name in ("trajectory.tum", "landmarks.csv"):
        assert (a / name).read_bytes() == (b / name).read_bytes(), name
    sa, sb = (json.loads((d / "summary.json").read_text()) for d in (a, b))
    keep = set(sa) - TIMING_KEYS - {k for k in sa if k.startswith("online_")}
    assert {k: sa[k] for k in keep} == {k: sb.get(k) for k in keep}
    assert sa["keyframes"] > 5 and sa["landmarks"] > 3


@pytest.fixture()
def counted(monkeypatch: pytest.MonkeyPatch) -> list[int]:
    """The image indices the frontend processes (process_image calls, lazy or not)."""
    seen: list[int] = []
    real = frontend_pipeline.process_image

    def spy(image: object, t: float, index: int, *a: object, **k: object) -> CeilingFrame:
        seen.append(index)
        return real(image, t, index, *a, **k)  # type: ignore[arg-type]

    # every path (iter_run, lazy and eager frame sources) goes through this one
    monkeypatch.setattr(frontend_pipeline, "process_image", spy)
    return seen


def _read_by_rule(lab_run: LoggedRun) -> list[int]:
    """The frames the keyframe rule reads, found with every frame made ahead."""
    mirror = KeyframeMirror(motion_model(lab_run.rig.odometry), SlamConfig())
    read = []
    for t, wheel, frame in iter_steps(lab_run.odometry, list(iter_run(lab_run))):
        if mirror.reads(mirror.motion.check(t, wheel), frame):
            assert frame is not None
            read.append(frame.index)
    return read


@pytest.mark.parametrize("backend", ["isam2", "batch"])
def test_run_slam_lazy_is_bit_identical(lab_run: LoggedRun, eager: dict[str, Path],
                                        tmp_path: Path, counted: list[int], backend: str) -> None:
    """run_slam (lazy frames) writes main's files byte for byte, the frontend having run
    only on the frames the keyframe rule reads: every keyframe's, and fewer than all."""
    result = run_slam(lab_run.path, backend, out=tmp_path, run=lab_run)
    _same_files(tmp_path, eager[backend])
    n_frames, made = len(lab_run.images or ()), list(counted)
    assert made == _read_by_rule(lab_run)
    assert int(result.keyframes.sum()) <= len(made) < 0.8 * n_frames


def test_decoupled_lazy_is_bit_identical(lab_run: LoggedRun, eager: dict[str, Path],
                                         tmp_path: Path, counted: list[int]) -> None:
    """--online decoupled: the main process makes only the frames the mirrored keyframe
    rule says the worker's iSAM2 reads; the worker's result is main's byte for byte."""
    result, tm = run_slam_decoupled(lab_run, "isam2", tmp_path)
    _same_files(tmp_path, eager["isam2"])
    made = list(counted)
    assert made == _read_by_rule(lab_run)
    assert int(result.keyframes.sum()) <= len(made) < 0.8 * sum(tm.framed)
    assert sum(tm.framed) == len(lab_run.images or ())  # every frame still tracked


def test_ekf_reads_every_frame(lab_run: LoggedRun, tmp_path: Path, counted: list[int]) -> None:
    """The EKF uses every frame: each image goes through the frontend once."""
    run_slam(lab_run.path, "ekf", run=lab_run)
    assert counted == list(range(len(lab_run.images or ())))


def test_lazy_frame_reads_once_and_pickles_plain(lab_run: LoggedRun, counted: list[int]) -> None:
    """A lazy frame is made on first access only, equals the eager frame, and pickles as
    the plain CeilingFrame (bit for bit); ready time and CPU are recorded when made."""
    assert lab_run.images is not None
    ref = list(iter_run(lab_run))[:4]
    counted.clear()
    times = FrameTimes()
    lazy = list(frame_source(lab_run.images, lab_run.rig.camera, mode="sequential",
                             times=times))[:4]
    assert counted == [] and all(isinstance(f, LazyFrame) and not f.loaded for f in lazy)
    assert [f.t for f in lazy] == [f.t for f in ref] and lazy[2].index == 2
    assert len(lazy[2].corners) == len(ref[2].corners) > 5 and len(lazy[2].lamps) == len(ref[2].lamps)
    assert counted == [2] and lazy[2].loaded and not lazy[1].loaded
    assert times.ready[2] >= times.arrival[2] and times.worker_cpu_s > 0.0
    back = [pickle.loads(pickle.dumps(f)) for f in lazy]
    assert counted == [2, 0, 1, 3] and all(type(f) is CeilingFrame for f in back)
    assert [pickle.dumps(f) for f in back] == [pickle.dumps(f) for f in ref]


def test_bad_image_named_when_read(lab_run: LoggedRun, tmp_path: Path) -> None:
    """A corrupt image read by the backend fails the run naming the file (steps kept);
    lazily, an image the smoother never reads is never decoded."""
    assert lab_run.images is not None
    bad = tmp_path / "000000.png"
    bad.write_bytes(b"not a png")
    files = list(lab_run.images.files)
    files[0] = bad  # the first frame is always read (keyframe 1)
    run = dataclasses.replace(lab_run, images=dataclasses.replace(lab_run.images, files=files))
    with pytest.raises(EstimationError, match="000000.png"):
        run_slam(run.path, "isam2", out=tmp_path / "out", run=run)
    frames, _ = make_frames(run, "images", lazy=True)
    first = next(iter(frames))
    with pytest.raises(LampsamError, match="000000.png"):
        _ = first.lamps
    assert np.isfinite(first.t)
