"""iSAM / g2o text logs: reader, errors naming file and line, one step per pose, CLI."""

from __future__ import annotations

import json
import math
from pathlib import Path

import gtsam
import numpy as np
import pytest

from lampsam.backend.config import AssociationConfig, SlamConfig
from lampsam.backend.graph_log import graph_log_steps, run_graph_log
from lampsam.cli import main
from lampsam.datasets.graph_text import read_graph_text
from lampsam.errors import DatasetError

ISAM = """ODOMETRY 0 1 1.0 0.0 0.1 0.0001 0 0 4e-06 0 4e-06
LANDMARK 1 7 3.0 1.0 0.4 0 0.4
ODOMETRY 1 2 1.0 0.0 0.1 0.0001 0 0 4e-06 0 4e-06
BR 2 7 0.1 2.5 0.05 0.2
ODOMETRY 2 3 0.0 0.0 0.0 0.0001 0 0 4e-06 0 4e-06
"""


def test_isam_reader_builds_the_same_factors_as_gtsam(tmp_path: Path) -> None:
    """Odometry covariances and LANDMARK noise as ``gtsam.load2D`` builds them."""
    p = tmp_path / "log.txt"
    p.write_text(ISAM)
    g = read_graph_text(p)
    assert g.pose_ids == [0, 1, 2, 3] and g.n_landmarks == 1
    graph, _ = gtsam.load2D(str(p))
    f = graph.at(0)
    np.testing.assert_allclose(np.diag(g.odometry.cov[1]), np.array([0.01, 0.002, 0.002]) ** 2)
    np.testing.assert_allclose(f.noiseModel().sigmas(), [0.01, 0.002, 0.002])
    s = g.sightings[1][0]
    br = graph.at(1)
    assert br.measured().bearing().theta() == pytest.approx(s.bearing, abs=1e-12)
    assert br.measured().range() == pytest.approx(s.range, abs=1e-12)
    np.testing.assert_allclose(np.sqrt(np.diag(s.cov)), br.noiseModel().sigmas(), atol=1e-12)
    steps = list(graph_log_steps(g))
    assert len(steps) == 4  # one per pose
    assert steps[2][2] is not None and steps[2][2].observations[0].cov is not None


def test_g2o_reader_uses_information_and_vertices(tmp_path: Path) -> None:
    p = tmp_path / "log.g2o"
    p.write_text("VERTEX_SE2 0 1.0 2.0 0.5\nEDGE_SE2 0 1 1.0 0.0 0.0 100 0 0 100 0 400\n"
                 "EDGE_SE2_XY 1 9 2.0 0.0 100 0 100\n")
    g = read_graph_text(p)
    np.testing.assert_allclose(g.odometry.cov[1], np.diag([0.01, 0.01, 0.0025]))
    np.testing.assert_allclose(g.start_pose(), [1.0, 2.0, 0.5])
    s = g.sightings[1][0]
    assert s.range == pytest.approx(2.0) and s.bearing == pytest.approx(0.0)
    # range sigma 0.1 m; bearing sigma 0.1 m / 2 m
    np.testing.assert_allclose(s.cov, np.diag([(0.1 / 2) ** 2, 0.01]), atol=1e-12)


@pytest.mark.parametrize(("text", "match"), [
    ("ODOMETRY 0 1 1.0 0.0\n", r"log.txt:1: ODOMETRY needs 11 fields, got 4"),
    ("ODOMETRY 0 1 1.0 0.0 x 1 0 0 1 0 1\n", r"log.txt:1: ODOMETRY: not a number"),
    ("ODOMETRY 0 1 1 0 0 1 0 0 1 0 1\nFOO 1 2\n", r"log.txt:2: unknown record 'FOO'"),
    ("ODOMETRY 0 1 1 0 0 1 0 0 -1 0 1\n", r"log.txt:1: .*not positive definite"),
    ("ODOMETRY 0 1 1 0 0 1 0 0 1 0 1\nODOMETRY 5 6 1 0 0 1 0 0 1 0 1\n",
     r"log.txt:2: ODOMETRY 5 6: pose 5 is not on the odometry chain \(0 ... 1, 2 poses\)"),
    ("ODOMETRY 0 1 1 0 0 1 0 0 1 0 1\nBR 9 3 0.1 2.0 0.1 0.1\n",
     r"log.txt:2: sighting from pose 9, which no odometry reaches"),
    ("LANDMARK 0 3 1 1 0.4 0 0.4\n", r"log.txt: no odometry records"),
])
def test_reader_errors_name_file_and_line(tmp_path: Path, text: str, match: str) -> None:
    p = tmp_path / "log.txt"
    p.write_text(text)
    with pytest.raises(DatasetError, match=match):
        read_graph_text(p)


