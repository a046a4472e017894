"""The EKF's loop closure without ids: copies of re-found landmarks merged into their originals.

Every ``planar_merge_every`` steps, the planar landmarks created in the last
``planar_merge_window`` steps are matched as a rigid constellation against the older
ones (:func:`lampsam.backend.constellation.match_constellation`); each matched copy
is merged into its original by an equality update
(:func:`lampsam.backend.constellation.equality_gain`) and removed from the state,
its sightings counted on the original.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from lampsam.arrays import FloatArray
from lampsam.backend.constellation import equality_gain, match_constellation
from lampsam.backend.models import LandmarkKind

if TYPE_CHECKING:
    from lampsam.backend.ekf import EkfSlam

#: Variance of the merge constraint, m^2 (the copy and the original are one tree).
MERGE_VAR = 1e-4


def close_loops(ekf: EkfSlam) -> int:
    """Merge recently mapped copies into old landmarks (see the module docstring).

    Returns:
        Landmarks merged.
    """
    cfg = ekf.config.association
    step = ekf._step
    if not cfg.planar_merge or step % cfg.planar_merge_every:
        return 0
    slots = [s for s in ekf._slots.values()
             if s.kind == LandmarkKind.POINT2 and s.id not in ekf._doomed]
    new = [s for s in slots if step - s.created <= cfg.planar_merge_window]
    old = [s for s in slots if step - s.created > cfg.planar_merge_window]
    if len(new) < cfg.planar_merge_min_inliers or len(old) < cfg.planar_merge_min_inliers:
        return 0

    def xy(offsets: list[int]) -> FloatArray:
        return ekf._x[np.asarray(offsets)[:, None] + np.arange(2)[None, :]]

    m = match_constellation(xy([s.offset for s in new]), xy([s.offset for s in old]), cfg.planar_merge_radius, cfg.planar_merge_tol,
                            cfg.planar_merge_min_inliers, cfg.planar_merge_max_angle)
    if m is None:
        return 0
    pairs = [(old[a], new[i]) for i, a in m.pairs]
    out = equality_gain(ekf._cov, ekf._x[: ekf._n], [(a.offset, b.offset) for a, b in pairs],
                        MERGE_VAR)
    if out is None:
        return 0
    w, dx = out
    ekf._x[: ekf._n] += dx
    ekf._x[2] = (ekf._x[2] + np.pi) % (2 * np.pi) - np.pi
    ekf._cov.downdate(w)
    for a, b in pairs:
        a.n_obs += b.n_obs
        a.last_seen = max(a.last_seen, b.last_seen)
    ekf._remove([b.id for _, b in pairs])
    ekf.n_pruned -= len(pairs)
    ekf.merges.extend((a.id, b.id, step) for a, b in pairs)
    return len(pairs)
