"""GTSAM adapters: built-in parity, custom factors' linearize() vs numerical, small solves."""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import gtsam
import numpy as np
import pytest
from gtsam.symbol_shorthand import A, C, L, X
from gtsam.utils.numerical_derivative import numericalDerivative11

from lampsam.factors.axis_factors import (
    AxisObservation,
    axis_anchor_prior,
    lamp_axis_between_factor,
    lamp_axis_factor,
    lamp_axis_frame_factor,
)
from lampsam.factors.ceiling import HeightPrior, project_inverse_depth, project_point
from lampsam.factors.geometry import FactorError, wrap_angle
from lampsam.factors.gtsam_factors import (
    bearing_range_factor,
    height_prior_factor,
    huber_sqrt,
    odometry_factor,
    projection_factor,
)
from lampsam.factors.inverse_depth_factors import (
    InverseDepthObservation,
    inverse_depth_factor,
    inverse_depth_first_sight_prior,
    inverse_depth_frame_factor,
)
from lampsam.factors.motion import accumulate_odometry

SEEDS = [0, 1, 2, 3, 4]
OFFSET = np.array([0.12, -0.03, 0.35])
COV_M = np.array([[4e-5, 1e-5], [1e-5, 2.5e-5]])


def _arr(p: gtsam.Pose2) -> np.ndarray:
    return np.array([p.x(), p.y(), p.theta()])


def _get(values: gtsam.Values, key: int) -> Any:
    """The value at ``key`` as the object numerical_derivative retracts."""
    chars = chr(gtsam.Symbol(key).chr())
    if chars == "x":
        return values.atPose2(key)
    if chars == "a":
        return values.atRot2(key)
    return values.atVector(key)


def _replaced(values: gtsam.Values, key: int, value: Any) -> gtsam.Values:
    out = gtsam.Values(values)
    out.erase(key)
    if isinstance(value, gtsam.Pose2):
        out.insert(key, value)
    elif isinstance(value, gtsam.Rot2):
        out.insert(key, value)
    else:
        out.insert(key, np.asarray(value, dtype=float))
    return out


def _check_linearize(
    factor: gtsam.NonlinearFactor,
    values: gtsam.Values,
    residual: Callable[[gtsam.Values], np.ndarray] | None = None,
) -> None:
    """linearize()'s A blocks equal numerical derivatives of the whitened error.

    ``b = -whitened error`` too. ``residual`` defaults to ``factor.whitenedError``.
    """
    res = residual or factor.whitenedError
    lin = factor.linearize(values)
    a_full, b = lin.jacobian()
    np.testing.assert_allclose(b, -res(values), atol=1e-9)
    col = 0
    for key in factor.keys():
        x0 = _get(values, key)
        num = numericalDerivative11(lambda x, k=key: res(_replaced(values, k, x)), x0)
        dim = num.shape[1]
        np.testing.assert_allclose(a_full[:, col : col + dim], num, atol=1e-6, rtol=1e-6)
        col += dim
    assert col == a_full.shape[1]


def _random_pose(rng: np.random.Generator) -> gtsam.Pose2:
    return gtsam.Pose2(*rng.uniform(-3.0, 3.0, 2), rng.uniform(-3.0, 3.0))


# --- built-in parity ------------------------------------------------------------------


@pytest.mark.parametrize("seed", SEEDS)
def test_projection_builtin_matches_project_point(seed: int) -> None:
    rng = np.random.default_rng(seed)
    pose = _random_pose(rng)
    point = np.array(
        [pose.x() + rng.uniform(-2, 2), pose.y() + rng.uniform(-2, 2), rng.uniform(1.5, 3.0)]
    )
    m, m_D_pose, m_D_point = project_point(_arr(pose), point, OFFSET)
    meas = m + rng.normal(0.0, 0.01, 2)
    factor = projection_factor(X(0), L(0), meas, np.eye(2), OFFSET)
    values = gtsam.Values()
    values.insert(X(0), pose)
    values.insert(L(0), point)
    np.testing.assert_allclose(factor.unwhitenedError(values), m - meas, atol=1e-12)
    a_full, b = factor.linearize(values).jacobian()
    np.testing.assert_allclose(a_full, np.hstack([m_D_pose, m_D_point]), atol=1e-9)
    np.testing.assert_allclose(b, meas - m, atol=1e-12)


