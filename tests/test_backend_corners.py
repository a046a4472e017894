"""Ceiling SLAM with corners from the real frontend (no known ids), and its safeguards.

- a 6 s simulated lab run through the real frontend (lamps + ~44 FAST corners per
  frame, no ids): every backend finishes with status ok and tracks within 5 cm;
- a failed iSAM2 update (a corner below the camera makes GTSAM's projection factor
  throw) is recovered: the offending landmark is dropped and iSAM2 rebuilt;
- a lamp first seen without an axis and later with one is handled by all backends;
- an oriented lamp is gated without a joint marginal (batch, ``init = "odometry"``);
- the vectorised projection, screening and triangulation agree with the per-point
  models.
"""

from __future__ import annotations

import dataclasses
import logging
import math

import numpy as np
import pytest
from gtsam.symbol_shorthand import C, X

from lampsam.backend.association import corner_budget, mahalanobis2, pairwise_d2
from lampsam.backend.ceiling import CeilingModel
from lampsam.backend.ceiling_graph import CeilingHandler
from lampsam.backend.config import SlamConfig
from lampsam.backend.ekf import EkfSlam
from lampsam.backend.graph import BatchSlam, Isam2Slam
from lampsam.backend.handlers import GraphLandmark as _Landmark
from lampsam.backend.models import observations_from_frame
from lampsam.backend.slam import (
    drive,
    errors_vs_truth,
    iter_steps,
    make_backend,
    make_frames,
    start_pose_of,
)
from lampsam.datasets.logrun import LoggedRun, OdometryLog, OdometryModel, Rig, Trajectory, read_run
from lampsam.datasets.motion import follow_waypoints, noisy_wheel_travel
from lampsam.factors.ceiling import project_point
from lampsam.factors.gtsam_factors import projection_factor
from lampsam.frontend.measurements import CeilingFrame, CornerObservation, LampObservation
from tests.conftest import SimRun

K_WHEEL = 4e-5  # m, eq. 15 slip constant of the hand-built worlds


def _rms(x: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.square(x))))


@pytest.fixture(scope="module")
def lab(sim_run: SimRun) -> tuple[LoggedRun, list, bool]:
    """6 s of the simulated lab world and the real frontend's frames (made once)."""
    run = read_run(sim_run(seed=0, duration=6.0))
    frames, ceiling = make_frames(run, "images")
    return run, list(frames), ceiling


@pytest.mark.parametrize("name", ["ekf", "isam2", "batch"])
def test_corners_from_frontend_finish_and_track(name: str, lab: tuple) -> None:
    """Lamps + frontend corners (no ids): status ok, position RMS < 5 cm, corners mapped."""
    run, frames, ceiling = lab
    assert sum(len(f.corners) for f in frames) > 20 * len(frames)  # corners really used
    base = SlamConfig()  # defaults, but no final marginals (test time)
    cfg = dataclasses.replace(base, isam2=dataclasses.replace(base.isam2,
                                                              final_covariances=False))
    be = make_backend(name, run.rig.odometry, cfg, start_pose_of(run),
                      run.rig.camera if ceiling else None)
    result = drive(be, iter_steps(run.odometry, frames))
    assert result.status == "ok"
    pos, head = errors_vs_truth(result, run.groundtruth)
    assert _rms(pos) < 0.05
    assert np.degrees(_rms(head)) < 1.0
    corners = [lm for lm in result.landmarks if lm.type == "corner"]
    assert len(corners) >= 20
    z_cam = run.rig.camera.body_t_camera[2]
    assert all(lm.position[2] > z_cam + 0.1 for lm in corners)  # all above the camera


