"""Landmark book-keeping of the EKF state.

For :class:`lampsam.backend.ekf.EkfSlam`: each landmark's slot in ``x``/``P``, the amortised pruning test (paper 1, sec. IV: landmarks
seen once long ago, or still uncertain after a while) and the removal of landmarks'
rows and columns from ``x`` and ``P``.
"""

from __future__ import annotations

import collections
import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from lampsam.arrays import FloatArray
from lampsam.backend.config import AssociationConfig
from lampsam.backend.covariance import LowerCovariance

#: Landmarks examined by the EKF's pruning per step (round robin).
PRUNE_CHECKS_PER_STEP = 8
#: A planar landmark is pruned as uncertain only above this many times the sigma of
#: one sighting (and above ``prune_sigma``).
PRUNE_MEAS_SIGMAS = 3.0
#: Doomed landmarks are removed from the state in batches of this size (or this often).
PRUNE_BATCH = 16


@dataclass
class Slot:
    """Book-keeping of one landmark in the EKF state."""

    id: int
    kind: str
    offset: int  # first index of the landmark's state in x (and row/column in P)
    dim: int
    n_obs: int
    created: int  # step of the first sighting
    last_seen: int  # step of the last update
    patch: Any = None
    sigma_meas: float = 0.0  # largest horizontal sigma one sighting gives (planar points), m
    first: FloatArray | None = None  # state at initialisation (first-estimates Jacobians)
    # horizontal sigma conditional on the pose of the last sighting, m (NaN: not tracked)
    sigma_rel: float = math.nan


def max_sigma_2x2(cov: FloatArray) -> float:
    """Largest standard deviation of a 2x2 covariance (closed-form eigenvalue), m."""
    a, b, d = float(cov[0, 0]), float(cov[0, 1]), float(cov[1, 1])
    lam = 0.5 * (a + d) + math.sqrt(max(0.25 * (a - d) ** 2 + b * b, 0.0))
    return math.sqrt(max(lam, 0.0))


def conditional_sigma(p_pose: FloatArray, p_lp: FloatArray, p_ll: FloatArray) -> float:
    """Largest horizontal sigma of a landmark given the robot's pose, m.

    Args:
        p_pose: (3, 3) covariance of the pose ``(x, y, theta)`` (m, rad).
        p_lp: (2, 3) cross-covariance of the landmark's ``(x, y)`` (world frame, m)
            and the pose.
        p_ll: (2, 2) covariance of the landmark's ``(x, y)``, m^2.

    Returns:
        The largest standard deviation of ``p_ll - p_lp p_pose^-1 p_lp^T`` (the Schur
        complement: the landmark's uncertainty were the pose known), m; the
        absolute sigma if ``p_pose`` is singular.
    """
    try:
        cond = p_ll - p_lp @ np.linalg.solve(p_pose, p_lp.T)
    except np.linalg.LinAlgError:
        cond = p_ll
    return max_sigma_2x2(cond)


def note_relative_sigma(cov: LowerCovariance, pairs: list[tuple[Slot, Any]],
                        slots: dict[int, Slot]) -> None:
    """Record ``Slot.sigma_rel`` of the landmarks without a known id sighted (or
    started) this step: their horizontal sigma conditional on the current pose
    (:func:`conditional_sigma` on the 5x5 block of pose and landmark in ``cov``).

    Args:
        cov: the EKF's covariance, the pose ``(x, y, theta)`` in rows 0-2.
        pairs: (slot, observation) pairs of the step; observations with a
            ``landmark_id`` (known ids) are skipped: they keep the absolute rule.
        slots: the current slots (pairs whose landmark has gone are skipped).

    The pose of that sighting leaves the state at the next step, but later updates
    can only shrink the landmark's uncertainty given it: the value is an upper bound.
    """
    p_pose = None
    for sl, o in pairs:
        if o.landmark_id is not None or sl.id not in slots:
            continue
        if p_pose is None:
            p_pose = cov.block(0, 3, 0, 3)
        a = sl.offset
        sl.sigma_rel = conditional_sigma(p_pose, cov.block(a, a + 2, 0, 3),
                                         cov.block(a, a + 2, a, a + 2))


