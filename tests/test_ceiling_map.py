"""Map once, localize every day (issue 20): the saved ceiling map and localize-only tracking.

- a map written and read back is the same, bit for bit (landmarks, covariances,
  axes, patches, rig);
- a wrong map folder gives a DatasetError naming the file and the key or line;
- localize-only on a hand-built 20 s drive under a lamp-and-corner ceiling, against
  a map whose landmarks are off by their stated sigma, tracks within 2.5 cm of the
  truth (odometry alone drifts more), uses only map landmarks and adds none; with a
  start pose 10 cm / 2 deg off it recovers;
- end to end through the CLI on 4 s of the simulated lab: ``--save-map`` then
  ``--map --localize-only`` (RMS < 3 cm), and the clear errors of bad flags and maps.
"""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

import numpy as np
import pytest

from lampsam.backend.ceiling import CeilingModel
from lampsam.backend.ceiling_map_io import (
    CeilingMap,
    MapLandmark,
    read_map,
    write_map,
)
from lampsam.backend.config import SlamConfig
from lampsam.backend.localize_only import LocalizeConfig, MapLocalizer
from lampsam.backend.localize_run import parse_start, start_from_result
from lampsam.backend.slam import drive, errors_vs_truth, iter_steps
from lampsam.cli import main
from lampsam.datasets.logrun import OdometryLog, OdometryModel, Rig
from lampsam.datasets.motion import follow_waypoints, noisy_wheel_travel
from lampsam.errors import DatasetError, InputError
from lampsam.factors.ceiling import project_point
from lampsam.frontend.measurements import CeilingFrame, CornerObservation, LampObservation
from tests.conftest import SimRun

K_WHEEL = 4e-5  # m, eq. 15 slip constant (twice the lab's: a visible drift in 20 s)


def _rms(x: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.square(x))))


def _random_map(rng: np.random.Generator) -> CeilingMap:
    lms = []
    for i in range(12):
        kind = "lamp" if i < 4 else "corner"
        a = rng.normal(size=(4, 4))
        cov = 1e-4 * (a @ a.T)
        phi: float | None = float(rng.uniform(0, math.pi)) if i < 2 else None
        if phi is None:
            cov[3, :] = cov[:, 3] = 0.0
        patch = (rng.normal(size=(11, 11)).astype(np.float32) if kind == "corner" and i % 3
                 else None)
        lms.append(MapLandmark(100 + i, kind, rng.uniform(0, 10, 3), phi, cov,
                               int(rng.integers(2, 50)), patch))
    return CeilingMap(lms, Rig(), {"run": "synthetic", "backend": "batch"})


def test_map_round_trip_is_exact(tmp_path: Path, rng: np.random.Generator) -> None:
    """Every float, axis, patch and the rig come back identical."""
    cmap = _random_map(rng)
    back = read_map(write_map(tmp_path / "map", cmap))
    assert len(back.landmarks) == len(cmap.landmarks)
    for a, b in zip(cmap.landmarks, back.landmarks, strict=True):
        assert (a.id, a.kind, a.phi, a.n_obs) == (b.id, b.kind, b.phi, b.n_obs)
        assert np.array_equal(a.position, b.position)
        assert np.array_equal(a.cov, b.cov)
        if a.patch is None:
            assert b.patch is None
        else:
            assert b.patch is not None and b.patch.dtype == np.float32
            assert np.array_equal(a.patch, b.patch)
    assert back.rig.to_dict() == cmap.rig.to_dict()
    assert back.source == cmap.source
    assert not list((tmp_path / "map").glob(".tmp-*"))  # atomic writes left nothing behind


def _expect(folder: Path, *words: str) -> None:
    with pytest.raises(DatasetError) as exc:
        read_map(folder)
    msg = str(exc.value)
    for w in words:
        assert w in msg, f"{w!r} not in {msg!r}"


