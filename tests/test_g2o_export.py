"""``lampsam slam --g2o``: the smoothers' whole graph as g2o, read back by ``gtsam.readG2o``.

Range-bearing log: GTSAM reads every odometry and range-bearing factor back, and the
graph it reads has the original graph's error at the final estimate. Ceiling run:
the custom projection lines rebuild factors with the original errors. The EKF path,
pickling and the CLI's error cases.
"""

from __future__ import annotations

import pickle
from pathlib import Path

import gtsam
import numpy as np
import pytest

from lampsam.backend.config import AssociationConfig, SlamConfig
from lampsam.backend.g2o_export import write_result_g2o
from lampsam.backend.graph_log import run_graph_log
from lampsam.backend.slam import run_slam
from lampsam.cli import main
from lampsam.datasets.graph_text import read_graph_text
from lampsam.datasets.landmark_log_sim import LandmarkLogSpec, write_landmark_log
from lampsam.factors.gtsam_factors import projection_factor
from tests.conftest import SimRun


@pytest.fixture(scope="module")
def rb_log(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """80 poses among 30 point landmarks in a 20 m square (about 2,000 sightings)."""
    out = tmp_path_factory.mktemp("g2o") / "log.txt"
    spec = LandmarkLogSpec(n_poses=80, n_landmarks=30, extent=20.0, stop_every=0)
    write_landmark_log(out, spec, np.random.default_rng(16))
    return out


@pytest.fixture(scope="module")
def ceiling_run(sim_run: SimRun) -> Path:
    """2 s of the lab world, seed 3."""
    return sim_run(seed=3, duration=2.0)


def _lines(path: Path, tag: str) -> list[list[str]]:
    return [ln.split("#")[0].split() for ln in path.read_text().splitlines()
            if ln.split(" ", 1)[0] == tag]


def information_root(noise: gtsam.noiseModel.Base) -> np.ndarray:
    """R of a Gaussian noise model, or of the one under a robust kernel."""
    return (noise.noise() if isinstance(noise, gtsam.noiseModel.Robust) else noise).R()


def _factor_error(graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, kind: type) -> float:
    return sum(graph.at(i).error(values) for i in range(graph.size())
               if isinstance(graph.at(i), kind))


@pytest.mark.parametrize("backend", ["isam2", "batch"])
def test_range_bearing_graph_round_trip(rb_log: Path, backend: str, tmp_path: Path) -> None:
    res = run_graph_log(read_graph_text(rb_log), backend,
                        SlamConfig(association=AssociationConfig(min_observations=1)))
    assert res.status == "ok" and res.graph is not None
    snap = res.graph
    path = tmp_path / "g.g2o"
    summary = write_result_g2o(path, res, None)
    n_between = sum(isinstance(snap.factors.at(i), gtsam.BetweenFactorPose2)
                    for i in range(snap.factors.size()))
    n_br = sum(isinstance(snap.factors.at(i), gtsam.BearingRangeFactor2D)
               for i in range(snap.factors.size()))
    assert n_br > 1000 and summary.omitted == {}
    assert summary.lines["EDGE_SE2"] == n_between and summary.lines["BR"] == n_br
    assert summary.lines["EDGE_SE2_XY"] == n_br and path.read_text().splitlines()[-1] == "FIX 0"

    graph, values = gtsam.readG2o(str(path), False)
    assert graph.size() == n_between + n_br
    assert values.size() == summary.poses + summary.landmarks == 80 + 30
    for k in range(80):  # pose X(k) is vertex k, at the final estimate (1e-9 m/rad printed)
        a, b = values.atPose2(k), snap.values.atPose2(gtsam.symbol("x", k))
        np.testing.assert_allclose([a.x(), a.y(), a.theta()], [b.x(), b.y(), b.theta()], atol=2e-9)
    # same factors, same information: the read graph's error at the written estimate is
    # the original odometry + range-bearing error at the final estimate
    orig = (_factor_error(snap.factors, snap.values, gtsam.BetweenFactorPose2)
            + _factor_error(snap.factors, snap.values, gtsam.BearingRangeFactor2D))
    assert graph.error(values) == pytest.approx(orig, rel=1e-6)

    # EDGE_SE2_XY (g2o's point edge, body frame of pose i): to first order the same cost
    poses = {int(r[1]): np.array(r[2:5], float) for r in _lines(path, "VERTEX_SE2")}
    points = {int(r[1]): np.array(r[2:4], float) for r in _lines(path, "VERTEX_XY")}
    cost = 0.0
    for r in _lines(path, "EDGE_SE2_XY"):
        x, y, th = poses[int(r[1])]
        c, s = np.cos(th), np.sin(th)
        local = np.array([[c, s], [-s, c]]) @ (points[int(r[2])] - [x, y])
        i11, i12, i22 = map(float, r[5:8])
        e = local - np.array(r[3:5], float)
        cost += 0.5 * e @ np.array([[i11, i12], [i12, i22]]) @ e
    assert cost == pytest.approx(_factor_error(snap.factors, snap.values,
                                               gtsam.BearingRangeFactor2D), rel=0.05)


def test_ceiling_graph_custom_lines(ceiling_run: Path, tmp_path: Path) -> None:
    res = run_slam(ceiling_run, "isam2", frames="truth")
    assert res.graph is not None
    snap = res.graph
    path = tmp_path / "c.g2o"
    summary = write_result_g2o(path, res, None)
    assert summary.omitted == {} and summary.lines["LAMPSAM_EDGE_PROJ"] > 100
    graph, values = gtsam.readG2o(str(path), False)  # the standard part: poses + odometry
    assert graph.size() == summary.lines["EDGE_SE2"] == summary.poses - 1
    assert values.size() == summary.poses + summary.lines["VERTEX_XY"]

    # every projection line rebuilds a factor with the original's error at the estimate
    key_of = {}
    for ln in path.read_text().splitlines():
        if "  # " in ln:
            key_of[int(ln.split()[1])] = gtsam.Symbol(ln.split("  # ")[1][0],
                                                      int(ln.split("  # ")[1][1:])).key()
    for k in range(summary.poses):
        key_of[k] = gtsam.symbol("x", k)
    offset = np.array(_lines(path, "LAMPSAM_CAMERA")[0][1:4], float)
    np.testing.assert_allclose(offset, snap.body_t_camera)
    rebuilt = gtsam.NonlinearFactorGraph()
    for r in _lines(path, "LAMPSAM_EDGE_PROJ"):
        i11, i12, i22 = map(float, r[5:8])
        cov = np.linalg.inv(np.array([[i11, i12], [i12, i22]]))
        rebuilt.add(projection_factor(key_of[int(r[1])], key_of[int(r[2])],
                                      np.array(r[3:5], float), cov, offset))
    orig = [snap.factors.at(i) for i in range(snap.factors.size())
            if isinstance(snap.factors.at(i), gtsam.PlanarProjectionFactor2)]
    assert rebuilt.size() == len(orig) == summary.lines["LAMPSAM_EDGE_PROJ"]
    # same residual (measurement recovered to the 1e-9 printed) and the same base
    # information (a Huber kernel, if any, is not part of the file)
    for n, f in enumerate(orig):
        g = rebuilt.at(n)
        np.testing.assert_allclose(g.unwhitenedError(snap.values), f.unwhitenedError(snap.values),
                                   atol=2e-9)
        np.testing.assert_allclose(g.noiseModel().R(), information_root(f.noiseModel()), rtol=1e-6)


def test_result_pickles_without_its_graph(rb_log: Path) -> None:
    res = run_graph_log(read_graph_text(rb_log), "isam2")
    assert res.graph is not None
    back = pickle.loads(pickle.dumps(res))
    assert back.graph is None
    np.testing.assert_array_equal(back.poses, res.poses)


def test_cli_g2o(rb_log: Path, ceiling_run: Path, tmp_path: Path,
                 capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "g.g2o"
    assert main(["slam", str(rb_log), "--out", str(tmp_path / "o"), "--g2o", str(out)]) == 0
    assert "g2o graph written" in capsys.readouterr().out and out.read_text().endswith("FIX 0\n")
    # an existing file is refused before any computing; the EKF on a text log has no graph
    assert main(["slam", str(rb_log), "--out", str(tmp_path / "o2"), "--g2o", str(out)]) != 0
    assert "--g2o" in capsys.readouterr().err
    assert main(["slam", str(rb_log), "--backend", "ekf", "--out", str(tmp_path / "o3"),
                 "--g2o", str(tmp_path / "e.g2o")]) != 0
    assert "needs a run directory" in capsys.readouterr().err
    # the EKF on a run: keyframe poses, odometry edges, landmark vertices
    ekf = tmp_path / "ekf.g2o"
    assert main(["slam", str(ceiling_run), "--backend", "ekf", "--out", str(tmp_path / "o4"),
                 "--g2o", str(ekf)]) == 0
    graph, values = gtsam.readG2o(str(ekf), False)
    n_pose = len(_lines(ekf, "VERTEX_SE2"))
    assert n_pose > 2 and graph.size() == n_pose - 1
