"""Thin GTSAM adapters over the pure models (DESIGN sec. 4 and 6).

Variables (keys from ``gtsam.symbol_shorthand``):

* ``X(k)`` -- robot pose, ``gtsam.Pose2``.
* ``L(j)`` -- lamp position, ``Point3`` (numpy (3,)) in the world, ``z`` above the floor.
* ``A(j)`` -- lamp long axis: angle ``phi`` in the world, used mod pi; a ``gtsam.Pose2``
  with an information-free translation for :func:`lamp_axis_between_factor` (the
  smoothers), a ``gtsam.Rot2`` for the custom-factor forms.
  A separate variable so that the same lamp can be oriented or not: a round lamp, or
  a frame in which the lamp's ratio falls below the threshold, simply gets no axis
  factor (paper III.4), and ``A(j)`` exists only once an axis has been seen.
* ``C(j)`` -- corner, either inverse depth ``(alpha_x, alpha_y, rho)`` (numpy (3,),
  anchored at a pose key) or a ``Point3``; one parametrisation per run.
* range-bearing landmarks: ``L(j)`` as ``Point2``.

Factors, and which implementation each uses (the faster where a built-in exists):

==========================  ====================================================
odometry                    ``BetweenFactorPose2`` (built-in), covariance from
                            :func:`lampsam.factors.motion.accumulate_odometry`
lamp / corner position      ``PlanarProjectionFactor2`` (built-in C++), in
                            normalised coordinates: identity calibration and a
                            virtual camera with body axes; equals
                            :func:`lampsam.factors.ceiling.project_point`
lamp axis                   ``BetweenFactorPose2`` (built-in) on ``(X, A)`` with
                            ``A`` a ``Pose2`` whose translation has zero precision
                            (:func:`lamp_axis_between_factor`, used by the
                            smoothers); ``CustomFactor`` on ``(X, A)`` with ``A`` a
                            ``Rot2``, per observation or per frame
                            (:func:`lamp_axis_frame_factor`), kept as the reference
corner, inverse depth       ``CustomFactor`` on ``(X(k), X(anchor), C)``; per
                            observation or one per frame; the first sight and the
                            height prior are one built-in ``PriorFactorVector``
corner, Point3              ``PlanarProjectionFactor2`` + :func:`height_prior_factor`
                            (``PriorFactorPoint3`` with loose x/y sigmas)
range-bearing               ``BearingRangeFactor2D`` (built-in); a sensor offset
                            gives a ``CustomFactor``
==========================  ====================================================

Every adapter takes ``robust: float | None``: ``None`` = Gaussian, a float ``k`` =
Huber with threshold ``k`` (in sigmas) on the whitened residual of each observation.
For the per-frame factors GTSAM's robust model would weight the whole frame by one
weight, so they apply Huber per observation inside the callback, as an exact
square-root loss: ``r' = sign(e) sqrt(2 rho(e))`` (so ``0.5 r'^2`` is the Huber cost and
LM's error bookkeeping stays exact).

Measured cost (``scripts/bench/bench_factors.py``; gtsam 4.3.0; 2,000 poses, 264
landmarks, 10,000 observations; 2-core machine shared with about 8 other jobs, so
absolute times are inflated; median of 3)::

    case                                        linearize     LM, 2 iterations
    position, built-in PlanarProjectionFactor2     97 ms          0.46 s   (ref)
    position, CustomFactor(project_point)         889 ms  9.2x   53.6  s   117x
    inverse-depth corner, CustomFactor per obs    986 ms         96.8  s   (ref)
    inverse-depth corner, CustomFactor per frame  1.1-3.8 s      38.4  s   0.40x
    lamp axis, CustomFactor per obs              1889 ms         89.4  s   (ref)
    lamp axis, CustomFactor per frame             808 ms 0.43x   25.4  s   0.28x

Re-measured later on an idle machine, same case (``--cases axis``): lamp axis per
observation 282 ms / 17.2 s, per frame 133 ms / 4.0 s, and the built-in
``BetweenFactorPose2`` form (:func:`lamp_axis_between_factor`) 15 ms / 0.11 s.

``linearize`` is ``graph.linearize(values)`` called from Python on its own ``Values``
(no copy); inside an optimizer every callback gets a copy of the whole ``Values``,
which is what makes custom factors 100x dearer there. Hence:

* positions (lamps, Cartesian corners): always the built-in;
* lamp axes: the built-in ``BetweenFactorPose2`` form in the smoothers;
* inverse-depth corners (and the custom axis forms): the **per-frame** factors when a GTSAM
  optimizer (LM, iSAM2) evaluates them (2.5-3.6x faster); from a Python-driven loop
  the two are about equal (the inverse-depth frame factor's re-run alone: 1.1-1.5 s);
* corners in the smoothers: ``Point3`` + built-in projection + :func:`height_prior_factor`
  is recommended. Bench case 4 (LM to convergence from dead reckoning, noisy
  odometry and ``sigma_m = 0.003``): at 2,000 poses, Point3 6.3 s (27 iterations)
  vs inverse depth 55 s (5 iterations), the same pose RMS (6.61 cm, dead reckoning
  315 cm) and the same median corner height error (0.83 cm); the badly observed
  corners (little parallax) end worse with inverse depth (height RMS 39 cm, max
  3.9 m vs 17 cm, max 1.2 m) because its prior on ``rho`` is weaker in metres
  than the Gaussian on ``h``. At 300 poses: 0.1-0.2 s vs 3.6-7 s, same errors.
  Inverse depth stays available (no cheirality failure, well defined for far
  points, fewer iterations); the EKF uses the paper's undelayed Cartesian
  initialisation.

Caveat: ``PlanarProjectionFactor2`` throws ``CheiralityException`` (a ``RuntimeError``
in Python) if a point falls below the camera during optimisation; inverse-depth
corners cannot.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from functools import lru_cache
from typing import Any

import gtsam
import numpy as np

from lampsam.arrays import FloatArray
from lampsam.factors.ceiling import (
    HeightPrior,
    lamp_axis_residual,
    project_inverse_depth,
    project_inverse_depth_batch,
)
from lampsam.factors.geometry import FactorError, wrap_angle
from lampsam.factors.range_bearing import range_bearing

__all__ = [
    "AxisObservation",
    "InverseDepthObservation",
    "axis_anchor_prior",
    "bearing_range_factor",
    "height_prior_factor",
    "huber_sqrt",
    "inverse_depth_factor",
    "inverse_depth_first_sight_prior",
    "inverse_depth_frame_factor",
    "lamp_axis_between_factor",
    "lamp_axis_factor",
    "lamp_axis_frame_factor",
    "noise_model",
    "odometry_factor",
    "projection_factor",
    "virtual_camera",
]

#: x/y sigma (metres) of :func:`height_prior_factor`: loose enough to carry no
#: information on the horizontal position (information 1e-6 per m^2).
LOOSE_SIGMA = 1.0e3


def _pose(values: gtsam.Values, key: int) -> FloatArray:
    """(3,) ``(x, y, theta)`` of the ``Pose2`` stored under ``key``."""
    p = values.atPose2(key)
    return np.array([p.x(), p.y(), p.theta()])


def _positive_definite(sym: FloatArray) -> bool:
    """Whether a symmetric (d, d) matrix is positive definite.

    Sylvester's criterion (leading principal minors) in closed form for d <= 3,
    which every measurement here has; an eigenvalue test otherwise. About 20x
    cheaper than ``eigvalsh`` on 2x2 blocks, and this runs once per factor.
    """
    d = sym.shape[0]
    if d > 3:
        return bool(np.linalg.eigvalsh(sym)[0] > 0.0)
    a = sym.tolist()
    if not a[0][0] > 0.0:
        return False
    if d == 1:
        return True
    m2 = a[0][0] * a[1][1] - a[0][1] * a[1][0]
    if not m2 > 0.0:
        return False
    if d == 2:
        return True
    m3 = (a[0][0] * (a[1][1] * a[2][2] - a[1][2] * a[2][1])
          - a[0][1] * (a[1][0] * a[2][2] - a[1][2] * a[2][0])
          + a[0][2] * (a[1][0] * a[2][1] - a[1][1] * a[2][0]))
    return m3 > 0.0


def _check_cov(cov: FloatArray, dim: int, what: str) -> FloatArray:
    """``cov`` as a (dim, dim) float array; FactorError unless finite and positive definite."""
    arr = np.asarray(cov, dtype=float)
    if arr.shape != (dim, dim) or not np.isfinite(arr).all():
        raise FactorError(f"{what}: covariance must be a finite ({dim}, {dim}) array")
    if not _positive_definite(0.5 * (arr + arr.T)):
        raise FactorError(f"{what}: covariance is not positive definite")
    return arr


def _robust_wrap(base: gtsam.noiseModel.Base, robust: float | None) -> gtsam.noiseModel.Base:
    if robust is None:
        return base
    if not robust > 0.0:
        raise FactorError(f"Huber threshold must be > 0, got {robust}")
    return gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Huber.Create(robust), base)


def noise_model(cov: FloatArray, robust: float | None = None) -> gtsam.noiseModel.Base:
    """Gaussian noise model from a covariance, optionally wrapped in Huber.

    Args:
        cov: (d, d) covariance of the measurement, symmetric positive definite.
        robust: None for Gaussian; ``k > 0`` for a Huber kernel with threshold ``k``
            on the whitened residual norm (``k = 1.345`` is the usual 95 % efficiency).

    Returns:
        A ``gtsam.noiseModel`` (``Gaussian`` or ``Robust``).
    """
    return _robust_wrap(gtsam.noiseModel.Gaussian.Covariance(np.asarray(cov, dtype=float)), robust)


def huber_sqrt(e: FloatArray, k: float) -> tuple[FloatArray, FloatArray]:
    """Square-root Huber residual of a whitened residual block, and its derivative.

    For ``n = |e|``: ``rho(n) = n^2/2`` if ``n <= k`` else ``k n - k^2/2``; returns
    ``r' = e * s`` with ``s = sqrt(2 rho(n)) / n`` so that ``|r'|^2 / 2 = rho(n)``, and
    ``dr'/de`` (d, d).

    Args:
        e: (d,) whitened residual.
        k: Huber threshold (> 0).

    Returns:
        r: (d,) scaled residual.
        r_D_e: (d, d) Jacobian.
    """
    n = float(np.linalg.norm(e))
    if n <= k:
        return e, np.eye(e.shape[0])
    g = math.sqrt(2.0 * k * n - k * k)  # = |r'|
    s = g / n
    u = e / n
    # d(s e)/de = s I + e (ds/dn) u^T,  ds/dn = (k/g - s)/n
    ds_dn = (k / g - s) / n
    return s * e, s * np.eye(e.shape[0]) + ds_dn * np.outer(e, u)


# --- odometry -------------------------------------------------------------------------


def odometry_factor(
    key_from: int,
    key_to: int,
    delta: FloatArray,
    cov: FloatArray,
    robust: float | None = None,
) -> gtsam.BetweenFactorPose2:
    """Odometry between two poses (paper eqs. 13-15 propagated, built-in factor).

    Args:
        key_from: key of the start pose ``X(i)``.
        key_to: key of the end pose ``X(j)``.
        delta: (3,) ``start_T_end`` from :func:`lampsam.factors.motion.accumulate_odometry`.
        cov: (3, 3) its tangent covariance (same function; floored, never singular).
        robust: optional Huber threshold.

    Returns:
        ``gtsam.BetweenFactorPose2``.
    """
    cov = _check_cov(cov, 3, "odometry")
    return gtsam.BetweenFactorPose2(
        key_from, key_to, gtsam.Pose2(*np.asarray(delta, dtype=float)), noise_model(cov, robust)
    )


# --- positions: built-in projection ---------------------------------------------------


@lru_cache(maxsize=64)
def _virtual_camera(x_off: float, y_off: float, z_cam: float) -> tuple[gtsam.Pose3, gtsam.Cal3DS2]:
    """Upward camera at body offset ``(x_off, y_off)`` and height ``z_cam`` (m) with unit intrinsics."""
    return (
        gtsam.Pose3(gtsam.Rot3(), np.array([x_off, y_off, z_cam])),
        gtsam.Cal3DS2(1.0, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0),
    )


def virtual_camera(body_t_camera: FloatArray) -> tuple[gtsam.Pose3, gtsam.Cal3DS2]:
    """Camera pose and calibration under which GTSAM's pixels ARE normalised ``m``.

    The virtual camera sits at ``body_t_camera`` with its axes equal to the body axes
    (x forward, y left, z up: right-handed, optical axis up) and an identity
    calibration without distortion, so ``PinholeCamera.project`` returns
    ``(b_x / b_z, b_y / b_z) = m`` (conventions.md). The real mounting rotation and
    lens distortion are removed by the frontend before the estimator sees ``m``.

    Args:
        body_t_camera: (3,) ``(x_off, y_off, z_cam)``, metres.

    Returns:
        ``(body_T_camera: gtsam.Pose3, calibration: gtsam.Cal3DS2)``.
    """
    return _virtual_camera(
        float(body_t_camera[0]), float(body_t_camera[1]), float(body_t_camera[2])
    )


def projection_factor(
    pose_key: int,
    point_key: int,
    m: FloatArray,
    cov_m: FloatArray,
    body_t_camera: FloatArray,
    robust: float | None = None,
) -> gtsam.PlanarProjectionFactor2:
    """Lamp or corner position seen by the upward camera (built-in C++ factor).

    Same model as :func:`lampsam.factors.ceiling.project_point` (a test checks values
    and Jacobians). Residual = predicted - measured, in normalised units.

    Args:
        pose_key: ``X(k)``.
        point_key: ``L(j)`` or ``C(j)`` holding a world ``Point3``.
        m: (2,) measured normalised ceiling coordinates.
        cov_m: (2, 2) covariance of ``m``.
        body_t_camera: (3,) camera offset, metres.
        robust: optional Huber threshold.

    Returns:
        ``gtsam.PlanarProjectionFactor2``.
    """
    cov_m = _check_cov(cov_m, 2, "projection")
    b_T_c, cal = virtual_camera(body_t_camera)
    return gtsam.PlanarProjectionFactor2(
        pose_key, point_key, np.asarray(m, dtype=float), b_T_c, cal, noise_model(cov_m, robust)
    )


def height_prior_factor(
    point_key: int,
    xy_guess: FloatArray,
    body_t_camera: FloatArray,
    prior: HeightPrior | None = None,
    robust: float | None = None,
) -> gtsam.PriorFactorPoint3:
    """The 0-5 m height prior on a Cartesian landmark (built-in ``PriorFactorPoint3``).

    Gaussian on ``z`` with mean ``z_cam + prior.height_mean`` and sigma
    ``prior.height_sigma``; ``x, y`` get sigma :data:`LOOSE_SIGMA` (no information).

    Args:
        point_key: the landmark's ``Point3`` key.
        xy_guess: (2,) any horizontal position (its weight is negligible).
        body_t_camera: (3,) camera offset; ``z_cam`` turns height above the camera
            into world ``z``.
        prior: height range, default :class:`HeightPrior` ().
        robust: optional Huber threshold (rarely useful on a prior; offered for
            uniformity).

    Returns:
        ``gtsam.PriorFactorPoint3``.
    """
    prior = prior or HeightPrior()
    mean = np.array([xy_guess[0], xy_guess[1], body_t_camera[2] + prior.height_mean])
    var = np.array([LOOSE_SIGMA, LOOSE_SIGMA, prior.height_sigma]) ** 2
    return gtsam.PriorFactorPoint3(point_key, mean, noise_model(np.diag(var), robust))


# --- lamp axis ------------------------------------------------------------------------


@dataclass(frozen=True)
class AxisObservation:
    """One lamp-axis observation for :func:`lamp_axis_frame_factor`.

    Attributes:
        axis_key: ``A(j)`` (a ``Rot2``).
        alpha: measured axis in the ``(u, v)`` plane, radians (mod pi).
        sigma: its standard deviation, radians.
    """

    axis_key: int
    alpha: float
    sigma: float


def lamp_axis_factor(
    pose_key: int,
    axis_key: int,
    alpha: float,
    sigma: float,
    robust: float | None = None,
) -> gtsam.CustomFactor:
    """Lamp axis observation (``phi_i = phi - theta`` mod pi), one ``CustomFactor``.

    Args:
        pose_key: ``X(k)``.
        axis_key: ``A(j)``, a ``gtsam.Rot2``.
        alpha: measured axis, radians, any representative mod pi.
        sigma: its standard deviation, radians (> 0).
        robust: optional Huber threshold.

    Returns:
        ``gtsam.CustomFactor`` with a 1-D residual wrapped to ``(-pi/2, pi/2]``.
    """
    if not sigma > 0.0:
        raise FactorError(f"axis sigma must be > 0, got {sigma}")
    meas = float(alpha)

    def error(this: gtsam.CustomFactor, values: gtsam.Values, H: Any) -> FloatArray:
        pose = _pose(values, this.keys()[0])
        phi = values.atRot2(this.keys()[1]).theta()
        r, r_D_pose, r_D_phi = lamp_axis_residual(pose, phi, meas)
        if H is not None:
            H[0] = r_D_pose
            H[1] = r_D_phi
        return np.array([r])

    return gtsam.CustomFactor(
        noise_model(np.array([[sigma * sigma]]), robust), [pose_key, axis_key], error
    )


def lamp_axis_frame_factor(
    pose_key: int,
    observations: Sequence[AxisObservation],
    robust: float | None = None,
) -> gtsam.CustomFactor:
    """All lamp-axis observations of one frame in one ``CustomFactor``.

    Residual ``i`` is ``wrap_axis(phi_i - theta - alpha_i) / sigma_i`` (whitened, unit
    noise model), Huber per observation if ``robust`` is set.

    Args:
        pose_key: ``X(k)``.
        observations: one :class:`AxisObservation` per lamp, distinct axis keys.
        robust: optional Huber threshold.

    Returns:
        ``gtsam.CustomFactor`` on ``[pose_key, axis keys...]`` with a (K,) residual.
    """
    obs = list(observations)
    if not obs:
        raise FactorError("lamp_axis_frame_factor needs at least one observation")
    keys = [pose_key] + [o.axis_key for o in obs]
    if len(set(keys)) != len(keys):
        raise FactorError("lamp_axis_frame_factor: axis keys must be distinct")
    alphas = [float(o.alpha) for o in obs]
    inv_sig = [1.0 / float(o.sigma) for o in obs]
    n = len(obs)

    def error(this: gtsam.CustomFactor, values: gtsam.Values, H: Any) -> FloatArray:
        ks = this.keys()
        pose = _pose(values, ks[0])
        res = np.empty(n)
        d_pose = np.zeros((n, 3))
        d_phi = np.empty(n)
        for i in range(n):
            r, _, _ = lamp_axis_residual(pose, values.atRot2(ks[i + 1]).theta(), alphas[i])
            e = r * inv_sig[i]
            g = 1.0
            if robust is not None:
                e_arr, g_arr = huber_sqrt(np.array([e]), robust)
                e, g = float(e_arr[0]), float(g_arr[0, 0])
            res[i] = e
            d_pose[i, 2] = -g * inv_sig[i]
            d_phi[i] = g * inv_sig[i]
        if H is not None:
            H[0] = d_pose
            for i in range(n):
                col = np.zeros((n, 1))
                col[i, 0] = d_phi[i]
                H[i + 1] = col
        return res

    return gtsam.CustomFactor(gtsam.noiseModel.Unit.Create(n), keys, error)


@lru_cache(maxsize=1)
def _axis_anchor_noise() -> gtsam.noiseModel.Base:
    return gtsam.noiseModel.Diagonal.Precisions(np.array([1.0, 1.0, 0.0]))


def lamp_axis_between_factor(
    pose_key: int,
    axis_key: int,
    alpha: float,
    sigma: float,
    predicted: float,
    robust: float | None = None,
) -> gtsam.BetweenFactorPose2:
    """Lamp axis observation as GTSAM's built-in ``BetweenFactorPose2`` (no callback).

    The axis variable ``A(j)`` is then a ``Pose2`` whose rotation is the axis ``phi``
    and whose translation carries no information: the factor's noise model has zero
    precision on ``x, y`` and ``1/sigma^2`` on the angle, and :func:`axis_anchor_prior`
    holds the translation. With GTSAM's default ``Pose2`` chart the angle row of
    ``Local(measured, X^-1 A)`` is ``wrap_angle(phi - theta - alpha)`` and its
    Jacobians are ``-1`` on ``theta`` and ``+1`` on ``phi``, exactly those of
    :func:`lamp_axis_factor` (paper III.4, ``phi_i = phi - theta``); the ``x, y``
    rows are whitened to zero, so the two factors have the same error, gradient and
    Hessian (checked in ``tests/test_factors_gtsam.py``).

    A line's angle is known mod pi, a ``Pose2`` angle mod 2 pi: the representative
    of ``alpha`` nearest to ``predicted`` is fixed here, once. The residual stays
    right while the estimate moves by less than pi/2 from that prediction (a gated
    match is within a few sigma).

    Args:
        pose_key: ``X(k)``.
        axis_key: ``A(j)``, a ``gtsam.Pose2`` anchored by :func:`axis_anchor_prior`.
        alpha: measured axis in the image, radians (any representative mod pi).
        sigma: its standard deviation, radians (> 0).
        predicted: current prediction of ``phi - theta`` in the graph's own
            representative of ``phi``, radians.
        robust: optional Huber threshold (on the angle residual alone, since the
            other rows whiten to zero).

    Returns:
        ``gtsam.BetweenFactorPose2`` on ``(X(k), A(j))``.
    """
    if not sigma > 0.0:
        raise FactorError(f"axis sigma must be > 0, got {sigma}")
    a = float(alpha)
    a += math.pi * round((float(predicted) - a) / math.pi)
    base = gtsam.noiseModel.Diagonal.Precisions(np.array([0.0, 0.0, 1.0 / (sigma * sigma)]))
    return gtsam.BetweenFactorPose2(pose_key, axis_key, gtsam.Pose2(0.0, 0.0, a),
                                    _robust_wrap(base, robust))


def axis_anchor_prior(axis_key: int, xy: FloatArray, phi: float) -> gtsam.PriorFactorPose2:
    """Fix the information-free translation of a ``Pose2`` axis variable.

    Unit precision on ``x, y`` (metres), zero on the angle, so the prior says nothing
    about the axis itself. Put its mean at the variable's initial value: the
    translation then never moves (it is decoupled from the angle in ``Pose2``'s
    chart, see :func:`lamp_axis_between_factor`).

    Args:
        axis_key: ``A(j)``.
        xy: (2,) the translation the variable was inserted with, metres.
        phi: the angle it was inserted with, radians (unused by the error).

    Returns:
        ``gtsam.PriorFactorPose2``.
    """
    return gtsam.PriorFactorPose2(axis_key, gtsam.Pose2(float(xy[0]), float(xy[1]), float(phi)),
                                  _axis_anchor_noise())


# --- corners: inverse depth -----------------------------------------------------------


@dataclass(frozen=True)
class InverseDepthObservation:
    """One inverse-depth corner observation for :func:`inverse_depth_frame_factor`.

    Attributes:
        anchor_key: ``X(a)`` of the corner's first sight (not the observing pose).
        corner_key: ``C(j)`` holding ``(alpha_x, alpha_y, rho)``.
        m: (2,) measured normalised coordinates.
        cov_m: (2, 2) their covariance.
    """

    anchor_key: int
    corner_key: int
    m: FloatArray
    cov_m: FloatArray


def _huber_sqrt_rows(e: FloatArray, k: float) -> tuple[FloatArray, FloatArray]:
    """:func:`huber_sqrt` applied to each row of ``e`` (K, d); returns (K, d), (K, d, d)."""
    n_rows, d = e.shape
    norms = np.linalg.norm(e, axis=1)
    r = e.copy()
    r_D_e = np.broadcast_to(np.eye(d), (n_rows, d, d)).copy()
    big = norms > k
    if np.any(big):
        nb = norms[big]
        eb = e[big]
        gb = np.sqrt(2.0 * k * nb - k * k)
        sb = gb / nb
        ds_dn = (k / gb - sb) / nb
        r[big] = sb[:, None] * eb
        r_D_e[big] = sb[:, None, None] * np.eye(d) + (ds_dn / nb)[:, None, None] * np.einsum(
            "ki,kj->kij", eb, eb
        )
    return r, r_D_e


def _sqrt_info(cov: FloatArray) -> FloatArray:
    """Upper-triangular ``W`` with ``W^T W = cov^-1`` (whitening matrix)."""
    return np.linalg.cholesky(np.linalg.inv(cov)).T


def inverse_depth_factor(
    pose_key: int,
    anchor_key: int,
    corner_key: int,
    m: FloatArray,
    cov_m: FloatArray,
    body_t_camera: FloatArray,
    robust: float | None = None,
) -> gtsam.CustomFactor:
    """Inverse-depth corner seen from a pose other than its anchor (``CustomFactor``).

    Model :func:`lampsam.factors.ceiling.project_inverse_depth`; residual = predicted
    - measured. The first sight is :func:`inverse_depth_first_sight_prior`, not this.

    Args:
        pose_key: observing pose ``X(k)``.
        anchor_key: anchor pose ``X(a)``, ``a != k``.
        corner_key: ``C(j)``, a (3,) vector ``(alpha_x, alpha_y, rho)``.
        m: (2,) measured normalised coordinates.
        cov_m: (2, 2) their covariance.
        body_t_camera: (3,) camera offset, metres.
        robust: optional Huber threshold.

    Returns:
        ``gtsam.CustomFactor`` on ``[pose_key, anchor_key, corner_key]``.
    """
    if pose_key == anchor_key:
        raise FactorError("inverse_depth_factor: the anchor sight is a prior, not a factor")
    cov_m = _check_cov(cov_m, 2, "inverse depth")
    meas = np.asarray(m, dtype=float).copy()
    off = np.asarray(body_t_camera, dtype=float).copy()

    def error(this: gtsam.CustomFactor, values: gtsam.Values, H: Any) -> FloatArray:
        ks = this.keys()
        pred, j_pose, j_anchor, j_idp = project_inverse_depth(
            _pose(values, ks[0]), _pose(values, ks[1]), values.atVector(ks[2]), off
        )
        if H is not None:
            H[0], H[1], H[2] = j_pose, j_anchor, j_idp
        return pred - meas

    return gtsam.CustomFactor(noise_model(cov_m, robust), [pose_key, anchor_key, corner_key], error)


def inverse_depth_frame_factor(
    pose_key: int,
    observations: Sequence[InverseDepthObservation],
    body_t_camera: FloatArray,
    robust: float | None = None,
) -> gtsam.CustomFactor:
    """All inverse-depth corner observations of one frame in one ``CustomFactor``.

    Residuals are whitened per observation (unit noise model); Huber per observation
    when ``robust`` is set (:func:`huber_sqrt`). Anchors shared by several corners
    appear once among the keys and their Jacobian blocks are stacked.

    Args:
        pose_key: observing pose ``X(k)``.
        observations: :class:`InverseDepthObservation` s, distinct corners, anchors
            different from ``pose_key``.
        body_t_camera: (3,) camera offset, metres.
        robust: optional Huber threshold.

    Returns:
        ``gtsam.CustomFactor`` with a (2K,) residual.
    """
    obs = list(observations)
    if not obs:
        raise FactorError("inverse_depth_frame_factor needs at least one observation")
    anchor_keys: list[int] = []
    anchor_slot: dict[int, int] = {}
    corner_keys: list[int] = []
    for o in obs:
        if o.anchor_key == pose_key:
            raise FactorError("inverse_depth_frame_factor: anchor sight must be a prior")
        if o.anchor_key not in anchor_slot:
            anchor_slot[o.anchor_key] = len(anchor_keys)
            anchor_keys.append(o.anchor_key)
        corner_keys.append(o.corner_key)
    keys = [pose_key, *anchor_keys, *corner_keys]
    if len(set(keys)) != len(keys):
        raise FactorError("inverse_depth_frame_factor: corner keys must be distinct")
    n = len(obs)
    n_anchor = len(anchor_keys)
    which_anchor = np.array([anchor_slot[o.anchor_key] for o in obs])
    anchor_masks = [which_anchor == u for u in range(n_anchor)]
    whiten = np.stack([_sqrt_info(_check_cov(o.cov_m, 2, "inverse depth")) for o in obs])
    meas = np.stack([np.asarray(o.m, dtype=float) for o in obs])
    off = np.asarray(body_t_camera, dtype=float).copy()
    rows = np.arange(n)

    def error(this: gtsam.CustomFactor, values: gtsam.Values, H: Any) -> FloatArray:
        ks = this.keys()
        pose = _pose(values, ks[0])
        anchors = np.stack([_pose(values, ks[1 + u]) for u in range(n_anchor)])[which_anchor]
        idps = np.stack([values.atVector(ks[1 + n_anchor + i]) for i in range(n)])
        pred, j_pose, j_anchor, j_idp = project_inverse_depth_batch(pose, anchors, idps, off)
        e = np.einsum("kij,kj->ki", whiten, pred - meas)
        g = whiten
        if robust is not None:
            e, r_D_e = _huber_sqrt_rows(e, robust)
            g = r_D_e @ whiten
        if H is not None:
            H[0] = (g @ j_pose).reshape(2 * n, 3)
            g_anchor = g @ j_anchor
            for u in range(n_anchor):
                block = np.zeros((n, 2, 3))
                block[anchor_masks[u]] = g_anchor[anchor_masks[u]]
                H[1 + u] = block.reshape(2 * n, 3)
            g_idp = g @ j_idp
            for i in range(n):
                block = np.zeros((n, 2, 3))
                block[rows[i]] = g_idp[i]
                H[1 + n_anchor + i] = block.reshape(2 * n, 3)
        return e.reshape(2 * n)

    return gtsam.CustomFactor(gtsam.noiseModel.Unit.Create(2 * n), keys, error)


def inverse_depth_first_sight_prior(
    corner_key: int,
    m: FloatArray,
    cov_m: FloatArray,
    prior: HeightPrior | None = None,
    robust: float | None = None,
) -> gtsam.PriorFactorVector:
    """First sight of an inverse-depth corner plus the height prior, one built-in factor.

    Seen from its anchor the corner projects to ``alpha`` whatever the anchor pose
    (:func:`lampsam.factors.ceiling.project_inverse_depth`), so the first observation
    is the prior ``alpha ~ N(m, cov_m)``; with the height range as ``rho ~ N(rho_mean,
    rho_sigma^2)`` (:class:`HeightPrior`) it is one ``PriorFactorVector`` with a
    block-diagonal covariance.

    Args:
        corner_key: ``C(j)``.
        m: (2,) normalised coordinates at the anchor.
        cov_m: (2, 2) their covariance.
        prior: height range, default :class:`HeightPrior` ().
        robust: optional Huber threshold on the whitened 3-vector (the ``rho`` part
            is within 2 sigma by construction, so in practice it acts on ``alpha``).

    Returns:
        ``gtsam.PriorFactorVector`` on the (3,) inverse-depth vector.
    """
    prior = prior or HeightPrior()
    cov_m = _check_cov(cov_m, 2, "inverse depth prior")
    cov = np.zeros((3, 3))
    cov[:2, :2] = cov_m
    cov[2, 2] = prior.rho_sigma**2
    mean = np.array([float(m[0]), float(m[1]), prior.rho_mean])
    return gtsam.PriorFactorVector(corner_key, mean, noise_model(cov, robust))


# --- range-bearing --------------------------------------------------------------------


def bearing_range_factor(
    pose_key: int,
    landmark_key: int,
    bearing: float,
    range_: float,
    cov: FloatArray,
    body_T_sensor: FloatArray | None = None,
    robust: float | None = None,
) -> gtsam.NonlinearFactor:
    """Planar range-bearing observation of a ``Point2`` landmark.

    Without a sensor offset: the built-in ``gtsam.BearingRangeFactor2D``. With one:
    a ``CustomFactor`` over :func:`lampsam.factors.range_bearing.range_bearing`
    (bearing residual wrapped to ``(-pi, pi]``).

    Args:
        pose_key: ``X(k)``.
        landmark_key: ``L(j)`` holding a ``Point2``.
        bearing: measured bearing, radians.
        range_: measured range, metres.
        cov: (2, 2) covariance of ``[bearing, range]``.
        body_T_sensor: optional (3,) sensor pose in the body frame.
        robust: optional Huber threshold.

    Returns:
        The factor.
    """
    cov = _check_cov(cov, 2, "range-bearing")
    noise = noise_model(cov, robust)
    if body_T_sensor is None:
        return gtsam.BearingRangeFactor2D(
            pose_key, landmark_key, gtsam.Rot2(float(bearing)), float(range_), noise
        )
    off = np.asarray(body_T_sensor, dtype=float).copy()
    meas = np.array([float(bearing), float(range_)])

    def error(this: gtsam.CustomFactor, values: gtsam.Values, H: Any) -> FloatArray:
        ks = this.keys()
        z, z_D_pose, z_D_lm = range_bearing(_pose(values, ks[0]), values.atPoint2(ks[1]), off)
        if H is not None:
            H[0], H[1] = z_D_pose, z_D_lm
        r = z - meas
        r[0] = wrap_angle(r[0])
        return r

    return gtsam.CustomFactor(noise, [pose_key, landmark_key], error)