def test_projection_matches_real_pixel_convention() -> None:
    """The real mounting (image right = robot left) gives the DESIGN sec. 6 figure."""
    f, cx, cy = 200.0, 160.0, 120.0
    body_r_camera = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    off = np.array([0.1, 0.0, 0.3])
    pose = np.array([2.0, 1.0, 0.0])
    point = np.array([2.0 + 0.1 + 1.0, 1.0 + 0.5, 0.3 + 2.5])  # 1 m ahead, 0.5 m left
    m = project_point(pose, point, off)[0]
    real = gtsam.PlanarProjectionFactor2(
        X(0),
        L(0),
        np.zeros(2),
        gtsam.Pose3(gtsam.Rot3(body_r_camera), off),
        gtsam.Cal3DS2(f, f, 0.0, cx, cy, 0.0, 0.0, 0.0, 0.0),
        gtsam.noiseModel.Unit.Create(2),
    )
    values = gtsam.Values()
    values.insert(X(0), gtsam.Pose2(*pose))
    values.insert(L(0), point)
    px = real.unwhitenedError(values)
    # (x_n, y_n) = (v, -u): column = cx + f v, row = cy - f u
    np.testing.assert_allclose(px, [cx + f * m[1], cy - f * m[0]], atol=1e-9)
    np.testing.assert_allclose(px - [cx, cy], [40.0, -80.0], atol=1e-9)
    # DESIGN sec. 6's "(+80, +40) px with f = 200" is the camera with body axes
    # (u, v scaled by f), i.e. the virtual camera of projection_factor.
    np.testing.assert_allclose(200.0 * m, [80.0, 40.0], atol=1e-9)


@pytest.mark.parametrize("seed", SEEDS)
def test_bearing_range_builtin_and_offset_custom(seed: int) -> None:
    rng = np.random.default_rng(seed)
    pose = _random_pose(rng)
    lm = rng.uniform(-5.0, 5.0, 2)
    cov = np.diag([0.01**2, 0.05**2])
    values = gtsam.Values()
    values.insert(X(0), pose)
    values.insert(L(0), lm)
    meas = np.array([pose.bearing(lm).theta() + 0.02, pose.range(lm) - 0.1])
    builtin = bearing_range_factor(X(0), L(0), meas[0], meas[1], cov)
    # residual = predicted - measured, [bearing, range]
    np.testing.assert_allclose(builtin.unwhitenedError(values), [-0.02, 0.1], atol=1e-9)
    off = np.array([0.2, 0.1, 0.4])
    sensor = pose.compose(gtsam.Pose2(*off))
    custom = bearing_range_factor(X(0), L(0), meas[0], meas[1], cov, body_T_sensor=off)
    expect = np.array(
        [wrap_angle(sensor.bearing(lm).theta() - meas[0]), sensor.range(lm) - meas[1]]
    )
    np.testing.assert_allclose(custom.unwhitenedError(values), expect, atol=1e-9)

    def get_point(v: gtsam.Values) -> np.ndarray:
        return custom.whitenedError(v)

    lin = custom.linearize(values)
    a_full, _ = lin.jacobian()
    num_pose = numericalDerivative11(lambda p: get_point(_replaced(values, X(0), p)), pose)
    num_lm = numericalDerivative11(lambda q: get_point(_replaced(values, L(0), q)), lm)
    np.testing.assert_allclose(a_full, np.hstack([num_pose, num_lm]), atol=1e-6)


def test_odometry_factor_is_zero_at_truth_and_uses_cov() -> None:
    delta, cov = accumulate_odometry(np.full(5, 0.05), np.full(5, 0.06), 0.33, 1e-3, 1e-3)
    factor = odometry_factor(X(0), X(1), delta, cov)
    values = gtsam.Values()
    values.insert(X(0), gtsam.Pose2(1.0, 2.0, 0.3))
    values.insert(X(1), gtsam.Pose2(1.0, 2.0, 0.3).compose(gtsam.Pose2(*delta)))
    assert factor.error(values) == pytest.approx(0.0, abs=1e-18)
    info = np.linalg.inv(cov)
    # a tangent step d at the end pose costs 0.5 d^T info d
    d = np.array([0.01, -0.02, 0.005])
    values.update(X(1), values.atPose2(X(1)).retract(d))
    assert factor.error(values) == pytest.approx(0.5 * d @ info @ d, rel=1e-3)
    with pytest.raises(FactorError, match="positive definite"):
        odometry_factor(X(0), X(1), delta, np.zeros((3, 3)))