def _line_world(rng: np.random.Generator, axis_from: int = 6):
    """A 4 s straight drive under one oriented lamp (and three corners), known ids.

    The lamp's axis is withheld in the first ``axis_from`` frames (a point lamp,
    paper III.4) and measured afterwards.
    """
    base = Rig()
    rig = Rig(camera=base.camera, odometry=OdometryModel(base.odometry.wheel_base, K_WHEEL,
                                                         K_WHEEL))
    cam = rig.camera
    t, poses, wheel = follow_waypoints(np.array([[0.0, 0.0], [2.0, 0.0]]), speed=0.4,
                                       rate_hz=30.0, wheel_base=rig.odometry.wheel_base,
                                       duration=4.0)
    noisy = noisy_wheel_travel(wheel, K_WHEEL, K_WHEEL, rng)
    lamp = np.array([1.0, 0.2, 2.8])
    phi = 0.4
    corners = {10: np.array([0.6, -0.3, 2.8]), 11: np.array([1.2, 0.4, 2.8]),
               12: np.array([1.6, -0.2, 2.8])}
    sig = 0.5 / cam.fx
    cov = sig**2 * np.eye(2)
    frames = []
    for i in range(0, len(t), 3):
        m, _, _ = project_point(poses[i], lamp, cam.body_t_camera)
        m = m + rng.normal(0.0, sig, 2)
        if len(frames) < axis_from:
            lam = LampObservation(m, cov, None, math.inf, 1.0, 80.0, np.zeros(2), 0)
        else:
            ax = float((phi - poses[i, 2] + rng.normal(0.0, 0.02)) % math.pi)
            lam = LampObservation(m, cov, ax, 0.02**2, 2.0, 80.0, np.zeros(2), 0)
        cor = []
        for cid, p in corners.items():
            mc, _, _ = project_point(poses[i], p, cam.body_t_camera)
            cor.append(CornerObservation(mc + rng.normal(0.0, sig, 2), cov, np.zeros(2),
                                         np.zeros((1, 1), np.float32), 1.0, cid))
        frames.append(CeilingFrame(float(t[i]), len(frames), (lam,), tuple(cor)))
    odo = OdometryLog(t=t[1:], d_left=noisy[1:, 0], d_right=noisy[1:, 1])
    return rig, odo, frames, poses, lamp


@pytest.mark.parametrize("name", ["ekf", "isam2", "batch"])
def test_lamp_first_seen_without_axis_then_with_axis(name: str) -> None:
    """No backend breaks; the lamp stays a point lamp and is mapped within 5 cm."""
    rig, odo, frames, poses, lamp = _line_world(np.random.default_rng(4))
    model = CeilingModel.from_camera(rig.camera)
    cfg = SlamConfig()
    if name == "ekf":
        be = EkfSlam(rig.odometry, cfg, poses[0], model)
    else:
        cls = Isam2Slam if name == "isam2" else BatchSlam
        be = cls(rig.odometry, cfg, poses[0], model, CeilingHandler(model))
    result = drive(be, iter_steps(odo, frames))
    assert result.status == "ok"
    lamps = [lm for lm in result.landmarks if lm.type == "lamp"]
    assert len(lamps) == 1
    assert np.linalg.norm(lamps[0].position[:2] - lamp[:2]) < 0.05
    # every frame for the EKF; the smoothers' keyframes (first frame, then every 0.05 m)
    expected = len(frames) if name == "ekf" else int(result.keyframes.sum())
    assert expected > 3
    assert lamps[0].n_obs == expected


