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
from collections.abc import Callable, Iterable
from dataclasses import dataclass

import numpy as np
from lampsam.arrays import FloatArray
from lampsam.backend.config import AssociationConfig
from lampsam.backend.models import Obs

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
    return float(np.sum(np.asarray(a, float) * np.asarray(b, float)))


def associate(
    observations: list[Obs],
    candidates: dict[str, Iterable[int]],
    innovation: InnovationFn,
    config: AssociationConfig,
    existing: Callable[[int], bool],
    patches: dict[int, np.ndarray] | None = None,
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

    Returns:
        One :class:`Assignment` per observation, in input order.
    """
    result: dict[int, Assignment] = {}
    pairs: list[tuple[float, int, int, float]] = []  # (score, obs, landmark, d2)
    best_d2: dict[int, float] = {}
    for i, obs in enumerate(observations):
        if config.use_known_ids and obs.landmark_id is not None:
            lid = int(obs.landmark_id)
            result[i] = Assignment(i, lid, "matched" if existing(lid) else "new")
            continue
        gate = config.gate(len(obs.z))
        best = float("inf")
        for lid in candidates.get(obs.kind, ()):
            pred = innovation(lid, obs)
            if pred is None:
                continue
            d2 = mahalanobis2(*pred)
            best = min(best, d2)
            if d2 >= gate:
                continue
            if obs.kind == "corner":
                ncc = patch_ncc(obs.patch, (patches or {}).get(lid))
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
        del score
        result[i] = Assignment(i, lid, "matched", d2)
        used.add(lid)
    for i, obs in enumerate(observations):
        if i in result:
            continue
        if best_d2.get(i, float("inf")) > config.new_threshold(len(obs.z)):
            result[i] = Assignment(i, None, "new")
        else:
            result[i] = Assignment(i, None, "dropped", best_d2[i])
    return [result[i] for i in range(len(observations))]
