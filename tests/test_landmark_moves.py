"""Merging and splitting landmarks by description length (backend/landmark_moves.py)."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest
from gtsam.symbol_shorthand import L, X
from gtsam.utils.numerical_derivative import numericalDerivative11

from lampsam.backend.config import AssociationConfig
from lampsam.backend.final_moves import readmit, refine_final, sighting_moves
from lampsam.backend.landmark_moves import (
    cost_moves,
    fit_point,
    partition_cost,
    point_chi2,
    point_residuals,
    refine_by_cost,
)
from lampsam.backend.reassociate import Sightings, build_graph
from tests.test_reassociate import SIG_B, SIG_R, _loop_world, _prior

C_NEW = AssociationConfig().new_threshold(2)


def _optimum(poses: np.ndarray, odo: list, s: Sightings
             ) -> tuple[gtsam.NonlinearFactorGraph, gtsam.Values]:
    """The graph of the association ``s`` and its LM optimum from the true poses."""
    graph = build_graph(_prior(poses[0]), odo, s)
    v = gtsam.Values()
    for k, p in enumerate(poses):
        v.insert(X(k), gtsam.Pose2(*p))
    for lid in np.unique(s.lid).tolist():
        j = int(np.flatnonzero(s.lid == lid)[0])
        p = poses[s.k[j]]
        a = p[2] + s.z[j, 0]
        v.insert(L(lid), gtsam.Point2(*(p[:2] + s.z[j, 1] * np.array([np.cos(a), np.sin(a)]))))
    return graph, gtsam.LevenbergMarquardtOptimizer(graph, v).optimize()


def _estimate(values: gtsam.Values, n: int, s: Sightings
              ) -> tuple[np.ndarray, dict[int, np.ndarray]]:
    poses = np.array([[values.atPose2(X(k)).x(), values.atPose2(X(k)).y(),
                       values.atPose2(X(k)).theta()] for k in range(n)])
    return poses, {i: np.asarray(values.atPoint2(L(i))) for i in np.unique(s.lid).tolist()}



def _assert_one_landmark_per_tree(poses: np.ndarray, odo: list, s: Sightings,
                                  true: np.ndarray, values: gtsam.Values) -> None:
    """Each landmark holds exactly one tree's sightings and sits within 1 mm of that
    tree's landmark in the true association's optimum."""
    _, v_true = _optimum(poses, odo, Sightings(s.k, s.z, s.r, true))
    for lid in np.unique(s.lid).tolist():
        tree = np.unique(true[s.lid == lid])
        assert len(tree) == 1
        assert np.hypot(*(np.asarray(values.atPoint2(L(lid)))
                          - np.asarray(v_true.atPoint2(L(int(tree[0])))))) < 1e-3

def test_point_jacobian_matches_numerical_derivative() -> None:
    """``h_D_xy`` of :func:`point_residuals` against central differences of the
    prediction at 5 seeded points (tolerance 1e-6)."""
    rng = np.random.default_rng(11)
    for _ in range(5):
        pose = np.r_[rng.uniform(-5, 5, 2), rng.uniform(-np.pi, np.pi)]
        xy = pose[:2] + rng.uniform(2, 8) * np.array([np.cos(t := rng.uniform(0, 6)), np.sin(t)])

        def h(p: np.ndarray, pose: np.ndarray = pose) -> np.ndarray:
            nu, _ = point_residuals(pose[None, :], np.zeros((1, 2)), p)
            return -nu[0]  # nu = 0 - h, bearing wrapped: fine away from +-pi

        _, jac = point_residuals(pose[None, :], np.zeros((1, 2)), xy)
        np.testing.assert_allclose(jac[0], numericalDerivative11(h, xy), atol=1e-6)


def test_fit_point_recovers_a_tree_from_noise_free_sightings() -> None:
    """Six noise-free sightings from poses around a tree; started 3 m off, the fit is
    on the tree to 1e-6 m with chi-square ~0."""
    rng = np.random.default_rng(12)
    tree = np.array([2.0, -1.0])
    poses = np.c_[rng.uniform(-8, 8, (6, 2)), rng.uniform(-np.pi, np.pi, 6)]
    d = tree - poses[:, :2]
    z = np.c_[np.arctan2(d[:, 1], d[:, 0]) - poses[:, 2], np.hypot(*d.T)]
    z[:, 0] = np.arctan2(np.sin(z[:, 0]), np.cos(z[:, 0]))
    w = np.tile(np.diag([1 / SIG_B**2, 1 / SIG_R**2]), (6, 1, 1))
    xy, chi2 = fit_point(poses, z, w, tree + [3.0, 0.0])
    np.testing.assert_allclose(xy, tree, atol=1e-6)
    assert chi2 < 1e-9
    assert float(point_chi2(poses, z, w, tree + [0.5, 0]).sum()) > 1.0


def test_duplicated_landmark_is_merged() -> None:
    """One lap of the 24-tree circle (seed 3); tree 5's later half of sightings carry
    a new id (100: a duplicate, never sighted with the first copy). One round has
    exactly one move, the merge of 100 into 5, at a fitted point within 0.3 m of the
    tree; neighbours sighted together with tree 5 are not merged."""
    rng = np.random.default_rng(3)
    poses, trees, odo, s = _loop_world(rng, laps=1)
    true = s.lid.copy()
    half = np.median(s.k[s.lid == 5])
    dup = (s.lid == 5) & (s.k > half)
    assert dup.sum() >= 4 and ((s.lid == 5) & (s.k <= half)).sum() >= 4
    s.lid[dup] = 100
    graph, values = _optimum(poses, odo, s)
    est, lms = _estimate(values, len(poses), s)
    new, moved, moves = cost_moves(est, s.k, s.z, s.r, s.lid, lms, C_NEW, radius=10.0)
    assert [(m.kind, m.ids) for m in moves] == [("merge", (5, 100))]
    assert 0 < moves[0].gain < C_NEW
    np.testing.assert_array_equal(new, true)
    assert np.hypot(*(moved[5] - trees[5])) < 0.3


def test_two_trees_under_one_landmark_are_split() -> None:
    """Tree 3's sightings planted on tree 2's landmark (two trees under one landmark,
    the trajectory bent by it). :func:`refine_by_cost` splits them (a split of
    landmark 2 among its moves) and ends with one landmark per tree, each with exactly
    its tree's sightings and within 0.3 m of it."""
    rng = np.random.default_rng(3)
    poses, trees, odo, s = _loop_world(rng, laps=1)
    true = s.lid.copy()
    s.lid[true == 3] = 2
    graph, values = _optimum(poses, odo, s)
    graph, values, moves = refine_by_cost(_prior(poses[0]), odo, s, graph, values, C_NEW, 10.0)
    assert any(m.kind == "split" and m.ids[0] == 2 for m in moves)
    assert len(np.unique(s.lid)) == 24
    _assert_one_landmark_per_tree(poses, odo, s, true, values)


