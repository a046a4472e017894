"""Loop closures and backwards chains of graph text logs (issue #15; backend/pose_graph.py).

A seeded pose graph (a 10 m x 6 m loop driven twice, closures from the second lap to the
first) is written as g2o / iSAM text; lampsam reads it, and its batch and iSAM2 are held
against the truth, against dead reckoning and against GTSAM's LM on GTSAM's own reading
of the same file.
"""

from __future__ import annotations

import json
import logging
import math
from pathlib import Path

import gtsam
import numpy as np
import pytest

from lampsam.backend.config import SlamConfig
from lampsam.backend.config_graph import PoseGraphConfig
from lampsam.backend.graph_log import run_graph_log
from lampsam.datasets.graph_text import GraphLog, invert_edge, read_graph_text
from lampsam.factors.geometry import wrap_angle

ODO_COV = np.diag([0.03 ** 2, 0.03 ** 2, 0.015 ** 2])
LOOP_COV = np.diag([0.02 ** 2, 0.02 ** 2, 0.01 ** 2])
#: m RMS between lampsam's batch and GTSAM's LM on the same graph: both stop on a relative
#: error decrease, lampsam's at [batch] relative_error_tol 1e-4, GTSAM's default at 1e-5
#: (the same minimum: graph chi-square equal to 1e-7 relative on the backwards chain)
LM_TOL = 1e-3


def _chain_poses(g: GraphLog, start: np.ndarray) -> np.ndarray:
    """(N, 3) the chain's dead reckoning from ``start``: each pose the previous one
    composed with its odometry sample (theta wrapped)."""
    poses = np.zeros((len(g.pose_ids), 3))
    cur = gtsam.Pose2(*np.asarray(start, float))
    for k, d in enumerate(g.odometry.delta):
        if k:
            cur = cur.compose(gtsam.Pose2(*d))
        poses[k] = [cur.x(), cur.y(), cur.theta()]
    return poses


def _closure_chi2(g: GraphLog, poses: np.ndarray) -> np.ndarray:
    """(C,) each closure's squared Mahalanobis residual at the (N, 3) poses:
    ``e^T cov^-1 e`` with ``e = Log(i_T_j^-1 (x_i^-1 x_j))`` (GTSAM's between error)."""
    out = np.zeros(len(g.closures))
    for c, e in enumerate(g.closures):
        xi, xj = gtsam.Pose2(*poses[e.i]), gtsam.Pose2(*poses[e.j])
        r = gtsam.Pose2.Logmap(gtsam.Pose2(*e.delta).between(xi.between(xj)))
        r[2] = wrap_angle(r[2])
        out[c] = float(r @ np.linalg.solve(e.cov, r))
    return out


def _p(a: np.ndarray) -> gtsam.Pose2:
    return gtsam.Pose2(float(a[0]), float(a[1]), float(a[2]))


def _arr(p: gtsam.Pose2) -> np.ndarray:
    return np.array([p.x(), p.y(), p.theta()])


