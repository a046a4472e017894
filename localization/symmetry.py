"""Half-turn symmetry of a ceiling map, and telling a pose from its twin by the scan.

A ceiling whose lamp layout is symmetric under a half turn (the office's is)
cannot tell a pose from its twin rotated by pi about the symmetry centre: the
ceiling verification (paper 2, sec. 4.2) passes both. The floor-level scan can,
when the furniture is not symmetric too (:func:`resolve_half_turn`).
"""

from __future__ import annotations

import logging

import numpy as np

from lampsam.arrays import FloatArray
from lampsam.factors.geometry import wrap_angle
from lampsam.localization.filter_config import GlobalLocalizerConfig
from lampsam.localization.map_layers import EnvironmentMaps
from lampsam.localization.stages import mode_estimate, ray_model, recheck_modes
from lampsam.localization.virtual_scan import beam_angles

log = logging.getLogger(__name__)


def half_turn_centre(
    xy: FloatArray, phi: FloatArray | None = None, tol: float = 0.15
) -> FloatArray | None:
    """Centre of a half-turn symmetry of a ceiling map, if it has one.

    The map is half-turn symmetric about its centroid ``c`` when every feature
    ``p`` has a feature within ``tol`` of ``2 c - p`` (and, with axes, with
    the same axis mod pi: a half turn keeps a line's direction). A pose and
    its half-turn twin then see the same ceiling.

    Args:
        xy: (L, 2) feature positions, world frame (m).
        phi: (L,) long axes (rad, mod pi), NaN for none; None: not checked.
        tol: position tolerance (m).

    Returns:
        (2,) the centre (m), or None (no symmetry, or fewer than 2 features).
    """
    xy = np.asarray(xy, dtype=float).reshape(-1, 2)
    if len(xy) < 2:
        return None
    c = xy.mean(axis=0)
    mirrored = 2.0 * c - xy
    d = np.hypot(*(mirrored[:, None, :] - xy[None, :, :]).transpose(2, 0, 1))
    j = np.argmin(d, axis=1)
    if not np.all(d[np.arange(len(xy)), j] <= tol):
        return None
    if phi is not None:
        a = np.asarray(phi, dtype=float).reshape(-1)
        both = np.isfinite(a) & np.isfinite(a[j])
        if np.any(np.isfinite(a) != np.isfinite(a[j])):
            return None
        diff = np.abs(np.asarray(wrap_angle(2.0 * (a[both] - a[j][both])))) / 2.0
        if np.any(diff > np.deg2rad(10.0)):
            return None
    return c


def half_turn_twin(pose: FloatArray, centre: FloatArray) -> FloatArray:
    """(3,) the pose rotated by pi about ``centre`` (m): ``(2c - xy, theta + pi)``."""
    p = np.asarray(pose, dtype=float)
    return np.array(
        [2.0 * centre[0] - p[0], 2.0 * centre[1] - p[1], float(wrap_angle(p[2] + np.pi))]
    )

def resolve_half_turn(
    pose: FloatArray,
    scan: FloatArray,
    centre: FloatArray,
    maps: EnvironmentMaps,
    config: GlobalLocalizerConfig,
    rng: np.random.Generator,
) -> tuple[FloatArray, float]:
    """The estimate or its half-turn twin, whichever the scan prefers, and by how much.

    Each of the two poses is refined by a short ray-casting particle filter
    (:func:`~lampsam.localization.stages.recheck_modes`, one disc) and scored by the ray-casting model
    (eqs. 8-9, tempered); the ceiling cannot tell them apart when the map is
    half-turn symmetric about ``centre``.

    Args:
        pose: (3,) the filter's estimate (m, m, rad).
        scan: (360,) the virtual scan (m, NaN = no return).
        centre: (2,) the symmetry centre (m), :func:`half_turn_centre`.
        maps: the map layers.
        config: the configuration.
        rng: generator of the refinement.

    Returns:
        The preferred pose (3,) and its log-likelihood margin over the other (nats, >= 0).
    """
    fc = config.filter
    angles = beam_angles()[:: fc.beam_step]
    ranges = scan[:: fc.beam_step]
    model = ray_model(maps, config)
    refined, scores = [], []
    for h in (np.asarray(pose, dtype=float), half_turn_twin(pose, centre)):
        pf, _, _ = recheck_modes(h[None], ranges, angles, maps, config, rng)
        est = mode_estimate(pf.particles, pf.log_weights)
        refined.append(est)
        scores.append(float(model.log_likelihood(est[None], ranges, angles)[0]))
    best = int(np.argmax(scores))
    margin = abs(scores[0] - scores[1])
    log.info(
        "half-turn twin check: estimate %.1f, twin %.1f (log-likelihood): %s",
        scores[0],
        scores[1],
        "twin" if best == 1 else "estimate",
    )
    return refined[best], margin