def test_wrong_map_files_are_named(tmp_path: Path, rng: np.random.Generator) -> None:
    """Missing folder / map.yaml, wrong format, version, key, CSV header, number, id, patch."""
    _expect(tmp_path / "nothing", "nothing", "not a ceiling map")
    good = write_map(tmp_path / "good", _random_map(rng))
    meta = (good / "map.yaml").read_text()

    def variant(name: str, edit: dict[str, str], meta_text: str = meta) -> Path:
        folder = tmp_path / name
        folder.mkdir()
        for f in ("map.yaml", "landmarks.csv", "patches.npz"):
            (folder / f).write_bytes((good / f).read_bytes())
        (folder / "map.yaml").write_text(meta_text)
        for f, text in edit.items():
            (folder / f).write_text(text)
        return folder

    (tmp_path / "empty").mkdir()
    _expect(tmp_path / "empty", "map.yaml", "missing")
    _expect(variant("fmt", {}, meta.replace("lampsam-ceiling-map", "other-map")),
            "map.yaml", "'format'")
    _expect(variant("ver", {}, meta.replace("format_version: 3", "format_version: 9")),
            "map.yaml", "'format_version'", "9")
    _expect(variant("key", {}, meta.replace("units:", "unitz:")), "map.yaml", "units")
    _expect(variant("cal2", {}, meta.replace("format_version: 3", "format_version: 2")
                    + "calibration: {}\n"), "map.yaml", "'calibration'", "version 2")
    _expect(variant("cam", {}, meta.replace("  width: 320", "  widht: 320")), "map.yaml", "camera.width")
    csv_lines = (good / "landmarks.csv").read_text().splitlines()
    _expect(variant("hdr", {"landmarks.csv": "\n".join(["id,x"] + csv_lines[1:])}),
            "landmarks.csv", "line 1", "header")
    bad_row = csv_lines[3].split(",")
    bad_row[3] = "abc"
    _expect(variant("num", {"landmarks.csv": "\n".join(csv_lines[:3] + [",".join(bad_row)]
                                                       + csv_lines[4:])}),
            "landmarks.csv", "line 4", "column y", "abc")
    _expect(variant("dup", {"landmarks.csv": "\n".join(csv_lines + [csv_lines[1]])}),
            "landmarks.csv", "duplicate id")
    _expect(variant("cnt", {"landmarks.csv": "\n".join(csv_lines[:-1])}), "map.yaml", "counts")
    folder = variant("npz", {})
    np.savez(folder / "patches.npz", ids=np.array([999]), patches=np.zeros((1, 11, 11), np.float32))
    _expect(folder, "patches.npz", "999")
    (folder / "patches.npz").unlink()
    _expect(folder, "patches.npz", "missing")


