"""The finished subcommands run in-process through ``lampsam.cli.main`` on tiny inputs.

Each test asserts on what the command leaves behind (files, the numbers in them,
the exit code, the printed lines). Bad input must end with exit code 2 and a
one-line message on stderr that names the offending file, never a traceback.

The ``--config`` files of every command are tested in ``test_config_loader.py``.
"""

from __future__ import annotations

import csv
import json
import re
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from lampsam.angles import wrap_angle
from lampsam.cli import main
from tests.conftest import SimRun, require_shared


def _read_tum(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """(t (N,), poses (N, 3)) of a planar TUM file (yaw from qz, qw)."""
    rows = np.loadtxt(path, comments="#", ndmin=2)
    return rows[:, 0], np.column_stack([rows[:, 1], rows[:, 2],
                                        2.0 * np.arctan2(rows[:, 6], rows[:, 7])])


def _clean_failure(err: str, *names: str) -> None:
    """stderr is a ``lampsam ...: error: ...`` message naming ``names``, no traceback."""
    assert "Traceback" not in err
    assert "error:" in err
    for name in names:
        assert name in err, f"{name!r} not named in {err!r}"


# --------------------------------------------------------------------------- stereo
def test_stereo_sim_and_ekf_on_straight_scenario(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """``straight``, seed 0: the EKF's RMS error against the simulator's truth is below
    x 0.2 m, y 0.5 m, heading 0.1 rad (measured: 0.10 m, 0.30 m, 0.046 rad), the
    summary's RMS is what estimate.tum and groundtruth.tum give on the frames with a
    measurement, and the printed table carries the same numbers (heading in degrees)."""
    run_dir, out = tmp_path / "run", tmp_path / "ekf"
    assert main(["stereo-sim", "--scenario", "straight", "--out", str(run_dir)]) == 0
    for name in ("stereo_run.yaml", "measurements.csv", "odometry.csv", "groundtruth.tum"):
        assert (run_dir / name).is_file()
    assert main(["stereo", str(run_dir), "--estimator", "ekf", "--out", str(out)]) == 0
    printed = capsys.readouterr().out.strip().splitlines()[-2]  # the table's row

    summary = json.loads((out / "summary.json").read_text())
    rms = summary["rms"]
    assert summary["estimator"] == "ekf" and summary["frames"] == 171
    assert rms["x_m"] < 0.2 and rms["y_m"] < 0.5 and rms["heading_rad"] < 0.1
    assert (f"| {rms['x_m']:.4f} | {rms['y_m']:.4f} | {np.degrees(rms['heading_rad']):.3f} "
            f"| {rms['frames']} |") in printed

    # recompute the RMS from the written files: frames whose status is "ok"
    with open(out / "status.csv", newline="") as fh:
        status = list(csv.DictReader(fh))
    assert len(status) == 171
    ok = np.array([r["status"] == "ok" for r in status])
    assert ok.sum() == rms["frames"] == summary["status_counts"]["ok"]
    t_est, est = _read_tum(out / "estimate.tum")
    t_gt, gt = _read_tum(run_dir / "groundtruth.tum")
    t_ok = np.array([float(r["t"]) for r in status])[ok]
    idx_est = np.searchsorted(t_est, t_ok)
    idx_gt = np.searchsorted(t_gt, t_ok)
    np.testing.assert_allclose(t_est[idx_est], t_ok, atol=1e-9)
    err = est[idx_est] - gt[idx_gt]
    err[:, 2] = wrap_angle(err[:, 2])
    mine = np.sqrt(np.mean(err**2, axis=0))
    np.testing.assert_allclose(mine, [rms["x_m"], rms["y_m"], rms["heading_rad"]],
                               rtol=1e-6, atol=1e-8)


def test_stereo_sim_turn_and_estimate(tmp_path: Path) -> None:
    """``turn``, seed 4: every frame measured and estimated; RMS x and heading below 0.2."""
    run_dir, out = tmp_path / "run", tmp_path / "ekf"
    assert main(["stereo-sim", "--scenario", "turn", "--out", str(run_dir), "--seed", "4"]) == 0
    assert main(["stereo", str(run_dir), "--estimator", "ekf", "--out", str(out)]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["frames"] == 161 and summary["status_counts"] == {"ok": 161}
    assert summary["rms"]["x_m"] < 0.2 and summary["rms"]["heading_rad"] < 0.2
    assert len((out / "status.csv").read_text().splitlines()) == 162
    assert (out / "errors.png").stat().st_size > 10_000
    # a missing run is a clean error (exit 2), not a traceback
    assert main(["stereo", str(tmp_path / "nothing"), "--estimator", "raw",
                 "--out", str(out)]) == 2


def test_stereo_bad_inputs(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Missing run directory; a malformed measurements line (named by file and line);
    output paths that cannot be created."""
    missing = tmp_path / "no_such_run"
    assert main(["stereo", str(missing), "--estimator", "ekf", "--out", str(tmp_path / "o")]) == 2
    _clean_failure(capsys.readouterr().err, "no_such_run")

    run_dir = tmp_path / "run"
    assert main(["stereo-sim", "--scenario", "turn", "--out", str(run_dir)]) == 0
    meas = run_dir / "measurements.csv"
    lines = meas.read_text().splitlines()
    good_line = lines[4]
    lines[4] = "0.3,1,abc,74.5,27.5"  # line 5: a field short
    meas.write_text("\n".join(lines) + "\n")
    capsys.readouterr()
    assert main(["stereo", str(run_dir), "--estimator", "ekf", "--out", str(tmp_path / "o")]) == 2
    _clean_failure(capsys.readouterr().err, "measurements.csv:5")
    assert not (tmp_path / "o" / "summary.json").exists()

    # an output path that cannot be a directory: named, no traceback
    blocker = tmp_path / "a_file"
    blocker.write_text("not a directory")
    assert main(["stereo-sim", "--scenario", "turn", "--out", str(blocker / "run")]) == 2
    _clean_failure(capsys.readouterr().err, "a_file")
    lines[4] = good_line  # repair the run
    meas.write_text("\n".join(lines) + "\n")
    assert main(["stereo", str(run_dir), "--estimator", "raw", "--out", str(blocker)]) == 2
    _clean_failure(capsys.readouterr().err, "a_file", "output directory")


@pytest.mark.parametrize(
    ("argv", "option"),
    [
        (["stereo", "RUN", "--estimator", "kalman", "--out", "OUT"], "--estimator"),
        (["stereo-sim", "--scenario", "zigzag", "--out", "OUT"], "--scenario"),
        (["compare", "RUN", "--frames", "lidar", "--out", "OUT"], "--frames"),
        (["frontend-eval", "RUN", "--max-frames", "five"], "--max-frames"),
    ],
)
def test_unknown_option_value_exits_2(
    argv: list[str], option: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """argparse rejects the value: exit code 2, usage and the option named, no traceback."""
    argv = [a.replace("RUN", str(tmp_path / "run")).replace("OUT", str(tmp_path / "out"))
            for a in argv]
    with pytest.raises(SystemExit) as exc:
        main(argv)
    assert exc.value.code == 2
    err = capsys.readouterr().err
    _clean_failure(err, option, "usage:")
    assert not (tmp_path / "out").exists()


# --------------------------------------------------------------------------- frontend-eval
@pytest.fixture(scope="module")
def lab_run(sim_run: SimRun) -> Path:
    """Half a second of the simulated lab (8 images of 320x240)."""
    return sim_run(seed=3, duration=0.5)


def test_frontend_eval_on_tiny_run(
    lab_run: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """5 frames: exit 0 (targets met), the JSON's figures meet the issue's targets
    (recall >= 99 %, no false lamp, centroid RMS <= 0.3 px, axis RMS <= 0.5 deg)."""
    out = tmp_path / "fe.json"
    assert main(["frontend-eval", str(lab_run), "--max-frames", "5", "--out", str(out)]) == 0
    res = json.loads(out.read_text())
    assert res["n_frames"] == 5
    assert res["n_truth_lamps_full"] >= 5 and res["lamp_recall"] >= 0.99
    assert res["n_false"] == 0
    assert res["centroid_rms_px"] <= 0.3
    assert res["n_axis"] >= 1 and res["axis_rms_deg"] <= 0.5
    assert all(res["targets_met"].values())
    printed = capsys.readouterr().out
    assert "frames: 5" in printed and f"found {res['n_found']}" in printed


def test_frontend_eval_bad_inputs(
    lab_run: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Missing run directory; a PNG full of garbage bytes (named, with its images.csv
    line); ``--max-frames`` below 1."""
    assert main(["frontend-eval", str(tmp_path / "no_such_run")]) == 2
    _clean_failure(capsys.readouterr().err, "no_such_run")

    bad = tmp_path / "bad_run"
    shutil.copytree(lab_run, bad)
    (bad / "images" / "000002.png").write_bytes(np.random.default_rng(7).bytes(300))
    out = tmp_path / "fe.json"
    assert main(["frontend-eval", str(bad), "--max-frames", "5", "--out", str(out)]) == 2
    _clean_failure(capsys.readouterr().err, "000002.png", "images.csv")
    assert not out.exists()

    # no frames to evaluate is bad input, not a report of NaNs
    for n in ("0", "-3"):
        assert main(["frontend-eval", str(lab_run), "--max-frames", n, "--out", str(out)]) == 2
        _clean_failure(capsys.readouterr().err, "max_frames", n)
    assert not out.exists()

    # an output below a file
    blocker = tmp_path / "a_file"
    blocker.write_text("not a directory")
    assert main(["frontend-eval", str(lab_run), "--max-frames", "1",
                 "--out", str(blocker / "fe.json")]) == 2
    _clean_failure(capsys.readouterr().err, "a_file", "output directory")


# --------------------------------------------------------------------------- gallery
_GALLERY_LINE = re.compile(r"^(\S+) (\d+)x(\d+): (\d+) lamps \((\d+) oriented\)")


def test_gallery_on_simulated_frames(
    lab_run: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Two simulated frames as photos: per photo, the printed lamp count equals the
    visible lamps of the simulator's truth, the oriented count its visible strip
    (``lamp_rect``) lamps; the gallery PNG is written."""
    photos = tmp_path / "photos"
    photos.mkdir()
    for i in (1, 2):
        shutil.copy(lab_run / "images" / f"{i:06d}.png", photos / f"{i:06d}.png")
    out = tmp_path / "gallery.png"
    assert main(["gallery", str(photos), "--out", str(out), "--small-only"]) == 0
    assert out.stat().st_size > 10_000

    with open(lab_run / "truth" / "projections.csv", newline="") as fh:
        truth = [r for r in csv.DictReader(fh) if r["type"].startswith("lamp") and r["visible"] == "1"]
    lines = [m for m in map(_GALLERY_LINE.match, capsys.readouterr().out.splitlines()) if m]
    assert [m.group(1) for m in lines] == ["000001.png", "000002.png"]
    for m in lines:
        frame = str(int(m.group(1)[:6]))
        visible = [r for r in truth if r["frame"] == frame]
        assert (int(m.group(2)), int(m.group(3))) == (320, 240)
        assert int(m.group(4)) == len(visible)
        assert int(m.group(5)) == sum(r["type"] == "lamp_rect" for r in visible)


def test_gallery_bad_inputs(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A missing folder, an empty folder, a PNG full of garbage bytes, an output below a file."""
    out = tmp_path / "g.png"
    assert main(["gallery", str(tmp_path / "no_photos"), "--out", str(out)]) == 2
    _clean_failure(capsys.readouterr().err, "no_photos")
    empty = tmp_path / "empty"
    empty.mkdir()
    assert main(["gallery", str(empty), "--out", str(out)]) == 2
    _clean_failure(capsys.readouterr().err, "empty")
    (empty / "broken.png").write_bytes(np.random.default_rng(8).bytes(300))
    assert main(["gallery", str(empty), "--out", str(out), "--small-only"]) == 2
    _clean_failure(capsys.readouterr().err, "broken.png")
    assert not out.exists()
    (empty / "broken.png").unlink()
    cv2.imwrite(str(empty / "flat.png"), np.full((240, 320), 90, np.uint8))
    blocker = tmp_path / "a_file"
    blocker.write_text("not a directory")
    assert main(["gallery", str(empty), "--out", str(blocker / "g.png"), "--small-only"]) == 2
    _clean_failure(capsys.readouterr().err, "a_file", "output directory")


@pytest.mark.shared_data
def test_gallery_on_real_photo(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """The 808 ceiling photo at 320x240: its 3 strip lamps, all oriented (counted by eye,
    see tests/test_frontend_runs.py)."""
    folder = require_shared("ceiling_photos")
    photos = tmp_path / "photos"
    photos.mkdir()
    (photos / "808.jpg").symlink_to(folder / "808_db_photo.jpg")
    out = tmp_path / "gallery.png"
    assert main(["gallery", str(photos), "--out", str(out), "--small-only"]) == 0
    assert out.stat().st_size > 10_000
    m = _GALLERY_LINE.match(capsys.readouterr().out.splitlines()[0])
    assert m is not None and m.group(1) == "808.jpg"
    assert (int(m.group(2)), int(m.group(3))) == (320, 240)
    assert int(m.group(4)) == 3 and int(m.group(5)) == 3


# --------------------------------------------------------------------------- compare
def test_compare_bad_inputs(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A run that is neither a directory nor a world; an unknown backend name; an output
    path that is a file (refused before any run is simulated)."""
    out = tmp_path / "cmp"
    assert main(["compare", str(tmp_path / "no_such_run"), "--backends", "ekf",
                 "--out", str(out)]) == 2
    _clean_failure(capsys.readouterr().err, "no_such_run")
    assert main(["compare", "lab", "--backends", "kalman", "--out", str(out)]) == 2
    _clean_failure(capsys.readouterr().err, "kalman")
    blocker = tmp_path / "a_file"
    blocker.write_text("not a directory")
    assert main(["compare", "lab", "--backends", "ekf", "--out", str(blocker)]) == 2
    _clean_failure(capsys.readouterr().err, "a_file", "output directory")

