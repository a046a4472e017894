"""Twin file ids (evaluation/twin_ids.py) and new landmarks from the left-out sightings no
landmark explains (backend/held_placement.py, ``online_final_held_new_unexplained``)."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import gtsam
import numpy as np
from gtsam.symbol_shorthand import L, X
from scipy.stats import chi2 as chi2_dist

from lampsam.backend.config import SlamConfig
from lampsam.backend.graph_log import run_graph_log_backend
from lampsam.backend.held_placement import new_landmarks
from lampsam.backend.noids_offline import dropped_sightings
from lampsam.backend.online_final import final_solve, online_association
from lampsam.backend.reassociate import Sightings
from lampsam.datasets.graph_text import GraphLog, Sighting, read_graph_text
from lampsam.datasets.landmark_log_sim import LandmarkLogSpec, write_landmark_log
from lampsam.datasets.odometry import Pose2OdometryLog
from lampsam.evaluation.twin_ids import (
    lm_reference,
    merged_log,
    merged_start,
    pair_models,
    point_residuals,
    twin_groups,
    twin_map,
    twin_tests,
)
from lampsam.factors.range_bearing import range_bearing

#: sightings' stated noise: bearing 0.01 rad, range 0.05 m (sigma)
R = np.diag([0.01**2, 0.05**2])
N_POSES = 20


def _log(points: dict[int, tuple[float, float]], seen: dict[int, range],
         rng: np.random.Generator, radius: float = 0.0) -> GraphLog:
    """Poses ``(k, 0, 0)``, k < 20, odometry 1 m (sigma 1 cm, 0.002 rad, noise-free);
    file id ``i`` at ``points[i]`` sighted from the poses ``seen[i]`` with the stated
    noise, its range measured to a circle of ``radius`` m about it."""
    cov = np.diag([1e-4, 1e-4, 4e-6])
    delta = np.array([[0.0, 0.0, 0.0]] + [[1.0, 0.0, 0.0]] * (N_POSES - 1))
    odo = Pose2OdometryLog(np.arange(N_POSES, dtype=float), delta,
                           np.repeat(cov[None], N_POSES, 0))
    sightings: list[list[Sighting]] = [[] for _ in range(N_POSES)]
    for i, xy in points.items():
        for k in seen[i]:
            z, _, _ = range_bearing(np.array([float(k), 0.0, 0.0]), np.array(xy))
            z = z + rng.normal(0.0, np.sqrt(np.diag(R)))
            sightings[k].append(Sighting(i, float(z[0]), float(z[1]) - radius, R))
    return GraphLog(path=Path("hand.txt"), pose_ids=list(range(N_POSES)), odometry=odo,
                    sightings=sightings, vertices={0: np.zeros(3)})


def _start(g: GraphLog, points: dict[int, tuple[float, float]]) -> gtsam.Values:
    v = gtsam.Values()
    for k in range(N_POSES):
        v.insert(X(k), gtsam.Pose2(float(k), 0.0, 0.0))
    for i, xy in points.items():
        v.insert(L(i), gtsam.Point2(*xy))
    return v


#: two ids 0.3 m apart (1 seen from poses 0-9, 2 from 10-19: never together) and two
#: trees seen from every pose
TWINS = {1: (10.0, 3.0), 2: (10.3, 3.0), 3: (5.0, -3.0), 4: (15.0, -3.0)}
SEEN = {1: range(0, 10), 2: range(10, 20), 3: range(N_POSES), 4: range(N_POSES)}


def test_twin_ids_count_as_one_tree_in_the_merged_reference() -> None:
    """Hand-made: two ids 0.3 m apart never sighted together are one twin group; the
    merged log has one landmark fewer (3 trees for 4 ids) and its LM optimum has them
    as one landmark between the two; ids sighted together (3, 4) stay apart even when
    closer than the radius."""
    g = _log(TWINS, SEEN, np.random.default_rng(0))
    ref = lm_reference(g, SlamConfig(), _start(g, TWINS))
    assert np.hypot(*(ref.landmarks[1] - ref.landmarks[2])) < 0.5
    tw = twin_map(g, ref.landmarks)
    assert twin_groups(tw) == [[1, 2]]
    assert tw[2] == 1 and tw[3] == 3 and tw[4] == 4
    gm = merged_log(g, tw)
    assert {x.landmark for ss in gm.sightings for x in ss} == {1, 3, 4}
    ref_m = lm_reference(gm, SlamConfig(), merged_start(ref, tw))
    assert sorted(ref_m.landmarks) == [1, 3, 4]
    assert 10.0 < ref_m.landmarks[1][0] < 10.3
    assert ref_m.chi2 > ref.chi2  # one point for two costs chi-square
    # sighted together: 3 and 4 are 10 m apart; at a radius of 11 m they stay two trees
    assert twin_groups(twin_map(g, ref.landmarks, radius=11.0)) == [[1, 2]]


def test_merge_chi2_rejects_two_points_and_accepts_one() -> None:
    """The pair test: the 0.3 m pair at range noise 0.05 m costs far more than the 2-dof
    99.9 % quantile to merge; one point under two ids costs less than the 99 % one."""
    cfg = SlamConfig()
    g2 = _log(TWINS, SEEN, np.random.default_rng(1))
    r2 = lm_reference(g2, cfg, _start(g2, TWINS))
    (t2,) = twin_tests(g2, cfg, r2, twin_map(g2, r2.landmarks))
    assert t2.ids == (1, 2) and t2.n == (10, 10)
    assert t2.chi2_merge > chi2_dist.ppf(0.999, 2) and t2.p_stated < 1e-3
    one = {**TWINS, 2: TWINS[1]}
    g1 = _log(one, SEEN, np.random.default_rng(1))
    r1 = lm_reference(g1, cfg, _start(g1, one))
    (t1,) = twin_tests(g1, cfg, r1, twin_map(g1, r1.landmarks))
    assert t1.chi2_merge < chi2_dist.ppf(0.99, 2) and t1.p_stated > 0.01
    assert abs(t1.scale - 1.0) < 0.5  # the residuals show the stated noise


def test_one_trunk_seen_from_two_sides() -> None:
    """A trunk of radius 0.4 m at (10, 0.6): id 1's sightings from its left (poses
    0-4, x < 5), id 2's from its right (poses 15-19); ranges to the surface. The trunk
    model finds the radius within 0.05 m and fits as well as two points (chi-square
    within 10 of theirs), while one point with ranges to the centre does not."""
    rng = np.random.default_rng(2)
    pts = {1: (10.0, 0.6), 2: (10.0, 0.6)}
    g = _log(pts, {1: range(0, 5), 2: range(15, 20)}, rng, radius=0.4)
    p = np.array([[float(k), 0.0, 0.0] for k, ss in enumerate(g.sightings) for _ in ss])
    z = np.array([[x.bearing, x.range] for ss in g.sightings for x in ss])
    w = np.repeat(np.linalg.cholesky(np.linalg.inv(R)).T[None], len(p), 0)
    which = np.array([x.landmark - 1 for ss in g.sightings for x in ss])
    two, one, trunk, radius = pair_models(p, z, w, which,
                                          (np.array([9.7, 0.5]), np.array([10.3, 0.5])))
    assert abs(radius - 0.4) < 0.05
    assert trunk < two + 10.0 and one > trunk + 100.0
    # the residual function: zero at the truth without noise
    zt = np.array([range_bearing(pp, np.array([10.0, 0.6]))[0] for pp in p])
    zt[:, 1] -= 0.4
    assert np.abs(point_residuals(p, zt, w, np.array([10.0, 0.6]), 0.4)).max() < 1e-9


def test_new_landmarks_from_unexplained_sightings_only() -> None:
    """Left-out sightings of a mapped landmark's neighbourhood (each within ``c_new`` of
    it, together a point of their own that pays) become a new landmark only without
    ``unexplained``; a cluster that no landmark explains becomes one either way."""
    cfg = SlamConfig()
    c_new, gate = cfg.association.new_threshold(2), cfg.association.gate(2)
    poses = np.array([[float(k), 0.0, 0.0] for k in range(N_POSES)])
    lms = {0: np.array([5.0, 4.0])}
    s = Sightings(np.array([0, 1]), np.array([range_bearing(poses[k], lms[0])[0] for k in (0, 1)]),
                  np.repeat(R[None], 2, 0), np.array([0, 0]))
    # near: 0.2 m from landmark 0 (d2 ~ 16 at range sigma 0.05 m); far: 20 m away
    near, far = np.array([5.0, 4.2]), np.array([15.0, 8.0])
    dk = np.array([5, 6, 12, 13])
    dz = np.array([range_bearing(poses[k], x)[0] for k, x in zip(dk, [near, near, far, far],
                                                                 strict=True)])
    dr = np.repeat(R[None], 4, 0)
    every = new_landmarks(poses, lms, s, dk, dz, dr, c_new, gate, unexplained=False)
    only = new_landmarks(poses, lms, s, dk, dz, dr, c_new, gate, unexplained=True)
    assert len(every) == 2 and len(only) == 1
    (xy,) = only.values()
    assert np.hypot(*(xy - far)) < 0.05


def test_placement_at_the_residual_noise_puts_no_sighting_on_a_neighbour(
        tmp_path: Path) -> None:
    """A seeded 200-pose log whose sightings are stated at 10x their true variance (as
    Victoria Park's, which fit at 0.1): the final solve's left-out sightings placed with
    ``online_final_held_residual_scale`` go to their own tree's landmark only (file ids),
    no more of them than at the stated noise, and ``C`` falls."""
    spec = LandmarkLogSpec(n_poses=200, n_landmarks=30, extent=40.0, stop_every=0)
    g = read_graph_text(write_landmark_log(tmp_path / "log.txt", spec,
                                           np.random.default_rng(1))[0])
    g = dataclasses.replace(g, sightings=[[dataclasses.replace(x, cov=10.0 * x.cov)
                                           for x in ss] for ss in g.sightings])
    base_cfg = SlamConfig()
    cfg16 = dataclasses.replace(base_cfg, pose2_odometry=dataclasses.replace(
        base_cfg.pose2_odometry, cov_scale=16.0), reassociation=dataclasses.replace(
        base_cfg.reassociation, online_final_held_mixture=False))
    online, be = run_graph_log_backend(g, "isam2", cfg16, known_ids=False)
    assert be is not None and online.status == "ok"
    s = online_association(be, online)
    base = final_solve(g, cfg16, online, Sightings(s.k, s.z, s.r, s.lid.copy()))
    assert len(dropped_sightings(g, base.sightings)[0]) > 0
    assert base.chi2_sightings / base.dof_sightings < 0.3
    placed = {}
    for scaled in (False, True):
        on = dataclasses.replace(cfg16, reassociation=dataclasses.replace(
            cfg16.reassociation, online_final_held_mixture=True,
            online_final_held_residual_scale=scaled))
        placed[scaled] = final_solve(g, on, online, Sightings(s.k, s.z, s.r, s.lid.copy()))
    n0 = len(base.sightings.k)
    mix = placed[True]
    assert n0 < len(mix.sightings.k) <= len(placed[False].sightings.k)
    assert mix.cost <= base.cost
    fid = np.array([min(g.sightings[k], key=lambda c: abs(c.range - z[1])).landmark
                    for k, z in zip(mix.sightings.k.tolist(), mix.sightings.z, strict=True)])
    for j in range(n0, len(mix.sightings.k)):
        own = fid[:n0][base.sightings.lid == mix.sightings.lid[j]]
        assert len(own) and np.bincount(own).argmax() == fid[j]