# --------------------------------------------------------------------------- localize-only
def _drive(rng: np.random.Generator, map_sigma: float = 0.004):
    """20 s of a square drive under 4 oriented lamps and a 0.6 m corner grid.

    Returns ``(rig, odometry, frames, true poses (N, 3), times (N,), map)``; the map's
    landmarks are the truth plus Gaussian noise of ``map_sigma`` per coordinate and
    covariance ``map_sigma^2 I``; frames carry no landmark ids.
    """
    base = Rig()
    rig = Rig(camera=base.camera, odometry=OdometryModel(base.odometry.wheel_base, K_WHEEL, K_WHEEL))
    cam = rig.camera
    wps = np.array([[0.0, 0.0], [2.0, 0.0], [2.0, 2.0], [0.0, 2.0], [0.0, 0.5]])
    t, poses, wheel = follow_waypoints(wps, speed=0.4, rate_hz=30.0,
                                       wheel_base=rig.odometry.wheel_base, duration=20.0)
    noisy = noisy_wheel_travel(wheel, K_WHEEL, K_WHEEL, rng)
    lamps = {1: (np.array([1.0, 0.1, 2.5]), 0.0), 2: (np.array([1.9, 1.0, 2.5]), 1.5),
             3: (np.array([1.0, 1.9, 2.5]), 0.3), 4: (np.array([0.1, 1.0, 2.5]), 2.0)}
    gx, gy = np.meshgrid(np.arange(-0.9, 3.0, 0.6), np.arange(-0.9, 3.0, 0.6))
    corners = {100 + k: np.array([x, y, 2.7])
               for k, (x, y) in enumerate(zip(gx.ravel(), gy.ravel(), strict=True))}
    lms = []
    for lid, (p, phi) in lamps.items():
        lms.append(MapLandmark(lid, "lamp", p + rng.normal(0, map_sigma, 3),
                               float((phi + rng.normal(0, 0.01)) % math.pi),
                               np.diag([map_sigma**2] * 3 + [0.01**2]), 10))
    for lid, p in corners.items():
        lms.append(MapLandmark(lid, "corner", p + rng.normal(0, map_sigma, 3), None,
                               np.diag([map_sigma**2] * 3 + [0.0]), 10))
    cmap = CeilingMap(lms, rig)
    model = CeilingModel.from_camera(cam)
    sig = 0.5 / cam.fx
    cov = sig**2 * np.eye(2)
    frames = []
    for i in range(0, len(t), 2):
        lam_obs, cor_obs = [], []
        for p, phi in lamps.values():
            m, _, _ = project_point(poses[i], p, cam.body_t_camera)
            if np.hypot(*m) < model.max_radius:
                ax = float((phi - poses[i, 2] + rng.normal(0.0, 0.02)) % math.pi)
                lam_obs.append(LampObservation(m + rng.normal(0, sig, 2), cov, ax, 0.02**2, 2.0,
                                               80.0, np.zeros(2)))
        for p in corners.values():
            m, _, _ = project_point(poses[i], p, cam.body_t_camera)
            if np.hypot(*m) < 0.8 * model.max_radius:
                cor_obs.append(CornerObservation(m + rng.normal(0, sig, 2), cov, np.zeros(2),
                                                 np.zeros((1, 1), np.float32), 1.0))
        frames.append(CeilingFrame(float(t[i]), len(frames), tuple(lam_obs), tuple(cor_obs)))
    odo = OdometryLog(t=t[1:], d_left=noisy[1:, 0], d_right=noisy[1:, 1])
    return rig, odo, frames, poses, t, cmap


