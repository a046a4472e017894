"""Twin file ids (evaluation/twin_ids.py) and new landmarks from the left-out sightings no
landmark explains (backend/held_placement.py, ``online_final_held_new_unexplained``)."""

from __future__ import annotations

from pathlib import Path

import gtsam
import numpy as np
from gtsam.symbol_shorthand import L, X
from scipy.stats import chi2 as chi2_dist

from lampsam.backend.config import SlamConfig
from lampsam.backend.held_placement import new_landmarks
from lampsam.backend.reassociate import Sightings
from lampsam.datasets.graph_text import GraphLog, Sighting
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