def test_height_prior_factor() -> None:
    prior = HeightPrior()
    factor = height_prior_factor(C(0), np.array([1.0, 2.0]), OFFSET, prior)
    values = gtsam.Values()
    z0 = OFFSET[2] + prior.height_mean
    values.insert(C(0), np.array([5.0, -3.0, z0 + prior.height_sigma]))
    # 1 sigma in z -> error 0.5; x/y 4-5 m off weigh < 1e-4
    assert factor.error(values) == pytest.approx(0.5, abs=1e-4)


# --- custom factors: linearize() vs numerical ------------------------------------------


@pytest.mark.parametrize("seed", SEEDS)
@pytest.mark.parametrize("robust", [None, 1.0])
def test_lamp_axis_factors_linearize(seed: int, robust: float | None) -> None:
    rng = np.random.default_rng(seed)
    values = gtsam.Values()
    values.insert(X(0), _random_pose(rng))
    obs = []
    for j in range(3):
        values.insert(A(j), gtsam.Rot2(rng.uniform(-3, 3)))
        obs.append(AxisObservation(A(j), rng.uniform(-3, 3), rng.uniform(0.02, 0.1)))
    single = lamp_axis_factor(X(0), A(0), obs[0].alpha, obs[0].sigma)
    _check_linearize(single, values)
    frame = lamp_axis_frame_factor(X(0), obs, robust=robust)
    _check_linearize(frame, values)
    # same cost as the per-observation factors (Huber per observation when robust)
    graph = gtsam.NonlinearFactorGraph()
    for o in obs:
        graph.add(lamp_axis_factor(X(0), o.axis_key, o.alpha, o.sigma, robust=robust))
    assert frame.error(values) == pytest.approx(graph.error(values), rel=1e-9)


@pytest.mark.parametrize("seed", SEEDS)
@pytest.mark.parametrize("robust", [None, 1.0])
def test_lamp_axis_between_factor_equals_custom(seed: int, robust: float | None) -> None:
    """The built-in Pose2 form has the custom factor's error and whitened Jacobian row.

    ``A(j)`` as a ``Pose2``: its angle row must match the ``Rot2`` custom factor (itself
    checked against numerical derivatives above); its ``x, y`` rows must be zero, and
    the anchor prior must carry nothing on the angle. The measurement is given with a
    random representative mod pi and a prediction off by up to 1 rad.
    """
    rng = np.random.default_rng(seed)
    pose = _random_pose(rng)
    phi = rng.uniform(-3, 3)
    sigma = rng.uniform(0.02, 0.1)
    r_true = rng.normal(0.0, 3 * sigma)  # residual phi - theta - alpha, mod pi
    alpha = phi - pose.theta() - r_true + math.pi * rng.integers(-3, 4)
    predicted = phi - pose.theta() + rng.uniform(-1.0, 1.0)
    custom = lamp_axis_factor(X(0), A(0), alpha, sigma, robust=robust)
    between = lamp_axis_between_factor(X(0), A(0), alpha, sigma, predicted, robust=robust)
    v_rot = gtsam.Values()
    v_rot.insert(X(0), pose)
    v_rot.insert(A(0), gtsam.Rot2(phi))
    xy = rng.uniform(-5, 5, 2)
    v_pose = gtsam.Values()
    v_pose.insert(X(0), pose)
    v_pose.insert(A(0), gtsam.Pose2(xy[0], xy[1], phi))
    assert between.error(v_pose) == pytest.approx(custom.error(v_rot), rel=1e-9, abs=1e-12)
    a_c, b_c = custom.linearize(v_rot).jacobian()
    a_b, b_b = between.linearize(v_pose).jacobian()
    assert a_b.shape == (3, 6)
    np.testing.assert_allclose(a_b[:2], 0.0, atol=1e-12)  # x, y rows carry nothing
    np.testing.assert_allclose(b_b[:2], 0.0, atol=1e-12)
    np.testing.assert_allclose(a_b[2, :3], a_c[0, :3], rtol=1e-9, atol=1e-9)  # pose
    np.testing.assert_allclose(a_b[2, 3:5], 0.0, atol=1e-12)  # A's translation
    np.testing.assert_allclose(a_b[2, 5], a_c[0, 3], rtol=1e-9)  # A's angle
    np.testing.assert_allclose(abs(b_b[2]), abs(b_c[0]), rtol=1e-9, atol=1e-12)
    anchor = axis_anchor_prior(A(0), xy, phi + 0.3)
    assert anchor.error(v_pose) == pytest.approx(0.0, abs=1e-20)
    a_p, _ = anchor.linearize(v_pose).jacobian()
    np.testing.assert_allclose(a_p[:, 2], 0.0, atol=1e-12)  # no information on the axis
    np.testing.assert_allclose(a_p[2], 0.0, atol=1e-12)


