"""Whether a scan-only estimate can be trusted: its margin over the best competing mode.

Without a ceiling to verify against (paper 2's ``grid_only`` and ``no_ceiling``
rows, laser-only maps), a converged particle filter can still sit on the wrong
one of several places that explain the scan nearly as well (a 90- or
180-degree twin of a near-symmetric room, a corridor that looks the same along
its length). The test here is a likelihood ratio: the estimate is compared with
the best competitor among the distinct modes after the filter's first update
(each refined by a short ray-casting filter, :func:`~lampsam.localization.stages.recheck_modes`),
and it is accepted when its scan log-likelihood (tempered, eqs. 8-9) exceeds
the competitor's by ``min_margin`` nats. This is the spirit of Cartographer's
``min_score`` for a global match, applied to the ratio between modes rather than
to the absolute score, which depends on the scan's size and the clutter.
The margin's false-accept rate is measured on trials (docs/localization.md).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from lampsam.arrays import FloatArray
from lampsam.factors.geometry import wrap_angle
from lampsam.localization.filter_config import GlobalLocalizerConfig
from lampsam.localization.map_layers import EnvironmentMaps
from lampsam.localization.stages import mode_estimate, ray_model, recheck_modes


@dataclass(frozen=True)
class ModeMargin:
    """The estimate against its best competitor.

    Attributes:
        margin: log-likelihood of the estimate minus the competitor's (nats,
            tempered; +inf when there is no competitor).
        competitor: (3,) the competitor's refined pose, or None.
        score: the estimate's scan log-likelihood per used beam (nats).
    """

    margin: float
    competitor: FloatArray | None
    score: float


def separated(a: FloatArray, b: FloatArray, separation: tuple[float, float]) -> bool:
    """Poses ``a`` and ``b`` differ by more than ``separation`` (m, rad) in position or heading."""
    return bool(
        math.hypot(a[0] - b[0], a[1] - b[1]) >= separation[0]
        or abs(float(wrap_angle(float(a[2] - b[2])))) >= separation[1]
    )


def mode_margin(
    pose: FloatArray,
    modes: FloatArray,
    scan: FloatArray,
    maps: EnvironmentMaps,
    config: GlobalLocalizerConfig,
    rng: np.random.Generator,
) -> ModeMargin:
    """The estimate's log-likelihood margin over the best well-separated competing mode.

    Args:
        pose: (3,) the filter's estimate (m, m, rad).
        modes: (M, 3) distinct modes of the filter's first update.
        scan: (360,) the virtual scan (m, NaN = no return).
        maps: the map layers.
        config: the (resolved) configuration (beam model, separation).
        rng: generator of the competitors' refinement.
    """
    fc = config.filter
    from lampsam.localization.virtual_scan import beam_angles

    angles = beam_angles()[:: fc.beam_step]
    ranges = scan[:: fc.beam_step]
    model = ray_model(maps, config)
    ll_pose = float(model.log_likelihood(np.asarray(pose, dtype=float)[None], ranges, angles)[0])
    n_used = max(int(np.count_nonzero(np.isfinite(ranges))), 1)
    score = ll_pose / n_used
    rivals = [m for m in np.asarray(modes).reshape(-1, 3) if separated(m, pose, fc.mode_separation)]
    if not rivals:
        return ModeMargin(math.inf, None, score)
    pf, _, _ = recheck_modes(np.asarray(rivals), ranges, angles, maps, config, rng)
    alt = mode_estimate(pf.particles, pf.log_weights)
    if not separated(alt, pose, fc.mode_separation):
        return ModeMargin(math.inf, None, score)
    ll_alt = float(model.log_likelihood(alt[None], ranges, angles)[0])
    return ModeMargin(ll_pose - ll_alt, alt, score)
