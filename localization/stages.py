"""The turn and filter stages of global localization (paper 2, secs. 3-4.1, Fig. 11).

1. **Turn in place** (:func:`turn_stage`): every Kinect frame's SIFT features
   give pose candidates (:mod:`.candidates`, eqs. 1-7), carried along with the
   turn by odometry, and the depth is accumulated in the 360-beam virtual scan
   (:mod:`.virtual_scan`).
2. **Particle filter** (:func:`filter_stage`) on the grid map
   (:mod:`.particle_filter`, beam model eqs. 8-9): the same number of particles
   in each candidate (or particles over the whole free space when there is
   none), updated on the virtual scan until their spread is below a bound.

Poses are ``world_T_body`` (m, m, rad) unless named ``odom``.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace

import numpy as np

from lampsam.arrays import FloatArray
from lampsam.factors.geometry import between, wrap_angle
from lampsam.localization.candidates import CandidateCollector, PoseCandidate, pf_candidates
from lampsam.localization.filter_config import GlobalLocalizerConfig, Mode
from lampsam.localization.likelihood import LikelihoodFieldModel, MeasurementModel, RayCastModel
from lampsam.localization.map_layers import EnvironmentMaps
from lampsam.localization.particle_filter import (
    KldConfig,
    ParticleFilter,
    normalise_log_weights,
    sample_candidate_discs,
    sample_free_space,
)
from lampsam.localization.robot import GlobalLocalizationError, Robot
from lampsam.localization.virtual_scan import VirtualScan, beam_angles
from lampsam.observe import emit

log = logging.getLogger(__name__)

#: distinct modes kept from the filter's first update (the estimate's competitors)
FIRST_MODES = 6


def mode_estimate(
    particles: FloatArray, log_weights: FloatArray, radius: float = 0.5
) -> FloatArray:
    """Weighted mean of the particles near the heaviest one.

    Unlike the global weighted mean, it stays on one mode when the filter has
    not (yet) collapsed to a single hypothesis.

    Args:
        particles: (N, 3) poses ``(x, y, theta)``.
        log_weights: (N,) log-weights.
        radius: neighbourhood of the heaviest particle (m in x, y; rad in theta).

    Returns:
        (3,) pose, circular mean heading.
    """
    w = np.exp(log_weights - log_weights.max())
    best = particles[int(np.argmax(w))]
    near = (np.hypot(particles[:, 0] - best[0], particles[:, 1] - best[1]) < radius) & (
        np.abs(np.asarray(wrap_angle(particles[:, 2] - best[2]))) < radius
    )
    ws = w[near] / w[near].sum()
    p = particles[near]
    th = float(np.arctan2(ws @ np.sin(p[:, 2]), ws @ np.cos(p[:, 2])))
    xy = ws @ p[:, :2]
    return np.array([xy[0], xy[1], th])


# ----------------------------------------------------------------------------- pipeline
#: Range tables already built, keyed by ``(id(grid), max_range)``; the grid is


def ray_model(maps: EnvironmentMaps, config: GlobalLocalizerConfig) -> RayCastModel:
    """The ray-casting beam model of the configuration (range-table lookup or marching)."""
    beam = config.filter.beam
    if config.filter.expected_ranges == "table":
        return RayCastModel(
            maps.grid, beam, method="table", table=maps.range_table(beam.max_range)
        )
    return RayCastModel(maps.grid, beam, method="march")


def scan_model(
    maps: EnvironmentMaps, config: GlobalLocalizerConfig
) -> RayCastModel | LikelihoodFieldModel:
    """The per-scan measurement model: the likelihood field when configured, else ray casting."""
    if config.filter.likelihood_field:
        return LikelihoodFieldModel(maps.grid, config.filter.beam)
    return ray_model(maps, config)


def turn_stage(
    robot: Robot,
    maps: EnvironmentMaps,
    config: GlobalLocalizerConfig,
    rng: np.random.Generator,
    required: bool = True,
) -> tuple[list[PoseCandidate], FloatArray, FloatArray, float, float] | None:
    """Turn in place: candidates and the virtual scan.

    Args:
        robot, maps, config, rng: the robot, map layers, configuration, generator.
        required: a turn without any frame is an error (else None is returned:
            a replayed log has run out).

    Returns:
        candidates (in the body frame at the end of the turn), the 360-beam scan
        (360,), the odometry pose at the end (3,), robot seconds, compute seconds.

    Raises:
        GlobalLocalizationError: no frame although ``required``.
    """
    frames = robot.turn(config.turn_angle, config.turn_rate)
    if not frames:
        if not required:
            return None
        raise GlobalLocalizationError("the robot returned no frame while turning")
    t0 = time.perf_counter()
    collector = CandidateCollector(
        maps.spatial_xyz, maps.spatial_descriptors, config.candidates, rng
    )
    vscan = VirtualScan(config.scan)
    use_candidates = config.mode is not Mode.GRID_ONLY
    for f in frames:
        vscan.add(f.odom, f.depth_points)
        if use_candidates:
            collector.add_frame(f.t, f.odom, f.sift_points, f.sift_descriptors)
        else:
            collector.move_to(f.odom)
    odom_end = np.asarray(frames[-1].odom, dtype=float)
    scan = vscan.scan(odom_end)
    compute = time.perf_counter() - t0
    robot_s = float(frames[-1].t - frames[0].t)
    log.info(
        "turn: %d frames, %d candidates, %d/360 beams",
        len(frames),
        len(collector.candidates),
        int(np.count_nonzero(np.isfinite(scan))),
    )
    emit("localize.candidates", candidates=list(collector.candidates))
    return collector.candidates, scan, odom_end, robot_s, compute


@dataclass(frozen=True)
class KeptScan:
    """A virtual scan of an earlier turn, kept for the next attempt.

    Attributes:
        ranges: (B,) ranges of the scan's used beams (m, NaN = no return).
        angles: (B,) their bearings (rad, body frame).
        odom: (3,) the odometry pose at the end of that turn.
    """

    ranges: FloatArray
    angles: FloatArray
    odom: FloatArray


class JointScanModel:
    """A measurement model that also scores earlier scans through the odometry.

    ``log p(z, z_1..z_K | x) = log p(z | x) + sum_k log p(z_k | x (+) delta_k)``
    with ``delta_k = between(odom_now, odom_k)``: the pose at the end of turn
    ``k`` seen from the current one (odometry frame), so ``x (+) delta_k`` is
    where a particle now was then.

    Args:
        model: the per-scan model (ray casting or likelihood field).
        kept: the earlier scans.
        odom_now: (3,) the odometry pose the particles refer to.
    """

    def __init__(
        self, model: MeasurementModel, kept: Sequence[KeptScan], odom_now: FloatArray
    ) -> None:
        self.model = model
        self.config = model.config
        self.kept = list(kept)
        self.deltas = [between(np.asarray(odom_now, dtype=float), k.odom) for k in self.kept]

    def log_likelihood(
        self, poses: FloatArray, ranges: FloatArray, angles: FloatArray
    ) -> FloatArray:
        """(P,) joint log-likelihood of the current scan and the kept ones (see class)."""
        ll = np.asarray(self.model.log_likelihood(poses, ranges, angles), dtype=np.float64)
        poses = np.asarray(poses, dtype=np.float64).reshape(-1, 3)
        for k, delta in zip(self.kept, self.deltas, strict=True):
            c, sn = np.cos(poses[:, 2]), np.sin(poses[:, 2])
            then = np.column_stack([
                poses[:, 0] + c * delta[0] - sn * delta[1],
                poses[:, 1] + sn * delta[0] + c * delta[1],
                wrap_angle(poses[:, 2] + delta[2]),
            ])  # fmt: skip
            ll = ll + self.model.log_likelihood(then, k.ranges, k.angles)
        return ll


def filter_stage(
    cands: Sequence[PoseCandidate],
    scan: FloatArray,
    model: MeasurementModel,
    maps: EnvironmentMaps,
    config: GlobalLocalizerConfig,
    rng: np.random.Generator,
    kept: Sequence[KeptScan] = (),
    odom_now: FloatArray | None = None,
) -> tuple[ParticleFilter, int, bool, FloatArray]:
    """Particle filter on the virtual scan until the spread is below the bound.

    The robot stands still after the turn, so the same scan is applied
    repeatedly, resampling (with roughening) in between, as the paper's
    "repeated process" (sec. 4.1) does. ``kept`` scans of earlier turns
    (``odom_now``: the odometry at the end of this turn) are scored along
    with it (:class:`JointScanModel`). ``config`` must be resolved
    (:meth:`GlobalLocalizerConfig.resolved`).

    Returns:
        The filter (particles at the end), the number of updates, converged or
        not, and the distinct modes (M, 3) after the first update (heaviest
        first, at most :data:`FIRST_MODES`; the competitors of the estimate).
    """
    fc = config.filter
    if kept:
        assert odom_now is not None
        model = JointScanModel(model, kept, odom_now)
    pf_config = fc.pf
    if fc.adaptive_sample_size and pf_config.kld is None:
        pf_config = replace(pf_config, kld=KldConfig())
    pf = ParticleFilter(model, pf_config, rng)
    if cands and config.mode is not Mode.GRID_ONLY and fc.uniform_beside_candidates > 0:
        disc = sample_candidate_discs(
            pf_candidates(cands), fc.particles_per_candidate, config.candidates.sigma_theta, rng
        )
        n_free = fc.uniform_beside_candidates
        pf.init_particles(np.vstack([disc, sample_free_space(maps.grid, n_free, rng)]))
        share = min(max(fc.uniform_share, 1e-6), 1.0 - 1e-6)
        prior = np.concatenate([
            np.full(len(disc), np.log((1.0 - share) / len(disc))),
            np.full(n_free, np.log(share / n_free)),
        ])  # fmt: skip
        pf.log_weights = normalise_log_weights(prior)
    elif cands and config.mode is not Mode.GRID_ONLY:
        pf.init_candidates(
            pf_candidates(cands), fc.particles_per_candidate, config.candidates.sigma_theta
        )
    else:
        pf.init_uniform(maps.grid, fc.n_uniform)
    angles = beam_angles()[:: fc.beam_step]
    ranges = scan[:: fc.beam_step]
    recheck = fc.recheck_modes > 0
    first: list[FloatArray] = []

    def after_update(n: int) -> None:
        if n == 1:
            first.append(distinct_modes(pf.particles, pf.log_weights,
                                        max(fc.recheck_modes, FIRST_MODES), fc.mode_separation))

    n_updates, converged = update_until_converged(pf, ranges, angles, fc.max_updates,
                                                  after_update)
    first_modes = first[0] if first else np.zeros((0, 3))
    log.info("filter: %d updates, %d particles, converged %s", n_updates, pf.n, converged)
    if recheck:
        best = mode_estimate(pf.particles, pf.log_weights)
        some = first_modes[: fc.recheck_modes]
        modes = distinct_modes(
            np.vstack([best[None], some]),
            np.concatenate([[0.0], np.full(len(some), -1.0)]),
            fc.recheck_modes,
            fc.mode_separation,
        )
        pf, n_more, converged = recheck_modes(
            modes, ranges, angles, maps, config, rng, kept, odom_now
        )
        n_updates += n_more
    return pf, n_updates, converged, first_modes


def update_until_converged(
    pf: ParticleFilter,
    ranges: FloatArray,
    angles: FloatArray,
    max_updates: int,
    after_update: Callable[[int], None] | None = None,
) -> tuple[int, bool]:
    """Update ``pf`` on one scan until it converges, resampling in between.

    Each update is published (``localize.particles``, :mod:`lampsam.observe`) and
    handed to ``after_update(n)`` (n = 1, 2, ...) before the convergence test.

    Args:
        pf: the filter, initialised.
        ranges, angles: (B,) the scan's used beams (m, NaN = no return; rad).
        max_updates: at most this many updates.

    Returns:
        The number of updates, converged or not.
    """
    n_updates = 0
    while n_updates < max_updates:
        n_updates += 1
        pf.update(ranges, angles)
        emit("localize.particles", particles=pf.particles, log_weights=pf.log_weights,
             update=n_updates)
        if after_update is not None:
            after_update(n_updates)
        if pf.converged():
            return n_updates, True
        pf.resample()
    return n_updates, False


def distinct_modes(
    particles: FloatArray, log_weights: FloatArray, k: int, separation: tuple[float, float]
) -> FloatArray:
    """The heaviest particles that are pairwise distinct (greedy non-maximum suppression).

    Args:
        particles: (N, 3) poses (m, m, rad).
        log_weights: (N,) log-weights (only their order matters).
        k: at most this many modes.
        separation: ``(metres, radians)``: a particle closer than both to a
            chosen mode is suppressed.

    Returns:
        (M, 3) modes, M <= k, heaviest first.
    """
    order = np.argsort(-np.asarray(log_weights, dtype=float))[: max(50 * k, 1000)]
    chosen: list[FloatArray] = []
    for i in order:
        p = particles[i]
        if chosen:
            c = np.asarray(chosen)
            near = (np.hypot(c[:, 0] - p[0], c[:, 1] - p[1]) < separation[0]) & (
                np.abs(np.asarray(wrap_angle(c[:, 2] - p[2]))) < separation[1]
            )
            if near.any():
                continue
        chosen.append(np.asarray(p, dtype=float))
        if len(chosen) >= k:
            break
    return np.asarray(chosen, dtype=float).reshape(-1, 3)


def recheck_modes(
    modes: FloatArray,
    ranges: FloatArray,
    angles: FloatArray,
    maps: EnvironmentMaps,
    config: GlobalLocalizerConfig,
    rng: np.random.Generator,
    kept: Sequence[KeptScan] = (),
    odom_now: FloatArray | None = None,
) -> tuple[ParticleFilter, int, bool]:
    """A short ray-casting particle filter over discs around the given modes.

    The same number of particles in each disc (as the paper does with its
    candidates), updated on the virtual scan until converged.

    Args:
        modes: (M, 3) poses to re-score (m, m, rad).
        ranges, angles: (B,) the scan's used beams (m, NaN = no return; rad).
        maps, config, rng: the map layers, the (resolved) configuration, the generator.
        kept, odom_now: earlier scans scored along (see :func:`filter_stage`).

    Returns:
        The filter, the number of updates, converged or not.
    """
    fc = config.filter
    model: MeasurementModel = ray_model(maps, config)
    if kept:
        assert odom_now is not None
        model = JointScanModel(model, kept, odom_now)
    pf = ParticleFilter(model, fc.pf, rng)
    pf.init_candidates(
        [(m, fc.recheck_radius) for m in modes], fc.recheck_particles, config.candidates.sigma_theta
    )
    n_updates, converged = update_until_converged(pf, ranges, angles, fc.max_updates)
    log.info(
        "re-check of %d modes by ray casting: %d updates, converged %s",
        len(modes),
        n_updates,
        converged,
    )
    return pf, n_updates, converged
