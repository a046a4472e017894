"""The localize-only smoother (issue 20): the run's poses and the used map landmarks in one graph.

- on a 20 s drive whose map is the truth moved by a known frame offset g (8 mm, -6 mm,
  0.5 deg) about its centre, with the frame model saying so (S, C = the rigid Jacobian),
  and a start known to 1 mm: the smoother's estimate of g is within 1 mm and 0.05 deg
  of the truth and its final poses are under 1.5 mm RMS, where the same smoother without
  the frame model (independent marginals) stays in the map's frame (RMS above 4 mm); the
  default shift-only model recovers a pure shift as well;
- its online poses are the filter's, step for step, and it adds no landmark;
- the frame model's factor is zero at the map and whitened by ``D``; the shift-only
  model keeps every landmark's marginal.

Every test seeds its own ``numpy.random.Generator`` (the ``rng`` fixture).
"""

from __future__ import annotations

import math

import gtsam
import numpy as np
from gtsam.symbol_shorthand import A, L

from lampsam.backend.ceiling import CeilingModel
from lampsam.backend.config import SlamConfig
from lampsam.backend.localize_only import LocalizeConfig, MapLocalizer
from lampsam.backend.map_frame import MapFrame
from lampsam.backend.map_smoother import (
    G,
    MapSmoother,
    MapSmootherConfig,
    frame_to_rigid,
    map_tie_factor,
    shift_only,
)
from lampsam.backend.slam import iter_steps
from tests.test_ceiling_map import _drive, _rms, _truth_errors
from tests.test_map_frame import _shifted_map


def test_smoother_recovers_a_known_map_frame(rng: np.random.Generator) -> None:
    """See the module docstring: g within 1 mm / 0.05 deg, final RMS < 1.5 mm with the frame
    model, > 4 mm without; online poses are the filter's."""
    rig, odo, frames, poses, t, cmap = _drive(rng, map_sigma=3e-4)
    g_true = np.array([0.008, -0.006, np.radians(0.5)])
    shifted = _shifted_map(cmap, g_true, 3e-4, axis_sigma=0.002)
    model = CeilingModel.from_camera(rig.camera)
    loc = LocalizeConfig(max_corner_sigma=0.05, sigma_start_xy=1e-3, sigma_start_theta=1e-3)
    steps = list(iter_steps(odo, frames))
    sm = MapSmoother(rig.odometry, SlamConfig(), poses[0], shifted, model, loc,
                     smooth=MapSmootherConfig(frame_turn=True))
    online = [sm.step(*s).pose for s in steps]
    res = sm.finish()
    pos, head = _truth_errors(res, t, poses)
    g = np.array([res.extra[k] for k in ("map_frame_dx_m", "map_frame_dy_m",
                                         "map_frame_dtheta_rad")])
    assert np.all(np.abs(g[:2] - g_true[:2]) < 0.001), g
    assert abs(np.degrees(g[2] - g_true[2])) < 0.05, g
    assert res.extra["map_frame_sigma_dtheta_rad"] < np.radians(0.1)
    assert _rms(pos) < 0.0015
    assert np.degrees(_rms(head)) < 0.1
    assert res.extra["smoother_landmarks"] > 10
    assert [lm.id for lm in res.landmarks] == [lm.id for lm in cmap.landmarks]
    # the online poses are the filter's
    fl = MapLocalizer(rig.odometry, SlamConfig(), poses[0], shifted, model, loc)
    filtered = np.array([fl.step(*s).pose for s in steps])
    assert np.array_equal(np.array(online), filtered)
    # without the frame model the map's frame is kept
    sm = MapSmoother(rig.odometry, SlamConfig(), poses[0], shifted, model, loc,
                     smooth=MapSmootherConfig(frame=False))
    for s in steps:
        sm.step(*s)
    pos, _ = _truth_errors(sm.finish(), t, poses)
    assert _rms(pos) > 0.004
    # a pure shift with the default (shift-only) model
    g_shift = np.array([0.008, -0.006, 0.0])
    sm = MapSmoother(rig.odometry, SlamConfig(), poses[0],
                     _shifted_map(cmap, g_shift, 3e-4, axis_sigma=0.002), model, loc)
    for s in steps:
        sm.step(*s)
    res = sm.finish()
    pos, _ = _truth_errors(res, t, poses)
    g = np.array([res.extra["map_frame_dx_m"], res.extra["map_frame_dy_m"]])
    assert np.all(np.abs(g - g_shift[:2]) < 0.001), g
    assert _rms(pos) < 0.0015


