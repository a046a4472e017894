"""Releasing map landmarks that today's sightings contradict (lifelong localize-only).

A saved map's landmark can be wrong today: the lamp was moved or replaced, or it was
mapped from poses that were off the same way on every pass (no test on the mapping
drive alone can see that). In localize-only with the map as priors
(:attr:`lampsam.backend.localize_only.LocalizeConfig.map_mode` ``"priors"``), each used
map landmark ``l`` is a state with the map's prior ``N(m_l, D_l)`` (``D_l`` its
conditional covariance given the map frame's offset, or its marginal without a frame
model). After the run's updates its estimate is ``p_l`` with covariance ``P_l``; the
correction ``d_l = p_l - m_l`` is, when the map is right and the models linear,
zero-mean with covariance ``D_l - P_l`` (the covariance of a Kalman correction is the
prior's minus the posterior's). Its test statistic on the horizontal rows,

    T_l = d_l^T (D_l - P_l)^-1 d_l        (x, y: 2 dof; ``D_l - P_l`` floored at
                                            :data:`VAR_FLOOR` per eigenvalue)

is the standardised residual of the landmark's map prior (Baarda's w-test for a prior
factor): with a map frame state, the common shift of the whole map is in ``g`` and not
in ``d_l``, so ``T_l`` tests the landmark against the rest of the map. A landmark whose
``T_l`` exceeds the chi-square quantile of :attr:`LocalizeConfig.release_prob` (2 dof)
after at least ``release_min_sightings`` of today's sightings is **released**: its state
covariance gets ``release_sigma^2`` added on ``x, y, z`` (the "lamp may have moved"
process noise), so from then on the run's sightings place it and it no longer pulls the
pose towards the map's value; a released lamp's axis is no longer used. One landmark at
a time, the largest ``T_l`` first (data snooping: releasing the worst one changes the
others' statistics), and only while the failing landmarks of its kind are at most
``release_max_fraction`` of the tested ones (at least :data:`MIN_TESTED`): when most of
the map disagrees with the run it is the pose that is wrong (a lost robot, a bad
start), not the map, and nothing is released (counted as ``blocked``).

The pure functions here are the test; :class:`lampsam.backend.localize_only.MapLocalizer`
keeps the state and applies it. Accuracy on lab: docs/ceiling-map.md.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from lampsam.arrays import FloatArray

#: eigenvalue floor on ``D_l - P_l``, m^2 (0.1 mm: a correction smaller than that is noise)
VAR_FLOOR = 1e-8

#: fewest tested landmarks of a kind for the majority guard to allow any release
MIN_TESTED = 3


@dataclass(frozen=True)
class Released:
    """A released map landmark.

    Attributes:
        id: the map landmark's id.
        kind: ``"lamp"`` or ``"corner"``.
        t: run time of the release, s.
        chi2: its statistic ``T_l`` at the release (2 dof).
        sightings: today's sightings of it up to the release.
    """

    id: int
    kind: str
    t: float
    chi2: float
    sightings: int


def release_statistic(delta: FloatArray, prior_cov: FloatArray, post_cov: FloatArray) -> FloatArray:
    """``T_l = d^T (D - P)^-1 d`` per landmark (module docstring).

    Args:
        delta: (N, 2) corrections ``p_l - m_l``, m (horizontal rows).
        prior_cov: (N, 2, 2) the map prior's covariance ``D_l``, m^2.
        post_cov: (N, 2, 2) the current state covariance ``P_l``, m^2.

    Returns:
        (N,) statistics (chi-square with 2 dof when the map is right).
    """
    c = np.asarray(prior_cov, float) - np.asarray(post_cov, float)
    c = 0.5 * (c + np.transpose(c, (0, 2, 1)))
    w, v = np.linalg.eigh(c)
    w = np.maximum(w, VAR_FLOOR)
    proj = np.einsum("nji,nj->ni", v, np.asarray(delta, float))  # V^T d
    return np.asarray(np.sum(proj * proj / w, axis=1), float)


def pick_release(stat: FloatArray, tested: np.ndarray, threshold: float,
                 max_fraction: float) -> tuple[int | None, int, bool]:
    """The landmark to release now, if any (module docstring).

    Args:
        stat: (N,) statistics ``T_l``.
        tested: (N,) bool, landmarks tested (enough sightings today, not yet released).
        threshold: the chi-square quantile.
        max_fraction: release only while the failing are at most this fraction of the
            tested.

    Returns:
        ``(index or None, number failing, blocked)``; ``blocked``: some fail but too many
        (or too few landmarks are tested) for the map to be the one that is wrong.
    """
    tested = np.asarray(tested, bool)
    fail = tested & (np.asarray(stat, float) > threshold)
    n_fail = int(fail.sum())
    if n_fail == 0:
        return None, 0, False
    n_tested = int(tested.sum())
    if n_tested < MIN_TESTED or n_fail > max_fraction * n_tested:
        return None, n_fail, True
    return int(np.argmax(np.where(fail, stat, -np.inf))), n_fail, False


def chi2_quantile_2dof(prob: float) -> float:
    """The chi-square quantile with 2 dof: ``-2 ln(1 - prob)`` (0.99: 9.21, 0.999: 13.82)."""
    return -2.0 * float(np.log1p(-float(prob)))


def release_cov(sigma: float) -> FloatArray:
    """(3, 3) covariance added to a released landmark's ``x, y, z``, m^2."""
    return float(sigma) ** 2 * np.eye(3)


__all__ = ["MIN_TESTED", "VAR_FLOOR", "Released", "chi2_quantile_2dof", "pick_release", "release_cov", "release_statistic"]
