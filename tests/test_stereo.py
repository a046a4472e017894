"""Stereo two-point models (paper 3, eqs. 1-5), their GTSAM adapters and the run format."""

from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path

import gtsam
import numpy as np
import pytest
from gtsam.symbol_shorthand import X
from gtsam.utils.numerical_derivative import numericalDerivative11

from lampsam.datasets.stereo_sim import (
    StereoRig,
    read_stereo_run,
    render_columns,
    simulate_stereo,
    write_stereo_run,
)
from lampsam.errors import DatasetError
from lampsam.factors.stereo import (
    camera_point,
    motion_factor,
    motion_model,
    stereo_project,
    triangulate_point,
    two_point_factor,
    two_point_measurement,
)

B = 0.12
F_PX = 500.0
POINTS = np.array([[0.0, 0.3], [0.0, -0.3]])


def _random_poses(rng: np.random.Generator, n: int = 6) -> list[gtsam.Pose2]:
    """Poses 2-8 m before the target, facing it roughly."""
    return [
        gtsam.Pose2(rng.uniform(-8, -2), rng.uniform(-1, 1), rng.uniform(-0.4, 0.4))
        for _ in range(n)
    ]


def test_projection_hand_computed() -> None:
    # Rig 4 m before the point (0, 0.5), heading +x: c = (4, 0.5);
    # x_l = 500 (0.5 - 0.06) / 4 = 55, x_r = 500 (0.5 + 0.06) / 4 = 70.
    z, _ = two_point_measurement(
        np.array([-4.0, 0.0, 0.0]), np.array([[0.0, 0.5], [0.0, -0.5]]), B, F_PX
    )
    np.testing.assert_allclose(z, [55.0, 70.0, -70.0, -55.0], atol=1e-12)
    # Rig at the origin facing +y (theta = pi/2), point (0, 3): c = (3, 0);
    # x_l = 500 (0 - 0.06) / 3 = -10, x_r = +10.
    c, _, _ = camera_point(np.array([0.0, 0.0, math.pi / 2]), np.array([0.0, 3.0]))
    np.testing.assert_allclose(c, [3.0, 0.0], atol=1e-12)
    x, _ = stereo_project(c, B, F_PX)
    np.testing.assert_allclose(x, [-10.0, 10.0], atol=1e-12)
    # disparity = f B / depth = 500 * 0.12 / 3 = 20 px
    assert x[1] - x[0] == pytest.approx(20.0, abs=1e-12)


def test_simulator_renderer_agrees_with_model(rng: np.random.Generator) -> None:
    """The simulator's independent pinhole renderer matches eq. 2 (sign conventions)."""
    rig = StereoRig()
    for pose in _random_poses(rng):
        vec = np.array([pose.x(), pose.y(), pose.theta()])
        u, ok = render_columns(vec, POINTS, rig)
        z, _ = two_point_measurement(vec, POINTS, rig.baseline, rig.f_px)
        if ok.all():
            np.testing.assert_allclose(rig.cu_px - u.reshape(4), z, atol=1e-9)


def test_triangulate_inverts_projection(rng: np.random.Generator) -> None:
    for _ in range(5):
        c = np.array([rng.uniform(1, 20), rng.uniform(-3, 3)])
        x, _ = stereo_project(c, B, F_PX)
        np.testing.assert_allclose(triangulate_point(x[0], x[1], B, F_PX), c, atol=1e-9)


def test_camera_point_jacobians(rng: np.random.Generator) -> None:
    for pose in _random_poses(rng):
        p = rng.uniform(-1, 1, 2)
        _, c_D_pose, c_D_point = camera_point(pose, p)
        num_pose = numericalDerivative11(lambda q, p=p: camera_point(q, p)[0], pose)
        num_point = numericalDerivative11(lambda q, pose=pose: camera_point(pose, q)[0], p)
        np.testing.assert_allclose(c_D_pose, num_pose, atol=1e-6)
        np.testing.assert_allclose(c_D_point, num_point, atol=1e-6)


def test_stereo_project_jacobian(rng: np.random.Generator) -> None:
    for _ in range(6):
        c = np.array([rng.uniform(0.5, 15), rng.uniform(-3, 3)])
        _, x_D_c = stereo_project(c, B, F_PX)
        num = numericalDerivative11(lambda q: stereo_project(q, B, F_PX)[0], c)
        np.testing.assert_allclose(x_D_c, num, atol=1e-6 * F_PX)


def test_two_point_measurement_jacobian(rng: np.random.Generator) -> None:
    for pose in _random_poses(rng):
        _, z_D_pose = two_point_measurement(pose, POINTS, B, F_PX)
        num = numericalDerivative11(lambda q: two_point_measurement(q, POINTS, B, F_PX)[0], pose)
        np.testing.assert_allclose(z_D_pose, num, atol=1e-5)


