"""Upward camera models: projection, lamp axis, inverse-depth corners, initialisation."""

from __future__ import annotations

import math

import gtsam
import numpy as np
import pytest
from gtsam.utils.numerical_derivative import (
    numericalDerivative11,
    numericalDerivative21,
    numericalDerivative22,
    numericalDerivative31,
    numericalDerivative32,
    numericalDerivative33,
)

from lampsam.factors.ceiling import (
    HeightPrior,
    init_inverse_depth,
    init_point_from_observation,
    inverse_depth_to_point,
    lamp_axis,
    lamp_axis_residual,
    project_inverse_depth,
    project_inverse_depth_batch,
    project_point,
)
from lampsam.factors.geometry import FactorError, wrap_axis

SEEDS = [0, 1, 2, 3, 4, 5]
OFFSET = np.array([0.12, -0.03, 0.35])  # x_off, y_off, z_cam


def _arr(p: gtsam.Pose2) -> np.ndarray:
    return np.array([p.x(), p.y(), p.theta()])


def _case(rng: np.random.Generator) -> tuple[gtsam.Pose2, np.ndarray]:
    pose = gtsam.Pose2(*rng.uniform(-3.0, 3.0, 2), rng.uniform(-3.0, 3.0))
    point = np.array(
        [*(np.array([pose.x(), pose.y()]) + rng.uniform(-2, 2, 2)), rng.uniform(1.5, 3.0)]
    )
    return pose, point


def test_project_point_known_geometry() -> None:
    # robot at the origin facing +y; camera 0.12 m ahead (world (0, 0.12)); lamp 1 m
    # ahead of the camera and 0.5 m to its left at 2.5 m above it.
    off = np.array([0.12, 0.0, 0.3])
    pose = np.array([0.0, 0.0, math.pi / 2])
    point = np.array([-0.5, 1.12, 2.8])
    m = project_point(pose, point, off)[0]
    np.testing.assert_allclose(m, [1.0 / 2.5, 0.5 / 2.5], atol=1e-12)
    with pytest.raises(FactorError, match="not above the camera"):
        project_point(pose, np.array([0.0, 1.0, 0.3]), off)


@pytest.mark.parametrize("seed", SEEDS)
def test_project_point_jacobians(seed: int) -> None:
    rng = np.random.default_rng(seed)
    pose, point = _case(rng)
    _, m_D_pose, m_D_point = project_point(_arr(pose), point, OFFSET)

    def h(p: gtsam.Pose2, q: np.ndarray) -> np.ndarray:
        return project_point(_arr(p), q, OFFSET)[0]

    np.testing.assert_allclose(m_D_pose, numericalDerivative21(h, pose, point), atol=1e-6)
    np.testing.assert_allclose(m_D_point, numericalDerivative22(h, pose, point), atol=1e-6)


def test_overhead_landmark_is_well_conditioned() -> None:
    """m -> 0 (lamp straight above the camera): finite, full-rank Jacobians.

    The polar form's bearing atan2(v, u) has a Jacobian growing like 1/|m|; the
    Cartesian one does not change at all near m = 0.
    """
    pose = np.array([1.0, -2.0, 0.4])
    centre = (
        pose[:2]
        + np.array([[math.cos(0.4), -math.sin(0.4)], [math.sin(0.4), math.cos(0.4)]]) @ OFFSET[:2]
    )
    for eps in (0.0, 1e-9, 1e-5):
        point = np.array([centre[0] + eps, centre[1], 2.6])
        m, m_D_pose, m_D_point = project_point(pose, point, OFFSET)
        assert np.linalg.norm(m) <= eps / 2.0 + 1e-12
        assert np.all(np.isfinite(m_D_pose)) and np.all(np.isfinite(m_D_point))
        assert np.linalg.cond(m_D_pose[:, :2]) < 1.0 + 1e-9
        assert np.linalg.svd(m_D_point, compute_uv=False)[-1] > 0.1
        # inverse depth: the same, anchored elsewhere
        anchor = np.array([0.5, -2.5, -0.3])
        idp = np.array([*project_point(anchor, point, OFFSET)[0], 1.0 / (2.6 - OFFSET[2])])
        m2, j_pose, j_anchor, j_idp = project_inverse_depth(pose, anchor, idp, OFFSET)
        np.testing.assert_allclose(m2, m, atol=1e-12)
        assert np.linalg.cond(j_idp[:, :2]) < 1.0 + 1e-9


