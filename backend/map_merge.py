"""Merge ceiling maps of the same floor made on separate mapping drives.

A robot maps its floor once, but it may drive the floor twice (or more) for it. Each
drive starts from the same known dock pose, so their batch maps share the world frame
and differ by independent errors: the drift of each drive (a few millimetres and
hundredths of a degree over a 3-minute lab run) and the noise of each landmark. Merging
the drives' maps landmark by landmark averages those errors out.

:func:`merge_maps` pairs the landmarks of two maps (same kind, mutual nearest neighbours
inside a Mahalanobis gate on the positions, eq. 20 of paper 1 with the two map
covariances as the innovation covariance ``S = Sigma_a + Sigma_b``) and fuses each pair
as two independent Gaussian estimates of one point (information-weighted mean):

    Sigma = (Sigma_a^-1 + Sigma_b^-1)^-1,   p = Sigma (Sigma_a^-1 p_a + Sigma_b^-1 p_b)

on ``(x, y, z)``, and the lamp axes ``phi`` the same way as scalars modulo pi. A landmark
without a partner is kept as it is. This is what one batch over both drives gives when
the drives share nothing but the landmarks, except that each map's landmark
marginals are used and their correlations within one map (the drift a drive applies to
all its landmarks) are dropped: the fused covariances are somewhat optimistic.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from lampsam.arrays import FloatArray
from lampsam.backend.ceiling_map_io import CeilingMap, MapLandmark
from lampsam.config_loader import check_limits, limits
from lampsam.errors import InputError
from lampsam.factors.geometry import wrap_axis


@dataclass(frozen=True)
class MergeConfig:
    """How two maps' landmarks are paired.

    Attributes:
        gate_d2: squared Mahalanobis distance under which two landmarks of one kind may
            be the same one (default 16.27, chi-square 3 dof at 0.999).
        max_dist: and their horizontal distance at most this, m (default 0.1: a pair
            with huge covariances is not taken on the gate alone).
    """

    gate_d2: float = field(default=16.27, metadata=limits(gt=0.0))
    max_dist: float = field(default=0.1, metadata=limits(gt=0.0))

    def __post_init__(self) -> None:
        """Check the declared ranges (:class:`FieldValueError` naming the key)."""
        check_limits(self)


def _pos_cov(lm: MapLandmark) -> FloatArray | None:
    """(3, 3) position covariance, or None when unknown (NaN) or not positive definite."""
    c = np.asarray(lm.cov, float)[:3, :3]
    if not np.all(np.isfinite(c)):
        return None
    try:
        np.linalg.cholesky(c)
    except np.linalg.LinAlgError:
        return None
    return c


def pair_landmarks(a: list[MapLandmark], b: list[MapLandmark],
                   config: MergeConfig | None = None) -> list[tuple[int, int]]:
    """Pairs ``(i, j)`` of ``a[i]`` and ``b[j]`` (one kind) that are one landmark.

    Mutual nearest neighbours in the Mahalanobis distance with ``S = Sigma_a + Sigma_b``
    (the identity when either covariance is unknown: then only ``max_dist`` decides),
    kept when under ``gate_d2`` and ``max_dist``.
    """
    cfg = config or MergeConfig()
    if not a or not b:
        return []
    pa = np.array([lm.position for lm in a], float)
    pb = np.array([lm.position for lm in b], float)
    ca = [_pos_cov(lm) for lm in a]
    cb = [_pos_cov(lm) for lm in b]
    diff = pa[:, None, :] - pb[None, :, :]  # (A, B, 3)
    horiz = np.linalg.norm(diff[..., :2], axis=2)
    d2 = np.full(horiz.shape, np.inf)
    for i, j in zip(*np.nonzero(horiz <= cfg.max_dist), strict=True):
        cai, cbj = ca[i], cb[j]
        if cai is None or cbj is None:
            d2[i, j] = 0.0  # no covariance: the distance cap alone decides
            continue
        e = diff[i, j]
        d2[i, j] = float(e @ np.linalg.solve(cai + cbj, e))
    best_b = np.argmin(d2, axis=1)
    best_a = np.argmin(d2, axis=0)
    return [(i, int(j)) for i, j in enumerate(best_b)
            if best_a[j] == i and d2[i, j] < cfg.gate_d2]


def fuse(a: MapLandmark, b: MapLandmark, new_id: int) -> MapLandmark:
    """One landmark from two independent estimates of it (module docstring).

    Without both position covariances the positions are averaged weighted by the
    observation counts and the covariance is NaN.
    """
    ca, cb = _pos_cov(a), _pos_cov(b)
    cov = np.zeros((4, 4))
    if ca is None or cb is None:
        wa = a.n_obs / max(a.n_obs + b.n_obs, 1)
        pos = wa * np.asarray(a.position, float) + (1.0 - wa) * np.asarray(b.position, float)
        cov[:3, :3] = np.nan
    else:
        ia, ib = np.linalg.inv(ca), np.linalg.inv(cb)
        c = np.linalg.inv(ia + ib)
        pos = c @ (ia @ np.asarray(a.position, float) + ib @ np.asarray(b.position, float))
        cov[:3, :3] = 0.5 * (c + c.T)
    phi: float | None
    if a.phi is None or b.phi is None:
        src = a if b.phi is None else b
        phi = src.phi
        cov[3, 3] = src.cov[3, 3] if phi is not None else 0.0
    else:
        va, vb = float(a.cov[3, 3]), float(b.cov[3, 3])
        wa = 0.5 if not (va > 0 and vb > 0) else vb / (va + vb)
        d = float(wrap_axis(b.phi - a.phi))  # b's axis taken to within pi/2 of a's
        phi = float(np.mod(a.phi + (1.0 - wa) * d, math.pi))
        cov[3, 3] = va * vb / (va + vb) if va > 0 and vb > 0 else max(va, vb)
    patch = a.patch if a.patch is not None else b.patch
    return MapLandmark(new_id, a.kind, pos, phi, cov, a.n_obs + b.n_obs, patch)


def merge_maps(a: CeilingMap, b: CeilingMap, config: MergeConfig | None = None
               ) -> tuple[CeilingMap, dict[str, int]]:
    """The merged map of ``a`` and ``b`` and counts (``fused``, ``only_a``, ``only_b``).

    Landmark ids: ``a``'s ids are kept (a fused landmark takes ``a``'s id); a landmark of
    ``b`` alone gets a new id above every id of ``a``. The rig is ``a``'s.

    Raises:
        InputError: the maps were made with different cameras (their landmarks would
            not be comparable observations of one ceiling).
    """
    if a.rig.camera.to_dict() != b.rig.camera.to_dict():
        raise InputError("the maps were made with different cameras: not merged")
    out: list[MapLandmark] = []
    counts = {"fused": 0, "only_a": 0, "only_b": 0}
    next_id = max((lm.id for lm in a.landmarks), default=-1) + 1
    for kind in ("lamp", "corner"):
        la, lb = a.by_kind(kind), b.by_kind(kind)
        pairs = pair_landmarks(la, lb, config)
        used_a = {i for i, _ in pairs}
        used_b = {j for _, j in pairs}
        partner = dict(pairs)
        for i, lm in enumerate(la):
            out.append(fuse(lm, lb[partner[i]], lm.id) if i in used_a else lm)
        for j, lm in enumerate(lb):
            if j not in used_b:
                out.append(MapLandmark(next_id, lm.kind, lm.position, lm.phi, lm.cov, lm.n_obs,
                                       lm.patch))
                next_id += 1
        counts["fused"] += len(pairs)
        counts["only_a"] += len(la) - len(pairs)
        counts["only_b"] += len(lb) - len(pairs)
    source: dict[str, Any] = {"merged": [dict(a.source), dict(b.source)], **counts}
    return CeilingMap(out, a.rig, source), counts
