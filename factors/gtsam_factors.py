"""Thin GTSAM adapters over the pure models (DESIGN sec. 4 and 6): noise, odometry, positions.

The lamp-axis factors are in :mod:`lampsam.factors.axis_factors`, the inverse-depth
corner factors in :mod:`lampsam.factors.inverse_depth_factors`; this docstring gives
the whole picture and the measured costs that chose between the forms.

Variables (keys from ``gtsam.symbol_shorthand``):

* ``X(k)`` -- robot pose, ``gtsam.Pose2``.
* ``L(j)`` -- lamp position, ``Point3`` (numpy (3,)) in the world, ``z`` above the floor.
* ``A(j)`` -- lamp long axis: angle ``phi`` in the world, used mod pi; a ``gtsam.Pose2``
  with an information-free translation for :func:`~lampsam.factors.axis_factors.lamp_axis_between_factor` (the
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
                            (:func:`~lampsam.factors.axis_factors.lamp_axis_between_factor`, used by the
                            smoothers); ``CustomFactor`` on ``(X, A)`` with ``A`` a
                            ``Rot2``, per observation or per frame
                            (:func:`~lampsam.factors.axis_factors.lamp_axis_frame_factor`), kept as the reference
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
``BetweenFactorPose2`` form (:func:`~lampsam.factors.axis_factors.lamp_axis_between_factor`) 15 ms / 0.11 s.

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
from functools import lru_cache
from typing import Any

import gtsam
import numpy as np

from lampsam.arrays import FloatArray
from lampsam.factors.ceiling import HeightPrior
from lampsam.factors.geometry import FactorError, wrap_angle
from lampsam.factors.range_bearing import range_bearing

__all__ = [
    "bearing_range_factor",
    "check_cov",
    "height_prior_factor",
    "huber_sqrt",
    "noise_model",
    "odometry_factor",
    "pose_array",
    "projection_factor",
    "robust_wrap",
    "sqrt_information",
    "virtual_camera",
]

#: x/y sigma (metres) of :func:`height_prior_factor`: loose enough to carry no
#: information on the horizontal position (information 1e-6 per m^2).
LOOSE_SIGMA = 1.0e3


def pose_array(p: gtsam.Pose2) -> FloatArray:
    """A ``gtsam.Pose2`` as a (3,) array ``(x, y, theta)``, m and rad, theta in ``(-pi, pi]``.

    GTSAM's ``Rot2.theta()`` is ``atan2(sin, cos)``, already in ``[-pi, pi]``; only
    ``-pi`` is mapped to ``pi`` (docs/conventions.md), so every other angle is GTSAM's
    to the bit. For a value in a ``gtsam.Values``: ``pose_array(values.atPose2(key))``.
    """
    theta = p.theta()
    return np.array([p.x(), p.y(), math.pi if theta == -math.pi else theta])


def _positive_definite(sym: FloatArray) -> bool:
    """Whether a symmetric (d, d) matrix is positive definite.

    Sylvester's criterion (leading principal minors) in closed form for d <= 3,
    which every measurement here has; an eigenvalue test otherwise. About 20x
    cheaper than ``eigvalsh`` on 2x2 blocks, and this runs once per factor.
    """
    d = sym.shape[0]
    if d > 3:
        return bool(np.linalg.eigvalsh(sym)[0] > 0.0)
    return _minors_positive(sym.tolist())


def _minors_positive(a: list[list[float]]) -> bool:
    """Sylvester's criterion on a symmetric (d, d) matrix given as rows, d <= 3."""
    d = len(a)
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