def _noisy(rel: gtsam.Pose2, cov: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """``rel exp(xi)``, ``xi ~ N(0, cov)`` (GTSAM's right perturbation)."""
    return _arr(rel.compose(gtsam.Pose2.Expmap(rng.multivariate_normal(np.zeros(3), cov))))


def loop_truth(laps: int = 2) -> np.ndarray:
    """(N, 3) poses around a 10 m x 6 m rectangle, 1 m steps, turning at the corners."""
    out = []
    for _ in range(laps):
        for side, n in ((0, 10), (1, 6), (2, 10), (3, 6)):
            th = side * math.pi / 2
            for k in range(n):
                corner = [(0, 0), (10, 0), (10, 6), (0, 6)][side]
                out.append([corner[0] + k * math.cos(th), corner[1] + k * math.sin(th), th])
    return np.array(out)


def _info_text(cov: np.ndarray) -> str:
    i = np.linalg.inv(cov)
    return " ".join(f"{v:.10g}" for v in (i[0, 0], i[0, 1], i[0, 2], i[1, 1], i[1, 2], i[2, 2]))


def write_loop_g2o(path: Path, rng: np.random.Generator, wrong: int = 0
                   ) -> tuple[np.ndarray, list[tuple[int, int]]]:
    """A g2o pose graph of :func:`loop_truth`: the chain, a closure from each pose of the
    second lap to the same place on the first, and ``wrong`` closures between random
    poses that claim they are at the same place (outliers). Returns the truth and the
    closures' pose pairs."""
    x = loop_truth()
    n = len(x)
    lap = n // 2
    lines = [f"VERTEX_SE2 0 {x[0, 0]} {x[0, 1]} {x[0, 2]}"]
    for k in range(1, n):
        d = _noisy(_p(x[k - 1]).between(_p(x[k])), ODO_COV, rng)
        lines.append(f"EDGE_SE2 {k - 1} {k} {d[0]:.10g} {d[1]:.10g} {d[2]:.10g} {_info_text(ODO_COV)}")
    pairs = [(k - lap, k) for k in range(lap, n, 2)]
    for i, j in pairs:
        d = _noisy(_p(x[i]).between(_p(x[j])), LOOP_COV, rng)
        lines.append(f"EDGE_SE2 {i} {j} {d[0]:.10g} {d[1]:.10g} {d[2]:.10g} {_info_text(LOOP_COV)}")
    for _ in range(wrong):
        i, j = sorted(int(v) for v in rng.choice(n, 2, replace=False))
        lines.append(f"EDGE_SE2 {i} {j} 0 0 0 {_info_text(LOOP_COV)}")
    path.write_text("\n".join(lines) + "\n")
    return x, pairs


def gtsam_lm(path: Path, start: np.ndarray, ids: list[int]) -> np.ndarray:
    """GTSAM's LM on its own reading of the file, with lampsam's prior on the first pose,
    from the file's vertices if it has them all, else from GTSAM's LAGO (``load2D``'s own
    guess of the poses a file leaves out is not a start: on a backwards chain LM stops
    metres away from it)."""
    graph, initial = (gtsam.readG2o(str(path), False) if path.suffix == ".g2o"
                      else gtsam.load2D(str(path)))
    c = SlamConfig().isam2
    graph.add(gtsam.PriorFactorPose2(ids[0], _p(start), gtsam.noiseModel.Diagonal.Sigmas(
        np.array([c.sigma_start_xy, c.sigma_start_xy, c.sigma_start_theta]))))
    verts = read_graph_text(path).vertices
    init = initial if all(i in verts for i in ids) else gtsam.lago.initialize(graph)
    for key in initial.keys():
        if not init.exists(key):  # landmarks: load2D's first-sighting guess
            init.insert(key, initial.atPoint2(key))
    est = gtsam.LevenbergMarquardtOptimizer(graph, init, gtsam.LevenbergMarquardtParams()).optimize()
    return np.array([_arr(est.atPose2(i)) for i in ids])


def rms_xy(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.sum((a[:, :2] - b[:, :2]) ** 2, axis=1))))


def test_invert_edge_jacobian_and_monte_carlo() -> None:
    """The inverse's covariance ``Ad cov Ad^T`` against the numerical Jacobian of the
    inverse (right perturbations) and against 20,000 sampled inverses."""
    rng = np.random.default_rng(7)
    delta = np.array([1.3, -0.4, 0.9])
    a = rng.normal(size=(3, 3)) * 0.1
    cov = a @ a.T + 1e-3 * np.eye(3)
    inv, inv_cov = invert_edge(delta, cov)
    t = _p(delta)
    assert np.allclose(_arr(t.inverse()), inv, atol=1e-12)
    h = 1e-6
    jac = np.zeros((3, 3))
    for c in range(3):
        e = np.zeros(3)
        e[c] = h
        plus = t.compose(gtsam.Pose2.Expmap(e)).inverse()
        minus = t.compose(gtsam.Pose2.Expmap(-e)).inverse()
        jac[:, c] = (gtsam.Pose2.Logmap(t.inverse().between(plus))
                     - gtsam.Pose2.Logmap(t.inverse().between(minus))) / (2 * h)
    assert np.allclose(jac @ cov @ jac.T, inv_cov, atol=1e-8)
    xs = rng.multivariate_normal(np.zeros(3), cov, size=20000)
    errs = np.array([gtsam.Pose2.Logmap(t.inverse().between(t.compose(gtsam.Pose2.Expmap(x)).inverse()))
                     for x in xs])
    mc = np.cov(errs.T)
    # sampling error of a covariance entry ~ sqrt(2/N) of its scale: 1 % at N = 20,000
    assert np.allclose(mc, inv_cov, atol=0.05 * np.abs(inv_cov).max())


