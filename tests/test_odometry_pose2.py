"""Pose2-increment odometry: model Jacobians and covariance, the log format, every backend."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import gtsam
import numpy as np
import pytest

from lampsam.backend.odometry import Pose2Motion, WheelMotion
from lampsam.backend.slam import (
    errors_vs_truth,
    frames_from_range_bearing,
    iter_steps,
    make_backend,
    run_slam,
)
from lampsam.datasets.logrun import LoggedRun, OdometryModel, read_run, write_run
from lampsam.datasets.odometry import (
    Pose2OdometryLog,
    Pose2OdometryModel,
    increments_from_poses,
    pose2_odometry_from_poses,
    read_pose2_odometry,
    write_pose2_odometry,
)
from lampsam.errors import DatasetError
from lampsam.factors.geometry import wrap_angle
from lampsam.factors.motion import diff_drive_step
from lampsam.factors.pose2_odometry import (
    accumulate_pose2,
    pose2_step,
    se2_adjoint,
)
from tests.test_backend import range_bearing_world


def _num_jac(f, x: np.ndarray, eps: float = 1e-6) -> np.ndarray:
    cols = []
    for i in range(len(x)):
        dx = np.zeros(len(x))
        dx[i] = eps
        d = f(x + dx) - f(x - dx)
        d[2] = wrap_angle(d[2])
        cols.append(d / (2 * eps))
    return np.array(cols).T


def _exp(xi: np.ndarray) -> np.ndarray:
    p = gtsam.Pose2.Expmap(xi)
    return np.array([p.x(), p.y(), p.theta()])


@pytest.mark.parametrize("seed", range(5))
def test_pose2_step_jacobians_match_numerical(seed: int) -> None:
    """next_D_pose (plain coordinates) and next_D_delta (right tangent of delta), 1e-6."""
    rng = np.random.default_rng(seed)
    pose = rng.uniform([-3, -3, -np.pi], [3, 3, np.pi])
    delta = rng.uniform([-0.5, -0.2, -0.5], [0.5, 0.2, 0.5])
    _, j_pose, j_delta = pose2_step(pose, delta)
    np.testing.assert_allclose(j_pose, _num_jac(lambda p: pose2_step(p, delta)[0], pose), atol=1e-6)

    def through_tangent(xi: np.ndarray) -> np.ndarray:
        d = gtsam.Pose2(*delta).compose(gtsam.Pose2.Expmap(xi))
        return pose2_step(pose, np.array([d.x(), d.y(), d.theta()]))[0]

    np.testing.assert_allclose(j_delta, _num_jac(through_tangent, np.zeros(3)), atol=1e-6)


def test_pose2_step_and_adjoint_agree_with_gtsam() -> None:
    rng = np.random.default_rng(7)
    for _ in range(5):
        a = rng.uniform([-3, -3, -3], [3, 3, 3])
        b = rng.uniform([-1, -1, -1], [1, 1, 1])
        c = gtsam.Pose2(*a).compose(gtsam.Pose2(*b))
        np.testing.assert_allclose(pose2_step(a, b)[0], [c.x(), c.y(), c.theta()], atol=1e-12)
        np.testing.assert_allclose(se2_adjoint(a), gtsam.Pose2(*a).AdjointMap(), atol=1e-12)


def test_accumulated_pose2_covariance_matches_monte_carlo() -> None:
    """N = 4,000 draws of 10 noisy increments (sideways noise 3x forward): the
    right-tangent covariance of the composed pose within 10 % (3 sigma of a variance
    estimate at N = 4,000 is 6.7 %; first-order model error adds a little)."""
    rng = np.random.default_rng(11)
    deltas = np.tile([0.2, 0.0, 0.05], (10, 1))
    c = np.diag([0.004**2, 0.012**2, 0.01**2])
    covs = np.tile(c, (10, 1, 1))
    mean, cov = accumulate_pose2(deltas, covs)
    n = 4000
    noise = rng.multivariate_normal(np.zeros(3), c, size=(n, len(deltas)))
    xi = np.empty((n, 3))
    m_inv = gtsam.Pose2(*mean).inverse()
    steps = [gtsam.Pose2(*d) for d in deltas]
    for s in range(n):
        p = gtsam.Pose2()
        for d, e in zip(steps, noise[s], strict=True):
            p = p.compose(d).compose(gtsam.Pose2.Expmap(e))
        xi[s] = gtsam.Pose2.Logmap(m_inv.compose(p))
    emp = np.cov(xi.T)
    np.testing.assert_allclose(np.diag(emp), np.diag(cov), rtol=0.10)
    np.testing.assert_allclose(emp, cov, atol=0.10 * float(np.max(np.diag(cov))))


def test_increments_from_absolute_poses_recompose() -> None:
    rng = np.random.default_rng(3)
    poses = np.cumsum(rng.uniform(-0.3, 0.3, (20, 3)), axis=0)
    inc = increments_from_poses(poses)
    np.testing.assert_allclose(inc[0], 0.0)
    p = poses[0].copy()
    for d in inc[1:]:
        p = pose2_step(p, d)[0]
    np.testing.assert_allclose(p[:2], poses[-1, :2], atol=1e-9)
    assert abs(wrap_angle(p[2] - poses[-1, 2])) < 1e-9


def test_stationary_robot_is_never_singular() -> None:
    """1,000 zero increments without covariance: the relative covariance is 1,000 floors
    (positive definite), for the model and through the graph (iSAM2 finishes ok)."""
    model = Pose2OdometryModel()
    motion = Pose2Motion(model)
    samples = np.hstack([np.zeros((1000, 3)), np.full((1000, 9), np.nan)])
    _, cov = motion.relative(motion.check(0.0, samples), 0.0)
    np.testing.assert_allclose(np.diag(cov), 1000 * np.array([model.var_floor_xy,
                                                              model.var_floor_xy,
                                                              model.var_floor_theta]), rtol=1e-9)
    assert np.min(np.linalg.eigvalsh(cov)) > 0
    with pytest.raises(ValueError, match="var_floor_xy: must be > 0"):
        Pose2OdometryModel(var_floor_xy=0.0)
    # a robot at rest for 600 steps with frames of the same landmark: no failure
    from lampsam.backend.config import AssociationConfig, SlamConfig
    from lampsam.frontend.measurements import RangeBearingFrame, RangeBearingObservation

    cfg = SlamConfig(association=AssociationConfig(min_observations=1))
    for name in ("ekf", "isam2", "batch"):
        be = make_backend(name, model, cfg, np.zeros(3))
        for i in range(600):
            frame = RangeBearingFrame(0.1 * i, (RangeBearingObservation(3.0, 0.5, 0),))
            be.step(0.1 * i, samples[:1], frame)
        res = be.finish()
        assert res.status == "ok"
        assert be.__dict__.get("n_recoveries", 0) == 0
        np.testing.assert_allclose(res.poses[-1], 0.0, atol=1e-6)


def test_wheel_motion_is_the_paper_model() -> None:
    """WheelMotion.ekf_predict chains eq. 13 and equals diff_drive_step's composition."""
    wm = WheelMotion(OdometryModel(0.4, 1e-4, 1e-4))
    wheel = np.array([[0.01, 0.012], [0.011, 0.009], [0.0, 0.0]])
    pose = np.array([1.0, 2.0, 0.3])
    out, _, q = wm.ekf_predict(pose, wheel)
    p = pose
    for dl, dr in wheel:
        p = diff_drive_step(p, dl, dr, 0.4)[0]
    np.testing.assert_allclose(out, p, atol=1e-12)
    assert np.all(np.linalg.eigvalsh(q) >= -1e-15)


