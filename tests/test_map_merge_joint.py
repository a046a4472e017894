"""The joint merge of several drives' maps with a similarity per drive (issue 20).

Every test seeds its own ``numpy.random.Generator``. Synthetic maps: a truth of lamps (z
2.5 m) and corners (z 2.7 m) over a 10 m x 6 m ceiling; map ``k`` is the truth moved by a
known small similarity (shift, turn, scale about the ceiling's center and the camera
height, 0.3 m) plus independent 0.3 mm noise, with covariances (0.3 mm)^2 I and no frame
model. The drives' true errors sum to zero (the merge's gauge: the average drive).
"""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from lampsam.backend.ceiling_map_io import CeilingMap, MapLandmark
from lampsam.backend.map_frame import MapFrame
from lampsam.backend.map_merge import (
    JointMergeConfig,
    merge_all,
    merge_maps,
    similarity_jacobian,
)
from lampsam.datasets.camera import CameraModel
from lampsam.datasets.logrun import Rig
from lampsam.errors import InputError

SIGMA = 0.0003
MARGINAL = 0.003  # the maps' marginal sigma (mostly their frame error, as a real map's)
CENTER = np.array([5.0, 3.0])
Z_CAM = 0.3  # Rig()'s camera height, m


def _truth(rng: np.random.Generator) -> tuple[np.ndarray, list[str]]:
    lamps = np.array([[1.0 + 2.0 * i, 1.0 + 2.0 * j, 2.5] for i in range(5) for j in range(3)])
    corners = np.c_[rng.uniform([0.0, 0.0], [10.0, 6.0], (60, 2)), np.full(60, 2.7)]
    return np.vstack([lamps, corners]), ["lamp"] * len(lamps) + ["corner"] * len(corners)


def _similar(p: np.ndarray, a: np.ndarray) -> np.ndarray:
    """Points (N, 3) moved by the exact similarity ``a = (dx, dy, dtheta, ds)``."""
    dx, dy, th, ds = a
    c, s = np.cos(th), np.sin(th)
    q = p - np.r_[CENTER, Z_CAM]
    xy = (1.0 + ds) * (q[:, :2] @ np.array([[c, s], [-s, c]]))
    return np.c_[xy + CENTER + [dx, dy], (1.0 + ds) * q[:, 2] + Z_CAM]


def _map(rng: np.random.Generator, truth: np.ndarray, kinds: list[str], a: np.ndarray,
         keep: np.ndarray, rig: Rig) -> CeilingMap:
    pos = _similar(truth, a) + rng.normal(0.0, SIGMA, truth.shape)
    cov = np.diag([MARGINAL**2] * 3 + [0.0])
    return CeilingMap([MapLandmark(i, kinds[i], pos[i], None, cov, 20)
                       for i in range(len(truth)) if keep[i]], rig, {"run": "synthetic"})


def _errors(cmap: CeilingMap, truth: np.ndarray) -> np.ndarray:
    """(L, 3) each landmark's error against its nearest true point."""
    p = np.array([lm.position for lm in cmap.landmarks])
    near = np.argmin(np.linalg.norm(p[:, None, :2] - truth[None, :, :2], axis=2), axis=1)
    return np.asarray(p - truth[near])


def _rms(e: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.sum(e**2, axis=1))))


# errors of three drives, summing to zero: shift m, turn rad, scale
DRIVES = np.array([[0.002, -0.001, 2e-4, 6e-4],
                   [-0.0005, 0.0015, -1e-4, -2e-4],
                   [-0.0015, -0.0005, -1e-4, -4e-4]])


def test_similarity_jacobian_matches_the_similarity(rng: np.random.Generator) -> None:
    """The (3, 4) Jacobian against central differences of the exact similarity."""
    p = np.array([7.3, 1.2, 2.6])
    j = similarity_jacobian(p, CENTER, Z_CAM)
    num = np.zeros((3, 4))
    for i in range(4):
        d = np.zeros(4)
        d[i] = 1e-6
        num[:, i] = (_similar(p[None], d)[0] - _similar(p[None], -d)[0]) / 2e-6
    assert np.allclose(j, num, atol=1e-8)