def test_inverted_edge_factor_has_the_same_error() -> None:
    """``BetweenFactorPose2(1, 0, T, cov)`` and ``(0, 1, T^-1, Ad cov Ad^T)`` give the same
    error at random pose pairs (exact, not first order)."""
    rng = np.random.default_rng(3)
    delta = np.array([-0.99879, 0.0417574, -0.00818381])
    cov = np.diag([0.1, 0.2, 0.05])
    inv, inv_cov = invert_edge(delta, cov)
    f10 = gtsam.BetweenFactorPose2(1, 0, _p(delta), gtsam.noiseModel.Gaussian.Covariance(cov))
    f01 = gtsam.BetweenFactorPose2(0, 1, _p(inv), gtsam.noiseModel.Gaussian.Covariance(inv_cov))
    for _ in range(20):
        v = gtsam.Values()
        v.insert(0, _p(rng.normal(size=3)))
        v.insert(1, _p(rng.normal(size=3)))
        assert f10.error(v) == pytest.approx(f01.error(v), rel=1e-9, abs=1e-12)


def test_backwards_chain_reads_like_the_forward_one(tmp_path: Path) -> None:
    """``EDGE2 k k-1`` (GTSAM's w100.graph layout) is read as the chain, each edge inverted;
    batch on it matches GTSAM's LM on GTSAM's reading of the backwards file."""
    rng = np.random.default_rng(11)
    x = loop_truth(1)
    fwd, bwd = [], []
    cov_text = "0.01 0 0 0.01 0 0.0025"  # c11 c12 c13 c22 c23 c33 (upper triangle)
    for k in range(1, len(x)):
        d = _noisy(_p(x[k - 1]).between(_p(x[k])), np.diag([0.01, 0.01, 0.0025]), rng)
        b = _arr(_p(d).inverse())
        fwd.append(f"EDGE2 {k - 1} {k} {d[0]:.12g} {d[1]:.12g} {d[2]:.12g} {cov_text}")
        bwd.append(f"EDGE2 {k} {k - 1} {b[0]:.12g} {b[1]:.12g} {b[2]:.12g} {cov_text}")
    c = _arr(_p(x[-1]).between(_p(x[0])))  # a closure from the last pose to the first
    bwd.append(f"EDGE2 {len(x) - 1} 0 {c[0]:.12g} {c[1]:.12g} {c[2]:.12g} {cov_text}")
    (tmp_path / "f.txt").write_text("\n".join(fwd) + "\n")
    (tmp_path / "b.txt").write_text("\n".join(bwd) + "\n")
    gf, gb = read_graph_text(tmp_path / "f.txt"), read_graph_text(tmp_path / "b.txt")
    assert gb.pose_ids == gf.pose_ids and gb.n_reversed == len(x) - 1 and len(gb.closures) == 1
    assert np.allclose(gb.odometry.delta, gf.odometry.delta, atol=1e-9)
    # the inverse of the inverse's covariance is not the file's (each edge has the same
    # stated covariance in both files, so they differ by Ad): check one by its formula
    assert np.allclose(gb.odometry.cov[1], invert_edge(_arr(_p(gf.odometry.delta[1]).inverse()),
                                                       np.diag([0.01, 0.01, 0.0025]))[1])
    res = run_graph_log(gb, "batch", SlamConfig())
    ref = gtsam_lm(tmp_path / "b.txt", gb.start_pose(), gb.pose_ids)
    assert res.status == "ok" and rms_xy(res.poses, ref) < LM_TOL


