"""Localize-only with the map as priors, and merging two drives' maps (issue 20).

Every test seeds its own ``numpy.random.Generator`` (the ``rng`` fixture).
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from lampsam.backend.ceiling import CeilingModel
from lampsam.backend.ceiling_map_io import CeilingMap, MapLandmark
from lampsam.backend.config import SlamConfig
from lampsam.backend.localize_only import LocalizeConfig, MapLocalizer
from lampsam.backend.map_merge import merge_maps, pair_landmarks
from lampsam.backend.slam import drive, iter_steps
from lampsam.datasets.camera import CameraModel
from lampsam.datasets.logrun import Rig
from lampsam.errors import InputError
from tests.test_ceiling_map import _drive, _rms, _truth_errors


def _shifted(cmap: CeilingMap, shift: np.ndarray, sigma: float) -> CeilingMap:
    """Every landmark moved by ``shift`` (a map whose frame is off), covariance sigma^2 I."""
    out = []
    for lm in cmap.landmarks:
        cov = np.array(lm.cov, float)
        cov[:3, :3] = sigma**2 * np.eye(3)
        out.append(dataclasses.replace(lm, position=lm.position + shift, cov=cov))
    return CeilingMap(out, cmap.rig)


def test_map_priors_pull_out_a_map_offset(rng: np.random.Generator) -> None:
    """A map 1 cm off (sigma 1 cm) and a start known to 1 mm: the fixed map drags the track
    to the map's frame (RMS near 1 cm), the map as priors keeps it within 3/4 of that;
    no landmark is added and the result's map is the input map."""
    rig, odo, frames, poses, t, cmap = _drive(rng, map_sigma=0.001)
    off = _shifted(cmap, np.array([0.008, -0.006, 0.0]), 0.01)
    loose = dict(max_corner_sigma=0.05, sigma_start_xy=1e-3, sigma_start_theta=1e-3)
    model = CeilingModel.from_camera(rig.camera)
    rms = {}
    for priors in (False, True):
        be = MapLocalizer(rig.odometry, SlamConfig(), poses[0], off, model,
                          LocalizeConfig(map_mode="priors" if priors else "fixed", **loose))
        estimates = [be.step(*s) for s in iter_steps(odo, frames)]
        result = be.finish()
        pos, head = _truth_errors(result, t, poses)
        rms[priors] = _rms(pos)
        assert np.degrees(_rms(head)) < 0.5
        assert all(e.n_new == 0 for e in estimates)
        assert result.extra["observations_used"] > 10 * len(frames)
        for a, b in zip(result.landmarks, off.landmarks, strict=True):
            assert np.array_equal(a.position, b.position)
    assert 0.006 < rms[False] < 0.014
    assert rms[True] < 0.75 * rms[False]  # measured 0.64x: the priors are independent, the offset common


def test_map_modes_agree_when_the_map_is_exact(rng: np.random.Generator) -> None:
    """A map with tiny covariances: fixed, priors and consider give the same track (0.2 mm)."""
    rig, odo, frames, poses, t, cmap = _drive(rng, map_sigma=1e-5)
    model = CeilingModel.from_camera(rig.camera)
    res = [drive(MapLocalizer(rig.odometry, SlamConfig(), poses[0], cmap, model,
                              LocalizeConfig(map_mode=mode)), iter_steps(odo, frames))
           for mode in ("fixed", "priors", "consider")]
    for other in res[1:]:
        assert np.max(np.abs(res[0].poses[:, :2] - other.poses[:, :2])) < 2e-4
    pos, _ = _truth_errors(res[1], t, poses)
    assert _rms(pos) < 0.01


def test_consider_keeps_the_map_and_its_covariance(rng: np.random.Generator) -> None:
    """Schmidt update: the landmarks' values and covariance blocks never change, the
    pose-landmark cross-covariance does; its pose covariance is larger than the fixed
    map's (the repeated sightings of one landmark are not independent)."""
    rig, odo, frames, poses, t, cmap = _drive(rng, map_sigma=0.004)
    model = CeilingModel.from_camera(rig.camera)
    loc = dict(max_corner_sigma=0.05)
    be = MapLocalizer(rig.odometry, SlamConfig(), poses[0], cmap, model,
                      LocalizeConfig(map_mode="consider", **loc))
    assert be._pj is not None
    p0 = be._pj[3:, 3:].copy()
    points0 = {k: a.points.copy() for k, a in be._kinds.items()}
    steps = list(iter_steps(odo, frames))
    for s in steps:
        be.step(*s)
    assert np.array_equal(be._pj[3:, 3:], p0)
    assert all(np.array_equal(a.points, points0[k]) for k, a in be._kinds.items())
    assert np.abs(be._pj[:3, 3:]).max() > 0
    fixed = MapLocalizer(rig.odometry, SlamConfig(), poses[0], cmap, model, LocalizeConfig(map_mode="fixed", **loc))
    for s in steps:
        fixed.step(*s)
    assert np.trace(be.P[:2, :2]) > 1.5 * np.trace(fixed.P[:2, :2])
    with pytest.raises(ValueError, match="map_mode"):
        LocalizeConfig(map_mode="moving")  # type: ignore[arg-type]