def test_joint_merge_recovers_drive_similarities_and_the_true_landmarks(
        rng: np.random.Generator) -> None:
    """Three maps with known shift / turn / scale errors, each missing a fifth of the
    corners: the fitted turns and scales within 0.02 mrad and 30 ppm of the truth, the
    points they move within 0.2 mm of where the drive moved them,
    the merged landmarks (the corners seen once too) at most 0.6 of the best map's error
    RMS against the truth, and the pairwise merge of the same maps (no similarity) not
    that good (its landmarks seen once keep their drive's error)."""
    rig = Rig()
    truth, kinds = _truth(rng)
    maps = []
    for k, a in enumerate(DRIVES):
        keep = np.ones(len(truth), bool)
        keep[15 + k::5] = False  # corners only
        maps.append(_map(rng, truth, kinds, a, keep, rig))
    merged, counts = merge_all(maps)
    assert counts["maps"] == 3 and len(merged.landmarks) == len(truth)
    fit = np.array(counts["similarity"])
    assert np.allclose(fit[:, 2], DRIVES[:, 2], atol=2e-5)
    assert np.allclose(fit[:, 3], DRIVES[:, 3], atol=3e-5)
    # the fitted similarity (about the merge's own center) moves every true point as the
    # drive's did, to 0.2 mm
    center = np.mean([np.mean([lm.position[:2] for lm in m.landmarks], axis=0) for m in maps],
                     axis=0)
    for a_fit, a_true in zip(fit, DRIVES, strict=True):
        moved = np.array([similarity_jacobian(p, center, Z_CAM) @ a_fit for p in truth])
        assert np.max(np.abs(moved - (_similar(truth, a_true) - truth))) < 2e-4
    best = min(_rms(_errors(m, truth)) for m in maps)
    joint = _rms(_errors(merged, truth))
    assert joint < 0.6 * best
    seq = maps[0]
    for m in maps[1:]:
        seq, _ = merge_maps(seq, m)
    assert joint < 0.8 * _rms(_errors(seq, truth))
    # the lamps' heights (scale errors move z - z_cam too): RMS under 0.3 mm (the noise
    # alone gives 0.17 mm)
    lamps = np.array([lm.position for lm in merged.by_kind("lamp")])
    assert np.sqrt(np.mean((lamps[:, 2] - 2.5) ** 2)) < 3e-4


def test_joint_merge_of_two_maps_beats_either(rng: np.random.Generator) -> None:
    """Two drives with opposite scale errors (+-600 ppm) and shifts: the merged map's
    error RMS against the truth under 0.5 of either map's."""
    rig = Rig()
    truth, kinds = _truth(rng)
    a = np.array([0.001, 0.0, 1e-4, 6e-4])
    keep = np.ones(len(truth), bool)
    maps = [_map(rng, truth, kinds, a, keep, rig), _map(rng, truth, kinds, -a, keep, rig)]
    merged, _ = merge_all(maps)
    e = _rms(_errors(merged, truth))
    assert all(e < 0.5 * _rms(_errors(m, truth)) for m in maps)


def test_joint_merge_does_not_depend_on_the_maps_order(rng: np.random.Generator) -> None:
    """Every order of four maps gives the same landmarks (ids, positions to 1e-9 m,
    covariances to 1e-9 relative) and the same frame model."""
    rig = Rig()
    truth, kinds = _truth(rng)
    drives = np.vstack([DRIVES, np.zeros(4)])  # a fourth drive without error
    maps = []
    for a in drives:
        keep = rng.uniform(size=len(truth)) > 0.2
        maps.append(_map(rng, truth, kinds, a, keep, rig))
    ref, _ = merge_all(maps)
    assert ref.frame is not None
    for perm in list(itertools.permutations(range(4)))[1::5]:
        m, _ = merge_all([maps[i] for i in perm])
        assert [lm.id for lm in m.landmarks] == [lm.id for lm in ref.landmarks]
        for x, y in zip(m.landmarks, ref.landmarks, strict=True):
            assert x.kind == y.kind and x.n_obs == y.n_obs
            assert np.allclose(x.position, y.position, atol=1e-9, rtol=0.0)
            assert np.allclose(x.cov, y.cov, rtol=1e-9, atol=1e-18)
        assert m.frame is not None
        assert np.allclose(m.frame.cov, ref.frame.cov, rtol=1e-9, atol=1e-18)