@pytest.mark.parametrize("backend", ["batch", "isam2"])
def test_loop_closures_reduce_the_error_and_match_gtsam(tmp_path: Path, backend: str) -> None:
    """On the seeded two-lap loop: dead reckoning drifts; with the closures the error
    against the truth drops by more than half, and the result is GTSAM's LM on the same
    file (batch to LM_TOL; iSAM2, which relinearises lazily, to 1 cm)."""
    path = tmp_path / "loop.g2o"
    truth, pairs = write_loop_g2o(path, np.random.default_rng(5))
    g = read_graph_text(path)
    assert len(g.closures) == len(pairs) == 16 and g.n_reversed == 0
    dead = _chain_poses(g, g.start_pose())
    res = run_graph_log(g, backend, SlamConfig())
    assert res.status == "ok" and res.extra["loop_closures_used"] == len(pairs)
    err_dead, err = rms_xy(dead, truth), rms_xy(res.poses, truth)
    assert err_dead > 0.3 and err < 0.5 * err_dead, (err_dead, err)
    ref = gtsam_lm(path, g.start_pose(), g.pose_ids)
    assert rms_xy(res.poses, ref) < (LM_TOL if backend == "batch" else 1e-2)


@pytest.mark.parametrize("init", ["lago", "chain", "backend"])
def test_batch_starts_reach_the_same_minimum(tmp_path: Path, init: str) -> None:
    """Each ``[graph] batch_init`` reaches GTSAM's LM minimum on the seeded loop (LM_TOL)."""
    import dataclasses

    path = tmp_path / "loop.g2o"
    write_loop_g2o(path, np.random.default_rng(5))
    g = read_graph_text(path)
    cfg = dataclasses.replace(SlamConfig(), graph=PoseGraphConfig(batch_init=init))
    res = run_graph_log(g, "batch", cfg)
    assert rms_xy(res.poses, gtsam_lm(path, g.start_pose(), g.pose_ids)) < LM_TOL


def test_landmarks_and_closures_in_one_file(tmp_path: Path) -> None:
    """An iSAM file with odometry, BR sightings and loop closures: batch uses both and
    matches GTSAM's LM on ``load2D`` of it; the landmarks land within 0.2 m of the truth."""
    rng = np.random.default_rng(21)
    x = loop_truth()
    n, lap = len(x), len(x) // 2
    lms = {7: np.array([5.0, 3.0]), 8: np.array([2.0, 2.0]), 9: np.array([8.0, 4.0])}
    odo_txt = "0.0009 0 0 0.0009 0 0.000225"
    lines = []
    for k in range(1, n):
        d = _noisy(_p(x[k - 1]).between(_p(x[k])), ODO_COV, rng)
        lines.append(f"EDGE2 {k - 1} {k} {d[0]:.10g} {d[1]:.10g} {d[2]:.10g} {odo_txt}")
    for k in range(0, n, 3):
        for lid, p in lms.items():
            rel = _p(x[k]).transformTo(p)
            b = math.atan2(rel[1], rel[0]) + rng.normal(0, 0.01)
            r = float(np.hypot(*rel)) + rng.normal(0, 0.05)
            lines.append(f"BR {k} {lid} {b:.10g} {r:.10g} 0.01 0.05")
    for i in range(0, lap, 4):
        d = _noisy(_p(x[i]).between(_p(x[i + lap])), LOOP_COV, rng)
        lines.append(f"EDGE2 {i} {i + lap} {d[0]:.10g} {d[1]:.10g} {d[2]:.10g} 0.0004 0 0 0.0004 0 0.0001")
    path = tmp_path / "both.txt"
    path.write_text("\n".join(lines) + "\n")
    g = read_graph_text(path)
    assert g.n_landmarks == 3 and len(g.closures) == 8
    res = run_graph_log(g, "batch", SlamConfig())
    assert res.status == "ok" and res.extra["loop_closures_used"] == 8
    assert rms_xy(res.poses, gtsam_lm(path, g.start_pose(), g.pose_ids)) < LM_TOL
    for lm in res.landmarks:
        assert np.linalg.norm(np.asarray(lm.position)[:2] - lms[lm.id]) < 0.2
    res2 = run_graph_log(g, "isam2", SlamConfig())
    assert res2.extra["loop_closures_used"] == 8 and rms_xy(res2.poses, res.poses) < 0.02