def test_oriented_lamp_gate_without_joint_marginal() -> None:
    """Batch with ``init = "odometry"`` (no iSAM2: every gate is the fallback without a
    joint marginal) and no ids: an oriented lamp whose gating covariance was tightened
    by triangulation (position block) keeps a (4, 4) covariance, so the fallback's
    ``Psi = H_p Sigma_x H_p^T + H_l Sigma_l H_l^T + R`` has the (3, 4) axis Jacobian's
    shape; every sight is matched to the one lamp."""
    rig, odo, frames, poses, lamp = _line_world(np.random.default_rng(6), axis_from=0)
    model = CeilingModel.from_camera(rig.camera)
    base = SlamConfig()
    cfg = dataclasses.replace(
        base, association=dataclasses.replace(base.association, use_known_ids=False),
        batch=dataclasses.replace(base.batch, init="odometry"))
    be = BatchSlam(rig.odometry, cfg, poses[0], model, CeilingHandler(model))
    result = drive(be, iter_steps(odo, frames))
    assert result.status == "ok", result.status
    lamps = [lm for lm in result.landmarks if lm.type == "lamp"]
    assert len(lamps) == 1
    assert np.linalg.norm(lamps[0].position[:2] - lamp[:2]) < 0.05
    assert lamps[0].n_obs >= 5  # re-matched after the gate was tightened (3 sights)
    lm = next(m for m in be._landmarks.values() if m.kind == "lamp")
    assert lm.oriented and lm.cov.shape == (4, 4)
    assert np.allclose(lm.cov, lm.cov.T) and np.linalg.eigvalsh(lm.cov).min() > 0
    obs = observations_from_frame(frames[-1], cfg.features, cfg.noise)[0]
    assert obs.kind == "lamp" and obs.has_axis
    pose = be.current_pose()
    nu, psi = be._innovation((be._k, pose, np.zeros(3), np.zeros((3, 3))), lm.id, obs)
    assert nu.shape == (3,) and psi.shape == (3, 3) and np.allclose(psi, psi.T)
    assert np.linalg.eigvalsh(psi - obs.R).min() > 0  # pose and lamp terms add to R
    assert psi[2, 2] - obs.R[2, 2] > 0.5 * lm.cov[3, 3]  # the lamp's axis variance counts


def test_failed_isam2_update_is_recovered(caplog: pytest.LogCaptureFixture) -> None:
    """A corner below the camera makes the update throw; it is dropped, the run goes on."""
    rig, odo, frames, poses, _ = _line_world(np.random.default_rng(5))
    model = CeilingModel.from_camera(rig.camera)
    be = Isam2Slam(rig.odometry, SlamConfig(), poses[0], model, CeilingHandler(model))
    steps = list(iter_steps(odo, frames))
    half = len(steps) // 2
    for s in steps[:half]:
        be.step(*s)
    k = be._k
    bad = 999
    below = np.array([poses[0, 0] + 0.5, 0.0, model.body_t_camera[2] - 0.5])  # under the lens
    be._landmarks[bad] = _Landmark(bad, "corner", True, 2, below, np.eye(3), [], None, False, k)
    be._add_value(C(bad), below)
    be._add_factor(projection_factor(X(k), C(bad), np.array([0.1, 0.0]), 1e-6 * np.eye(2),
                                     model.body_t_camera), bad)
    with caplog.at_level(logging.WARNING, logger="lampsam.backend.isam2_update"):
        be._flush()
    assert "rebuilding iSAM2" in caplog.text
    assert be.n_recoveries == 1 and bad not in be._landmarks
    assert not be.isam.valueExists(C(bad))
    for s in steps[half:]:
        be.step(*s)
    result = be.finish()
    assert result.status == "ok"
    pos, _ = errors_vs_truth(result, Trajectory(t=np.arange(len(poses)) / 30.0, poses=poses))
    assert float(pos.max()) < 0.05


def test_project_many_matches_project_point() -> None:
    """Vectorised projection (values and Jacobians) equals the per-point model."""
    rng = np.random.default_rng(8)
    model = CeilingModel(np.array([0.05, -0.02, 0.3]), 1.0)
    pose = np.array([0.4, -0.2, 0.7])
    pts = np.column_stack([rng.uniform(-1, 2, (20, 2)), rng.uniform(1.5, 3.0, 20)])
    m, m_d_pose, m_d_pt, vis = model.project_many(pose, pts)
    for j, p in enumerate(pts):
        mj, dpj, dlj = project_point(pose, p, model.body_t_camera)
        np.testing.assert_allclose(m[j], mj, atol=1e-12)
        np.testing.assert_allclose(m_d_pose[j], dpj, atol=1e-12)
        np.testing.assert_allclose(m_d_pt[j], dlj, atol=1e-12)
        assert vis[j] == model.in_view(pose, p)
    low = model.project_many(pose, np.array([[0.0, 0.0, 0.35]]))[3]
    assert not low[0]  # 5 cm above the lens: not usable


