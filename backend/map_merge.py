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

:func:`merge_all` (what ``lampsam slam RUN --map A --map B ... --localize-only`` uses) merges
any number of maps jointly and models what the pairwise merge drops: each drive's map is off
the truth by a small **similarity** (shift, turn and the drive's odometry **scale**, which
moves ``x, y`` and the lamp's height above the camera together: the ceiling camera cannot
tell them apart), fitted for all maps at once with the common landmark positions; the
landmarks are fused with their covariances given their map's frame (``D_l``), and the merged
map gets a frame model (:class:`lampsam.backend.map_frame.MapFrame`) for the error its fitted
similarities leave. It does not depend on the maps' order. docs/ceiling-map.md, "Maps from
several drives".
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from lampsam.arrays import FloatArray
from lampsam.backend.ceiling_map_io import CeilingMap, MapLandmark
from lampsam.backend.map_frame import MapFrame
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


# --------------------------------------------------------------------------- joint merge
@dataclass(frozen=True)
class JointMergeConfig:
    """How :func:`merge_all` fits each drive's map to the common one.

    Attributes:
        pairing: how landmarks of two maps are paired (:class:`MergeConfig`).
        sigma_shift: prior sigma of a map's frame shift when the map has no frame model
            (a version-1 map), m (default 0.005).
        sigma_turn: the same for its turn, rad (default 0.001).
        sigma_scale: prior sigma of every map's scale error (the drive's odometry scale),
            dimensionless (default 0.001, 1000 ppm; the lab maps are -608 to +571 ppm).
        scale: fit each map's scale (default True); False fits shift and turn alone.
        rounds: pair, fit, and pair again on the maps moved by the fit, this many times
            (default 2: drives whose errors differ by more than the pairing gate pair on
            the second round).
        common_scale_in_cov: keep the merged map's common scale error (the drives' mean
            scale, ``sigma_scale / sqrt(N)`` a priori, the same error for every landmark)
            in the landmarks' covariances as independent noise (default False: left out,
            as a single map's covariances leave out its drive's scale error; the frame
            model has no scale to carry it).
    """

    pairing: MergeConfig = field(default_factory=MergeConfig)
    sigma_shift: float = field(default=0.005, metadata=limits(gt=0.0))
    sigma_turn: float = field(default=0.001, metadata=limits(gt=0.0))
    sigma_scale: float = field(default=0.001, metadata=limits(gt=0.0))
    scale: bool = True
    rounds: int = field(default=2, metadata=limits(ge=1))
    common_scale_in_cov: bool = False

    def __post_init__(self) -> None:
        """Check the declared ranges (:class:`FieldValueError` naming the key)."""
        check_limits(self)


def similarity_jacobian(position: FloatArray, center: FloatArray, z_cam: float) -> FloatArray:
    """(3, 4) ``d (x, y, z) / d (dx, dy, dtheta, ds)`` of a small similarity.

    A turn ``dtheta`` about ``center`` (2,), a scale ``1 + ds`` about ``(center, z_cam)``
    (the camera's height, m: a sighting fixes a lamp's offset over its height above the
    camera, so an odometry scale error scales ``x, y`` and ``z - z_cam`` together), then a
    shift ``(dx, dy)``.
    """
    x, y, z = (float(v) for v in position)
    cx, cy = float(center[0]), float(center[1])
    return np.array([[1.0, 0.0, -(y - cy), x - cx],
                     [0.0, 1.0, x - cx, y - cy],
                     [0.0, 0.0, 0.0, z - z_cam]])


def _weight(lm: MapLandmark, frame: MapFrame | None) -> FloatArray | None:
    """(3, 3) information of a landmark's position given its map's frame (``D_l^-1``, or
    the marginal's inverse without a frame model), None when unknown."""
    c = _pos_cov(lm)
    if c is None:
        return None
    if frame is not None and lm.id in frame.gains:
        c = frame.conditional(lm.id, np.asarray(lm.cov, float))[:3, :3]
        c = c + 1e-12 * np.eye(3)
    return np.asarray(np.linalg.inv(c), float)