def test_motion_model_jacobians_and_pose2_compose(rng: np.random.Generator) -> None:
    for _ in range(6):
        state = np.array([rng.uniform(-5, 5), rng.uniform(-5, 5), rng.uniform(-3, 3)])
        u = np.array([rng.uniform(-0.2, 0.5), rng.uniform(-0.2, 0.2)])
        nxt, n_D_s, n_D_u = motion_model(state, u[0], u[1])
        np.testing.assert_allclose(
            n_D_s, numericalDerivative11(lambda s, u=u: motion_model(s, u[0], u[1])[0], state),
            atol=1e-6)
        np.testing.assert_allclose(
            n_D_u, numericalDerivative11(lambda q, s0=state: motion_model(s0, q[0], q[1])[0], u),
            atol=1e-6)
        # eq. 4 is Pose2 composition with (v dt, 0, omega dt)
        composed = gtsam.Pose2(*state).compose(gtsam.Pose2(u[0], 0.0, u[1]))
        np.testing.assert_allclose(
            [composed.x(), composed.y()], nxt[:2], atol=1e-9)
        assert math.remainder(composed.theta() - nxt[2], 2 * math.pi) == pytest.approx(0, abs=1e-9)
        factor = motion_factor(X(0), X(1), u[0], u[1], gtsam.noiseModel.Unit.Create(3))
        values = gtsam.Values()
        values.insert(X(0), gtsam.Pose2(*state))
        values.insert(X(1), gtsam.Pose2(*nxt))
        assert factor.error(values) == pytest.approx(0.0, abs=1e-16)


def test_two_point_factor_matches_model(rng: np.random.Generator) -> None:
    sigma = 0.5
    noise = gtsam.noiseModel.Isotropic.Sigma(4, sigma)
    for pose in _random_poses(rng, 5):
        z = rng.normal(0, 50, 4)
        factor = two_point_factor(X(3), z, POINTS, B, F_PX, noise)
        values = gtsam.Values()
        values.insert(X(3), pose)
        h, h_D = two_point_measurement(pose, POINTS, B, F_PX)
        assert factor.error(values) == pytest.approx(0.5 * np.sum((h - z) ** 2) / sigma**2)
        lin = factor.linearize(values)
        a, b = lin.jacobian()
        np.testing.assert_allclose(a, h_D / sigma, atol=1e-9)
        np.testing.assert_allclose(b, -(h - z) / sigma, atol=1e-9)


def test_run_round_trip_and_bad_input(tmp_path: Path, rng: np.random.Generator) -> None:
    run = simulate_stereo("turn", rng, seed=3)
    write_stereo_run(run, tmp_path / "run")
    back = read_stereo_run(tmp_path / "run")
    assert back.rig == run.rig and back.noise == run.noise
    np.testing.assert_allclose(back.z, run.z, atol=1e-6)
    np.testing.assert_array_equal(back.seen, run.seen)
    assert back.truth is not None and run.truth is not None
    np.testing.assert_allclose(back.truth, run.truth, atol=1e-8)
    # quantised, paper coordinates are half-integers for an even image width
    seen_z = run.z[run.seen]
    np.testing.assert_allclose(np.mod(seen_z, 1.0), 0.5, atol=1e-9)

    with pytest.raises(DatasetError, match="stereo_run.yaml"):
        read_stereo_run(tmp_path / "nothing")
    meas = tmp_path / "run" / "measurements.csv"
    lines = meas.read_text().splitlines()
    meas.write_text("\n".join(lines[:3] + ["0.3,1,nan,2,3,4"] + lines[4:]) + "\n")
    with pytest.raises(DatasetError, match=r"measurements.csv:4"):
        read_stereo_run(tmp_path / "run")
    meas.write_text("\n".join(lines[:3] + [lines[2]] + lines[4:]) + "\n")
    with pytest.raises(DatasetError, match="time does not increase"):
        read_stereo_run(tmp_path / "run")


def test_simulated_noise_statistics() -> None:
    """Per-coordinate error variance ~ 1/12 + sigma^2 (N = 4 x 161 x 8 samples)."""
    errs = []
    for seed in range(8):
        run = simulate_stereo("turn", np.random.default_rng(seed))
        quiet = simulate_stereo(
            "turn", np.random.default_rng(seed),
            noise=replace(run.noise, sigma_detect_px=0.0, quantise=False))
        errs.append((run.z - quiet.z)[run.seen].ravel())
    e = np.concatenate(errs)
    expected = run.noise.var_measurement_px2
    # the variance of N ~ 5000 samples is within ~3 sigma = 3 * sqrt(2/N) * var of its mean
    assert np.var(e) == pytest.approx(expected, rel=3 * math.sqrt(2 / len(e)) + 0.02)