def test_ekf_warns_and_leaves_the_closures_out(tmp_path: Path, caplog: pytest.LogCaptureFixture
                                              ) -> None:
    """The EKF (current pose only) cannot close a loop: it runs on the odometry, says so in
    the log, the printed line and summary.json; iSAM2 on the same file uses every closure."""
    from lampsam.cli import main

    path = tmp_path / "loop.g2o"
    write_loop_g2o(path, np.random.default_rng(5))
    with caplog.at_level(logging.WARNING):
        assert main(["slam", str(path), "--backend", "ekf", "--out", str(tmp_path / "e")]) == 0
    assert "loop closures are not used" in caplog.text and "EKF" in caplog.text
    s = json.loads((tmp_path / "e" / "summary.json").read_text())["input"]
    assert s["loop_closures"] == 16 and s["loop_closures_used"] == 0
    assert "EKF" in s["closures_warning"]
    assert main(["slam", str(path), "--backend", "isam2", "--out", str(tmp_path / "i")]) == 0
    s = json.loads((tmp_path / "i" / "summary.json").read_text())["input"]
    assert s["loop_closures_used"] == 16 and "closures_warning" not in s and "warning" not in s


def test_closure_chi2_is_the_factor_error(tmp_path: Path) -> None:
    """The closures' chi-square (_closure_chi2) equals twice the closures' BetweenFactorPose2 error at the same poses."""
    path = tmp_path / "loop.g2o"
    write_loop_g2o(path, np.random.default_rng(5))
    g = read_graph_text(path)
    poses = _chain_poses(g, g.start_pose())
    total = 0.0
    for e in g.closures:
        f = gtsam.BetweenFactorPose2(e.i, e.j, _p(e.delta), gtsam.noiseModel.Gaussian.Covariance(e.cov))
        v = gtsam.Values()
        v.insert(e.i, _p(poses[e.i]))
        v.insert(e.j, _p(poses[e.j]))
        total += 2 * f.error(v)
    assert float(_closure_chi2(g, poses).sum()) == pytest.approx(total, rel=1e-9)


def test_cauchy_kernel_resists_wrong_closures(tmp_path: Path) -> None:
    """Four wrong closures (random pose pairs claimed at one place) pull the Gaussian batch
    metres off; ``[graph] closure_kernel = "cauchy"`` from the chain stays within 0.1 m of
    the clean graph's solution."""
    import dataclasses

    clean, bad = tmp_path / "clean.g2o", tmp_path / "bad.g2o"
    write_loop_g2o(clean, np.random.default_rng(5))
    truth, _ = write_loop_g2o(bad, np.random.default_rng(5), wrong=4)
    ref = run_graph_log(read_graph_text(clean), "batch", SlamConfig()).poses
    g = read_graph_text(bad)
    plain = run_graph_log(g, "batch", SlamConfig()).poses
    robust_cfg = dataclasses.replace(SlamConfig(), graph=PoseGraphConfig(
        batch_init="chain", closure_kernel="cauchy", closure_kernel_k=1.0))
    robust = run_graph_log(g, "batch", robust_cfg).poses
    assert rms_xy(plain, ref) > 1.0
    assert rms_xy(robust, ref) < 0.1, (rms_xy(robust, ref), rms_xy(plain, ref))


def test_graph_table_is_read_and_bad_values_are_named() -> None:
    """``[graph]`` in a config file: read, and a bad value names its dotted key."""
    from lampsam.config_loader import ConfigError

    cfg = SlamConfig.from_dict({"graph": {"batch_init": "lago", "closure_kernel": "huber"}})
    assert cfg.graph == PoseGraphConfig(batch_init="lago", closure_kernel="huber")
    with pytest.raises(ConfigError, match=r"graph\.batch_init.*'lago', 'chain' or 'backend'"):
        SlamConfig.from_dict({"graph": {"batch_init": "odometry"}})
    with pytest.raises(ConfigError, match=r"graph\.closure_kernel_k"):
        SlamConfig.from_dict({"graph": {"closure_kernel_k": -1.0}})
