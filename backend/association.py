"""Data association shared by the EKF, iSAM2 and batch backends (paper 1, eqs. 19-20).

For every observation and every candidate landmark of the same kind, the backend
supplies the innovation ``nu = z - h(x)`` and its covariance
``Psi = H P H^T + R`` (eq. 19; ``P`` is the EKF's covariance or iSAM2's marginals).
An observation is associated with a landmark when the squared Mahalanobis
distance ``nu^T Psi^-1 nu`` is below the chi-square gate ``d`` (eq. 20):

- lamps and planar points: the gate alone (nearest in Mahalanobis distance);
- corners: among the gated candidates, the best normalised cross-correlation of
  the image patches, if at least ``ncc_min``;
- each landmark takes at most one observation per frame (greedy, best first);
- an observation farther than the "new" threshold from every landmark starts a new
  landmark; one between the two thresholds is ambiguous and dropped.

With known association (``landmark_id`` set and ``use_known_ids``) the id decides.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from lampsam.arrays import FloatArray
from lampsam.backend.alias_gate import psi_logdet, refuses
from lampsam.backend.config import AssociationConfig
from lampsam.backend.models import Obs
from lampsam.backend.planar_gate import rival_material
from lampsam.factors.geometry import mahalanobis2_2x2

log = logging.getLogger(__name__)

#: Innovation callback: ``(landmark_id, obs) -> (nu (k,), Psi (k, k))`` or None
#: when the landmark cannot be predicted for this observation (behind, out of view).
InnovationFn = Callable[[int, Obs], "tuple[FloatArray, FloatArray] | None"]


@dataclass(frozen=True)
class Assignment:
    """The association decision for one observation.

    Attributes:
        obs_index: index into the frame's observation list.
        landmark_id: the matched (or, for ``"new"`` with known ids, the new) landmark
            id; None for a new landmark whose id the backend assigns, or a drop.
        status: ``"matched"`` (an existing landmark), ``"new"``, or ``"dropped"``
            (ambiguous: inside the new-landmark threshold but outside the gate).
        d2: squared Mahalanobis distance of the match (NaN for new/dropped/known).
    """

    obs_index: int
    landmark_id: int | None
    status: str
    d2: float = float("nan")


def mahalanobis2(nu: FloatArray, psi: FloatArray) -> float:
    """Squared Mahalanobis distance ``nu^T Psi^-1 nu`` (paper eq. 20).

    Args:
        nu: (k,) innovation.
        psi: (k, k) innovation covariance (eq. 19), symmetric positive definite.

    Returns:
        The distance; ``inf`` when ``psi`` is singular.
    """
    try:
        return float(nu @ np.linalg.solve(psi, nu))
    except np.linalg.LinAlgError:
        return float("inf")


def patch_ncc(a: np.ndarray | None, b: np.ndarray | None) -> float:
    """Normalised cross-correlation of two corner patches.

    The frontend stores patches zero-mean and unit-norm
    (:class:`lampsam.frontend.measurements.CornerObservation`), so the NCC is their
    dot product. Missing or mismatched patches give -1 (never a match).

    Args:
        a, b: (P, P) float patches or None.

    Returns:
        NCC in [-1, 1].
    """
    if a is None or b is None or np.shape(a) != np.shape(b):
        return -1.0
    return float(np.vdot(np.asarray(a, float), np.asarray(b, float)))


def associate(
    observations: list[Obs],
    candidates: Mapping[str, Iterable[int]],
    innovation: InnovationFn,
    config: AssociationConfig,
    existing: Callable[[int], bool],
    patches: Mapping[int, np.ndarray | None] | None = None,
    screened: dict[int, dict[int, tuple[float, bool]]] | None = None,
    same_place: Callable[[int, int], bool] | None = None,
    alias_density: float = 0.0,
) -> list[Assignment]:
    """Associate one frame's observations with the map (paper eqs. 19-20, NCC for corners).

    Args:
        observations: the frame's observations.
        candidates: landmark ids per kind that may be visible (the backend's
            pre-selection), e.g. ``{"lamp": [...], "corner": [...]}``.
        innovation: the backend's innovation callback (eq. 19).
        config: gate probabilities and NCC threshold.
        existing: ``existing(id)`` tells whether a landmark id is in the map (for
            known association).
        patches: corner landmark id -> reference patch, for NCC.
        screened: optional pre-screening by the backend (:func:`screen_pairs`):
            observation index -> {landmark id: (d2, exact)}. For a screened
            observation only these landmarks are candidates (the others are beyond
            the new-landmark threshold); an ``exact`` distance is used as is, an
            inexact one (a cheaper, wider gate) only to skip the pair or, when it is
            below the gate and the NCC passes, to ask ``innovation`` for the exact
            one. Corner pairs failing the NCC never cost an innovation call.
        same_place: ``planar_unique``: ``same_place(a, b)`` tells that landmarks ``a``
            and ``b`` stand at one place (a tree mapped twice): such a rival of the
            nearest landmark does not hold the sighting.
        alias_density: ``alias_odds``: landmarks per m^2 (the map's,
            :func:`lampsam.backend.alias_gate.map_density`); a range-bearing pair
            inside the gate is kept only when its likelihood is ``alias_odds`` times
            that of an unmapped landmark at this density (0: no test). A sighting
            whose every gated pair fails is ``"new"`` with ``alias_new``, else
            ``"dropped"`` (held with ``planar_unique``).

    Returns:
        One :class:`Assignment` per observation, in input order.
    """
    result: dict[int, Assignment] = {}
    pairs: list[tuple[float, int, int, float]] = []  # (score, obs, landmark, d2)
    best_d2: dict[int, float] = {}
    # planar_unique: (d2, log det Psi) of the landmarks within its threshold (NaN: not known)
    near: dict[int, list[tuple[float, float, int]]] = {}
    aliased: set[int] = set()  # sightings with a gated pair the alias test refused
    for i, obs in enumerate(observations):
        if config.use_known_ids and obs.landmark_id is not None:
            lid = int(obs.landmark_id)
            result[i] = Assignment(i, lid, "matched" if existing(lid) else "new")
            continue
        gate = config.gate(len(obs.z))
        best = float("inf")
        items: Iterable[tuple[int, tuple[float, bool]]]
        if screened is not None and i in screened:
            items = screened[i].items()
        else:
            items = ((lid, (float("nan"), False)) for lid in candidates.get(obs.kind, ()))
        unique = config.planar_unique and obs.kind == "point2"
        unique_t = config.unique_threshold(len(obs.z))
        alias = alias_density > 0.0 and obs.kind == "point2" and config.alias_odds > 0.0
        for lid, (d2_screen, exact) in items:
            screen_only = not math.isnan(d2_screen)
            if screen_only and d2_screen >= gate and not (unique and d2_screen < unique_t):
                best = min(best, d2_screen)  # cannot match: the screen is wider
                continue
            ncc = 0.0
            if obs.kind == "corner":
                ncc = patch_ncc(obs.patch, (patches or {}).get(lid))
                if ncc < config.ncc_min and screen_only:
                    best = min(best, d2_screen)
                    continue
            logdet = math.nan
            pred = None
            if exact:
                d2 = d2_screen
            else:
                pred = innovation(lid, obs)
                if pred is None:
                    continue
                d2 = mahalanobis2(*pred)
                if unique:
                    logdet = psi_logdet(pred[1])
            best = min(best, d2)
            if unique and d2 < unique_t:
                near.setdefault(i, []).append((d2, logdet, lid))
            if d2 >= gate:
                continue
            if alias:
                if pred is None:  # an exact screen distance: the covariance is still needed
                    pred = innovation(lid, obs)
                if refuses(d2, None if pred is None else pred[1], float(obs.z[1]),
                           alias_density, config.alias_odds):
                    aliased.add(i)
                    continue
            if obs.kind == "corner":
                if ncc < config.ncc_min:
                    continue
                pairs.append((-ncc, i, lid, d2))
            else:
                pairs.append((d2, i, lid, d2))
        best_d2[i] = best
    # Greedy one-to-one assignment, best score first.
    used: set[int] = set()
    for score, i, lid, d2 in sorted(pairs):
        if i in result or lid in used:
            continue
        rivals = [(d, ld) for d, ld, b in near.get(i, ())
                  if b == lid or same_place is None or not same_place(lid, b)]
        if rival_material(rivals, config):  # a likely rival elsewhere: held
            result[i] = Assignment(i, None, "dropped", d2)
            continue
        del score
        result[i] = Assignment(i, lid, "matched", d2)
        used.add(lid)
    for i, obs in enumerate(observations):
        if i in result:
            continue
        if i in aliased:  # only refused pairs: held, or a landmark of its own
            result[i] = (Assignment(i, None, "new") if config.alias_new
                         else Assignment(i, None, "dropped", best_d2[i]))
            continue
        if best_d2.get(i, float("inf")) > config.new_threshold(len(obs.z)):
            result[i] = Assignment(i, None, "new")
        else:
            result[i] = Assignment(i, None, "dropped", best_d2[i])
    return [result[i] for i in range(len(observations))]


def pairwise_d2(z: FloatArray, r: FloatArray, z_hat: FloatArray, s: FloatArray) -> FloatArray:
    """Squared Mahalanobis distances of every observation to every prediction (eq. 20).

    For 2-D measurements: ``d2[i, j] = nu^T (S_j + R_i)^-1 nu`` with
    ``nu = z_i - z_hat_j`` (no angle: ceiling coordinates), the 2x2 inverse in
    closed form, all pairs at once.

    Args:
        z: (N, 2) measurements; r: (N, 2, 2) their noise.
        z_hat: (M, 2) predictions; s: (M, 2, 2) prediction covariances
            ``H P H^T`` (eq. 19 without ``R``).

    Returns:
        (N, M) distances; ``inf`` where the sum is not positive definite.
    """
    # the entries of psi = R_i + S_j as (N, M) planes (no (N, M, 2, 2) temporary)
    a = r[:, None, 0, 0] + s[None, :, 0, 0]
    b = 0.5 * ((r[:, None, 0, 1] + s[None, :, 0, 1]) + (r[:, None, 1, 0] + s[None, :, 1, 0]))
    d = r[:, None, 1, 1] + s[None, :, 1, 1]
    nu0 = z[:, None, 0] - z_hat[None, :, 0]
    nu1 = z[:, None, 1] - z_hat[None, :, 1]
    d2, pd = mahalanobis2_2x2(nu0, nu1, a, b, d)
    return np.where(pd, d2, np.inf)


def screen_pairs(observations: list[Obs], kind: str, lids: list[int], z_hat: FloatArray,
                 s: FloatArray, config: AssociationConfig, exact: bool
                 ) -> dict[int, dict[int, tuple[float, bool]]]:
    """Pre-screen observations of one kind against M predicted landmarks (vectorised).

    Uses the position part ``(u, v)`` of each observation (for a lamp with an axis
    the distance over the first two rows is a lower bound of the full one) and keeps
    the pairs below the new-landmark threshold (:meth:`AssociationConfig.new_threshold`):
    the others can neither match nor make the observation ambiguous.

    Args:
        observations: the frame's observations (all kinds).
        kind: the kind to screen.
        lids: (M,) landmark ids of the predictions.
        z_hat: (M, 2) predicted ``(u, v)``; s: (M, 2, 2) their covariance ``H P H^T``.
        config: association thresholds.
        exact: ``s`` is the full eq.-19 covariance (with the pose-landmark cross
            term), so a 2-D distance is final; otherwise every kept distance is a
            screen only.

    Returns:
        For :func:`associate`'s ``screened``: obs index -> {landmark id: (d2, exact)}.
    """
    idx = [i for i, o in enumerate(observations) if o.kind == kind]
    out: dict[int, dict[int, tuple[float, bool]]] = {i: {} for i in idx}
    if not idx or not lids:
        return out
    z = np.array([observations[i].z[:2] for i in idx], float)
    r = np.array([observations[i].R[:2, :2] for i in idx], float)
    d2 = pairwise_d2(z, r, np.asarray(z_hat, float), np.asarray(s, float))
    for row, i in enumerate(idx):
        dof = len(observations[i].z)
        keep = np.flatnonzero(d2[row] < config.new_threshold(dof))
        fin = exact and dof == 2
        out[i] = {lids[j]: (float(d2[row, j]), fin) for j in keep}
    return out


def corner_budget(matches: list[tuple[Any, Obs]], budget: int | None
                  ) -> tuple[list[tuple[Any, Obs]], int]:
    """Keep at most ``budget`` mapped corner landmarks per frame (smoothers; EKF optional).

    Every landmark in the graph that a keyframe observes becomes a variable of
    iSAM2's root clique (GTSAM orders the newly observed keys last), so the update
    and the pose marginal grow with the cube of the number observed: about 100
    ceiling corners per frame on the lab world made both 20-100 ms. The EKF's
    update costs ``O(n^2 K)`` for ``K`` measurement rows. The corners with the
    longest tracks (most observations, then the oldest id) are kept: they tie the
    frame to the most of the map. Lamps, planar points and corners not yet in the
    graph (pending, delayed initialisation) always pass. A landmark without an
    ``in_graph`` attribute (an EKF slot) counts as mapped.

    Args:
        matches: ``(landmark, observation)`` pairs of one keyframe; a landmark has
            ``kind``, ``n_obs``, ``id`` and optionally ``in_graph``.
        budget: the most in-graph corners kept, or None for no limit.

    Returns:
        ``(kept pairs in their input order, corners that may still enter the graph
        this frame = max(2, budget - mapped corners kept))``; with no budget
        the second is unbounded.
    """
    if budget is None:
        return matches, 1 << 30
    in_graph = [j for j, (lm, _) in enumerate(matches)
                if lm.kind == "corner" and getattr(lm, "in_graph", True)]
    ranked = sorted(in_graph, key=lambda j: (-matches[j][0].n_obs, matches[j][0].id))
    drop = set(ranked[budget:])
    kept = [m for j, m in enumerate(matches) if j not in drop]
    return kept, max(2, budget - min(len(in_graph), budget))


#: ``joint(pairs)`` -> stacked innovation (K,) and its joint covariance (K, K) of a
#: hypothesis ``[(observation index, landmark id), ...]``.
JointInnovationFn = Callable[[list[tuple[int, int]]], tuple[FloatArray, FloatArray] | None]


def jcbb(candidates: Mapping[int, Iterable[int]], joint: JointInnovationFn,
         config: AssociationConfig, obs_dim: int = 2, max_nodes: int = 20000
         ) -> list[tuple[int, int]]:
    """Joint compatibility branch and bound (Neira & Tardos 2001, IEEE T-RA 17(6)).

    Among hypotheses that pair observations with distinct landmarks, find the one
    with the most pairings whose *joint* Mahalanobis distance
    ``D2 = nu^T S^-1 nu`` (``nu``, ``S`` stacked over the pairings, with every
    cross-covariance: the shared robot pose makes the innovations of one frame
    correlated) is below the chi-square gate for its dimension (``config.gate``);
    ties go to the smaller ``D2``. Individually compatible pairs that are not
    jointly compatible (one tree taken for its neighbour because the pose is off)
    are rejected together instead of one by one.

    Args:
        candidates: observation index -> individually compatible landmark ids.
        joint: the backend's joint innovation of a hypothesis (None: not predictable).
        config: gate probability.
        obs_dim: rows per observation (2 for ``[bearing, range]``).
        max_nodes: search budget; the best hypothesis found so far is returned when
            it is spent (the search is exponential in the worst case).

    Returns:
        The best hypothesis as ``(observation index, landmark id)`` pairs.
    """
    obs_order = sorted(candidates, key=lambda i: len(list(candidates[i])))
    cand = {i: list(candidates[i]) for i in obs_order}
    best: list[tuple[int, int]] = []
    best_d2 = math.inf
    nodes = 0

    def d2_of(hyp: list[tuple[int, int]]) -> float | None:
        out = joint(hyp)
        if out is None:
            return None
        nu, s = out
        try:
            return float(nu @ np.linalg.solve(s, nu))
        except np.linalg.LinAlgError:
            return None

    def search(level: int, hyp: list[tuple[int, int]], used: set[int], d2: float) -> None:
        nonlocal best, best_d2, nodes
        nodes += 1
        if nodes > max_nodes:
            return
        if level == len(obs_order):
            if len(hyp) > len(best) or (len(hyp) == len(best) and d2 < best_d2):
                best, best_d2 = list(hyp), d2
            return
        i = obs_order[level]
        for lid in cand[i]:
            if lid in used:
                continue
            trial = [*hyp, (i, lid)]
            d2_t = d2_of(trial)
            if d2_t is None or d2_t >= config.gate(obs_dim * len(trial)):
                continue
            used.add(lid)
            search(level + 1, trial, used, d2_t)
            used.discard(lid)
        # leave observation i unpaired, if that can still beat the best
        if len(hyp) + len(obs_order) - level - 1 >= len(best):
            search(level + 1, hyp, used, d2)

    search(0, [], set(), 0.0)
    return best


def reassign_jointly(assignments: list[Assignment], candidates: Mapping[int, list[int]], joint: JointInnovationFn,
                     config: AssociationConfig) -> list[Assignment]:
    """Re-pair the observations in ``candidates`` by :func:`jcbb` (Neira & Tardos 2001).

    The observations JCBB pairs are ``"matched"`` to its landmark; one it leaves
    unpaired keeps a ``"new"`` from the individual gate (beyond the new-landmark
    threshold of every landmark) and is otherwise ``"dropped"`` (some landmark is
    near, but no pairing with it is jointly compatible): one tree is then neither
    given to its neighbour nor mapped twice. Observations not in ``candidates`` keep
    their assignment.

    Args:
        assignments: the individual gate's decisions (:func:`associate`).
        candidates: observation index -> landmarks individually inside the gate.
        joint: stacked innovation and its joint covariance of a hypothesis.
        config: the gate probability.

    Returns:
        One :class:`Assignment` per observation, in input order.
    """
    paired = dict(jcbb(candidates, joint, config))
    out: list[Assignment] = []
    for a in assignments:
        i = a.obs_index
        if i not in candidates:
            out.append(a)
        elif i in paired:
            out.append(Assignment(i, paired[i], "matched"))
        elif a.status == "new":
            out.append(a)
        else:
            out.append(Assignment(i, None, "dropped"))
    return out


@dataclass(eq=False)
class Tentative:
    """A candidate planar landmark not yet in the map.

    Attributes:
        xy: (2,) fused world position, m.
        cov: (2, 2) its covariance, m^2.
        hits: sightings fused so far.
        last_step: step of the latest sighting.
    """

    xy: FloatArray
    cov: FloatArray
    hits: int
    last_step: int


class TentativeLandmarks:
    """New-landmark rule without ids: a landmark enters the map after ``k`` sightings.

    One sighting of a tree with a 0.2 rad bearing sigma at 20 m puts it anywhere in a
    4 m wide arc; mapped at once, its next sighting (inside the new-landmark
    threshold of the wrong estimate, or beyond it) starts a second landmark, and the
    map fills with copies. Here an unassociated sighting goes to a tentative list
    first: a later unassociated sighting whose world position is within the
    chi-square ``gate`` (Mahalanobis, on the sum of both covariances) of a tentative
    one is fused into it (information-weighted); the one that brings it to
    ``confirm`` sightings is returned as confirmed (and the caller initialises the
    landmark from it, with its proper cross-covariances). A confirmed position within
    ``min_separation`` of a mapped landmark is discarded as a copy. Tentatives not
    seen for ``max_idle`` steps expire. The backend-independent part of the rule:
    backends give world positions and covariances.

    Args:
        confirm: sightings needed (1: every unassociated sighting starts a landmark,
            the paper's rule).
        gate: squared Mahalanobis distance for fusing into a tentative (2 dof).
        max_idle: steps after which an unconfirmed tentative is forgotten.
        min_separation: m; 0 disables the copy check.
    """

    def __init__(self, confirm: int, gate: float, max_idle: int, min_separation: float = 0.0
                 ) -> None:
        self.confirm = confirm
        self.gate = gate
        self.max_idle = max_idle
        self.min_separation = min_separation
        self.items: list[Tentative] = []
        self.n_expired = 0
        self.n_copies = 0

    def offer(self, xy: FloatArray, cov: FloatArray, step: int,
              mapped_xy: FloatArray | None = None) -> bool:
        """Add one unassociated sighting; True when it confirms a landmark.

        Args:
            xy: (2,) the sighting's world position, m; cov: (2, 2) its covariance.
            step: current step (for expiry).
            mapped_xy: (M, 2) positions of mapped landmarks (the copy check), or None.

        Returns:
            True when the caller should initialise a landmark from this sighting.
        """
        xy = np.asarray(xy, float)
        cov = np.asarray(cov, float)
        best, best_d2 = None, self.gate
        for t in self.items:
            d2 = mahalanobis2(xy - t.xy, cov + t.cov)
            if d2 < best_d2:
                best, best_d2 = t, d2
        if best is None:
            best = Tentative(xy.copy(), cov.copy(), 1, step)
            self.items.append(best)
        else:
            info_a, info_b = np.linalg.inv(best.cov), np.linalg.inv(cov)
            c = np.linalg.inv(info_a + info_b)
            best.xy = c @ (info_a @ best.xy + info_b @ xy)
            best.cov = c
            best.hits += 1
            best.last_step = step
        if best.hits < self.confirm:
            return False
        self.items = [t for t in self.items if t is not best]
        if (self.min_separation > 0 and mapped_xy is not None and len(mapped_xy)
                and float(np.min(np.linalg.norm(mapped_xy - best.xy, axis=1))) < self.min_separation):
            self.n_copies += 1
            return False
        return True

    def expire(self, step: int) -> None:
        """Forget tentatives not seen for more than ``max_idle`` steps."""
        keep = [t for t in self.items if step - t.last_step <= self.max_idle]
        self.n_expired += len(self.items) - len(keep)
        self.items = keep
