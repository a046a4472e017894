"""Online odometry noise scale by covariance matching on landmark innovations.

A log's stated odometry noise may be right at the optimum and still too small for an
estimator linearised at drifting estimates (Victoria Park: the EKF's re-sightings of
trees idle for 50 steps come back at a median squared distance of 5.3 even with known
ids; docs/graph-backend.md). Without ids that loses every revisit: the true tree is
beyond the gate of eq. 20 and is mapped again. A fixed variance factor
(``[pose2_odometry] cov_scale``) fixes one log and harms another; here the factor is
learnt from the run itself.

Model (covariance matching, Mehra 1972): split eq. 19's innovation covariance of a
match into ``A = H_p C H_p^T``, the part of the odometry accumulated since the
landmark's last sighting (``C``: the odometry covariance composed over those steps,
:class:`IdleOdometry`; the only part that grows with the odometry noise while the
landmark is out of sight), and the rest ``B = Psi - A`` (measurement noise, the
landmark's and the pose's uncertainty at the last sighting). The innovation of a
correct match is modelled ``nu ~ N(0, a A + b B)``: ``a`` is the factor by which the
odometry variance is understated, ``b`` absorbs a stated ``R`` that is too large (on
Victoria Park ~16x the residuals' variance). Only matches with ``tr A >=
INFORMATIVE tr B`` are used (the others say nothing about ``a``). ``(a, b)`` are
estimated by maximum likelihood over the last ``window`` such matches (Student-t with
``_DOF`` degrees of freedom, so one wrong match does not drag the scale; a log grid),
with the prior ``log a ~ N(0, PRIOR_SIGMA^2)`` (stay at the current scale unless the
matches say otherwise). Only matches inside the gate are ever seen, so each sample's
likelihood is divided by its probability of being accepted,
``P(nu^T Psi^-1 nu < g)`` (:func:`scale_likelihood`: a one-dimensional quadrature).
The backend then multiplies every new odometry sample's covariance by
``q = clamp(q_geo * a_hat, 1, max_scale)``, ``q_geo`` the geometric mean of the
scales the window's samples were taken under (the fixed point is ``a = 1``). The prior
is the stated noise (``q = 1`` until ``min_count`` matches); ``q`` never goes below it.

What it does on Victoria Park (docs/graph-backend.md): it does not hold. Informative
matches are rare (65 in the first 3,500 poses) and come after the first loop, by
which time the EKF has diverged; on a synthetic log whose stated odometry noise is 8x
too small the revisits are rejected by the gate, so the estimator never sees them.
Off by default (``association.odometry_noise_adapt``).

Frames and units: innovations ``[bearing, range]`` (rad, m); pose covariances in the
backend's pose coordinates (the EKF's plain ``(x, y, theta)``, the smoothers' right
tangent), with ``H_p`` the matching Jacobian; scales are variance factors.
"""

from __future__ import annotations

import collections
import math
from collections.abc import Callable, Mapping

import numpy as np

from lampsam.arrays import FloatArray
from lampsam.backend.association import Assignment
from lampsam.backend.config import AssociationConfig
from lampsam.backend.models import Obs
from lampsam.backend.odometry import MotionModel

#: Grid of the odometry factor ``a`` (relative to the current scale).
_K_GRID = np.exp(np.linspace(math.log(0.25), math.log(64.0), 33))
#: Prior sigma of ``log a`` per estimate (natural log: a factor e per sigma).
PRIOR_SIGMA = 1.0
#: A match is used when ``tr A >= INFORMATIVE tr B`` (its odometry part is not negligible).
INFORMATIVE = 0.05
#: Degrees of freedom of the robust (Student-t) innovation likelihood.
_DOF = 4.0
#: Angles of the acceptance-probability quadrature (midpoints over a quarter turn).
_PHI = (np.arange(16) + 0.5) * (0.5 * math.pi / 16)
#: Grid of the measurement-noise factor ``b``.
_B_GRID = np.exp(np.linspace(math.log(1e-4), math.log(4.0), 24))