def _clusters(maps: list[CeilingMap], kind: str, config: MergeConfig
              ) -> list[list[tuple[int, int]]]:
    """Groups of ``(map, index in map.by_kind(kind))`` that are one landmark.

    Every two maps are paired (:func:`pair_landmarks`), the pairs joined into connected
    groups; a group holding two landmarks of one map is not trusted and split into
    single landmarks. The result does not depend on the maps' order (sorted by map
    index, then index)."""
    lists = [m.by_kind(kind) for m in maps]
    parent: dict[tuple[int, int], tuple[int, int]] = {
        (k, i): (k, i) for k, lst in enumerate(lists) for i in range(len(lst))}

    def root(n: tuple[int, int]) -> tuple[int, int]:
        while parent[n] != n:
            parent[n] = parent[parent[n]]
            n = parent[n]
        return n

    for ka in range(len(lists)):
        for kb in range(ka + 1, len(lists)):
            for i, j in pair_landmarks(lists[ka], lists[kb], config):
                ra, rb = root((ka, i)), root((kb, j))
                if ra != rb:
                    parent[max(ra, rb)] = min(ra, rb)
    groups: dict[tuple[int, int], list[tuple[int, int]]] = {}
    for n in sorted(parent):
        groups.setdefault(root(n), []).append(n)
    out: list[list[tuple[int, int]]] = []
    for g in groups.values():
        if len({k for k, _ in g}) == len(g):
            out.append(g)
        else:
            out.extend([n] for n in g)
    return out


def _frame_prior(m: CeilingMap, center: FloatArray, cfg: JointMergeConfig) -> FloatArray:
    """(4, 4) prior covariance of a map's similarity ``(dx, dy, dtheta, ds)`` about the
    common ``center`` (2,): the map's own frame covariance (moved from the map's frame
    center: a turn about ``c_k`` is the turn about ``c`` and a shift ``-dtheta perp(c_k -
    c)``) when it has one, else the config's sigmas."""
    p = np.zeros((4, 4))
    if m.frame is not None:
        v = np.asarray(m.frame.center, float) - np.asarray(center, float)
        t = np.eye(3)
        t[0, 2], t[1, 2] = v[1], -v[0]
        p[:3, :3] = t @ np.asarray(m.frame.cov, float) @ t.T
    else:
        p[:3, :3] = np.diag([cfg.sigma_shift**2] * 2 + [cfg.sigma_turn**2])
    p[3, 3] = cfg.sigma_scale**2 if cfg.scale else 1e-18
    return p


def common_center(maps: list[CeilingMap]) -> FloatArray:
    """(2,) the point every map's turn and scale are taken about: the mean of the maps'
    frame centers (of their landmarks' centroids without a frame model), m. One point
    for all maps: with one center per map a common scale would move the maps apart."""
    cs = []
    for m in maps:
        if m.frame is not None:
            cs.append(np.asarray(m.frame.center, float))
        else:
            xy = np.array([lm.position[:2] for lm in m.landmarks], float).reshape(-1, 2)
            cs.append(xy.mean(axis=0) if len(xy) else np.zeros(2))
    return np.asarray(np.mean(np.array(cs), axis=0), float)