def _synthetic_log(path: Path, rng: np.random.Generator, n: int = 120) -> np.ndarray:
    """A loop around 12 landmarks; BR sightings within 6 m; returns true poses (n, 3)."""
    marks = np.array([[5 * math.cos(a), 5 * math.sin(a)] for a in np.linspace(0, 2 * np.pi, 12,
                                                                                endpoint=False)])
    poses = [np.array([3.0, 0.0, np.pi / 2])]
    lines = []
    d = np.array([2 * np.pi * 3.0 / n, 0.0, 2 * np.pi / n])
    c = np.diag([0.01**2, 0.005**2, 0.002**2])
    for k in range(1, n):
        true = gtsam.Pose2(*poses[-1]).compose(gtsam.Pose2(*d))
        poses.append(np.array([true.x(), true.y(), true.theta()]))
        meas = d + rng.multivariate_normal(np.zeros(3), c)
        lines.append(f"ODOMETRY {k - 1} {k} {meas[0]} {meas[1]} {meas[2]} "
                     f"{c[0, 0]} 0 0 {c[1, 1]} 0 {c[2, 2]}")
        p = gtsam.Pose2(*poses[-1])
        for j, m in enumerate(marks):
            loc = p.transformTo(m)
            r, b = float(np.hypot(*loc)), float(np.arctan2(loc[1], loc[0]))
            if r < 6.0:
                lines.append(f"BR {k} {1000 + j} {b + rng.normal(0, 0.01)} {r + rng.normal(0, 0.05)}"
                             " 0.01 0.05")
    path.write_text("VERTEX_SE2 0 3.0 0.0 1.5707963267948966\n" + "\n".join(lines) + "\n")
    truth = path.with_name("truth.g2o")
    truth.write_text("".join(f"VERTEX_SE2 {k} {p[0]} {p[1]} {p[2]}\n" for k, p in enumerate(poses)))
    return np.array(poses)


@pytest.mark.parametrize("name", ["ekf", "isam2", "batch"])
def test_every_backend_tracks_a_synthetic_text_log(name: str, tmp_path: Path) -> None:
    """Known ids: each backend within 0.15 m RMS of truth, all 12 landmarks mapped."""
    truth = _synthetic_log(tmp_path / "log.txt", np.random.default_rng(4))
    g = read_graph_text(tmp_path / "log.txt")
    cfg = SlamConfig(association=AssociationConfig(min_observations=1))
    res = run_graph_log(g, name, cfg)
    assert res.status == "ok" and len(res.times) == len(truth)
    err = np.linalg.norm(res.poses[:, :2] - truth[:, :2], axis=1)
    assert float(np.sqrt(np.mean(err**2))) < 0.15
    assert len(res.landmarks) == 12


def test_cli_slam_on_a_text_log(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    _synthetic_log(tmp_path / "log.txt", np.random.default_rng(4))
    out = tmp_path / "out"
    rc = main(["slam", str(tmp_path / "log.txt"), "--backend", "isam2", "--out", str(out),
               "--truth", str(tmp_path / "truth.g2o")])
    assert rc == 0
    s = json.loads((out / "summary.json").read_text())
    assert s["steps"] == 120 and s["input"]["start_pose"] == "the first pose's VERTEX"
    assert s["error"]["position_rms_m"] < 0.15
    assert (out / "trajectory.tum").exists() and "one per pose" in capsys.readouterr().out


@pytest.mark.parametrize("name", ["ekf", "isam2"])
def test_landmark_seen_once_stays_in_the_written_map_flagged(
        name: str, tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    p = tmp_path / "log.txt"
    p.write_text(ISAM + "BR 3 8 -0.5 4.0 0.05 0.2\n")
    out = tmp_path / "out"
    assert main(["slam", str(p), "--backend", name, "--out", str(out)]) == 0
    # the warning agrees with the written map: the landmark is kept, flagged
    assert "1 seen fewer than 2 times (written apart to landmarks.csv, flagged seen_once)" in caplog.text
    rows = (out / "landmarks.csv").read_text().splitlines()
    assert rows[0].endswith(",flag")
    flags = {r.split(",")[0]: r.split(",")[-1] for r in rows[1:]}
    assert flags == {"7": "", "8": "seen_once"}
    g = read_graph_text(p)
    cfg = SlamConfig(association=AssociationConfig(prune_once_seen=True))
    caplog.clear()
    res = run_graph_log(g, name, cfg)
    assert [lm.id for lm in res.landmarks] == [7] and res.provisional == []
    assert "1 seen fewer than 2 times" in caplog.text and "written apart" not in caplog.text


@pytest.mark.parametrize("confirm", [1, 3])
def test_no_ids_tentative_landmarks_confirmed_after_k_sightings(confirm: int, tmp_path: Path) -> None:
    """Without ids (smoothers' relative planar gate): the 12 trees are mapped once each and the
    path stays within 0.15 m RMS of truth; a clutter sighting seen once (8 m outside the
    ring) is mapped (flagged seen-once) when landmarks enter at their first sight, and
    is forgotten with ``planar_confirm_sightings = 3``."""
    truth = _synthetic_log(tmp_path / "log.txt", np.random.default_rng(4))
    with (tmp_path / "log.txt").open("a") as f:
        f.write("BR 40 2000 0.0 8.0 0.01 0.05\n")
    g = read_graph_text(tmp_path / "log.txt")
    cfg = SlamConfig(association=AssociationConfig(planar_confirm_sightings=confirm,
                                                   planar_reject_ambiguous=True,
                                                   planar_relative_gate=True))
    res = run_graph_log(g, "isam2", cfg, known_ids=False)
    assert res.status == "ok"
    err = np.linalg.norm(res.poses[:, :2] - truth[:, :2], axis=1)
    assert float(np.sqrt(np.mean(err**2))) < 0.15
    assert len(res.landmarks) == 12
    assert len(res.provisional) == (1 if confirm == 1 else 0)