def test_lamp_axis_pi_ambiguity() -> None:
    rng = np.random.default_rng(7)
    for _ in range(20):
        pose = np.array([*rng.uniform(-3, 3, 2), rng.uniform(-math.pi, math.pi)])
        phi = rng.uniform(-math.pi, math.pi)
        alpha = lamp_axis(pose, phi)[0]
        assert -math.pi / 2 < alpha <= math.pi / 2
        for measured in (alpha, alpha + math.pi, alpha - math.pi, alpha + 3 * math.pi):
            assert lamp_axis_residual(pose, phi, measured)[0] == pytest.approx(0.0, abs=1e-9)
        # the lamp itself is a line too: phi + pi predicts the same axis
        assert lamp_axis_residual(pose, phi + math.pi, alpha)[0] == pytest.approx(0.0, abs=1e-9)
        # near the wrap point the residual stays small
        r = lamp_axis_residual(pose, phi, alpha + math.pi / 2 - 0.01)[0]
        assert abs(r) == pytest.approx(math.pi / 2 - 0.01, abs=1e-9)


@pytest.mark.parametrize("seed", SEEDS)
def test_lamp_axis_jacobians(seed: int) -> None:
    rng = np.random.default_rng(seed)
    pose = gtsam.Pose2(*rng.uniform(-3, 3, 2), rng.uniform(-3, 3))
    phi = np.array([rng.uniform(-3, 3)])
    meas = lamp_axis(_arr(pose), float(phi[0]))[0] + 0.1

    def h(p: gtsam.Pose2, a: np.ndarray) -> np.ndarray:
        return np.array([lamp_axis_residual(_arr(p), float(a[0]), meas)[0]])

    _, r_D_pose, r_D_phi = lamp_axis_residual(_arr(pose), float(phi[0]), meas)
    alpha0, a_D_pose, a_D_phi = lamp_axis(_arr(pose), float(phi[0]))

    def g(p: gtsam.Pose2, a: np.ndarray) -> np.ndarray:  # no jump at the wrap point
        alpha = lamp_axis(_arr(p), float(a[0]))[0]
        return np.array([alpha0 + wrap_axis(alpha - alpha0)])

    np.testing.assert_allclose(a_D_pose, numericalDerivative21(g, pose, phi), atol=1e-6)
    np.testing.assert_allclose(a_D_phi, numericalDerivative22(g, pose, phi), atol=1e-6)
    np.testing.assert_allclose(r_D_pose, numericalDerivative21(h, pose, phi), atol=1e-6)
    np.testing.assert_allclose(r_D_phi, numericalDerivative22(h, pose, phi), atol=1e-6)


@pytest.mark.parametrize("seed", SEEDS)
def test_inverse_depth_projection_matches_point_and_jacobians(seed: int) -> None:
    rng = np.random.default_rng(seed)
    pose, point = _case(rng)
    anchor = gtsam.Pose2(
        pose.x() + rng.uniform(-1, 1), pose.y() + rng.uniform(-1, 1), rng.uniform(-3, 3)
    )
    idp = np.array([*project_point(_arr(anchor), point, OFFSET)[0], 1.0 / (point[2] - OFFSET[2])])
    m, m_D_pose, m_D_anchor, m_D_idp = project_inverse_depth(_arr(pose), _arr(anchor), idp, OFFSET)
    np.testing.assert_allclose(m, project_point(_arr(pose), point, OFFSET)[0], atol=1e-12)
    np.testing.assert_allclose(
        inverse_depth_to_point(_arr(anchor), idp, OFFSET)[0], point, atol=1e-12
    )
    # seen from the anchor itself it is alpha
    np.testing.assert_allclose(
        project_inverse_depth(_arr(anchor), _arr(anchor), idp, OFFSET)[0], idp[:2], atol=1e-12
    )

    def h(p: gtsam.Pose2, a: gtsam.Pose2, q: np.ndarray) -> np.ndarray:
        return project_inverse_depth(_arr(p), _arr(a), q, OFFSET)[0]

    np.testing.assert_allclose(m_D_pose, numericalDerivative31(h, pose, anchor, idp), atol=1e-6)
    np.testing.assert_allclose(m_D_anchor, numericalDerivative32(h, pose, anchor, idp), atol=1e-6)
    np.testing.assert_allclose(m_D_idp, numericalDerivative33(h, pose, anchor, idp), atol=1e-6)