def test_pose2_odometry_csv_round_trip_and_errors(tmp_path: Path) -> None:
    log = Pose2OdometryLog(t=np.array([0.1, 0.2]), delta=np.array([[0.1, 0.01, 0.02], [0.2, 0.0, -0.1]]),
                           cov=np.stack([np.diag([1e-4, 4e-6, 4e-6]), np.full((3, 3), np.nan)]))
    p = tmp_path / "odometry_pose2.csv"
    write_pose2_odometry(p, log)
    back = read_pose2_odometry(p)
    np.testing.assert_allclose(back.delta, log.delta, atol=1e-15)
    np.testing.assert_allclose(back.cov[0], log.cov[0], atol=1e-18)
    assert np.all(np.isnan(back.cov[1]))
    p.write_text(p.read_text().replace("0.2,0.0", "0.2,zero", 1))
    with pytest.raises(DatasetError, match=r"odometry_pose2.csv:3: column 'dy': not a number"):
        read_pose2_odometry(p)
    p.write_text("t,dx\n0,1\n")
    with pytest.raises(DatasetError, match=r"odometry_pose2.csv:1: header"):
        read_pose2_odometry(p)


@pytest.mark.parametrize("name", ["ekf", "isam2", "batch"])
def test_every_backend_runs_on_pose2_increments(name: str, tmp_path: Path) -> None:
    """The range-bearing world with its wheel odometry turned into absolute odometry
    poses, then Pose2 increments (model-default noise), written as a logged run and read
    back: each backend tracks within 0.1 m RMS (the wheel-odometry figure is < 0.1 m)."""
    rng = np.random.default_rng(5)
    rig, odo, rb, gt, _ = range_bearing_world(rng)
    wm = WheelMotion(rig.odometry)
    poses = [gt.poses[0]]
    for dl, dr in zip(odo.d_left, odo.d_right, strict=True):
        poses.append(wm.ekf_predict(poses[-1], np.array([[dl, dr]]))[0])
    t0 = gt.t[0]
    p2 = pose2_odometry_from_poses(np.r_[t0, odo.t], np.array(poses))
    run = LoggedRun(path=tmp_path / "run", rig=rig, odometry=p2, groundtruth=gt, range_bearing=rb)
    write_run(tmp_path / "run", rig=rig, odometry=p2, groundtruth=gt, range_bearing=rb)
    back = read_run(tmp_path / "run")
    assert isinstance(back.odometry, Pose2OdometryLog)
    res = run_slam(None, name, run=dataclasses.replace(run, odometry=back.odometry))
    assert res.status == "ok"
    err = errors_vs_truth(res, gt)[0]
    assert float(np.sqrt(np.mean(err**2))) < 0.1
    steps = list(iter_steps(back.odometry, frames_from_range_bearing(rb)))
    assert all(u.shape[1] == 12 for _, u, _ in steps)