def test_lamp_axis_between_factor_rejects_bad_sigma() -> None:
    with pytest.raises(FactorError, match="sigma"):
        lamp_axis_between_factor(X(0), A(0), 0.1, 0.0, 0.1)


@pytest.mark.parametrize("seed", SEEDS)
@pytest.mark.parametrize("robust", [None, 1.5])
def test_inverse_depth_factors_linearize(seed: int, robust: float | None) -> None:
    rng = np.random.default_rng(seed)
    values = gtsam.Values()
    pose = _random_pose(rng)
    values.insert(X(0), pose)
    values.insert(X(1), gtsam.Pose2(pose.x() + 0.5, pose.y() - 0.3, pose.theta() + 0.4))
    values.insert(X(2), gtsam.Pose2(pose.x() - 0.4, pose.y() + 0.2, pose.theta() - 0.2))
    obs = []
    for j, anchor in enumerate([X(1), X(2), X(1)]):  # X(1) anchors two corners
        idp = np.array([*rng.uniform(-0.5, 0.5, 2), rng.uniform(0.3, 1.0)])
        values.insert(C(j), idp)
        m = project_inverse_depth(_arr(pose), _arr(values.atPose2(anchor)), idp, OFFSET)[0]
        obs.append(InverseDepthObservation(anchor, C(j), m + rng.normal(0, 0.02, 2), COV_M))
    single = inverse_depth_factor(X(0), obs[0].anchor_key, C(0), obs[0].m, COV_M, OFFSET)
    np.testing.assert_allclose(
        single.unwhitenedError(values),
        project_inverse_depth(
            _arr(pose), _arr(values.atPose2(X(1))), values.atVector(C(0)), OFFSET
        )[0]
        - obs[0].m,
        atol=1e-12,
    )
    _check_linearize(single, values)
    frame = inverse_depth_frame_factor(X(0), obs, OFFSET, robust=robust)
    assert len(frame.keys()) == 1 + 2 + 3  # pose, two distinct anchors, three corners
    _check_linearize(frame, values)
    graph = gtsam.NonlinearFactorGraph()
    for o in obs:
        graph.add(
            inverse_depth_factor(
                X(0), o.anchor_key, o.corner_key, o.m, COV_M, OFFSET, robust=robust
            )
        )
    # per-observation Huber inside the frame factor = GTSAM's Robust model per factor
    assert frame.error(values) == pytest.approx(graph.error(values), rel=1e-9)
    with pytest.raises(FactorError, match="anchor"):
        inverse_depth_factor(X(1), X(1), C(0), obs[0].m, COV_M, OFFSET)


def test_huber_sqrt_cost_and_jacobian() -> None:
    rng = np.random.default_rng(3)
    k = 1.2
    for _ in range(5):
        e = rng.normal(0.0, 3.0, 2)
        r, r_D_e = huber_sqrt(e, k)
        n = np.linalg.norm(e)
        rho = 0.5 * n * n if n <= k else k * n - 0.5 * k * k
        assert 0.5 * r @ r == pytest.approx(rho, rel=1e-12)
        num = numericalDerivative11(lambda x: huber_sqrt(x, k)[0], e)
        np.testing.assert_allclose(r_D_e, num, atol=1e-6)


# --- small solves ---------------------------------------------------------------------