def test_inverse_depth_far_point_is_finite() -> None:
    m, j_pose, j_anchor, j_idp = project_inverse_depth(
        np.array([1.0, 0.0, 0.2]), np.zeros(3), np.array([0.3, -0.1, 0.0]), OFFSET
    )
    assert np.all(np.isfinite(np.hstack([j_pose, j_anchor, j_idp])))
    # a point at infinity only rotates with the robot
    np.testing.assert_allclose(
        m,
        np.array([[math.cos(0.2), math.sin(0.2)], [-math.sin(0.2), math.cos(0.2)]]) @ [0.3, -0.1],
        atol=1e-12,
    )
    with pytest.raises(FactorError, match="rho"):
        inverse_depth_to_point(np.zeros(3), np.array([0.1, 0.1, 0.0]), OFFSET)


@pytest.mark.parametrize("seed", SEEDS)
def test_inverse_depth_to_point_jacobians(seed: int) -> None:
    rng = np.random.default_rng(seed)
    anchor = gtsam.Pose2(*rng.uniform(-3, 3, 2), rng.uniform(-3, 3))
    idp = np.array([*rng.uniform(-0.8, 0.8, 2), rng.uniform(0.2, 2.0)])
    _, p_D_anchor, p_D_idp = inverse_depth_to_point(_arr(anchor), idp, OFFSET)

    def h(a: gtsam.Pose2, q: np.ndarray) -> np.ndarray:
        return inverse_depth_to_point(_arr(a), q, OFFSET)[0]

    np.testing.assert_allclose(p_D_anchor, numericalDerivative21(h, anchor, idp), atol=1e-6)
    np.testing.assert_allclose(p_D_idp, numericalDerivative22(h, anchor, idp), atol=1e-6)


@pytest.mark.parametrize("seed", SEEDS)
def test_init_point_from_observation(seed: int) -> None:
    rng = np.random.default_rng(seed)
    pose, point = _case(rng)
    m = project_point(_arr(pose), point, OFFSET)[0]
    h_true = point[2] - OFFSET[2]
    p, p_D_pose, p_D_m, p_D_h = init_point_from_observation(_arr(pose), m, h_true, OFFSET)
    np.testing.assert_allclose(p, point, atol=1e-12)  # right height -> the true point
    hh = np.array([h_true])

    def f_pose(x: gtsam.Pose2) -> np.ndarray:
        return init_point_from_observation(_arr(x), m, h_true, OFFSET)[0]

    def f_mh(mm: np.ndarray, h: np.ndarray) -> np.ndarray:
        return init_point_from_observation(_arr(pose), mm, float(h[0]), OFFSET)[0]

    np.testing.assert_allclose(p_D_pose, numericalDerivative11(f_pose, pose), atol=1e-6)
    np.testing.assert_allclose(p_D_m, numericalDerivative21(f_mh, m, hh), atol=1e-6)
    np.testing.assert_allclose(p_D_h, numericalDerivative22(f_mh, m, hh), atol=1e-6)
    # every height along the ray projects back onto m
    for h in (0.5, 2.0, 5.0):
        q = init_point_from_observation(_arr(pose), m, h, OFFSET)[0]
        np.testing.assert_allclose(project_point(_arr(pose), q, OFFSET)[0], m, atol=1e-12)


def test_height_prior_encodes_range() -> None:
    prior = HeightPrior()
    assert prior.height_mean - 2 * prior.height_sigma == pytest.approx(0.5)
    assert prior.height_mean + 2 * prior.height_sigma == pytest.approx(5.0)
    assert prior.rho_mean == pytest.approx(1 / prior.height_mean)
    assert prior.rho_mean + 2 * prior.rho_sigma == pytest.approx(1 / 0.5)
    assert prior.rho_mean - 2 * prior.rho_sigma < 1 / 5.0  # far points, even infinity
    np.testing.assert_allclose(
        init_inverse_depth(np.array([0.1, 0.2]), prior), [0.1, 0.2, prior.rho_mean]
    )
    with pytest.raises(FactorError):
        HeightPrior(h_min=3.0, h_max=2.0)


def test_inverse_depth_batch_matches_single() -> None:
    rng = np.random.default_rng(17)
    pose = np.array([0.5, -1.0, 0.7])
    anchors = np.column_stack([rng.uniform(-2, 2, (6, 2)), rng.uniform(-3, 3, 6)])
    idps = np.column_stack([rng.uniform(-0.8, 0.8, (6, 2)), rng.uniform(0.0, 2.0, 6)])
    batch = project_inverse_depth_batch(pose, anchors, idps, OFFSET)
    for i in range(6):
        single = project_inverse_depth(pose, anchors[i], idps[i], OFFSET)
        for b, s in zip(batch, single, strict=True):
            np.testing.assert_allclose(b[i], s, atol=1e-12)