def scale_likelihood(nu: FloatArray, s_x: FloatArray, r: FloatArray, gate: float,
                     k: FloatArray, b: FloatArray) -> FloatArray:
    """Log-likelihood of innovations under ``nu ~ N(0, k A + b B)``, truncated at the gate.

    Args:
        nu: (N, 2) innovations; s_x: (N, 2, 2) the odometry part ``A``; r: (N, 2, 2)
            the rest ``B``. The gate covariance is ``Psi = A + B``.
        gate: squared-distance gate ``g`` the samples passed.
        k: (K,) odometry factors (``a`` of the module doc); b: (B,) factors on the rest.

    Returns:
        (K, B) summed log-likelihoods (constants dropped).
    """
    kk = k[:, None, None, None, None]
    bb = b[None, :, None, None, None]
    sig = kk * s_x[None, None] + bb * r[None, None]  # (K, B, N, 2, 2)
    s00, s01, s11 = sig[..., 0, 0], 0.5 * (sig[..., 0, 1] + sig[..., 1, 0]), sig[..., 1, 1]
    det = s00 * s11 - s01 * s01
    n0, n1 = nu[:, 0], nu[:, 1]
    quad = (s11 * n0 * n0 - 2.0 * s01 * n0 * n1 + s00 * n1 * n1) / det
    # acceptance P(nu^T Psi^-1 nu < g): with (l1, l2) the eigenvalues of Psi^-1 Sigma,
    # nu^T Psi^-1 nu = rho^2 (l1 cos^2 phi + l2 sin^2 phi), rho^2 ~ Exp(mean 2) and phi
    # uniform, so P = mean over phi of 1 - exp(-g / (2 (l1 cos^2 + l2 sin^2)))
    pinv = np.linalg.inv(s_x + r)  # (N, 2, 2)
    half_tr = 0.5 * np.einsum("nij,abnji->abn", pinv, sig)
    det_rel = det / np.linalg.det(s_x + r)
    disc = np.sqrt(np.maximum(half_tr * half_tr - det_rel, 0.0))
    l1, l2 = half_tr + disc, np.maximum(half_tr - disc, 1e-12)
    c2 = np.cos(_PHI) ** 2
    lam = np.maximum(l1[..., None] * c2 + l2[..., None] * (1.0 - c2), 1e-12)
    p_acc = np.mean(-np.expm1(-gate / (2.0 * lam)), axis=-1)
    # Student-t (``_DOF``) instead of the Gaussian: a wrong match left in the sample
    # must not drag the scale up (the acceptance probability stays the Gaussian's)
    ll = (-0.5 * np.log(np.maximum(det, 1e-300))
          - 0.5 * (_DOF + 2.0) * np.log1p(np.maximum(quad, 0.0) / _DOF)
          - np.log(np.maximum(p_acc, 1e-300)))
    ll = np.where(det > 0, ll, -np.inf)
    return np.asarray(ll.sum(axis=-1), float)


class OdometryNoiseScale:
    """Running estimate of the odometry variance factor ``q`` (see the module doc).

    Args:
        gate: the squared-distance gate the samples passed (chi-square, 2 dof).
        window: the most recent matches used.
        min_count: matches before ``q`` leaves 1.
        every: re-estimate after this many new matches.
        max_scale: the largest ``q``.
    """

    def __init__(self, gate: float, window: int = 150, min_count: int = 30, every: int = 10,
                 max_scale: float = 100.0) -> None:
        if window < 1 or min_count < 1 or every < 1 or max_scale < 1.0:
            raise ValueError(f"OdometryNoiseScale: need window, min_count, every >= 1 and "
                             f"max_scale >= 1 (got {window}, {min_count}, {every}, {max_scale})")
        self.gate = gate
        self.min_count = min_count
        self.every = every
        self.max_scale = max_scale
        self._samples: collections.deque[tuple[FloatArray, FloatArray, FloatArray, float]] = (
            collections.deque(maxlen=window))
        self.scale = 1.0
        #: the last estimates of ``k`` and ``b``
        self.k_hat = 1.0
        self.b_hat = 1.0
        self.n_seen = 0
        #: ``(matches seen, q)`` after each estimate
        self.history: list[tuple[int, float]] = []

    def add(self, nu: FloatArray, a_part: FloatArray, b_part: FloatArray) -> float:
        """Add one match: innovation (2,), odometry part ``A`` (2, 2), the rest ``B``
        (2, 2); returns the scale."""
        nu = np.asarray(nu, float)
        if (nu.shape != (2,) or not np.all(np.isfinite(nu)) or not np.all(np.isfinite(a_part))
                or not np.all(np.isfinite(b_part))):
            return self.scale
        self._samples.append((nu, np.asarray(a_part, float), np.asarray(b_part, float),
                              self.scale))
        self.n_seen += 1
        if len(self._samples) >= self.min_count and self.n_seen % self.every == 0:
            self._estimate()
        return self.scale

    def _estimate(self) -> None:
        nu = np.array([s[0] for s in self._samples])
        a_part = np.array([s[1] for s in self._samples])
        b_part = np.array([s[2] for s in self._samples])
        q_geo = math.exp(float(np.mean([math.log(s[3]) for s in self._samples])))
        ll = scale_likelihood(nu, a_part, b_part, self.gate, _K_GRID, _B_GRID)
        # prior: log a ~ N(0, PRIOR_SIGMA^2), i.e. the current scale unless the
        # window's matches say otherwise (few carry information: A << B for most)
        ll = ll - 0.5 * (np.log(_K_GRID)[:, None] / PRIOR_SIGMA) ** 2
        ik, ib = np.unravel_index(int(np.argmax(ll)), ll.shape)
        self.k_hat, self.b_hat = float(_K_GRID[ik]), float(_B_GRID[ib])
        self.scale = min(self.max_scale, max(1.0, q_geo * self.k_hat))
        self.history.append((self.n_seen, self.scale))