def test_isam2_engine_matches_the_batch_solve(rng: np.random.Generator) -> None:
    """iSAM2 updated every 10 steps ends within 0.2 mm RMS of the one-shot solve."""
    rig, odo, frames, poses, t, cmap = _drive(rng, map_sigma=3e-4)
    shifted = _shifted_map(cmap, np.array([0.004, 0.002, np.radians(0.2)]), 3e-4,
                           axis_sigma=0.002)
    model = CeilingModel.from_camera(rig.camera)
    loc = LocalizeConfig(max_corner_sigma=0.05, sigma_start_xy=1e-3, sigma_start_theta=1e-3)
    out = []
    for cfg in (MapSmootherConfig(frame_turn=True),
                MapSmootherConfig(frame_turn=True, update_every=10)):
        sm = MapSmoother(rig.odometry, SlamConfig(), poses[0], shifted, model, loc, smooth=cfg)
        for s in iter_steps(odo, frames):
            sm.step(*s)
        out.append(sm.finish().poses)
    assert _rms(np.linalg.norm(out[0][:, :2] - out[1][:, :2], axis=1)) < 2e-4


def test_map_tie_factor_and_frame_to_rigid(rng: np.random.Generator) -> None:
    """The tie's error is 0 at the map and 0.5 e^T D^-1 e for a moved landmark (e = l - m - C g);
    ``frame_to_rigid`` maps the centre to centre + (dx, dy)."""
    rig, _, _, _, _, cmap = _drive(rng, map_sigma=1e-3)
    lm = next(lm for lm in cmap.landmarks if lm.phi is not None)
    gain = rng.normal(size=(4, 3))
    a = rng.normal(size=(4, 4))
    d = 1e-6 * (a @ a.T + np.eye(4))
    center = np.array([1.0, 2.0])
    f = map_tie_factor(lm, gain, d, True, center)
    v = gtsam.Values()
    v.insert(L(lm.id), np.asarray(lm.position, float))
    v.insert(A(lm.id), gtsam.Pose2(center[0], center[1], float(lm.phi)))
    v.insert(G, np.zeros(3))
    assert abs(f.error(v)) < 1e-12
    dl, dphi, g = rng.normal(0, 1e-3, 3), 2e-3, rng.normal(0, 1e-3, 3)
    v.update(L(lm.id), np.asarray(lm.position, float) + dl)
    v.update(A(lm.id), gtsam.Pose2(center[0], center[1], float(lm.phi) + dphi))
    v.update(G, g)
    e = np.r_[dl, dphi] - gain @ g
    want = 0.5 * e @ np.linalg.solve(d + 1e-12 * np.eye(4), e)
    assert math.isclose(f.error(v), want, rel_tol=1e-6)
    tr = frame_to_rigid(np.array([0.01, -0.02, 0.3]), center)
    c, s = math.cos(0.3), math.sin(0.3)
    moved = np.array([[c, -s], [s, c]]) @ center + tr[:2]
    assert np.allclose(moved, center + [0.01, -0.02], atol=1e-12)


def test_shift_only_keeps_the_marginals(rng: np.random.Generator) -> None:
    """``shift_only``: ``C' S' C'^T + D' = Sigma_ll`` for every landmark, no turn gain, and
    ``C'`` is the regression of the landmark's error on the shift (``Cov(e, g_xy) S_xy^-1``)."""
    a = rng.normal(size=(3, 3))
    s = 1e-5 * (a @ a.T + np.eye(3))
    gains = {i: rng.normal(size=(4, 3)) for i in range(5)}
    frame = MapFrame(np.array([1.0, 2.0]), s, gains)
    sh = shift_only(frame)
    assert np.all(sh.gains[0][:, 2] == 0.0) and sh.cov[2, 2] < 1e-11
    for i, c in gains.items():
        b = rng.normal(size=(4, 4))
        marginal = c @ s @ c.T + 1e-6 * (b @ b.T + np.eye(4))
        d_new = sh.conditional(i, marginal)
        assert np.allclose(sh.gains[i] @ sh.cov @ sh.gains[i].T + d_new, marginal, atol=1e-14)
        assert np.allclose(sh.gains[i][:, :2] @ s[:2, :2], (c @ s)[:, :2], atol=1e-15)