def test_merged_frame_model_is_a_valid_factor_model(rng: np.random.Generator) -> None:
    """The merged map's frame: ``S`` positive definite, every ``D_l = Sigma_ll - C_l S
    C_l^T`` positive semi-definite before clipping (to 1e-15 m^2)."""
    rig = Rig()
    truth, kinds = _truth(rng)
    keep = np.ones(len(truth), bool)
    maps = [_map(rng, truth, kinds, a, keep, rig) for a in DRIVES]
    merged, _ = merge_all(maps)
    frame = merged.frame
    assert isinstance(frame, MapFrame)
    assert np.all(np.linalg.eigvalsh(frame.cov) > 0.0)
    for lm in merged.landmarks:
        c = frame.gains[lm.id]
        d = np.asarray(lm.cov) - c @ frame.cov @ c.T
        assert np.linalg.eigvalsh(0.5 * (d + d.T)).min() > -1e-15


def test_joint_merge_refuses_other_cameras_and_no_maps(rng: np.random.Generator) -> None:
    """Maps of two cameras, or no map: an InputError saying so."""
    rig = Rig()
    truth, kinds = _truth(rng)
    a = _map(rng, truth, kinds, np.zeros(4), np.ones(len(truth), bool), rig)
    other = Rig(camera=CameraModel.from_fov(hfov_deg=100.0), odometry=rig.odometry)
    with pytest.raises(InputError, match="different cameras"):
        merge_all([a, CeilingMap(a.landmarks, other)])
    with pytest.raises(InputError, match="no maps"):
        merge_all([])
    with pytest.raises(ValueError, match="sigma_scale"):
        JointMergeConfig(sigma_scale=0.0)


def test_joint_merge_uses_the_maps_frame_models(rng: np.random.Generator) -> None:
    """Version-2 style maps (a frame model: shift 2 mm, turn 0.5 mrad about the ceiling's
    center; marginals = the frame's share + (0.3 mm)^2 I): the fit weights by ``D_l`` and
    takes ``S_k`` as the drive's prior; two drives with opposite errors merge to under 0.5 of
    either map's error RMS, with the fitted scales within 30 ppm."""
    from lampsam.backend.map_frame import rigid_jacobian

    rig = Rig()
    truth, kinds = _truth(rng)
    s = np.diag([0.002**2, 0.002**2, 0.0005**2])
    drive = np.array([0.0015, -0.001, 3e-4, 5e-4])
    maps = []
    for a in (drive, -drive):
        pos = _similar(truth, a) + rng.normal(0.0, SIGMA, truth.shape)
        lms, gains = [], {}
        for i, p in enumerate(pos):
            c = rigid_jacobian(p, CENTER, False)
            cov = c @ s @ c.T
            cov[:3, :3] += SIGMA**2 * np.eye(3)
            lms.append(MapLandmark(i, kinds[i], p, None, cov, 20))
            gains[i] = c
        maps.append(CeilingMap(lms, rig, {"run": "synthetic"},
                               frame=MapFrame(CENTER.copy(), s, gains)))
    merged, counts = merge_all(maps)
    fit = np.array(counts["similarity"])
    assert np.allclose(fit[:, 3], [drive[3], -drive[3]], atol=3e-5)
    e = _rms(_errors(merged, truth))
    assert all(e < 0.5 * _rms(_errors(m, truth)) for m in maps)