def fit_similarities(maps: list[CeilingMap], groups: list[list[tuple[int, int, MapLandmark]]],
                     cfg: JointMergeConfig, center: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Each map's small similarity to the common map, fitted jointly.

    Model: landmark ``l`` of map ``k`` is at ``q_c + J_kl a_k + r_kl`` with ``q_c`` its
    group's common position, ``a_k = (dx, dy, dtheta, ds)`` map ``k``'s error
    (:func:`similarity_jacobian`, prior ``N(0, P_k)``: :func:`_frame_prior`) and ``r_kl ~
    N(0, D_kl)`` (:func:`_weight`). The ``q_c`` are eliminated (Schur complement); the
    normal equations in the ``4 K`` unknowns are solved at once, so the result does not
    depend on the maps' order.

    Returns:
        ``a`` (K, 4) about ``center`` (:func:`common_center`) and its posterior
        covariance (4K, 4K).
    """
    n = len(maps)
    z_cam = float(maps[0].rig.camera.body_t_camera[2])
    priors = [_frame_prior(m, center, cfg) for m in maps]
    h = np.zeros((4 * n, 4 * n))
    g = np.zeros(4 * n)
    for k in range(n):
        h[4 * k:4 * k + 4, 4 * k:4 * k + 4] += np.linalg.inv(priors[k])
    for grp in groups:
        rows = [(k, w, np.asarray(lm.position, float))
                for k, _, lm in grp if (w := _weight(lm, maps[k].frame)) is not None]
        if len(rows) < 2:
            continue
        # one Jacobian per group (at its mean): with each landmark's own, the maps' mm
        # differences would leak the (unobservable) common scale out of its prior
        jc = similarity_jacobian(np.mean([p for _, _, p in rows], axis=0), center, z_cam)
        wc_inv = np.linalg.inv(sum(w for _, w, _ in rows))
        wp = sum(w @ p for _, w, p in rows)
        for k, wk, pk in rows:
            sk = slice(4 * k, 4 * k + 4)
            h[sk, sk] += jc.T @ wk @ jc
            g[sk] += jc.T @ wk @ pk - jc.T @ wk @ wc_inv @ wp
            for m, wm, _ in rows:
                sm = slice(4 * m, 4 * m + 4)
                h[sk, sm] -= jc.T @ wk @ wc_inv @ wm @ jc
    cov = np.asarray(np.linalg.inv(0.5 * (h + h.T)), float)
    a = np.asarray(cov @ g, float)
    return a.reshape(n, 4), cov


def _moved(m: CeilingMap, a: FloatArray, center: FloatArray, z_cam: float) -> CeilingMap:
    """The map with every landmark's position moved back by its fitted similarity
    ``a`` (4,) (covariances kept: only for pairing)."""
    out = [dataclasses.replace(lm, position=np.asarray(lm.position, float)
                               - similarity_jacobian(lm.position, center, z_cam) @ a)
           for lm in m.landmarks]
    return dataclasses.replace(m, landmarks=out)


def _phi_var(lm: MapLandmark, frame: MapFrame | None) -> float:
    """The lamp axis's variance given its map's frame (the marginal's without one), rad^2."""
    if frame is not None and lm.id in frame.gains:
        return float(frame.conditional(lm.id, np.asarray(lm.cov, float))[3, 3])
    return float(lm.cov[3, 3])


def merge_all(maps: list[CeilingMap], config: JointMergeConfig | None = None
              ) -> tuple[CeilingMap, dict[str, Any]]:
    """One map from the maps of several drives, fitted and fused jointly.

    1. Landmarks are grouped (:func:`_clusters`: every two maps paired, groups joined).
    2. Each map's similarity to the common map (shift, turn, scale about the camera
       height) is fitted jointly with the groups' positions (:func:`fit_similarities`),
       each map's prior its frame model (or the config's sigmas) and a 1000 ppm scale:
       the drives start at one dock, so the merged map's frame and scale are the
       information-weighted average of the drives'.
    3. Every landmark is moved by its map's fitted similarity and each group fused
       information-weighted with the landmarks' covariances given their map's frame
       (``D_l``, the independent part; marginals without a frame model).
    4. The merged map gets a frame model (:class:`MapFrame`): its common error is the
       error of the fitted similarities, ``g`` its rigid part; each landmark's marginal is
       that part through its gain plus its fused ``D``.

    Landmark ids are new, ``0 .. N-1`` in the order (kind, x, y): the merged map does not
    depend on the order of ``maps`` (but for its ``source`` list).

    Returns:
        The merged map and counts: ``maps``, ``fused`` (groups of two or more), ``alone``
        (landmarks in one map only, including those of a group split for holding two of
        one map), and ``similarity``: per map ``[dx m, dy m, dtheta rad, ds]``.

    Raises:
        InputError: no maps, or maps made with different cameras.
    """
    cfg = config or JointMergeConfig()
    if not maps:
        raise InputError("no maps to merge")
    cam = maps[0].rig.camera.to_dict()
    if any(m.rig.camera.to_dict() != cam for m in maps[1:]):
        raise InputError("the maps were made with different cameras: not merged")
    center = common_center(maps)
    n = len(maps)
    z_cam = float(maps[0].rig.camera.body_t_camera[2])
    paired = maps  # the maps the landmarks are paired on: moved by the last fit
    for _ in range(cfg.rounds):
        groups: list[list[tuple[int, int, MapLandmark]]] = []
        for kind in ("lamp", "corner"):
            lists = [m.by_kind(kind) for m in maps]
            groups += [[(k, i, lists[k][i]) for k, i in grp]
                       for grp in _clusters(paired, kind, cfg.pairing)]
        a, a_cov = fit_similarities(maps, groups, cfg, center)
        paired = [_moved(m, a[k], center, z_cam) for k, m in enumerate(maps)]
    # g = the merged map's rigid error: the fitted similarities' errors, averaged
    omega = np.hstack([np.eye(4) / n] * n)  # (4, 4K)
    s_full = omega @ a_cov @ omega.T
    s_g = s_full[:3, :3]
    s_g_inv = np.linalg.inv(s_g)
    s_full_inv = np.linalg.inv(s_full)
    fused: list[tuple[str, FloatArray, float | None, FloatArray, int, np.ndarray | None,
                      FloatArray]] = []
    for grp in groups:
        kind = grp[0][2].kind
        info = np.zeros((3, 3))
        rows = []
        j = similarity_jacobian(np.mean([lm.position for _, _, lm in grp], axis=0), center, z_cam)
        for k, _, lm in grp:
            w = _weight(lm, maps[k].frame)
            w = np.eye(3) * 1e6 if w is None else w
            rows.append((k, lm, w, j, np.asarray(lm.position, float) - j @ a[k]))
            info += w
        c_pos = np.linalg.inv(info)
        pos = c_pos @ sum(w @ p for _, _, w, _, p in rows)
        # error of the fused position through the fitted similarities: omega_c (a* - a)
        om = np.zeros((4, 4 * n))
        for k, _, w, j, _ in rows:
            om[:3, 4 * k:4 * k + 4] += c_pos @ w @ j
        phis = [(k, lm) for k, _, lm in grp if lm.phi is not None]
        phi: float | None = None
        var_phi = 0.0
        if phis:
            ref = float(phis[0][1].phi) - float(a[phis[0][0], 2])  # type: ignore[arg-type]
            vs = np.array([max(_phi_var(lm, maps[k].frame), 1e-12) for k, lm in phis])
            ds = np.array([float(wrap_axis(float(lm.phi) - float(a[k, 2]) - ref))  # type: ignore[arg-type]
                           for k, lm in phis])
            wts = (1.0 / vs) / np.sum(1.0 / vs)
            phi = float(np.mod(ref + float(wts @ ds), math.pi))
            var_phi = float(1.0 / np.sum(1.0 / vs))
            for (k, _), wt in zip(phis, wts, strict=True):
                om[3, 4 * k + 2] += wt
        cov = np.zeros((4, 4))
        cov[:3, :3] = c_pos
        cov[3, 3] = var_phi
        cov += om @ a_cov @ om.T
        cross = om @ a_cov @ omega.T  # (4, 4): Cov(landmark error, common similarity error)
        if not cfg.common_scale_in_cov:  # drop the share of the common scale (see config)
            cov -= (cross @ s_full_inv @ cross.T
                    - cross[:, :3] @ s_g_inv @ cross[:, :3].T)
        if phi is None:
            cov[3, :] = cov[:, 3] = 0.0
        gain = cross[:, :3] @ s_g_inv  # (4, 3) regression on g
        best = max(grp, key=lambda t: (t[2].n_obs, -t[0]))[2]
        patch = best.patch if best.patch is not None else next(
            (lm.patch for _, _, lm in grp if lm.patch is not None), None)
        fused.append((kind, pos, phi, 0.5 * (cov + cov.T), sum(lm.n_obs for _, _, lm in grp),
                      patch, gain))
    order = sorted(range(len(fused)), key=lambda i: (fused[i][0] != "lamp",
                                                     round(float(fused[i][1][0]), 9),
                                                     round(float(fused[i][1][1]), 9)))
    out: list[MapLandmark] = []
    gains: dict[int, FloatArray] = {}
    for new_id, i in enumerate(order):
        kind, pos, phi, cov, n_obs, patch, gain = fused[i]
        out.append(MapLandmark(new_id, kind, pos, phi, cov, n_obs, patch))
        gains[new_id] = gain
    counts: dict[str, Any] = {
        "maps": n, "fused": sum(len(g) > 1 for g in groups),
        "alone": sum(len(g) == 1 for g in groups),
        "similarity": [[float(v) for v in row] for row in a]}
    source: dict[str, Any] = {"merged": [dict(m.source) for m in maps],
                              "merge": "joint similarity (backend/map_merge.py merge_all)",
                              **counts}
    frame = MapFrame(center, 0.5 * (s_g + s_g.T), gains)
    return CeilingMap(out, maps[0].rig, source, frame=frame), counts