def test_pose2_noise_from_config_and_rig(tmp_path: Path) -> None:
    """``[pose2_odometry]`` in a TOML config and ``pose2_odometry`` in rig.yaml set the
    model (the rig's wins); bad values are errors naming the key and the file."""
    from lampsam.backend.config import SlamConfig
    from lampsam.backend.slam import pose2_model_for
    from lampsam.config_loader import ConfigError, load_config
    from lampsam.datasets.rig import Rig

    cfg_file = tmp_path / "slam.toml"
    cfg_file.write_text("[pose2_odometry]\nk_xy = 2e-3\nvar_floor_theta = 1e-6\n")
    cfg = load_config(SlamConfig, cfg_file)
    assert cfg.pose2_odometry == Pose2OdometryModel(k_xy=2e-3, var_floor_theta=1e-6)
    cfg_file.write_text("[pose2_odometry]\nvar_floor_xy = 0.0\n")
    with pytest.raises(ConfigError, match=r"pose2_odometry\.var_floor_xy: must be > 0"):
        load_config(SlamConfig, cfg_file)
    cfg_file.write_text("[pose2_odometry]\nk_xyz = 1.0\n")
    with pytest.raises(ConfigError, match=r"pose2_odometry\.k_xyz: unknown key"):
        load_config(SlamConfig, cfg_file)

    rng = np.random.default_rng(5)
    rig, odo, rb, gt, _ = range_bearing_world(rng)
    run = LoggedRun(path=tmp_path / "run", rig=rig, odometry=odo, groundtruth=gt, range_bearing=rb)
    assert pose2_model_for(run, cfg) is cfg.pose2_odometry  # the rig has no section
    rig2 = dataclasses.replace(rig, pose2_odometry=Pose2OdometryModel(k_theta=3e-3))
    rig2.to_yaml(tmp_path / "rig.yaml")
    back = Rig.from_yaml(tmp_path / "rig.yaml")
    assert back.pose2_odometry == Pose2OdometryModel(k_theta=3e-3)
    assert pose2_model_for(dataclasses.replace(run, rig=back), cfg) == back.pose2_odometry
    text = (tmp_path / "rig.yaml").read_text().replace("var_floor_xy: 1.0e-08", "var_floor_xy: -1.0")
    (tmp_path / "rig.yaml").write_text(text)
    with pytest.raises(DatasetError, match=r"pose2_odometry.var_floor_xy: must be > 0"):
        Rig.from_yaml(tmp_path / "rig.yaml")


def test_config_odometry_noise_reaches_the_factor() -> None:
    """A sample without covariance gets the configured default plus the floor in the
    smoother's odometry factor: over a 1 m forward step ``var_x = k_xy * 1 + floor``."""
    from lampsam.backend.config import SlamConfig

    model = Pose2OdometryModel(k_xy=4e-3, var_floor_xy=1e-6)
    cfg = SlamConfig(pose2_odometry=model)
    motion = Pose2Motion(cfg.pose2_odometry)
    sample = np.r_[1.0, 0.0, 0.0, np.full(9, np.nan)].reshape(1, 12)
    _, cov = motion.relative(sample, 0.0)
    assert abs(cov[0, 0] - (4e-3 + 1e-6)) < 1e-12
    assert abs(cov[1, 1] - (4e-3 + 1e-6)) < 1e-12
