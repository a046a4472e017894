"""Releasing map landmarks that today's sightings contradict (lifelong localize-only).

A saved map's landmark can be wrong today: the lamp was moved or replaced, or it was
mapped from poses that were off the same way on every pass (no test on the mapping
drive alone can see that). In localize-only with the map as priors
(:attr:`lampsam.backend.localize_config.LocalizeConfig.map_mode` ``"priors"``), each used
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
``release_max_fraction`` of the tested ones, counting those released before (at least
:data:`MIN_TESTED`): when most of the map disagrees with the run it is the pose that is
wrong (a lost robot, a bad start), not the map, and nothing is released (counted as
``blocked``); a run never releases more than that fraction of a kind's landmarks.

The pure functions here are the test; :class:`ReleaseTracker` keeps today's sightings
and applies it for :class:`lampsam.backend.localize_only.MapLocalizer`, and also reports
map lamps that were in view many times and never matched (removed, moved out of their
gate, or spurious). Accuracy on lab: docs/ceiling-map.md.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from lampsam.arrays import FloatArray
from lampsam.backend.config import chi2_quantile

if TYPE_CHECKING:
    from lampsam.backend.localize_config import LocalizeConfig

log = logging.getLogger(__name__)

#: eigenvalue floor on ``D_l - P_l``, m^2 (0.1 mm: a correction smaller than that is noise)
VAR_FLOOR = 1e-8

#: fewest tested landmarks of a kind for the majority guard to allow any release
MIN_TESTED = 3

#: a map lamp counts as in view when predicted within this fraction of the image's radius
UNSEEN_RADIUS = 0.8
#: frames in view before a map lamp never matched is reported (:meth:`ReleaseTracker.unseen_report`)
UNSEEN_MIN_FRAMES = 30
#: matched in fewer than this fraction of its frames in view: reported as unseen
UNSEEN_MAX_RATIO = 0.1


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


def release_statistic(delta: FloatArray, prior_cov: FloatArray, post_cov: FloatArray,
                      evidence_scale: float = 1.0) -> FloatArray:
    """``T_l = d^T C^-1 d`` per landmark, ``C = D - P`` (module docstring) or, with the
    run's evidence understated ``k`` times (``evidence_scale``), ``C = (D + (k - 1) P)
    D^-1 (D - P)`` (symmetrised).

    With ``K = (D - P) D^-1`` the gain and ``E = D (D - P)^-1 P`` the run's evidence
    covariance, ``d = K (e - m)`` has covariance ``K (D + k E) K^T``, which is the ``C``
    above (``D - P`` at ``k = 1``).

    Args:
        delta: (N, 2) corrections ``p_l - m_l``, m (horizontal rows).
        prior_cov: (N, 2, 2) the map prior's covariance ``D_l``, m^2.
        post_cov: (N, 2, 2) the current state covariance ``P_l``, m^2.
        evidence_scale: ``k >= 1``.

    Returns:
        (N,) statistics (chi-square with 2 dof when the map is right and ``k`` is).
    """
    d_cov = np.asarray(prior_cov, float)
    p_cov = np.asarray(post_cov, float)
    c = d_cov - p_cov
    if evidence_scale != 1.0:
        a = d_cov + (evidence_scale - 1.0) * p_cov
        c = a @ np.linalg.solve(d_cov + VAR_FLOOR * np.eye(2), c)
    c = 0.5 * (c + np.transpose(c, (0, 2, 1)))
    w, v = np.linalg.eigh(c)
    w = np.maximum(w, VAR_FLOOR)
    proj = np.einsum("nji,nj->ni", v, np.asarray(delta, float))  # V^T d
    return np.asarray(np.sum(proj * proj / w, axis=1), float)


def pick_release(stat: FloatArray, tested: np.ndarray, threshold: float,
                 max_fraction: float, n_released: int = 0) -> tuple[int | None, int, bool]:
    """The landmark to release now, if any (module docstring).

    Args:
        stat: (N,) statistics ``T_l``.
        tested: (N,) bool, landmarks tested (enough sightings today, not yet released).
        threshold: the chi-square quantile.
        max_fraction: release only while the failing and the already released are at
            most this fraction of the tested and released (so that a run never releases
            more than this fraction of a kind's landmarks).
        n_released: landmarks of the kind released before (not in ``tested``).

    Returns:
        ``(index or None, number failing, blocked)``; ``blocked``: some fail but too many
        (or too few landmarks are tested) for the map to be the one that is wrong.
    """
    tested = np.asarray(tested, bool)
    fail = tested & (np.asarray(stat, float) > threshold)
    n_fail = int(fail.sum())
    if n_fail == 0:
        return None, 0, False
    n_tested = int(tested.sum()) + n_released
    if n_tested < MIN_TESTED or n_fail + n_released > max_fraction * n_tested:
        return None, n_fail, True
    return int(np.argmax(np.where(fail, stat, -np.inf))), n_fail, False


def release_cov(sigma: float) -> FloatArray:
    """(3, 3) covariance added to a released landmark's ``x, y, z``, m^2."""
    return float(sigma) ** 2 * np.eye(3)


class ReleaseTracker:
    """Today's sightings of the map's landmarks, the release test, and unseen lamps.

    Kept by :class:`lampsam.backend.localize_only.MapLocalizer`, per kind (``"lamp"``,
    ``"corner"``) over the kind's used map landmarks in the localizer's order.

    Args:
        kinds: kind -> ``(ids, points (M, 3), cov (M, 3, 3))``: the map's priors as loaded
            (position m, covariance m^2: ``D_l`` with a frame model, else the marginal).
        loc: the release settings (``release_*`` of :class:`LocalizeConfig`).
    """

    def __init__(self, kinds: dict[str, tuple[list[int], FloatArray, FloatArray]],
                 loc: LocalizeConfig) -> None:
        self.loc = loc
        self.ids = {k: list(v[0]) for k, v in kinds.items()}
        self.prior_pts = {k: np.array(v[1], float) for k, v in kinds.items()}
        self.prior_cov = {k: np.array(v[2], float) for k, v in kinds.items()}
        #: today's matched sightings per landmark
        self.seen = {k: np.zeros(len(v[0]), int) for k, v in kinds.items()}
        #: frames with the landmark predicted inside :data:`UNSEEN_RADIUS` of the view
        self.view = {k: np.zeros(len(v[0]), int) for k, v in kinds.items()}
        self.released = {k: np.zeros(len(v[0]), bool) for k, v in kinds.items()}
        self.threshold = chi2_quantile(loc.release_prob, 2)
        self.releases: list[Released] = []
        self.blocked = 0
        self.lamps_unmatched = 0

    def in_view(self, kind: str, mask: np.ndarray) -> None:
        """Count a frame for the landmarks of ``kind`` in ``mask`` (M,) bool."""
        self.view[kind][mask] += 1

    def unmatched(self, kind: str, n: int) -> None:
        """Count ``n`` sightings of ``kind`` that matched no map landmark (lamps only)."""
        if kind == "lamp":
            self.lamps_unmatched += n

    def check(self, t: float, points: dict[str, FloatArray], covs: dict[str, FloatArray],
              pj: FloatArray, offsets: dict[str, int]) -> None:
        """Test the used landmarks; release at most one per kind (module docstring).

        Args:
            t: run time, s.
            points: kind -> (M, 3) current estimates, m.
            covs: kind -> (M, 3, 3) their current covariance blocks, m^2 (updated in place
                for a released landmark).
            pj: the joint state covariance (updated in place: ``release_cov`` added on the
                released landmark's block).
            offsets: kind -> index of the kind's first landmark in ``pj``.
        """
        for kind in self.loc.release_kinds:
            if kind not in offsets:
                continue
            tested = (self.seen[kind] >= self.loc.release_min_sightings) & ~self.released[kind]
            if not tested.any():
                continue
            stat = np.zeros(len(self.ids[kind]))
            sel = np.flatnonzero(tested)
            stat[sel] = release_statistic(points[kind][sel, :2] - self.prior_pts[kind][sel, :2],
                                          self.prior_cov[kind][sel, :2, :2],
                                          covs[kind][sel, :2, :2], self.loc.release_evidence_scale)
            j, _, blocked = pick_release(stat, tested, self.threshold,
                                         self.loc.release_max_fraction,
                                         int(self.released[kind].sum()))
            self.blocked += int(blocked)
            if j is None:
                continue
            o = offsets[kind] + 3 * j
            pj[o:o + 3, o:o + 3] += release_cov(self.loc.release_sigma)
            covs[kind][j] = pj[o:o + 3, o:o + 3]
            self.released[kind][j] = True
            lid = self.ids[kind][j]
            self.releases.append(Released(lid, kind, t, float(stat[j]), int(self.seen[kind][j])))
            log.info("t=%.2f s: map %s %d released (chi2 %.1f > %.1f after %d sightings)",
                     t, kind, lid, stat[j], self.threshold, self.seen[kind][j])

    def release_report(self, points: dict[str, FloatArray]) -> list[dict[str, object]]:
        """The released landmarks for ``summary.json``: id, kind, time (s), statistic,
        sightings up to the release and in all, and ``offset_m``: the run's estimate
        (``points``) minus the map's value, ``(x, y, z)`` m in the map's frame (the frame
        offset ``g`` not included)."""
        out: list[dict[str, object]] = []
        for r in self.releases:
            j = self.ids[r.kind].index(r.id)
            off = points[r.kind][j] - self.prior_pts[r.kind][j]
            out.append({"id": r.id, "kind": r.kind, "t_s": r.t, "chi2": r.chi2,
                        "sightings_at_release": r.sightings,
                        "sightings": int(self.seen[r.kind][j]),
                        "offset_m": [float(v) for v in off]})
        return out

    def unseen_report(self) -> list[dict[str, object]]:
        """Map lamps the run should have seen but did not: in view (:data:`UNSEEN_RADIUS`)
        in at least :data:`UNSEEN_MIN_FRAMES` frames and matched in under
        :data:`UNSEEN_MAX_RATIO` of them (a lamp removed, or moved out of its gate; a
        spurious map lamp): id, kind, frames in view, frames matched."""
        view, seen = self.view.get("lamp"), self.seen.get("lamp")
        if view is None or seen is None:
            return []
        return [{"id": self.ids["lamp"][j], "kind": "lamp", "frames_in_view": int(view[j]),
                 "frames_matched": int(seen[j])}
                for j in range(len(view))
                if view[j] >= UNSEEN_MIN_FRAMES and seen[j] < UNSEEN_MAX_RATIO * view[j]]


__all__ = ["ReleaseTracker", "UNSEEN_MAX_RATIO", "UNSEEN_MIN_FRAMES", "UNSEEN_RADIUS", "MIN_TESTED", "VAR_FLOOR", "Released", "pick_release", "release_cov", "release_statistic"]
