"""The per-step path on dense range-bearing logs (issue 15): the shortcuts give the plain way's numbers.

- the keyframe marginal computed on first read equals the one computed right
  after the update, and skipping the pose covariances changes no estimate;
- the single-sample Pose2 odometry path equals :func:`accumulate_pose2`;
- the 2x2 covariance check decides as an eigenvalue test does;
- the range-bearing handler shares one validated noise model per covariance.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
from gtsam.symbol_shorthand import X

from lampsam.backend.config import SlamConfig
from lampsam.backend.graph import Isam2Slam
from lampsam.backend.graph_log import graph_log_steps, run_graph_log
from lampsam.backend.handlers import GraphLandmark, Point2Handler
from lampsam.backend.interface import LandmarkKind
from lampsam.backend.models import Obs
from lampsam.backend.odometry import Pose2Motion
from lampsam.backend.pose_cov import tangent_to_coords_cov
from lampsam.backend.slam import drive
from lampsam.datasets.graph_text import read_graph_text
from lampsam.datasets.landmark_log_sim import LandmarkLogSpec, write_landmark_log
from lampsam.datasets.odometry import Pose2OdometryModel
from lampsam.factors.geometry import FactorError
from lampsam.factors.gtsam_factors import check_cov
from lampsam.factors.pose2_odometry import accumulate_pose2

SPEC = LandmarkLogSpec(n_poses=150, n_landmarks=40, extent=40.0, stop_every=60, stop_length=10)


@pytest.fixture(scope="module")
def small_log(tmp_path_factory: pytest.TempPathFactory):  # type: ignore[no-untyped-def]
    path, _ = write_landmark_log(tmp_path_factory.mktemp("dense") / "log.txt", SPEC,
                                 np.random.default_rng(3))
    return read_graph_text(Path(path))


class _EagerMarginal(Isam2Slam):
    """Records each keyframe's marginal right after its update (the plain way)."""

    def _flush(self) -> None:
        super()._flush()
        if not hasattr(self, "eager"):
            self.eager: dict[int, np.ndarray] = {}
        assert self.isam is not None
        self.eager[self._k] = np.asarray(self.isam.marginalCovariance(X(self._k)))


def test_lazy_keyframe_marginal_equals_the_eager_one(small_log) -> None:  # type: ignore[no-untyped-def]
    cfg = SlamConfig()
    cfg = dataclasses.replace(cfg, isam2=dataclasses.replace(cfg.isam2, every_frame=True))
    be = _EagerMarginal(cfg.pose2_odometry, cfg, small_log.start_pose())
    steps = []
    for t, u, frame in graph_log_steps(small_log):
        steps.append(be.step(t, u, frame))
    n_checked = 0
    for i, est in enumerate(steps):
        if est.keyframe:  # the step's covariance is its keyframe's marginal, read lazily
            ref = tangent_to_coords_cov(est.pose, be.eager[be._step_kf[i]])
            np.testing.assert_allclose(est.cov, ref, rtol=0, atol=1e-15 * np.abs(ref).max())
            n_checked += 1
    assert n_checked > 100


def test_no_pose_covariances_changes_no_estimate(small_log) -> None:  # type: ignore[no-untyped-def]
    with_cov = run_graph_log(small_log, "isam2", pose_covariances=True)
    without = run_graph_log(small_log, "isam2")
    assert with_cov.status == without.status == "ok"
    assert np.all(np.isfinite(with_cov.pose_covs)) and np.all(np.isnan(without.pose_covs))
    np.testing.assert_array_equal(with_cov.poses, without.poses)
    a = {lm.id: (lm.position, lm.cov) for lm in with_cov.landmarks}
    b = {lm.id: (lm.position, lm.cov) for lm in without.landmarks}
    assert a.keys() == b.keys() and len(a) > 20
    for lid, (p, c) in a.items():  # landmark covariances are computed either way
        np.testing.assert_array_equal(p, b[lid][0])
        np.testing.assert_array_equal(c, b[lid][1])
    # the gate without ids still reads its marginals: same estimate with and without
    od = small_log.odometry
    head = dataclasses.replace(small_log, pose_ids=small_log.pose_ids[:40],
                               sightings=small_log.sightings[:40],
                               odometry=type(od)(od.t[:40], od.delta[:40], od.cov[:40]))
    g1 = run_graph_log(head, "isam2", known_ids=False, pose_covariances=True)
    g2 = run_graph_log(head, "isam2", known_ids=False)
    assert g1.status == g2.status == "ok" and len(g1.landmarks) > 5
    np.testing.assert_array_equal(g1.poses, g2.poses)


