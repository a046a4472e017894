"""Every result/map writer goes through ``lampsam.safe_io``: a kill mid-write leaves no file that looks complete.

Two checks: (1) each writer is run with the final rename failing as a kill would
stop it (``os.replace`` raising ``KeyboardInterrupt``): the target keeps its old
content (or stays absent) and no temporary file is left; (2) a real subprocess
writing a large TUM file is killed with SIGKILL while the temporary file grows:
the target is never created. Plus the JSON-lines progress log's recovery.
"""

from __future__ import annotations

import signal
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

import lampsam.safe_io as safe_io
from lampsam.datasets.calibration import Intrinsics, write_camera_info
from lampsam.datasets.g2o_writer import write_g2o
from lampsam.datasets.logrun import write_meta
from lampsam.datasets.odometry import Pose2OdometryLog, write_pose2_odometry
from lampsam.datasets.tables import (
    LandmarkTable,
    OdometryLog,
    RangeBearingLog,
    Trajectory,
    write_landmarks,
    write_odometry,
    write_range_bearing,
)
from lampsam.datasets.tum import write_tum
from lampsam.errors import InputError
from lampsam.evaluation.laser_trials import write_json
from lampsam.localization.grid import OccupancyGrid, save_map_server
from lampsam.localization.map_tables import save_distance_field
from lampsam.safe_io import TMP_PREFIX, append_json_line, read_json_lines

RNG_SEED = 18


def _grid() -> OccupancyGrid:
    rng = np.random.default_rng(RNG_SEED)
    return OccupancyGrid(log_odds=rng.normal(0.0, 2.0, (20, 30)), resolution=0.05)


def _traj(n: int = 50) -> Trajectory:
    t = np.arange(n) * 0.1
    return Trajectory(t=t, poses=np.column_stack([t, 0.5 * t, 0.01 * t]))


# (name, files the writer produces relative to tmp_path, writer(tmp_path))
WRITERS: list[tuple[str, tuple[str, ...], Callable[[Path], object]]] = [
    ("tum", ("a.tum",), lambda d: write_tum(d / "a.tum", _traj())),
    ("odometry.csv", ("odometry.csv",), lambda d: write_odometry(
        d / "odometry.csv", OdometryLog(t=np.arange(5.0), d_left=np.full(5, 0.01),
                                        d_right=np.full(5, 0.02)))),
    ("landmarks.csv", ("landmarks.csv",), lambda d: write_landmarks(
        d / "landmarks.csv", LandmarkTable(
            ids=np.array([1, 2]), types=("lamp_rect", "corner"), xyz=np.ones((2, 3)),
            phi=np.zeros(2), length=np.zeros(2), width=np.zeros(2)))),
    ("rangebearing.csv", ("rb.csv",), lambda d: write_range_bearing(
        d / "rb.csv", RangeBearingLog(t=np.arange(3.0), landmark_id=np.array([1, 2, 3]),
                                      range=np.ones(3), bearing=np.zeros(3)))),
    ("odometry_pose2.csv", ("p2.csv",), lambda d: write_pose2_odometry(
        d / "p2.csv", Pose2OdometryLog(t=np.arange(3.0), delta=np.zeros((3, 3)),
                                       cov=np.tile(np.eye(3) * 1e-4, (3, 1, 1))))),
    ("meta.yaml", ("meta.yaml",), lambda d: write_meta(d / "meta.yaml", {"complete": True})),
    ("camera_info", ("cam.yaml",), lambda d: write_camera_info(
        d / "cam.yaml", Intrinsics(width=320, height=240, fx=200.0, fy=200.0, cx=160.0,
                                      cy=120.0, dist=np.zeros(5), model="pinhole"))),
    ("g2o", ("g.g2o",), lambda d: write_g2o(
        d / "g.g2o", np.array([0, 1]), np.array([[0.0, 0, 0], [1.0, 0, 0]]),
        [(0, 1, np.array([1.0, 0, 0]), np.eye(3))])),
    ("map_server", ("m.pgm", "m.yaml"), lambda d: save_map_server(_grid(), d / "m")),
    ("distance_field", ("distance_field.npz",),
     lambda d: save_distance_field(d, _grid(), np.zeros((20, 30)))),
    ("laser result.json", ("result.json",), lambda d: write_json({"a": 1.0}, d / "result.json")),
    ("json", ("x.json",), lambda d: safe_io.write_json_atomic(d / "x.json", {"a": np.float64(2)})),
]