class IdleOdometry:
    """Per landmark, the odometry covariance composed since its last sighting (3, 3).

    ``C <- F C F^T + Q`` for every landmark at once at each odometry step (``F``, ``Q``
    in the backend's pose coordinates); a sighting sets the landmark's ``C`` to zero.
    """

    def __init__(self) -> None:
        self._row: dict[int, int] = {}
        self._c = np.zeros((0, 3, 3))

    def propagate(self, f: FloatArray, q: FloatArray) -> None:
        """One odometry step: ``F`` (3, 3) the pose Jacobian, ``Q`` (3, 3) its noise."""
        if len(self._c):
            self._c = np.einsum("ab,nbc,dc->nad", f, self._c, f) + q

    def cov(self, lid: int) -> FloatArray | None:
        """``C`` of landmark ``lid`` (3, 3), or None if it was never registered."""
        row = self._row.get(lid)
        return None if row is None else self._c[row]

    def seen(self, lid: int) -> None:
        """Landmark ``lid`` was sighted now: its ``C`` restarts from zero."""
        row = self._row.get(lid)
        if row is None:
            self._row[lid] = len(self._c)
            self._c = np.concatenate([self._c, np.zeros((1, 3, 3))])
        else:
            self._c[row] = 0.0


#: ``(landmark id, observation) -> (nu (2,), Psi (2, 2), H_p (2, 3))`` of eq. 19 with the
#: stated ``R``, ``H_p`` in the coordinates of :class:`IdleOdometry`; None: not predictable.
InnovationWithPose = Callable[[int, Obs], "tuple[FloatArray, FloatArray, FloatArray] | None"]


def feed_scale(est: OdometryNoiseScale, idle: IdleOdometry, observations: list[Obs],
               assignments: list[Assignment],
               screened: Mapping[int, Mapping[int, tuple[float, bool]]],
               innovation: InnovationWithPose) -> int:
    """Give ``est`` a frame's unambiguous range-bearing matches without ids; reset ``idle``.

    A match counts when its observation has no id, exactly one landmark was below
    the new-landmark threshold (no rival: as clean as the gate can make it) and the
    landmark's idle odometry is known. Every matched landmark's idle odometry then
    restarts.

    Args:
        est: the estimator; idle: the landmarks' odometry since their last sighting.
        observations, assignments, screened: the frame's association
            (:func:`lampsam.backend.association.associate`).
        innovation: the backend's eq.-19 innovation with its pose Jacobian.

    Returns:
        The number of matches fed.
    """
    n = 0
    for a in assignments:
        i = a.obs_index
        o = observations[i]
        if a.status != "matched" or a.landmark_id is None or o.kind != "point2":
            continue
        c = idle.cov(a.landmark_id)
        if c is not None and o.landmark_id is None and len(screened.get(i, {})) == 1:
            pred = innovation(a.landmark_id, o)
            if pred is not None:
                nu, psi, h_p = pred
                a_part = h_p @ c @ h_p.T
                b_part = np.asarray(psi, float)[:2, :2] - a_part
                if np.trace(a_part) < INFORMATIVE * np.trace(b_part):
                    idle.seen(a.landmark_id)  # says nothing about the odometry
                    continue
                est.add(np.asarray(nu, float)[:2], a_part, np.asarray(psi, float)[:2, :2] - a_part)
                n += 1
        idle.seen(a.landmark_id)
    return n


class ScaledMotion:
    """A motion model whose covariances are multiplied by an online scale.

    Wraps a backend's :class:`~lampsam.backend.odometry.MotionModel`: the increments
    are the model's, every covariance (an odometry factor's, the EKF's ``Q``) is
    ``est.scale`` times the model's at the time it is computed. With ``idle``, each
    EKF prediction also propagates it.
    """

    def __init__(self, inner: MotionModel, est: OdometryNoiseScale,
                 idle: IdleOdometry | None = None) -> None:
        self.inner = inner
        self.est = est
        self.idle = idle
        self.width = inner.width

    def check(self, t: float, samples: FloatArray) -> FloatArray:
        """The inner model's check."""
        return self.inner.check(t, samples)

    def relative(self, samples: FloatArray, floor_var: float | FloatArray
                 ) -> tuple[FloatArray, FloatArray]:
        """The inner model's ``(delta, cov)`` with ``cov`` scaled."""
        delta, cov = self.inner.relative(samples, floor_var)
        return delta, cov * self.est.scale

    def ekf_predict(self, pose: FloatArray, samples: FloatArray
                    ) -> tuple[FloatArray, FloatArray, FloatArray]:
        """The inner model's ``(pose', F, Q)`` with ``Q`` scaled."""
        pose, f, q = self.inner.ekf_predict(pose, samples)
        q = q * self.est.scale
        if self.idle is not None:
            self.idle.propagate(f, q)
        return pose, f, q


def odometry_scale(config: AssociationConfig) -> OdometryNoiseScale | None:
    """The estimator ``config`` asks for (``odometry_noise_adapt``), or None."""
    if not config.odometry_noise_adapt or config.use_known_ids:
        return None
    return OdometryNoiseScale(config.gate(2), config.odometry_noise_window,
                              min(30, config.odometry_noise_window),
                              max_scale=config.odometry_noise_max)