def check_cov(cov: FloatArray, dim: int, what: str) -> FloatArray:
    """``cov`` as a (dim, dim) float array; FactorError unless finite and positive definite."""
    arr = np.asarray(cov, dtype=float)
    if arr.shape != (dim, dim):
        raise FactorError(f"{what}: covariance must be a finite ({dim}, {dim}) array")
    if dim == 2:  # in plain floats: ~10x cheaper than the array operations below
        (c00, c01), (c10, c11) = arr.tolist()
        if not (math.isfinite(c00) and math.isfinite(c01) and math.isfinite(c10)
                and math.isfinite(c11)):
            raise FactorError(f"{what}: covariance must be a finite (2, 2) array")
        off = 0.5 * (c01 + c10)
        if not (c00 > 0.0 and c00 * c11 - off * off > 0.0):  # Sylvester, as _minors_positive
            raise FactorError(f"{what}: covariance is not positive definite")
        return arr
    if dim in (1, 3):
        if not all(map(math.isfinite, arr.ravel().tolist())):
            raise FactorError(f"{what}: covariance must be a finite ({dim}, {dim}) array")
        a = arr.tolist()
        sym = [[0.5 * (a[i][j] + a[j][i]) for j in range(dim)] for i in range(dim)]
        if not _minors_positive(sym):
            raise FactorError(f"{what}: covariance is not positive definite")
        return arr
    if not np.isfinite(arr).all():
        raise FactorError(f"{what}: covariance must be a finite ({dim}, {dim}) array")
    if not _positive_definite(0.5 * (arr + arr.T)):
        raise FactorError(f"{what}: covariance is not positive definite")
    return arr


#: GTSAM's robust kernels by the names lampsam's configs use
_KERNELS = {"huber": gtsam.noiseModel.mEstimator.Huber.Create,
            "cauchy": gtsam.noiseModel.mEstimator.Cauchy.Create}


def robust_wrap(base: gtsam.noiseModel.Base, robust: float | None,
                kernel: str = "huber") -> gtsam.noiseModel.Base:
    """``base`` unchanged for ``robust=None``, else wrapped in a ``kernel`` (``"huber"`` or
    ``"cauchy"``) with threshold ``robust`` (> 0, in sigmas of ``base``)."""
    if robust is None:
        return base
    if not robust > 0.0:
        raise FactorError(f"{kernel.capitalize()} threshold must be > 0, got {robust}")
    return gtsam.noiseModel.Robust.Create(_KERNELS[kernel](robust), base)


def noise_model(cov: FloatArray, robust: float | None = None) -> gtsam.noiseModel.Base:
    """Gaussian noise model from a covariance, optionally wrapped in Huber.

    Args:
        cov: (d, d) covariance of the measurement, symmetric positive definite.
        robust: None for Gaussian; ``k > 0`` for a Huber kernel with threshold ``k``
            on the whitened residual norm (``k = 1.345`` is the usual 95 % efficiency).

    Returns:
        A ``gtsam.noiseModel`` (``Gaussian`` or ``Robust``).
    """
    return robust_wrap(gtsam.noiseModel.Gaussian.Covariance(np.asarray(cov, dtype=float)), robust)


def sqrt_information(cov: FloatArray) -> FloatArray:
    """Upper-triangular ``W`` with ``W^T W = cov^-1`` (the transposed Cholesky factor of
    the information), so that ``W e`` has unit covariance when ``e ~ N(0, cov)``.

    Args:
        cov: (d, d) covariance, symmetric positive definite.
    """
    return np.linalg.cholesky(np.linalg.inv(np.asarray(cov, dtype=float))).T


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
    cov = check_cov(cov, 3, "odometry")
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
    cov_m = check_cov(cov_m, 2, "projection")
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
    cov = check_cov(cov, 2, "range-bearing")
    noise = noise_model(cov, robust)
    if body_T_sensor is None:
        return gtsam.BearingRangeFactor2D(
            pose_key, landmark_key, gtsam.Rot2(float(bearing)), float(range_), noise
        )
    off = np.asarray(body_T_sensor, dtype=float).copy()
    meas = np.array([float(bearing), float(range_)])

    def error(this: gtsam.CustomFactor, values: gtsam.Values, H: Any) -> FloatArray:
        ks = this.keys()
        z, z_D_pose, z_D_lm = range_bearing(pose_array(values.atPose2(ks[0])), values.atPoint2(ks[1]), off)
        if H is not None:
            H[0], H[1] = z_D_pose, z_D_lm
        r = z - meas
        r[0] = wrap_angle(r[0])
        return r

    return gtsam.CustomFactor(noise, [pose_key, landmark_key], error)