@pytest.mark.parametrize(("name", "files", "writer"), WRITERS, ids=[w[0] for w in WRITERS])
def test_writer_interrupted_before_rename_keeps_old_file(
    name: str, files: tuple[str, ...], writer: Callable[[Path], object], tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    for f in files:  # a finished earlier result that must survive
        (tmp_path / f).write_bytes(b"old")
    writer(tmp_path)  # it works, and it replaces the files
    for f in files:
        assert (tmp_path / f).read_bytes() != b"old", f"{name}: {f} not written"
        (tmp_path / f).write_bytes(b"old")

    def killed(src: object, dst: object) -> None:
        raise KeyboardInterrupt

    monkeypatch.setattr(safe_io.os, "replace", killed)
    with pytest.raises(KeyboardInterrupt):
        writer(tmp_path)
    for f in files:
        assert (tmp_path / f).read_bytes() == b"old", f"{name}: {f} overwritten in place"
    assert not [p.name for p in tmp_path.iterdir() if p.name.startswith(TMP_PREFIX)]


#: Writes a 200,000-pose TUM file and stops half-way, its first 100,000 lines flushed to
#: the temporary file: prints "mid-write" and waits on stdin (until killed), so the kill
#: lands mid-write whatever the machine's speed or load.
_STALLED_WRITER = """
import sys
import numpy as np
import lampsam.datasets.tum as tum
from lampsam.datasets.tables import Trajectory

class Stalling:
    def __init__(self, fh):
        self.fh, self.n = fh, 0
    def __enter__(self):
        return self
    def __exit__(self, *exc):
        self.fh.close()
    def write(self, text):
        self.n += 1
        if self.n == 100_002:  # the header and 100,000 poses written
            self.fh.flush()
            print("mid-write", flush=True)
            sys.stdin.readline()
        return self.fh.write(text)

tum.open = lambda *a, **k: Stalling(open(*a, **k))
n = 200_000
tum.write_tum(sys.argv[1], Trajectory(t=np.arange(n) * 0.01, poses=np.zeros((n, 3))))
"""


def test_sigkill_mid_write_leaves_no_target(tmp_path: Path, cli_env: dict[str, str]) -> None:
    """SIGKILL while a TUM file is half written: the target never appears, the half of
    the data sits only under the temporary name."""
    target = tmp_path / "big.tum"
    proc = subprocess.Popen([sys.executable, "-c", _STALLED_WRITER, str(target)], env=cli_env,
                            stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    try:
        assert proc.stdout is not None
        assert proc.stdout.readline().strip() == "mid-write", "the writer ended before mid-write"
        tmp = [p for p in tmp_path.iterdir() if p.name.startswith(TMP_PREFIX)]
        assert len(tmp) == 1, "no temporary file while writing"
        proc.send_signal(signal.SIGKILL)
        proc.wait(30)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert not target.exists()  # the half-written data sits only under the temporary name
    assert len(tmp[0].read_text().splitlines()) == 100_001  # the header and 100,000 poses


def test_json_lines_skip_a_line_cut_short(tmp_path: Path) -> None:
    log = tmp_path / "jobs.jsonl"
    append_json_line(log, {"trial": 0, "x": np.float64(1.5)})
    append_json_line(log, {"trial": 1})
    with open(log, "a", encoding="utf-8") as fh:
        fh.write('{"trial": 2, "x"')  # what a kill mid-write leaves
    assert read_json_lines(log) == [{"trial": 0, "x": 1.5}, {"trial": 1}]
    log.write_text('{"trial": 0}\nnot json\n{"trial": 1}\n')
    with pytest.raises(InputError, match=r"jobs.jsonl:2: not JSON"):
        read_json_lines(log)