def test_lamps_and_inverse_depth_corners_solve_to_truth() -> None:
    """A short drive under 4 lamps (2 oriented) and 6 corners: LM recovers the truth.

    Noise-free measurements, perturbed start: every pose within 1 mm and every lamp
    axis within 1 mrad of the truth after LM.
    """
    rng = np.random.default_rng(42)
    wheel_base, k = 0.33, 1e-4
    lamps = np.array([[1.0, 0.3, 2.6], [2.0, -0.4, 2.6], [3.0, 0.2, 2.7], [1.5, -0.2, 2.7]])
    phis = [0.3, None, -1.2, None]
    corners = np.column_stack(
        [rng.uniform(0.5, 3.5, 6), rng.uniform(-0.8, 0.8, 6), np.full(6, 2.8)]
    )
    graph = gtsam.NonlinearFactorGraph()
    initial = gtsam.Values()
    truth = [np.zeros(3)]
    graph.add(
        gtsam.PriorFactorPose2(X(0), gtsam.Pose2(), gtsam.noiseModel.Isotropic.Sigma(3, 1e-6))
    )
    dl = np.full(10, 0.03)
    dr = np.full(10, 0.031)
    n_poses = 12
    for i in range(1, n_poses):
        delta, cov = accumulate_odometry(dl, dr, wheel_base, k, k)
        truth.append(_arr(gtsam.Pose2(*truth[-1]).compose(gtsam.Pose2(*delta))))
        graph.add(odometry_factor(X(i - 1), X(i), delta, cov))
    for i, t in enumerate(truth):
        initial.insert(X(i), gtsam.Pose2(*t).retract(rng.normal(0, 0.02, 3)))
    sigma_m = 0.005
    cov_m = np.eye(2) * sigma_m**2
    anchors: dict[int, int] = {}
    for i, t in enumerate(truth):
        axis_obs = []
        for j, (lamp, phi) in enumerate(zip(lamps, phis, strict=True)):
            m = project_point(t, lamp, OFFSET)[0]
            if np.linalg.norm(m) > 1.5:
                continue
            graph.add(projection_factor(X(i), L(j), m, cov_m, OFFSET, robust=1.345))
            if phi is not None:
                axis_obs.append(AxisObservation(A(j), wrap_angle(phi - t[2]) + math.pi, 0.02))
        if axis_obs:
            graph.add(lamp_axis_frame_factor(X(i), axis_obs))
        corner_obs = []
        for j, corner in enumerate(corners):
            m = project_point(t, corner, OFFSET)[0]
            if np.linalg.norm(m) > 1.5:
                continue
            if j not in anchors:
                anchors[j] = i
                graph.add(inverse_depth_first_sight_prior(C(j), m, cov_m))
                initial.insert(C(j), np.array([m[0], m[1], HeightPrior().rho_mean]))
            else:
                corner_obs.append(InverseDepthObservation(X(anchors[j]), C(j), m, cov_m))
        if corner_obs:
            graph.add(inverse_depth_frame_factor(X(i), corner_obs, OFFSET))
    for j, (lamp, phi) in enumerate(zip(lamps, phis, strict=True)):
        initial.insert(L(j), lamp + rng.normal(0, 0.05, 3))
        if phi is not None:
            initial.insert(A(j), gtsam.Rot2(phi + 0.1))
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(100)
    params.setRelativeErrorTol(1e-12)
    params.setAbsoluteErrorTol(1e-12)
    result = gtsam.LevenbergMarquardtOptimizer(graph, initial, params).optimize()
    assert len(anchors) >= 4
    for i, t in enumerate(truth):
        est = result.atPose2(X(i))
        assert np.linalg.norm([est.x() - t[0], est.y() - t[1]]) < 1e-3
        assert abs(wrap_angle(est.theta() - t[2])) < 1e-3
    for j, phi in enumerate(phis):
        if phi is not None:
            err = wrap_angle(2 * (result.atRot2(A(j)).theta() - phi)) / 2
            assert abs(err) < 1e-3
    for j in anchors:
        idp = result.atVector(C(j))
        assert 1.0 / idp[2] == pytest.approx(corners[j][2] - OFFSET[2], abs=1e-2)


def test_positive_definite_matches_eigenvalues() -> None:
    """The closed-form Sylvester test agrees with eigvalsh on random 1x1..4x4 matrices."""
    from lampsam.factors.gtsam_factors import _positive_definite

    rng = np.random.default_rng(11)
    for d in (1, 2, 3, 4):
        for _ in range(300):
            a = rng.normal(size=(d, d))
            s = a @ a.T - rng.uniform(0.0, 2.0) * np.eye(d)
            lam = np.linalg.eigvalsh(s)[0]
            if abs(lam) < 1e-9:  # too close to call in floating point
                continue
            assert _positive_definite(s) == (lam > 0.0)
    with pytest.raises(FactorError, match="positive definite"):
        projection_factor(X(0), L(0), np.zeros(2), np.array([[1.0, 2.0], [2.0, 1.0]]),
                          np.array([0.0, 0.0, 0.3]))
    with pytest.raises(FactorError, match="finite"):
        projection_factor(X(0), L(0), np.zeros(2), np.array([[np.nan, 0.0], [0.0, 1.0]]),
                          np.array([0.0, 0.0, 0.3]))