def test_refine_by_cost_lowers_the_description_length_to_the_true_association() -> None:
    """Same planted errors plus a third: tree 7's sightings split over two ids by
    keyframe parity (a copy seen at alternate poses, never together). After
    :func:`refine_by_cost` the association is the true one up to renaming (24
    landmarks, one tree each), ``2E + c_new n`` has dropped, and the planted-error
    answer's description length was higher than the true association's."""
    rng = np.random.default_rng(3)
    poses, trees, odo, s = _loop_world(rng, laps=1)
    true = s.lid.copy()
    s.lid[(true == 5) & (s.k > np.median(s.k[true == 5]))] = 100
    s.lid[true == 3] = 2
    s.lid[(true == 7) & (s.k % 2 == 1)] = 101
    graph, values = _optimum(poses, odo, s)
    c0 = 2 * graph.error(values) + C_NEW * len(np.unique(s.lid))
    g_true, v_true = _optimum(poses, odo, Sightings(s.k, s.z, s.r, true))
    c_true = 2 * g_true.error(v_true) + C_NEW * 24
    assert c_true < c0
    graph, values, moves = refine_by_cost(_prior(poses[0]), odo, s, graph, values, C_NEW, 10.0)
    assert len(moves) >= 3
    assert len(np.unique(s.lid)) == 24
    for lid in np.unique(s.lid).tolist():
        assert len(np.unique(true[s.lid == lid])) == 1
    c1 = 2 * graph.error(values) + C_NEW * len(np.unique(s.lid))
    assert c1 < c0
    assert abs(c1 - c_true) < 1e-3 * c_true


