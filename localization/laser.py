"""Global localization from planar laser scans on a grid map, from no prior knowledge.

There is no Kinect and hence no SIFT candidate (paper 2, sec. 3): the particle
filter (:mod:`.particle_filter`) starts uniform over the grid's free space and
is updated with one scan and the scans that follow, predicted between them by
odometry (Thrun et al., Probabilistic Robotics, ch. 8: MCL with a KLD-adaptive
sample size). Scans are weighed with the likelihood field
(:class:`~lampsam.localization.likelihood.LikelihoodFieldModel`), whose cost
does not depend on the map's size.

Frames: scan beams are in the laser frame (rad, CCW from forward), poses are
``world_T_laser`` (m, m, rad) on the map, odometry ``odom_T_laser``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from lampsam.arrays import FloatArray
from lampsam.localization.grid import OccupancyGrid
from lampsam.localization.likelihood import BeamModelConfig, LikelihoodFieldModel
from lampsam.localization.particle_filter import (
    KldConfig,
    MotionNoise,
    ParticleFilter,
    ParticleFilterConfig,
)


@dataclass(frozen=True)
class LaserLocalizerConfig:
    """The filter of laser-scan global localization.

    Attributes:
        particles: particles spread over the free space at the start. Default 100,000.
        beam: the beam model: sigma 0.15 m, 30 m range, beams tempered by 0.15
            (neighbouring beams of a 180-beam scan are far from independent).
        pf: the filter: KLD-adaptive sample size (500-20,000 after the first
            resampling), at most 90 beams per update, odometry noise of a
            wheeled robot, light roughening (2 cm, 0.01 rad).
    """

    particles: int = 100_000
    beam: BeamModelConfig = field(
        default_factory=lambda: BeamModelConfig(sigma_hit=0.15, max_range=30.0, beam_weight=0.15)
    )
    pf: ParticleFilterConfig = field(
        default_factory=lambda: ParticleFilterConfig(
            kld=KldConfig(n_min=500, n_max=20_000),
            max_beams=90,
            motion=MotionNoise(a_rot_rot=0.1, a_rot_trans=0.04, a_trans_trans=0.1,
                               a_trans_rot=0.02, sigma_trans_min=0.02, sigma_rot_min=0.01),
            jitter_xy=0.02,
            jitter_theta=0.01,
        )
    )  # fmt: skip


@dataclass(frozen=True)
class LaserEstimate:
    """The filter's answer after the last scan of a sequence.

    Attributes:
        pose: (3,) weighted mean ``world_T_laser`` (m, m, rad).
        covariance: (3, 3) particle covariance (heading wrapped).
        converged: the particles' spread is below the filter's bounds.
        spread_xy: position spread (m).
        spread_theta: heading spread (rad).
        particles: particles at the end.
    """

    pose: FloatArray
    covariance: FloatArray
    converged: bool
    spread_xy: float
    spread_theta: float
    particles: int


def localize_scans(
    model: LikelihoodFieldModel,
    grid: OccupancyGrid,
    ranges: FloatArray,
    angles: FloatArray,
    odom: FloatArray,
    config: LaserLocalizerConfig,
    rng: np.random.Generator,
) -> LaserEstimate:
    """Localize from a sequence of scans, starting with particles everywhere.

    Args:
        model: the measurement model on ``grid`` (build it once per map).
        grid: the map (its free space seeds the particles).
        ranges: (K, B) the scans' ranges (m, NaN = no usable return), in time order.
        angles: (B,) beam angles (rad, laser frame).
        odom: (K, 3) odometry poses at the scans.
        config: the filter settings.
        rng: generator of the particles.

    Returns:
        The estimate at the last scan.
    """
    pf = ParticleFilter(model, config.pf, rng)
    pf.init_uniform(grid, config.particles)
    k_last = len(ranges) - 1
    for k in range(len(ranges)):
        if k > 0:
            pf.predict(odom[k - 1], odom[k])
        pf.update(ranges[k], angles)
        if k < k_last:
            pf.resample_if_needed()
    mean, cov = pf.estimate()
    sxy, sth = pf.spread()
    return LaserEstimate(np.asarray(mean, dtype=float), np.asarray(cov, dtype=float),
                         bool(pf.converged()), float(sxy), float(sth), int(pf.n))  # fmt: skip