def _grid_map(rng: np.random.Generator, sigma: float, rig: Rig, drop: int = 0) -> CeilingMap:
    """A 0.6 m corner grid and 3 lamps, noise ``sigma`` per coordinate (independent)."""
    gx, gy = np.meshgrid(np.arange(0.0, 3.0, 0.6), np.arange(0.0, 3.0, 0.6))
    truth = np.column_stack([gx.ravel(), gy.ravel(), np.full(gx.size, 2.7)])
    lms = [MapLandmark(i, "lamp", np.array([0.3 + i, 0.3, 2.5]) + rng.normal(0, sigma, 3),
                       float((0.5 + rng.normal(0, 0.01)) % np.pi),
                       np.diag([sigma**2] * 3 + [1e-4]), 20) for i in range(3)]
    lms += [MapLandmark(10 + k, "corner", p + rng.normal(0, sigma, 3), None,
                        np.diag([sigma**2] * 3 + [0.0]), 15)
            for k, p in enumerate(truth[drop:])]
    return CeilingMap(lms, rig, {"run": "synthetic"})


def test_merge_pairs_and_averages_two_drives(rng: np.random.Generator) -> None:
    """Two maps of one grid with independent 3 mm noise: every landmark paired, the fused
    positions' error RMS ~ 1/sqrt(2) of one map's, the fused covariance halved; a corner of
    one map alone is kept with a new id; the lamp axis is averaged modulo pi."""
    rig = Rig()
    a = _grid_map(rng, 0.003, rig)
    b = _grid_map(rng, 0.003, rig, drop=2)
    merged, counts = merge_maps(a, b)
    assert counts == {"fused": len(b.landmarks), "only_a": 2, "only_b": 0}
    assert len(merged.landmarks) == len(a.landmarks)
    assert [lm.id for lm in merged.landmarks] == [lm.id for lm in a.landmarks]
    # errors against the truth grid
    err_a, err_m = [], []
    for lm_a, lm_m in zip(a.landmarks, merged.landmarks, strict=True):
        true = (np.array([0.3 + lm_a.id, 0.3, 2.5]) if lm_a.kind == "lamp"
                else np.array([0.6 * ((lm_a.id - 10) % 5), 0.6 * ((lm_a.id - 10) // 5), 2.7]))
        if lm_a.id >= 12 or lm_a.kind == "lamp":  # landmarks in both maps
            err_a.append(lm_a.position - true)
            err_m.append(lm_m.position - true)
            assert np.allclose(lm_m.cov[:3, :3], 0.5 * lm_a.cov[:3, :3], rtol=1e-9)
            assert lm_m.n_obs == 2 * lm_a.n_obs
    ratio = _rms(np.array(err_m)) / _rms(np.array(err_a))
    assert 0.5 < ratio < 0.9
    # axis average across the wrap: 0.01 and pi - 0.01 average to 0 (mod pi)
    la = dataclasses.replace(a.landmarks[0], phi=0.01)
    lb = dataclasses.replace(b.landmarks[0], phi=float(np.pi - 0.01))
    m2, _ = merge_maps(CeilingMap([la], rig), CeilingMap([lb], rig))
    phi = m2.landmarks[0].phi
    assert phi is not None and min(phi, np.pi - phi) < 1e-9
    # a corner of b alone: kept, id above a's
    extra = MapLandmark(10, "corner", np.array([9.0, 9.0, 2.7]), None, np.diag([1e-6] * 3 + [0.0]), 5)
    m3, c3 = merge_maps(a, CeilingMap([extra], rig))
    assert c3["only_b"] == 1 and m3.landmarks[-1].id == max(lm.id for lm in a.landmarks) + 1


def test_merge_does_not_pair_neighbours_or_other_cameras(rng: np.random.Generator) -> None:
    """Corners 2 cm apart with 1 mm sigmas are not one corner (gate), 8 cm apart with huge
    sigmas neither (distance cap); the same corners 1 mm apart are; maps of different
    cameras are refused."""
    rig = Rig()
    a = _grid_map(rng, 0.001, rig)
    corners = a.by_kind("corner")

    def moved(dx: float, sigma: float) -> list[MapLandmark]:
        return [dataclasses.replace(lm, position=lm.position + np.array([dx, 0.0, 0.0]),
                                    cov=np.diag([sigma**2] * 3 + [0.0])) for lm in corners]

    assert pair_landmarks(corners, moved(0.02, 0.001)) == []
    assert pair_landmarks(corners, moved(0.12, 1.0)) == []
    assert pair_landmarks(corners, moved(0.001, 0.001)) == [(i, i) for i in range(len(corners))]
    other = Rig(camera=CameraModel.from_fov(hfov_deg=100.0), odometry=rig.odometry)
    with pytest.raises(InputError, match="different cameras"):
        merge_maps(a, CeilingMap(a.landmarks, other))