def _two_trees(rng: np.random.Generator, apart: float = 0.25
               ) -> tuple[np.ndarray, np.ndarray, Sightings]:
    """Two trees ``apart`` m apart, 10 m north of a straight path of 20 poses; the
    first tree is sighted from poses 0-9 only, the second from poses 10-19 only
    (never together). Returns ``(poses (20, 3), trees (2, 2), sightings)`` labelled
    with the true tree (0, 1), stated noise ``SIG_B``, ``SIG_R`` (the lateral sigma at
    10 m is 0.1 m), drawn at 0.3 of it (a stated noise too large, as Victoria Park's)."""
    trees = np.array([[0.0, 10.0], [apart, 10.0]])
    poses = np.c_[np.linspace(-6.0, 6.0, 20), np.zeros(20), np.zeros(20)]
    ks, zs, ls = [], [], []
    for k, p in enumerate(poses):
        t = 0 if k < 10 else 1
        v = trees[t] - p[:2]
        ks.append(k)
        zs.append([np.arctan2(v[1], v[0]) - p[2] + rng.normal(0, 0.3 * SIG_B),
                   np.hypot(*v) + rng.normal(0, 0.3 * SIG_R)])
        ls.append(t)
    r = np.tile(np.diag([SIG_B**2, SIG_R**2]), (20, 1, 1))
    return poses, trees, Sightings(np.array(ks), np.array(zs), r, np.array(ls))


def _fitted(poses: np.ndarray, s: Sightings) -> dict[int, np.ndarray]:
    w = np.linalg.inv(s.r)
    out = {}
    for i in np.unique(s.lid).tolist():
        j = s.lid == i
        out[i], _ = fit_point(poses[s.k[j]], s.z[j], w[j], np.array([0.0, 10.0]))
    return out


def test_sighting_inside_a_neighbours_gate_moves_to_its_own_tree() -> None:
    """Two trees 0.25 m apart (seed 21); one sighting of the second tree planted on the
    first tree's landmark, where it stays inside the gate (d2 < 9.21, so the
    re-association passes keep it). :func:`sighting_moves` moves exactly that sighting
    back, with a gain equal to the drop of the two landmarks' fitted chi-square less
    the change of the labels' description (11/9 before the move, 10/10 after)."""
    rng = np.random.default_rng(21)
    poses, trees, s = _two_trees(rng)
    true = s.lid.copy()
    s.lid[12] = 0
    lms = _fitted(poses, s)
    w = np.linalg.inv(s.r)
    gate = AssociationConfig().gate(2)
    assert point_chi2(poses[12:13], s.z[12:13], w[12:13], lms[0])[0] < gate
    new, moved, moves = sighting_moves(poses, s.k, s.z, s.r, s.lid, lms, C_NEW, gate)
    assert [(m.kind, m.ids) for m in moves] == [("sighting", (0, 1))]
    np.testing.assert_array_equal(new, true)
    c_before = sum(fit_point(poses[s.k[s.lid == i]], s.z[s.lid == i], w[s.lid == i],
                             lms[i])[1] for i in (0, 1))
    c_after = sum(fit_point(poses[s.k[new == i]], s.z[new == i], w[new == i], lms[i])[1]
                  for i in (0, 1))
    assert moves[0].partition == pytest.approx(partition_cost(10, 10) - partition_cost(11, 9))
    assert moves[0].gain == pytest.approx(c_before - c_after - moves[0].partition, abs=1e-3)
    assert np.hypot(*(moved[1] - trees[1])) < 0.1