def _truth_errors(result, t: np.ndarray, poses: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    from lampsam.datasets.logrun import Trajectory

    return errors_vs_truth(result, Trajectory(t=t, poses=poses))


def test_localize_only_tracks_and_adds_nothing(rng: np.random.Generator) -> None:
    """RMS < 2.5 cm and < half of dead reckoning's; the map comes out unchanged."""
    rig, odo, frames, poses, t, cmap = _drive(rng)
    config = SlamConfig()
    config = dataclasses.replace(config, association=dataclasses.replace(
        config.association, use_known_ids=False))
    be = MapLocalizer(rig.odometry, config, poses[0], cmap, CeilingModel.from_camera(rig.camera))
    estimates = []
    steps = list(iter_steps(odo, frames))
    for step in steps:
        estimates.append(be.step(*step))
    result = be.finish()
    pos, head = _truth_errors(result, t, poses)
    assert _rms(pos) < 0.025
    assert np.degrees(_rms(head)) < 0.5
    assert all(e.n_new == 0 for e in estimates)
    assert result.extra["observations_used"] > 10 * len(frames)
    assert [lm.id for lm in result.landmarks] == [lm.id for lm in cmap.landmarks]
    for a, b in zip(result.landmarks, cmap.landmarks, strict=True):
        assert np.array_equal(a.position, b.position)
    # odometry alone (no frames) drifts clearly more
    dr = MapLocalizer(rig.odometry, config, poses[0], cmap, CeilingModel.from_camera(rig.camera))
    dr_result = drive(dr, ((s[0], s[1], None) for s in steps))
    dr_pos, _ = _truth_errors(dr_result, t, poses)
    assert _rms(pos) < 0.5 * _rms(dr_pos)


def test_localize_only_recovers_from_an_offset_start(rng: np.random.Generator) -> None:
    """Start 10 cm and 2 deg off with a matching covariance: within 2.5 cm after 5 s."""
    rig, odo, frames, poses, t, cmap = _drive(rng)
    start = poses[0] + np.array([0.07, -0.07, math.radians(2.0)])
    loc = LocalizeConfig(sigma_start_xy=0.1, sigma_start_theta=math.radians(3.0))
    be = MapLocalizer(rig.odometry, SlamConfig(), start, cmap, CeilingModel.from_camera(rig.camera),
                      loc)
    result = drive(be, iter_steps(odo, frames))
    pos, _ = _truth_errors(result, t, poses)
    late = result.times[result.times >= t[0] + 5.0]
    assert float(np.max(pos[-len(late):])) < 0.025


def test_start_parsing(tmp_path: Path) -> None:
    """--start X,Y,THETA and a localize result.json; bad ones are named."""
    typed = parse_start("1,2,0.5")
    assert np.allclose(typed.pose, [1, 2, 0.5])
    assert typed.cov is not None  # a typed start is looser than the known start's 1 mm
    assert np.allclose(np.sqrt(np.diag(typed.cov)), [0.02, 0.02, 0.01])
    with pytest.raises(InputError, match="X,Y,THETA"):
        parse_start("1,2")
    doc = {"status": "localized", "pose": [1.0, 2.0, 0.1],
           "covariance": (0.01 * np.eye(3)).tolist(), "trial": {"t": 3.5}}
    path = tmp_path / "result.json"
    path.write_text(json.dumps(doc))
    s = start_from_result(path)
    assert s.t == 3.5 and np.allclose(s.pose, [1, 2, 0.1]) and s.cov is not None
    path.write_text(json.dumps(doc | {"status": "ambiguous"}))
    with pytest.raises(DatasetError, match="ambiguous"):
        start_from_result(path)
    path.write_text(json.dumps({"status": "localized"}))
    with pytest.raises(DatasetError, match="'pose'"):
        start_from_result(path)


# --------------------------------------------------------------------------- CLI end to end
@pytest.fixture(scope="module")
def lab4(sim_run: SimRun) -> Path:
    """4 s of the simulated lab (61 images)."""
    return sim_run(seed=5, duration=4.0)


def test_cli_save_map_then_localize_only(lab4: Path, tmp_path: Path,
                                         capsys: pytest.CaptureFixture[str]) -> None:
    """batch --save-map, then --map --localize-only: RMS < 3 cm, the map's landmarks only;
    the same with merged maps and ``--map-mode smooth``."""
    mp = tmp_path / "map"
    assert main(["slam", str(lab4), "--backend", "batch", "--frames", "truth", "--out",
                 str(tmp_path / "slam"), "--save-map", str(mp)]) == 0
    cmap = read_map(mp)
    assert len(cmap.by_kind("lamp")) >= 1 and len(cmap.by_kind("corner")) >= 20
    # the pass-split test's figures are recorded, the covariances not inflated
    assert cmap.calibration is not None
    assert {k: v["inflated"] for k, v in cmap.calibration.items()} == {"lamp": 0, "corner": 0}
    assert main(["slam", str(lab4), "--frames", "truth", "--map", str(mp), "--localize-only",
                 "--out", str(tmp_path / "loc")]) == 0
    assert "none added" in capsys.readouterr().out
    s = json.loads((tmp_path / "loc" / "summary.json").read_text())
    assert s["backend"] == "localize" and s["error"]["position_rms_m"] < 0.03
    assert s["landmarks"] == len(cmap.landmarks)
    # the release test is on by default and, on the map of the same run, releases nothing
    lo = s["localize_only"]
    assert lo["release"] is True and lo["released_landmarks"] == []
    assert lo["unseen_lamps"] == [] and isinstance(lo["lamp_sightings_unmatched"], int)
    ids = np.loadtxt(tmp_path / "loc" / "landmarks.csv", delimiter=",", skiprows=1, usecols=0)
    assert sorted(ids.astype(int).tolist()) == sorted(lm.id for lm in cmap.landmarks)
    # the same map given twice merges into one (every landmark fused) and, with
    # --map-priors, tracks as well
    assert main(["slam", str(lab4), "--frames", "truth", "--map", str(mp), "--map", str(mp),
                 "--localize-only", "--map-priors", "--out", str(tmp_path / "loc2")]) == 0
    out = capsys.readouterr().out
    assert f"{len(cmap.landmarks)} landmarks fused, 0 in one map only" in out
    s2 = json.loads((tmp_path / "loc2" / "summary.json").read_text())
    assert s2["error"]["position_rms_m"] < 0.03 and s2["landmarks"] == len(cmap.landmarks)
    # --no-release turns the test off
    assert main(["slam", str(lab4), "--frames", "truth", "--map", str(mp), "--localize-only",
                 "--no-release", "--out", str(tmp_path / "loc4")]) == 0
    s4 = json.loads((tmp_path / "loc4" / "summary.json").read_text())
    assert s4["localize_only"]["release"] is False
    # --map-mode smooth: the smoothed poses, and the map frame's estimate in the summary
    assert main(["slam", str(lab4), "--frames", "truth", "--map", str(mp), "--localize-only",
                 "--map-mode", "smooth", "--out", str(tmp_path / "loc3")]) == 0
    s3 = json.loads((tmp_path / "loc3" / "summary.json").read_text())
    assert s3["backend"] == "localize-smooth" and s3["error"]["position_rms_m"] < 0.03
    assert cmap.frame is not None and abs(s3["map_frame_dtheta_rad"]) < 0.01


def test_cli_map_flags_and_bad_map(lab4: Path, tmp_path: Path,
                                   capsys: pytest.CaptureFixture[str]) -> None:
    """Exit 2 with the offending flag or file named."""
    out = str(tmp_path / "o")
    assert main(["slam", str(lab4), "--localize-only", "--out", out]) == 2
    assert "--map" in capsys.readouterr().err
    assert main(["slam", str(lab4), "--map", str(tmp_path), "--out", out]) == 2
    assert "--localize-only" in capsys.readouterr().err
    assert main(["slam", str(lab4), "--map-priors", "--out", out, "--force"]) == 2
    assert "--map-priors" in capsys.readouterr().err
    assert main(["slam", str(lab4), "--no-release", "--out", out, "--force"]) == 2
    assert "--release" in capsys.readouterr().err
    (tmp_path / "badmap").mkdir()
    (tmp_path / "badmap" / "map.yaml").write_text("format: lampsam-ceiling-map\n")
    assert main(["slam", str(lab4), "--map", str(tmp_path / "badmap"), "--localize-only",
                 "--out", out, "--force"]) == 2
    err = capsys.readouterr().err
    assert "map.yaml" in err and "missing key" in err and "Traceback" not in err


def test_binary_or_cut_short_map_files_are_named(tmp_path: Path, rng: np.random.Generator) -> None:
    """A binary map.yaml / landmarks.csv and an empty or cut-short patches.npz name their file
    (were UnicodeDecodeError, EOFError and BadZipFile: 'internal error')."""
    good = write_map(tmp_path / "good", _random_map(rng))
    binary = bytes(range(128, 256)) * 4

    def variant(name: str, f: str, data: bytes) -> Path:
        folder = tmp_path / name
        folder.mkdir()
        for g in ("map.yaml", "landmarks.csv", "patches.npz"):
            (folder / g).write_bytes((good / g).read_bytes())
        (folder / f).write_bytes(data)
        return folder

    _expect(variant("bin_yaml", "map.yaml", binary), "map.yaml", "UTF-8")
    _expect(variant("bin_csv", "landmarks.csv", binary), "landmarks.csv", "UTF-8")
    _expect(variant("empty_npz", "patches.npz", b""), "patches.npz", "not a readable .npz")
    cut = (good / "patches.npz").read_bytes()
    _expect(variant("cut_npz", "patches.npz", cut[: len(cut) // 2]), "patches.npz",
            "not a readable .npz")