def test_final_marginals_without_step_covariances(small_log) -> None:  # type: ignore[no-untyped-def]
    cfg = SlamConfig()
    cfg = dataclasses.replace(cfg, isam2=dataclasses.replace(cfg.isam2, every_frame=True,
                                                             pose_cov_every_step=False))
    be = Isam2Slam(cfg.pose2_odometry, cfg, small_log.start_pose())
    res = drive(be, graph_log_steps(small_log))
    assert res.status == "ok" and np.all(np.isfinite(res.pose_covs))  # final marginals
    ref = run_graph_log(small_log, "isam2", pose_covariances=True)
    np.testing.assert_array_equal(res.poses, ref.poses)
    np.testing.assert_array_equal(res.pose_covs, ref.pose_covs)


def test_single_sample_pose2_odometry_equals_accumulate_pose2() -> None:
    motion = Pose2Motion(Pose2OdometryModel())
    rng = np.random.default_rng(7)
    for i in range(300):
        a = rng.normal(size=(3, 3)) * 1e-2
        row = np.r_[rng.normal(size=3) * [1.0, 1.0, 4.0], (a @ a.T).ravel()][None]
        if i % 5 == 0:
            row[0, 3:] = np.nan  # no covariance: the model's default
        for floor in (1e-9, 1e-14, 0.0):
            d, c = motion.relative(row, floor)
            d_ref, c_ref = accumulate_pose2(row[:, :3], motion._covs(row), floor)
            np.testing.assert_array_equal(d, d_ref)
            np.testing.assert_array_equal(c, c_ref)
    with pytest.raises(FactorError):
        motion.relative(np.r_[0.1, 0.0, 0.0, np.eye(3).ravel()][None], -1.0)


def test_2x2_covariance_check_decides_as_the_eigenvalues() -> None:
    rng = np.random.default_rng(11)
    for _ in range(2000):
        c = rng.normal(size=(2, 2))
        c = c + c.T if rng.random() < 0.5 else c @ c.T
        sym = 0.5 * (c + c.T)
        ok = bool(np.linalg.eigvalsh(sym)[0] > 1e-12 * np.abs(sym).max())
        if abs(np.linalg.eigvalsh(sym)[0]) < 1e-9 * np.abs(sym).max():
            continue  # at the boundary the two tests may round differently
        if ok:
            check_cov(c, 2, "t")
        else:
            with pytest.raises(FactorError, match="positive definite"):
                check_cov(c, 2, "t")
    for bad in (np.array([[np.nan, 0.0], [0.0, 1.0]]), np.array([[1.0, np.inf], [0.0, 1.0]]),
                np.eye(3)):
        with pytest.raises(FactorError, match="finite"):
            check_cov(bad, 2, "t")


def test_point2_handler_shares_one_validated_noise_model_per_covariance() -> None:
    h = Point2Handler()
    lm = GraphLandmark(4, LandmarkKind.POINT2, True, 1, np.zeros(2), np.eye(2))
    r = np.diag([0.01, 0.04])
    f1 = h.factors(lm, 1, Obs(LandmarkKind.POINT2, np.array([0.2, 3.0]), r.copy()), None)[0]
    f2 = h.factors(lm, 2, Obs(LandmarkKind.POINT2, np.array([-0.1, 5.0]), r.copy()), None)[0]
    assert f1.noiseModel() is f2.noiseModel() or np.array_equal(
        f1.noiseModel().covariance(), f2.noiseModel().covariance())
    np.testing.assert_allclose(f1.noiseModel().covariance(), r, rtol=1e-12)
    assert list(f2.keys()) == [X(2), lm_key(4)]
    np.testing.assert_allclose(f2.measured().bearing().theta(), -0.1, rtol=1e-15)
    assert f2.measured().range() == 5.0
    with pytest.raises(FactorError, match="positive definite"):
        h.factors(lm, 3, Obs(LandmarkKind.POINT2, np.array([0.0, 1.0]), -r), None)
    with pytest.raises(FactorError, match="finite"):  # same bytes as a cached 2x2, other shape
        h.noise(r.ravel(), None)


def lm_key(j: int) -> int:
    """``L(j)``."""
    from gtsam.symbol_shorthand import L

    return int(L(j))