def prune_reason(s: Slot, step: int, cfg: AssociationConfig,
                 position_cov: Callable[[Slot], FloatArray]) -> str:
    """Why landmark ``s`` should go at ``step``, or "" to keep it.

    ``"seen_too_few"``: fewer than ``min_observations`` sightings and idle for more
    than ``prune_after_steps``; ``"uncertain"``: older and idle for more than
    ``prune_after_steps`` with a horizontal sigma above ``prune_sigma`` and above
    :data:`PRUNE_MEAS_SIGMAS` times the sigma of one sighting. The sigma is the
    landmark's own, conditional on the pose of its last sighting (``s.sigma_rel``),
    when ``cfg.prune_relative`` and it is tracked; else the absolute one (of
    ``position_cov(s)``, the (2, 2) block of ``P``), which also holds the robot's
    uncertainty.
    """
    idle = step - s.last_seen
    if s.n_obs < cfg.min_observations and idle > cfg.prune_after_steps:
        return "seen_too_few"
    if step - s.created > cfg.prune_after_steps and idle > cfg.prune_after_steps:
        limit = max(cfg.prune_sigma, PRUNE_MEAS_SIGMAS * s.sigma_meas)
        rel = cfg.prune_relative and not math.isnan(s.sigma_rel)
        sigma = s.sigma_rel if rel else max_sigma_2x2(position_cov(s))
        return "uncertain" if sigma > limit else ""
    return ""


def prune_round(queue: collections.deque[int], slots: dict[int, Slot], doomed: set[int],
                step: int, cfg: AssociationConfig,
                position_cov: Callable[[Slot], FloatArray]) -> list[tuple[int, str]]:
    """Check the next :data:`PRUNE_CHECKS_PER_STEP` landmarks of the round-robin ``queue``.

    Amortised O(1) per step (each landmark is checked every ``n /
    PRUNE_CHECKS_PER_STEP`` steps). Landmarks to drop are added to ``doomed`` (they
    stop being candidates at once); the others go back to the end of the queue; ids
    no longer in ``slots`` or already doomed leave it.

    Returns:
        ``(landmark id, reason)`` of the newly doomed, in queue order.
    """
    newly: list[tuple[int, str]] = []
    for _ in range(min(PRUNE_CHECKS_PER_STEP, len(queue))):
        lid = queue.popleft()
        s = slots.get(lid)
        if s is None or lid in doomed:
            continue
        reason = prune_reason(s, step, cfg, position_cov)
        if reason:
            doomed.add(lid)
            newly.append((lid, reason))
        else:
            queue.append(lid)
    return newly


def remove_landmarks(x: FloatArray, n: int, cov: LowerCovariance, slots: dict[int, Slot],
                     lids: list[int]) -> int:
    """Cut landmarks ``lids`` out of the state ``x[:n]`` and ``cov`` in place.

    Their slots are popped from ``slots`` and the others' offsets shifted down; ``cov``
    is compacted in place (O(n^2)).

    Returns:
        The new state size.
    """
    keep = np.ones(n, dtype=bool)
    for lid in lids:
        s = slots.pop(lid)
        keep[s.offset : s.offset + s.dim] = False
    idx = np.flatnonzero(keep)
    kept = x[idx].copy()
    cov.delete(keep)
    x[: len(idx)] = kept
    new_offset = np.cumsum(keep) - 1
    for s in slots.values():
        s.offset = int(new_offset[s.offset])
    return len(idx)


def grown_state(x: FloatArray, n: int, extra: int) -> FloatArray:
    """The state buffer ``x`` (``n`` entries used) with room for ``extra`` more: ``x``
    itself when it has the room, else a copy of ``x[:n]`` in a buffer 1.5x larger (at
    least ``n + extra``)."""
    cap = len(x)
    if n + extra <= cap:
        return x
    out = np.zeros(max(n + extra, cap + cap // 2))
    out[:n] = x[:n]
    return out


def free_id(slots: dict[int, Slot], start: int) -> int:
    """The first landmark id ``>= start`` not in ``slots``."""
    while start in slots:
        start += 1
    return start
