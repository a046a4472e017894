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

import math
from dataclasses import dataclass, field, replace

import numpy as np

from lampsam.arrays import FloatArray
from lampsam.factors.geometry import between, compose, wrap_angle
from lampsam.localization.correlative import (
    CorrelativeError,
    ScorePyramid,
    SearchConfig,
    branch_and_bound,
    scan_points,
)
from lampsam.localization.grid import OccupancyGrid
from lampsam.localization.likelihood import BeamModelConfig, LikelihoodFieldModel
from lampsam.localization.particle_filter import (
    KldConfig,
    MotionNoise,
    ParticleFilter,
    ParticleFilterConfig,
    sample_candidate_discs,
)
from lampsam.localization.stages import distinct_modes


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
        seeding: ``"search"`` (default): particles in the discs of the
            branch-and-bound candidates; ``"uniform"``: ``particles`` over the
            free space.
        search: the branch-and-bound search (10 cm cells, 1 deg, 8 candidates).
        search_scans: at most this many first scans joined by odometry for the
            search (default 4), and only while the odometry has turned less
            than ``search_max_turn`` and moved less than ``search_max_move``
            since the first: odometry error on a turn would smear the joined points.
        search_max_turn: degrees (default 20).
        search_max_move: metres (default 3).
        research_after: while not accepted this many scans after the first
            test, search again over the newest scans and add the candidates
            as extra modes (default 4).
        research_share: the weight the re-search's candidates take together
            (default 0.2; the filter's own particles keep the rest).
        per_candidate: particles per candidate disc (radius one search cell,
            heading spread one step). Default 2,000.
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
    seeding: str = "search"
    search: SearchConfig = field(default_factory=SearchConfig)
    search_scans: int = 4
    search_max_turn: float = 20.0
    search_max_move: float = 3.0
    research_after: int = 4
    research_share: float = 0.2
    per_candidate: int = 2000


def search_pyramid(model: LikelihoodFieldModel, config: LaserLocalizerConfig) -> ScorePyramid:
    """The branch-and-bound score pyramid of ``model``'s map (build once per map).

    The per-cell score is the model's likelihood field (untempered per-beam
    log-likelihood), max-pooled to ``config.search.resolution`` (rounded to a
    whole number of map cells).
    """
    res = model.grid.resolution * max(round(config.search.resolution / model.grid.resolution), 1)
    cfg = replace(config.search, resolution=res,
                  max_range=min(config.search.max_range, model.config.max_range))  # fmt: skip
    return ScorePyramid(model.grid, model.field, model.far, cfg)


def joined_scans(odom: FloatArray, config: LaserLocalizerConfig) -> int:
    """How many of the first scans the search joins (at least 1; see ``search_max_turn``)."""
    o = np.asarray(odom, dtype=float).reshape(-1, 3)
    turn = np.degrees(np.abs(np.asarray(wrap_angle(o[:, 2] - o[0, 2]))))
    move = np.hypot(o[:, 0] - o[0, 0], o[:, 1] - o[0, 1])
    bad = np.nonzero((turn >= config.search_max_turn) | (move >= config.search_max_move))[0]
    return int(bad[0]) if bad.size and bad[0] > 0 else (len(o) if not bad.size else 1)


def search_candidates(
    model: LikelihoodFieldModel, pyramid: ScorePyramid, ranges: FloatArray, angles: FloatArray,
    odom: FloatArray, config: LaserLocalizerConfig, accept: LaserAcceptConfig,
) -> tuple[FloatArray, FloatArray]:
    """Candidate poses at the first scan from a global search over the first scans.

    The scans are joined by odometry (:func:`~lampsam.localization.correlative.scan_points`),
    matched over the map by branch and bound, and each of the top-K leaves is
    refined on the map's cells by :func:`chain_log_likelihood` (one search cell
    and one heading step around it, then a quarter of that).

    Returns:
        (M, 3) refined poses at scan 0 (best search score first; M may be 0)
        and their (M,) search scores (nats per point).
    """
    cfg = replace(config.search, resolution=pyramid.res, max_range=pyramid.pad * pyramid.res)
    try:
        pts = scan_points(ranges, angles, odom, min(cfg.max_range, model.config.max_range),
                          cfg.resolution, cfg.max_points)  # fmt: skip
    except CorrelativeError:
        return np.zeros((0, 3)), np.zeros(0)
    cands, _ = branch_and_bound(pyramid, pts, cfg)
    step = math.radians(cfg.angle_step_deg)
    coarse = replace(accept, refine=(pyramid.res, step), refine_steps=5)
    fine = replace(accept, refine=(pyramid.res / 4, step / 4), refine_steps=5)
    out = []
    for c in cands:
        _, a = chain_log_likelihood(model, c.pose, 0, odom, ranges, angles, coarse)
        _, a = chain_log_likelihood(model, a, 0, odom, ranges, angles, fine)
        out.append(a)
    return np.asarray(out, dtype=float).reshape(-1, 3), np.array([c.score for c in cands])


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
        status: ``localized`` (accepted), ``ambiguous`` (a competitor within
            the margin) or ``failed`` (not converged); see :class:`LaserAcceptConfig`.
        margin: the likelihood-ratio margin over the best competitor (nats).
        competitor: (3,) the best competitor's pose at the last scan, or None.
        scans_used: scans used.
        score: the estimate's fit, log-likelihood per used beam (nats).
    """

    pose: FloatArray
    covariance: FloatArray
    converged: bool
    spread_xy: float
    spread_theta: float
    particles: int
    status: str = "failed"
    margin: float = math.nan
    competitor: FloatArray | None = None
    scans_used: int = 0
    score: float = math.nan


@dataclass(frozen=True)
class LaserAcceptConfig:
    """The acceptance test of a laser estimate (a likelihood ratio between hypotheses).

    Attributes:
        min_margin: accept (``localized``) when the estimate's joint scan
            log-likelihood exceeds the best competing hypothesis' by this many
            nats (tempered; default 8). Calibrated on tuning trials (docs/localization.md).
        min_score: and when the scans fit the map at the estimate: joint
            log-likelihood per used beam (nats, untempered) at least this, over
            the last ``fit_scans`` scans (a long odometry chain drifts beyond
            the per-scan refinement window, so older scans are left out; default 0.45).
        fit_scans: scans of the fit (default 4).
        modes: competing hypotheses: the distinct modes of the first update (default 8).
        separation: two hypotheses are distinct when this far apart (m, rad; default (1.0, 0.5)).
        refine: half-width of the grid search refining each hypothesis'
            anchor pose (m, rad; default (0.2, 0.1)), with ``refine_steps`` values per axis.
        refine_steps: grid values per axis (odd; default 5).
        max_scans: while not accepted, keep adding scans up to this many in all (default 12).
    """

    min_margin: float = 8.0
    min_score: float = 0.45
    fit_scans: int = 4
    modes: int = 8
    separation: tuple[float, float] = (1.0, 0.5)
    refine: tuple[float, float] = (0.2, 0.1)
    refine_steps: int = 5
    max_scans: int = 12


def chain(anchor: FloatArray, k_anchor: int, odom: FloatArray) -> FloatArray:
    """(K, 3) poses at every scan given the pose ``anchor`` at scan ``k_anchor`` and the odometry.

    ``x_k = anchor (+) between(odom[k_anchor], odom[k])``: the hypothesis moved
    with the robot's own odometry (no noise), backwards or forwards.
    """
    out = np.empty_like(np.asarray(odom, dtype=float))
    for k in range(len(odom)):
        out[k] = compose(anchor, between(odom[k_anchor], odom[k]))
    return out


def chain_log_likelihood(
    model: LikelihoodFieldModel, anchor: FloatArray, k_anchor: int, odom: FloatArray,
    ranges: FloatArray, angles: FloatArray, accept: LaserAcceptConfig,
) -> tuple[float, FloatArray]:
    """Best joint log-likelihood of the scans over a small grid of anchor poses around ``anchor``.

    Returns:
        The best sum over scans of the tempered scan log-likelihoods (nats) and
        the refined anchor (3,).
    """
    n = accept.refine_steps
    dxy, dth = accept.refine
    g = np.linspace(-1.0, 1.0, n)
    ox, oy, ot = np.meshgrid(g * dxy, g * dxy, g * dth, indexing="ij")
    anchors = np.asarray(anchor, dtype=float) + np.column_stack([ox.ravel(), oy.ravel(), ot.ravel()])
    total = np.zeros(len(anchors))
    for k in range(len(odom)):
        d = between(odom[k_anchor], odom[k])
        c, s = np.cos(anchors[:, 2]), np.sin(anchors[:, 2])
        poses = np.column_stack([anchors[:, 0] + c * d[0] - s * d[1],
                                 anchors[:, 1] + s * d[0] + c * d[1], anchors[:, 2] + d[2]])  # fmt: skip
        total += model.log_likelihood(poses, ranges[k], angles)
    i = int(np.argmax(total))
    return float(total[i]), anchors[i]


def scan_fit(
    model: LikelihoodFieldModel, poses: FloatArray, ranges: FloatArray, angles: FloatArray,
    accept: LaserAcceptConfig,
) -> float:
    """How well the scans fit the map near ``poses``: log-likelihood per used beam (nats, untempered).

    Each scan is matched on its own over the small grid of
    :attr:`LaserAcceptConfig.refine` around its pose, so that odometry drift
    along a hypothesis does not lower the fit (Cartographer's ``min_score`` of a
    scan match, with the beam model's likelihood as the score).
    """
    n = accept.refine_steps
    dxy, dth = accept.refine
    g = np.linspace(-1.0, 1.0, n)
    ox, oy, ot = np.meshgrid(g * dxy, g * dxy, g * dth, indexing="ij")
    offsets = np.column_stack([ox.ravel(), oy.ravel(), ot.ravel()])
    total, n_beams = 0.0, 0
    for k in range(len(poses)):
        ll = model.log_likelihood(np.asarray(poses[k], dtype=float) + offsets, ranges[k], angles)
        total += float(np.max(ll))
        n_beams += int(np.count_nonzero(np.isfinite(ranges[k]) & (ranges[k] < model.config.max_range)))
    return total / (model.config.beam_weight * max(n_beams, 1))


def hypothesis_margin(
    model: LikelihoodFieldModel, ranges: FloatArray, angles: FloatArray, odom: FloatArray,
    estimate: FloatArray, first_modes: FloatArray, accept: LaserAcceptConfig,
) -> tuple[float, FloatArray | None, float, FloatArray]:
    """The estimate's joint log-likelihood margin over the best distinct competing hypothesis.

    The estimate (at the last scan) and every first-update mode (at the first
    scan) are moved along the scans by odometry (:func:`chain`), each refined by
    a small grid search, and scored on all scans jointly.

    Returns:
        The margin (nats; +inf without a competitor), the competitor's pose at
        the last scan (or None), and the estimate's fit: its joint
        log-likelihood per used beam (nats, untempered), and the estimate
        refined by the grid search (two levels) at the last scan (3,).
    """
    last = len(odom) - 1
    ll_est, a_est = chain_log_likelihood(model, estimate, last, odom, ranges, angles, accept)
    fine = replace(accept, refine=(accept.refine[0] / 4, accept.refine[1] / 4))
    ll_est, a_est = chain_log_likelihood(model, a_est, last, odom, ranges, angles, fine)
    w = max(1, accept.fit_scans)
    score = scan_fit(model, chain(a_est, last, odom)[-w:], ranges[-w:], angles, accept)
    best_ll, best_pose = -math.inf, None
    for m in np.asarray(first_modes).reshape(-1, 3):
        ll, a = chain_log_likelihood(model, m, 0, odom, ranges, angles, accept)
        at_last = chain(a, 0, odom)[last]
        if _near(at_last, a_est, accept.separation):
            continue
        if ll > best_ll:
            best_ll, best_pose = ll, at_last
    if best_pose is None:
        return math.inf, None, score, a_est
    return ll_est - best_ll, best_pose, score, a_est


def _near(a: FloatArray, b: FloatArray, separation: tuple[float, float]) -> bool:
    return bool(math.hypot(a[0] - b[0], a[1] - b[1]) < separation[0]
                and abs(math.remainder(float(a[2] - b[2]), 2 * math.pi)) < separation[1])


def localize_scans(
    model: LikelihoodFieldModel,
    grid: OccupancyGrid,
    ranges: FloatArray,
    angles: FloatArray,
    odom: FloatArray,
    config: LaserLocalizerConfig,
    rng: np.random.Generator,
    min_scans: int | None = None,
    accept: LaserAcceptConfig | None = None,
    pyramid: ScorePyramid | None = None,
) -> LaserEstimate:
    """Localize from a sequence of scans, starting with particles everywhere.

    After ``min_scans`` scans the estimate is tested (:func:`hypothesis_margin`);
    while it is not accepted and scans remain (up to ``accept.max_scans``), the
    filter takes the next scan and tests again.

    Args:
        model: the measurement model on ``grid`` (build it once per map).
        grid: the map (its free space seeds the particles).
        ranges: (K, B) the scans' ranges (m, NaN = no usable return), in time order.
        angles: (B,) beam angles (rad, laser frame).
        odom: (K, 3) odometry poses at the scans.
        config: the filter settings.
        rng: generator of the particles.
        min_scans: scans before the first test (default all ``K``).
        accept: the acceptance test (default :class:`LaserAcceptConfig`).
        pyramid: the map's search pyramid (:func:`search_pyramid`; built here
            when the seeding is ``"search"`` and none is given).

    Returns:
        The estimate at the last scan used, with its answer.
    """
    accept = LaserAcceptConfig() if accept is None else accept
    k_min = len(ranges) if min_scans is None else min(int(min_scans), len(ranges))
    k_max = min(len(ranges), max(k_min, accept.max_scans))
    pf = ParticleFilter(model, config.pf, rng)
    first_modes = np.zeros((0, 3))
    if config.seeding == "search":
        pyramid = search_pyramid(model, config) if pyramid is None else pyramid
        m = joined_scans(odom[: max(1, min(config.search_scans, k_min))], config)
        first_modes, _ = search_candidates(model, pyramid, ranges[:m], angles, odom[:m], config,
                                           accept)  # fmt: skip
        if len(first_modes) == 0:
            return LaserEstimate(np.full(3, np.nan), np.full((3, 3), np.nan), False, math.inf,
                                 math.inf, 0, "failed", scans_used=m)  # fmt: skip
        pf.init_candidates([(p, pyramid.res) for p in first_modes], config.per_candidate,
                           math.radians(config.search.angle_step_deg))  # fmt: skip
    elif config.seeding == "uniform":
        pf.init_uniform(grid, config.particles)
    else:
        raise ValueError(f"seeding must be search or uniform, not {config.seeding!r}")
    margin, competitor, score = math.nan, None, math.nan
    k = 0
    while True:
        if k > 0:
            pf.predict(odom[k - 1], odom[k])
        pf.update(ranges[k], angles)
        if k == 0 and config.seeding == "uniform":
            first_modes = distinct_modes(pf.particles, pf.log_weights, accept.modes,
                                         accept.separation)  # fmt: skip
        k += 1
        if k >= k_min:
            mean, _ = pf.estimate()
            margin, competitor, score, _ = hypothesis_margin(model, ranges[:k], angles, odom[:k],
                                                          mean, first_modes, accept)  # fmt: skip
            if _accepted(pf.converged(), margin, score, accept) or k >= k_max:
                break
            if (config.seeding == "search" and pyramid is not None
                    and k == k_min + config.research_after):
                first_modes = _research(model, pyramid, pf, ranges[:k], angles, odom[:k], config,
                                        accept, first_modes)  # fmt: skip
                continue
        pf.resample_if_needed()
    mean, cov = pf.estimate()
    sxy, sth = pf.spread()
    converged = bool(pf.converged())
    status = ("localized" if _accepted(converged, margin, score, accept)
              else "ambiguous" if converged else "failed")  # fmt: skip
    return LaserEstimate(np.asarray(mean, dtype=float), np.asarray(cov, dtype=float), converged,
                         float(sxy), float(sth), int(pf.n), status, float(margin), competitor,
                         k, float(score))  # fmt: skip


def _research(
    model: LikelihoodFieldModel, pyramid: ScorePyramid, pf: ParticleFilter, ranges: FloatArray,
    angles: FloatArray, odom: FloatArray, config: LaserLocalizerConfig,
    accept: LaserAcceptConfig, first_modes: FloatArray,
) -> FloatArray:
    """Search again over the latest scans while not accepted; add the candidates as extra modes.

    The first scans may fit the map badly (people, a door): the newest scans
    (joined as in the first search, counted back from the last) get their own
    candidates. Those not within ``accept.separation`` of the filter's estimate
    join the filter as extra modes (:meth:`ParticleFilter.add_particles`, with
    ``config.research_share`` of the weight), so that a cluster the filter has
    nearly converged to is kept; the following scans decide between them. The
    new candidates, carried back to scan 0 by odometry, also join the competing
    hypotheses. Returns the hypotheses at scan 0.
    """
    last = len(odom) - 1
    j = last
    while j > 0 and last - j + 1 < config.search_scans and (
            joined_scans(odom[j - 1 : last + 1], config) == last - j + 2):
        j -= 1
    cands, _ = search_candidates(model, pyramid, ranges[j:], angles, odom[j:], config, accept)
    if len(cands) == 0:
        return first_modes
    now = [chain(c, 0, odom[j:])[-1] for c in cands]
    mean, _ = pf.estimate()
    extra = [(p, pyramid.res) for p in now if not _near(p, mean, accept.separation)]
    if extra:
        pf.add_particles(sample_candidate_discs(extra, config.per_candidate,
                                                math.radians(config.search.angle_step_deg), pf.rng),
                         config.research_share)  # fmt: skip
    back = np.array([chain(c, last, odom)[0] for c in now])
    return np.vstack([np.asarray(first_modes).reshape(-1, 3), back])


def _accepted(converged: bool, margin: float, score: float, accept: LaserAcceptConfig) -> bool:
    return bool(converged and margin >= accept.min_margin and score >= accept.min_score)