def test_sighting_moves_leave_the_true_association_and_mutual_exclusion_alone() -> None:
    """Same two trees: on the true association no sighting moves; and a sighting of
    the second tree on the first tree's landmark is not moved to a landmark already
    sighted at its keyframe (the second tree's landmark taking a made-up sighting
    there): mutual exclusion."""
    rng = np.random.default_rng(21)
    poses, _, s = _two_trees(rng)
    gate = AssociationConfig().gate(2)
    _, _, moves = sighting_moves(poses, s.k, s.z, s.r, s.lid, _fitted(poses, s), C_NEW, gate)
    assert moves == []
    # a second sighting at keyframe 12, of tree 1 and labelled 1; the planted one on 0
    s2 = Sightings(np.r_[s.k, 12], np.r_[s.z, s.z[12:13]], np.r_[s.r, s.r[12:13]],
                   np.r_[s.lid, 1])
    s2.lid[12] = 0
    _, _, moves = sighting_moves(poses, s2.k, s2.z, s2.r, s2.lid, _fitted(poses, s2), C_NEW,
                                 gate)
    assert all(m.ids != (0, 1) for m in moves)


def test_missed_revisit_is_merged_only_with_the_poses_free() -> None:
    """Two laps of the 24-tree circle with a slip into the second lap (0.15 rad, 1.5 m;
    its odometry record uncertain, seed 3), every second-lap sighting on a new id
    (100 + tree): each copy is offset from its tree, so no merge pays with the poses
    fixed (:func:`refine_by_cost` keeps 48 landmarks). :func:`refine_final`'s first
    merge re-optimised with the poses free closes the loop,
    the rest follow, and the association is the true one (24 landmarks, one tree each)
    with the true association's optimum (landmarks within 1 mm)."""
    rng = np.random.default_rng(3)
    poses, trees, odo, s = _loop_world(rng, laps=2, glitch=0.15)
    true = s.lid.copy()
    s.lid = np.where(s.k >= 120, s.lid + 100, s.lid)
    start = s.lid.copy()
    graph, values = _optimum(poses, odo, s)
    _, _, moves = refine_by_cost(_prior(poses[0]), odo, s, graph, values, C_NEW, 10.0)
    assert len(np.unique(s.lid)) == 48 and not moves
    s.lid = start.copy()
    graph, values, moves = refine_final(_prior(poses[0]), odo, s, graph, values, C_NEW,
                                        10.0, AssociationConfig().gate(2))
    assert len(np.unique(s.lid)) == 24
    _assert_one_landmark_per_tree(poses, odo, s, true, values)


def test_dropped_sightings_are_taken_back_only_where_that_pays() -> None:
    """Two trees 0.25 m apart (seed 21); three sightings taken out as if the online
    pass had dropped them: one of tree 1 at keyframe 15 (d2 ~0 to its landmark: taken
    back), the same sighting again at keyframe 15 (landmark 1 is then taken at that
    keyframe, so it takes landmark 0, 0.25 m away and still under c_new), and one 3 m
    off every landmark (d2 far above c_new: stays dropped)."""
    rng = np.random.default_rng(21)
    poses, _, s = _two_trees(rng)
    lms = _fitted(poses, s)
    keep = np.arange(len(s.k)) != 15
    rec = Sightings(s.k[keep], s.z[keep], s.r[keep], s.lid[keep])
    far = s.z[3] + np.array([0.0, 3.0])
    dk = np.array([15, 15, 3])
    dz = np.array([s.z[15], s.z[15] + [1e-4, 0.0], far])
    back = readmit(poses, lms, rec, dk, dz, s.r[:3], C_NEW)
    np.testing.assert_array_equal(back, [1, 0, -1])