def test_pairwise_d2_matches_mahalanobis() -> None:
    """All-pairs closed-form 2x2 distances equal nu^T (S + R)^-1 nu (eq. 20)."""
    rng = np.random.default_rng(9)
    z, z_hat = rng.normal(size=(5, 2)), rng.normal(size=(4, 2))
    a, b = rng.normal(size=(5, 2, 2)), rng.normal(size=(4, 2, 2))
    r = a @ np.transpose(a, (0, 2, 1)) + 0.1 * np.eye(2)
    s = b @ np.transpose(b, (0, 2, 1))
    d2 = pairwise_d2(z, r, z_hat, s)
    for i in range(5):
        for j in range(4):
            assert d2[i, j] == pytest.approx(mahalanobis2(z[i] - z_hat[j], r[i] + s[j]),
                                             rel=1e-10)


def test_triangulate_recovers_corner_and_flags_no_parallax() -> None:
    """Two sights 0.3 m apart give the point within 1 cm; one repeated sight has no depth."""
    rng = np.random.default_rng(10)
    model = CeilingModel(np.array([0.05, 0.0, 0.3]), 1.0)
    p = np.array([1.0, 0.5, 2.8])
    poses = np.array([[0.0, 0.0, 0.1], [0.3, 0.05, 0.15]])
    sig = 1e-3
    ms = np.array([project_point(q, p, model.body_t_camera)[0] + rng.normal(0, sig, 2)
                   for q in poses])
    covs = np.array([sig**2 * np.eye(2)] * 2)
    point, cov = model.triangulate(poses, ms, covs)
    assert np.linalg.norm(point - p) < 0.01 * 3
    assert math.sqrt(cov[2, 2]) < 0.1
    assert np.linalg.norm(point - p) < 4 * math.sqrt(np.trace(cov))
    _, cov0 = model.triangulate(poses[[0, 0]], ms[[0, 0]], covs)
    assert math.sqrt(cov0[2, 2]) > 1.0  # no baseline: height undetermined


def test_corner_budget_keeps_longest_tracks() -> None:
    """In-graph corners over the budget are dropped, longest tracks kept; others pass."""
    def lm(lid: int, kind: str, in_graph: bool, n_obs: int) -> _Landmark:
        return _Landmark(lid, kind, in_graph, n_obs, np.zeros(3), np.eye(3))

    marks = [lm(0, "corner", True, 5), lm(1, "corner", True, 9), lm(2, "lamp", True, 1),
             lm(3, "corner", False, 1), lm(4, "corner", True, 9), lm(5, "corner", True, 2)]
    pairs = [(m, None) for m in marks]
    kept, entries = corner_budget(pairs, 2)  # type: ignore[arg-type]
    assert [m.id for m, _ in kept] == [1, 2, 3, 4]  # ids 1 and 4 (9 sights) win, order kept
    assert entries == 2  # budget used up: the floor of 2 new entries
    kept, entries = corner_budget(pairs, 10)  # type: ignore[arg-type]
    assert [m.id for m, _ in kept] == [0, 1, 2, 3, 4, 5]
    assert entries == 10 - 4
    kept, entries = corner_budget(pairs, None)  # type: ignore[arg-type]
    assert len(kept) == 6 and entries > 1000


def test_corner_budget_counts_ekf_slots_as_mapped() -> None:
    """Landmarks without ``in_graph`` (EKF slots: always in the state) all count."""
    from lampsam.backend.ekf_landmarks import Slot as _Slot

    slots = [_Slot(i, "corner", 3 * i, 3, n, 0, 0) for i, n in enumerate([4, 1, 7, 2])]
    slots.append(_Slot(9, "lamp", 12, 4, 1, 0, 0))
    kept, entries = corner_budget([(s, None) for s in slots], 2)  # type: ignore[misc]
    assert [s.id for s, _ in kept] == [0, 2, 9]  # 7 and 4 sights win; the lamp passes
    assert entries == 2
