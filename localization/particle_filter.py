"""Particle filter on a grid map (paper 2, sec. 4; DESIGN.md sec. 2, step 2).

Particles are planar poses ``(x, y, theta)`` in the world frame
(``docs/conventions.md``) with log-weights normalised so that
``logsumexp(log_weights) = 0``. One cycle:

1. :meth:`ParticleFilter.predict`: every particle moves by the odometry increment
   with sampled noise (the rot1-trans-rot2 odometry model, Thrun, Burgard & Fox,
   *Probabilistic Robotics*, table 5.6, written with standard deviations).
2. :meth:`ParticleFilter.update`: log-weights += the scan log-likelihood of a
   measurement model (:mod:`lampsam.localization.likelihood`: per-beam Gaussian
   summed in log space, the corrected eqs. 8-9); any subset of beams works
   (NaN = no return), so a 180-degree laser is handled like a 360-degree scan.
3. :meth:`ParticleFilter.resample_if_needed`: low-variance (systematic)
   resampling (Probabilistic Robotics, table 4.4) when the effective sample size
   ``N_eff = 1 / sum w^2`` falls below a fraction of ``N``; optionally with a
   KLD-adaptive sample size (Fox 2003, eq. 13).

Initialisation: uniform over the free cells of the map, or the same number of
particles in each ``(pose, radius)`` candidate disc (paper sec. 3). The estimate
is the weighted mean with a circular mean for the heading; the filter has
converged when the position spread and the circular heading spread fall below
bounds. The per-beam scan evidence ``log(sum_i w_i p(z | x_i)) / B`` after each
update tells a kidnapped robot (a collapse of the likelihood).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from scipy.special import logsumexp

from lampsam.angles import wrap_angle
from lampsam.arrays import BoolArray, FloatArray, IntArray
from lampsam.errors import LocalizationError
from lampsam.localization.grid import OccupancyGrid, free_mask
from lampsam.localization.likelihood import MeasurementModel, valid_beams

log = logging.getLogger(__name__)


class ParticleFilterError(LocalizationError):
    """Bad particle-filter input (no free space, empty candidates, NaN odometry)."""


#: Alias of :func:`lampsam.angles.wrap_angle`, kept for the callers of ``wrap``.
wrap = wrap_angle


@dataclass(frozen=True)
class MotionNoise:
    """Odometry motion noise, rot1-trans-rot2 model with standard deviations.

    ``sigma_rot = a_rot_rot |rot| + a_rot_trans |trans| + sigma_rot_min`` for each of
    the two rotations, ``sigma_trans = a_trans_trans |trans| + a_trans_rot
    (|rot1| + |rot2|) + sigma_trans_min`` (Probabilistic Robotics table 5.6 uses
    variances ``alpha_i``; here the spreads scale linearly).

    Attributes:
        a_rot_rot: rad of rotation noise per rad turned (default 0.05).
        a_rot_trans: rad per metre driven (default 0.02).
        a_trans_trans: metres per metre driven (default 0.05).
        a_trans_rot: metres per rad turned (default 0.01).
        sigma_trans_min: floor on the translation noise, m (default 0.005).
        sigma_rot_min: floor on each rotation's noise, rad (default 0.002).
    """

    a_rot_rot: float = 0.05
    a_rot_trans: float = 0.02
    a_trans_trans: float = 0.05
    a_trans_rot: float = 0.01
    sigma_trans_min: float = 0.005
    sigma_rot_min: float = 0.002


@dataclass(frozen=True)
class KldConfig:
    """KLD-adaptive sample size (Fox, IJRR 2003).

    Attributes:
        epsilon: bound on the K-L divergence (default 0.05).
        z_quantile: upper ``1 - delta`` standard-normal quantile (default 2.326, delta = 0.01).
        bin_xy: histogram bin size, m (default 0.25).
        bin_theta: histogram bin size, rad (default 10 deg).
        n_min: fewest particles (default 300).
        n_max: most particles (default 20,000).
    """

    epsilon: float = 0.05
    z_quantile: float = 2.326
    bin_xy: float = 0.25
    bin_theta: float = math.radians(10.0)
    n_min: int = 300
    n_max: int = 20_000


@dataclass(frozen=True)
class ParticleFilterConfig:
    """Particle filter settings.

    Attributes:
        resample_threshold: resample when ``N_eff < resample_threshold * N`` (default 0.5).
        motion: odometry noise.
        kld: adaptive sample size, or None for a fixed size (default None).
        jitter_xy: roughening added to resampled particles, m std (default 0.01).
        jitter_theta: roughening, rad std (default 0.005).
        converged_sigma_xy: position spread bound for convergence, m (default 0.15):
            square root of the largest eigenvalue of the position covariance.
        converged_sigma_theta: circular heading spread bound, rad (default 5 deg).
        max_beams: at most this many valid beams per update, evenly subsampled
            (default None: all).
        alpha_slow: smoothing of the slow average of the per-beam evidence
            (default 0.1; Probabilistic Robotics table 8.3's ``w_slow``, in log space).
        alpha_fast: smoothing of the fast average (default 0.7, ``w_fast``).
        collapse_drop: the likelihood has collapsed (kidnapped robot) when the fast
            average falls this many nats per beam below the slow one (default 0.5).
    """

    resample_threshold: float = 0.5
    motion: MotionNoise = field(default_factory=MotionNoise)
    kld: KldConfig | None = None
    jitter_xy: float = 0.01
    jitter_theta: float = 0.005
    converged_sigma_xy: float = 0.15
    converged_sigma_theta: float = math.radians(5.0)
    max_beams: int | None = None
    alpha_slow: float = 0.1
    alpha_fast: float = 0.7
    collapse_drop: float = 0.5


# ---------------------------------------------------------------------- pure functions
def normalise_log_weights(log_weights: FloatArray) -> FloatArray:
    """Shift log-weights (N,) so that ``logsumexp = 0``; all ``-inf`` gives uniform weights."""
    total = logsumexp(log_weights)
    if not np.isfinite(total):
        return np.full(log_weights.shape, -math.log(len(log_weights)))
    return log_weights - total


def effective_sample_size(log_weights: FloatArray) -> float:
    """``N_eff = 1 / sum w_i^2`` of normalised log-weights (N,)."""
    return float(math.exp(-logsumexp(2.0 * normalise_log_weights(log_weights))))


def systematic_resample(weights: FloatArray, n_out: int, rng: np.random.Generator) -> IntArray:
    """Low-variance (systematic) resampling (Probabilistic Robotics, table 4.4).

    One uniform offset ``u ~ U[0, 1/n)``; sample ``i`` takes the particle whose
    cumulative weight interval holds ``u + i / n``. Particle ``j`` is copied
    ``floor(n w_j)`` or ``ceil(n w_j)`` times.

    Args:
        weights: (N,) non-negative weights (normalised here).
        n_out: number of samples.
        rng: generator.

    Returns:
        (n_out,) int64 indices, sorted.
    """
    w = np.asarray(weights, dtype=np.float64)
    total = w.sum()
    if not (total > 0 and np.isfinite(total)):
        raise ParticleFilterError(f"weights must have a positive finite sum, got {total}")
    cdf = np.cumsum(w / total)
    cdf[-1] = 1.0
    positions = (rng.uniform(0.0, 1.0 / n_out) + np.arange(n_out) / n_out)
    return np.minimum(np.searchsorted(cdf, positions, side="right"), len(w) - 1)


def kld_sample_size(k_bins: IntArray | int, config: KldConfig) -> IntArray:
    """Particles needed for ``k`` occupied histogram bins (Fox 2003, eq. 13).

    ``n = (k - 1) / (2 eps) * (1 - 2 / (9 (k - 1)) + sqrt(2 / (9 (k - 1))) z)^3``,
    clipped to ``[n_min, n_max]``.

    Args:
        k_bins: number(s) of occupied bins.
        config: KLD settings.

    Returns:
        The same shape, int64.
    """
    k = np.maximum(np.asarray(k_bins, dtype=np.float64) - 1.0, 1.0)
    a = 2.0 / (9.0 * k)
    n = k / (2 * config.epsilon) * (1 - a + np.sqrt(a) * config.z_quantile) ** 3
    return np.clip(np.ceil(n), config.n_min, config.n_max).astype(np.int64)


def sample_motion(particles: FloatArray, odom_prev: FloatArray, odom_now: FloatArray,
                  noise: MotionNoise, rng: np.random.Generator) -> FloatArray:
    """Move particles by an odometry increment with sampled noise (rot1-trans-rot2).

    Args:
        particles: (N, 3) world poses.
        odom_prev: (3,) odometry pose at the previous step (odometry frame).
        odom_now: (3,) odometry pose now.
        noise: the noise model.
        rng: generator.

    Returns:
        (N, 3) new poses, heading wrapped.
    """
    odom_prev = np.asarray(odom_prev, dtype=np.float64)
    odom_now = np.asarray(odom_now, dtype=np.float64)
    if not (np.all(np.isfinite(odom_prev)) and np.all(np.isfinite(odom_now))):
        raise ParticleFilterError("odometry pose is not finite")
    dx, dy = odom_now[0] - odom_prev[0], odom_now[1] - odom_prev[1]
    trans = math.hypot(dx, dy)
    dtheta = float(wrap_angle(odom_now[2] - odom_prev[2]))
    rot1 = float(wrap_angle(math.atan2(dy, dx) - odom_prev[2])) if trans > 1e-6 else 0.0
    if abs(rot1) > math.pi / 2 and trans > 1e-6:  # driving backwards: keep rotations small
        rot1 = float(wrap_angle(rot1 + math.pi))
        trans = -trans
    rot2 = float(wrap_angle(dtheta - rot1))
    n = len(particles)
    s_rot1 = noise.a_rot_rot * abs(rot1) + noise.a_rot_trans * abs(trans) + noise.sigma_rot_min
    s_rot2 = noise.a_rot_rot * abs(rot2) + noise.a_rot_trans * abs(trans) + noise.sigma_rot_min
    s_trans = (noise.a_trans_trans * abs(trans) + noise.a_trans_rot * (abs(rot1) + abs(rot2))
               + noise.sigma_trans_min)
    r1 = rot1 + rng.normal(0.0, s_rot1, n)
    tr = trans + rng.normal(0.0, s_trans, n)
    r2 = rot2 + rng.normal(0.0, s_rot2, n)
    out = np.empty_like(particles)
    heading = particles[:, 2] + r1
    out[:, 0] = particles[:, 0] + tr * np.cos(heading)
    out[:, 1] = particles[:, 1] + tr * np.sin(heading)
    out[:, 2] = wrap_angle(heading + r2)
    return out


def weighted_estimate(particles: FloatArray,
                      log_weights: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Weighted mean pose and covariance, circular mean for the heading.

    Args:
        particles: (N, 3) poses.
        log_weights: (N,) log-weights (normalised here).

    Returns:
        ``(mean (3,), cov (3, 3))``; heading residuals are wrapped about the mean.
    """
    w = np.exp(normalise_log_weights(log_weights))
    mean_xy = w @ particles[:, :2]
    mean_th = math.atan2(float(w @ np.sin(particles[:, 2])), float(w @ np.cos(particles[:, 2])))
    mean = np.array([mean_xy[0], mean_xy[1], mean_th])
    d = particles - mean
    d[:, 2] = wrap_angle(d[:, 2])
    cov = (d * w[:, None]).T @ d
    return mean, cov


def spread(particles: FloatArray, log_weights: FloatArray) -> tuple[float, float]:
    """Position spread (sqrt of the largest eigenvalue of the xy covariance, m) and
    circular heading spread ``sqrt(-2 ln R)`` (rad, R = mean resultant length)."""
    w = np.exp(normalise_log_weights(log_weights))
    _, cov = weighted_estimate(particles, log_weights)
    sigma_xy = math.sqrt(max(float(np.linalg.eigvalsh(cov[:2, :2])[-1]), 0.0))
    r = math.hypot(float(w @ np.cos(particles[:, 2])), float(w @ np.sin(particles[:, 2])))
    sigma_th = math.sqrt(max(-2.0 * math.log(max(r, 1e-300)), 0.0))
    return sigma_xy, sigma_th


def sample_free_space(grid: OccupancyGrid, n: int, rng: np.random.Generator,
                      mask: BoolArray | None = None) -> FloatArray:
    """Poses uniform over the free cells (uniform within each cell), heading uniform.

    Args:
        grid: the map.
        n: number of poses.
        rng: generator.
        mask: (H, W) cells allowed (default :func:`free_mask`).

    Returns:
        (n, 3) world poses.
    """
    mask = free_mask(grid) if mask is None else mask
    iy, ix = np.nonzero(mask)
    if iy.size == 0:
        raise ParticleFilterError("the map has no free cells to sample")
    pick = rng.integers(0, iy.size, n)
    uv = np.stack([ix[pick], iy[pick]], axis=1) + rng.uniform(0.0, 1.0, (n, 2))
    xy = grid.cell_to_world(uv - 0.5)
    return np.column_stack([xy, rng.uniform(-math.pi, math.pi, n)])


def sample_candidate_discs(candidates: Sequence[tuple[FloatArray, float]], per_candidate: int,
                           sigma_theta: float, rng: np.random.Generator) -> FloatArray:
    """The same number of particles in each ``(pose, radius)`` candidate (paper sec. 3).

    Positions uniform over the disc (radius ``sqrt(u) r``), headings
    ``theta + N(0, sigma_theta^2)``.

    Args:
        candidates: ``[(pose (3,), radius m), ...]``.
        per_candidate: particles per candidate.
        sigma_theta: heading spread, rad.
        rng: generator.

    Returns:
        (len(candidates) * per_candidate, 3) poses.
    """
    if len(candidates) == 0:
        raise ParticleFilterError("no candidates to sample from")
    out = []
    for pose, radius in candidates:
        pose = np.asarray(pose, dtype=np.float64).reshape(3)
        if not (np.all(np.isfinite(pose)) and radius >= 0):
            raise ParticleFilterError(f"bad candidate: pose {pose}, radius {radius}")
        rho = radius * np.sqrt(rng.uniform(0.0, 1.0, per_candidate))
        phi = rng.uniform(-math.pi, math.pi, per_candidate)
        out.append(np.column_stack([pose[0] + rho * np.cos(phi), pose[1] + rho * np.sin(phi),
                                    wrap_angle(pose[2] + rng.normal(0.0, sigma_theta, per_candidate))]))
    return np.concatenate(out)


# ---------------------------------------------------------------------- the filter
class ParticleFilter:
    """Monte Carlo localization on a measurement model.

    Args:
        model: the measurement model (ray casting or likelihood field).
        config: filter settings.
        rng: the generator every random draw uses.

    Attributes:
        particles: (N, 3) world poses.
        log_weights: (N,) normalised log-weights.
        evidence_per_beam: per-beam log of the last scan's marginal likelihood
            ``log(sum_i w_i p(z | x_i)) / B`` (NaN before any update).
        evidence_slow: slow moving average of ``evidence_per_beam``.
        evidence_fast: fast moving average of ``evidence_per_beam``.
        n_updates: number of measurement updates since initialisation.
    """

    def __init__(self, model: MeasurementModel, config: ParticleFilterConfig,
                 rng: np.random.Generator) -> None:
        self.model = model
        self.config = config
        self.rng = rng
        self.particles = np.zeros((0, 3))
        self.log_weights = np.zeros(0)
        self.evidence_per_beam = math.nan
        self.evidence_slow = math.nan
        self.evidence_fast = math.nan
        self.n_updates = 0

    # ------------------------------------------------------------------ initialisation
    def init_particles(self, particles: FloatArray) -> None:
        """Start from given poses (N, 3) with equal weights."""
        particles = np.asarray(particles, dtype=np.float64).reshape(-1, 3)
        if len(particles) == 0 or not np.all(np.isfinite(particles)):
            raise ParticleFilterError("initial particles must be non-empty and finite")
        self.particles = particles.copy()
        self.particles[:, 2] = wrap_angle(self.particles[:, 2])
        self.log_weights = np.full(len(particles), -math.log(len(particles)))
        self.evidence_per_beam = math.nan
        self.evidence_slow = math.nan
        self.evidence_fast = math.nan
        self.n_updates = 0

    def init_uniform(self, grid: OccupancyGrid, n: int, mask: BoolArray | None = None) -> None:
        """Particles uniform over the free space of ``grid`` (global localization)."""
        self.init_particles(sample_free_space(grid, n, self.rng, mask))

    def init_candidates(self, candidates: Sequence[tuple[FloatArray, float]],
                        per_candidate: int, sigma_theta: float = 0.1) -> None:
        """The same number of particles in each ``(pose, radius)`` candidate disc."""
        self.init_particles(sample_candidate_discs(candidates, per_candidate, sigma_theta,
                                                   self.rng))

    def add_particles(self, particles: FloatArray, share: float) -> None:
        """Add poses (M, 3) as extra modes that take ``share`` of the total weight.

        The existing particles keep their relative weights (scaled by
        ``1 - share``), so a converged cluster is kept, not re-spread; the new
        ones share ``share`` equally. A defensive mixture ``(1 - share) p + share q``
        of the current posterior ``p`` and the proposal ``q``: a new mode
        overtakes the current one only when the next scans favour it by more
        than ``log((1 - share) / share)`` nats per particle's likelihood ratio.
        The evidence averages and the update count are kept.
        """
        new = np.asarray(particles, dtype=np.float64).reshape(-1, 3)
        if len(new) == 0:
            return
        if not (0.0 < share < 1.0) or not np.all(np.isfinite(new)):
            raise ParticleFilterError(f"extra particles must be finite with a share in (0, 1), got {share}")
        new = new.copy()
        new[:, 2] = wrap_angle(new[:, 2])
        self.particles = np.concatenate([self.particles, new])
        self.log_weights = np.concatenate([self.log_weights + math.log1p(-share),
                                           np.full(len(new), math.log(share / len(new)))])  # fmt: skip

    # ------------------------------------------------------------------ cycle
    @property
    def n(self) -> int:
        """Current number of particles."""
        return int(len(self.particles))

    def predict(self, odom_prev: FloatArray, odom_now: FloatArray) -> None:
        """Motion update from two odometry poses (3,) (odometry frame)."""
        self.particles = sample_motion(self.particles, odom_prev, odom_now, self.config.motion,
                                       self.rng)

    def update(self, ranges: FloatArray, angles: FloatArray) -> float:
        """Measurement update with one scan (any subset of beams; NaN = no return).

        Args:
            ranges: (B,) metres.
            angles: (B,) beam angles in the body frame, rad.

        Returns:
            The effective sample size after the update.
        """
        ranges = np.asarray(ranges, dtype=np.float64).reshape(-1)
        angles = np.asarray(angles, dtype=np.float64).reshape(-1)
        ok = np.nonzero(valid_beams(ranges, self.model.config.max_range))[0]
        if ok.size == 0:
            log.warning("scan without valid beams: measurement update skipped")
            return effective_sample_size(self.log_weights)
        if self.config.max_beams is not None and ok.size > self.config.max_beams:
            ok = ok[np.linspace(0, ok.size - 1, self.config.max_beams).round().astype(int)]
        ll = self.model.log_likelihood(self.particles, ranges[ok], angles[ok])
        joint = self.log_weights + ll
        ev = float(logsumexp(joint)) / ok.size
        self.evidence_per_beam = ev
        if self.n_updates == 0:
            self.evidence_slow = self.evidence_fast = ev
        else:
            self.evidence_slow += self.config.alpha_slow * (ev - self.evidence_slow)
            self.evidence_fast += self.config.alpha_fast * (ev - self.evidence_fast)
        self.log_weights = normalise_log_weights(joint)
        self.n_updates += 1
        return effective_sample_size(self.log_weights)

    def resample_if_needed(self) -> bool:
        """Systematic resampling when ``N_eff`` is low (KLD-adaptive size if configured).

        Returns:
            True if the particles were resampled.
        """
        n_eff = effective_sample_size(self.log_weights)
        if n_eff >= self.config.resample_threshold * self.n:
            return False
        self.resample()
        return True

    def resample(self) -> None:
        """Resample now (systematic; the new size from KLD if configured)."""
        w = np.exp(self.log_weights)
        kld = self.config.kld
        if kld is None:
            idx = systematic_resample(w, self.n, self.rng)
        else:
            idx = systematic_resample(w, kld.n_max, self.rng)
            idx = idx[self.rng.permutation(idx.size)]
            n_new = self._kld_size(self.particles[idx], kld)
            idx = idx[:n_new]
        new = self.particles[idx].copy()
        if self.config.jitter_xy > 0:
            new[:, :2] += self.rng.normal(0.0, self.config.jitter_xy, (len(new), 2))
        if self.config.jitter_theta > 0:
            new[:, 2] = wrap_angle(new[:, 2] + self.rng.normal(0.0, self.config.jitter_theta, len(new)))
        self.particles = new
        self.log_weights = np.full(len(new), -math.log(len(new)))

    @staticmethod
    def _kld_size(ordered: FloatArray, kld: KldConfig) -> int:
        """Smallest prefix length n of ``ordered`` with n >= kld_sample_size(bins in prefix)."""
        bins = np.column_stack([np.floor(ordered[:, 0] / kld.bin_xy),
                                np.floor(ordered[:, 1] / kld.bin_xy),
                                np.floor((ordered[:, 2] + math.pi) / kld.bin_theta)])
        bins = bins.astype(np.int64)
        _, first = np.unique(bins, axis=0, return_index=True)
        is_new = np.zeros(len(ordered), dtype=bool)
        is_new[first] = True
        k = np.cumsum(is_new)
        need = kld_sample_size(k, kld)
        n = np.arange(1, len(ordered) + 1)
        ok = np.nonzero(n >= need)[0]
        return int(ok[0] + 1) if ok.size else len(ordered)

    # ------------------------------------------------------------------ results
    def estimate(self) -> tuple[FloatArray, FloatArray]:
        """Weighted mean pose (3,) (circular mean heading) and covariance (3, 3)."""
        return weighted_estimate(self.particles, self.log_weights)

    def spread(self) -> tuple[float, float]:
        """``(sigma_xy m, sigma_theta rad)``, see :func:`spread`."""
        return spread(self.particles, self.log_weights)

    def likelihood_collapsed(self) -> bool:
        """Whether the scans stopped fitting the particles (e.g. a kidnapped robot).

        True when the fast average of the per-beam evidence has fallen
        ``collapse_drop`` nats below the slow one (augmented MCL's
        ``w_fast / w_slow``, Probabilistic Robotics table 8.3, per beam and in log space).
        """
        if self.n_updates < 2:
            return False
        return self.evidence_fast < self.evidence_slow - self.config.collapse_drop

    def converged(self) -> bool:
        """Whether both spreads are below the configured bounds."""
        sxy, sth = self.spread()
        return sxy < self.config.converged_sigma_xy and sth < self.config.converged_sigma_theta
