"""JCBB on a hand-made ambiguous case where nearest neighbour takes the wrong tree."""

from __future__ import annotations

import numpy as np

from lampsam.backend.association import TentativeLandmarks, associate, jcbb
from lampsam.backend.config import AssociationConfig
from lampsam.backend.models import Obs


def test_jcbb_recovers_the_jointly_consistent_pairing() -> None:
    """Two trees 1 m apart; the robot's position is off by 0.6 m (pose sigma 0.5 m,
    sensor sigma 0.05 m), so both observations are shifted by the same 0.6 m. The
    first is individually nearer the *second* tree: greedy nearest neighbour takes it
    and leaves the second observation unpaired. Joint compatibility (the shared pose
    error correlates the innovations) pairs each observation with its own tree."""
    trees = {10: np.array([5.0, 0.0]), 11: np.array([5.0, 1.0])}
    shift = np.array([0.0, 0.6])
    z = [trees[10] + shift, trees[11] + shift]
    s_pose, s_meas = 0.5**2, 0.05**2
    cfg = AssociationConfig(use_known_ids=False)

    def innovation(lid: int, o: Obs) -> tuple[np.ndarray, np.ndarray]:
        return o.z - trees[lid], (s_pose + s_meas) * np.eye(2)

    obs = [Obs("point2", zi, s_meas * np.eye(2)) for zi in z]
    greedy = associate(obs, {"point2": [10, 11]}, innovation, cfg, lambda i: True)
    assert greedy[0].landmark_id == 11 and greedy[1].status != "matched"  # NN fails

    def joint(hyp: list[tuple[int, int]]) -> tuple[np.ndarray, np.ndarray]:
        nu = np.concatenate([z[i] - trees[lid] for i, lid in hyp])
        k = len(hyp)
        s = np.kron(np.ones((k, k)), s_pose * np.eye(2)) + s_meas * np.eye(2 * k)
        return nu, s

    cands = {0: [10, 11], 1: [10, 11]}
    assert sorted(jcbb(cands, joint, cfg)) == [(0, 10), (1, 11)]
    # an outlier third observation stays unpaired; the other two still pair right
    z.append(np.array([9.0, -4.0]))
    cands[2] = [10, 11]
    assert sorted(jcbb(cands, joint, cfg)) == [(0, 10), (1, 11)]


def test_tentative_landmarks_need_k_sightings_and_reject_copies() -> None:
    """Three sightings of one tree (2 m sigma each, scattered by 1 m) make one landmark
    on the third, at the information-weighted mean; a sighting 10 m away (d2 = 12.5 >
    the 9.21 gate) starts its own tentative; a tentative idle for longer than
    ``max_idle`` expires; a confirmed position 0.5 m from a mapped landmark is
    discarded as a copy when ``min_separation`` is 1 m."""
    gate = AssociationConfig().gate(2)
    cov = 4.0 * np.eye(2)
    tl = TentativeLandmarks(confirm=3, gate=gate, max_idle=10)
    assert not tl.offer(np.array([10.0, 0.0]), cov, 0)
    assert not tl.offer(np.array([20.0, 0.0]), cov, 1)  # another tree
    assert len(tl.items) == 2
    assert not tl.offer(np.array([11.0, 1.0]), cov, 2)
    assert tl.offer(np.array([10.0, 2.0]), cov, 3)  # third sighting: confirmed
    assert len(tl.items) == 1
    tl.expire(12)
    assert len(tl.items) == 0 and tl.n_expired == 1
    # fusion: information-weighted mean of equal covariances = the plain mean
    tl2 = TentativeLandmarks(confirm=3, gate=gate, max_idle=10)
    tl2.offer(np.array([0.0, 0.0]), cov, 0)
    tl2.offer(np.array([2.0, 0.0]), 3 * cov, 1)
    assert len(tl2.items) == 1 and tl2.items[0].hits == 2
    np.testing.assert_allclose(tl2.items[0].xy, [0.5, 0.0], atol=1e-12)  # weights 3:1
    np.testing.assert_allclose(tl2.items[0].cov, 3.0 * np.eye(2), atol=1e-12)
    t3 = TentativeLandmarks(confirm=2, gate=gate, max_idle=10)
    t3.offer(np.array([0.0, 0.0]), cov, 0)
    t3.offer(np.array([1.0, 1.0]), 0.5 * cov, 1)  # no mapped list: confirmed
    assert t3.n_copies == 0
    t4 = TentativeLandmarks(confirm=2, gate=gate, max_idle=10, min_separation=1.0)
    t4.offer(np.array([0.0, 0.0]), cov, 0)
    mapped = np.array([[0.5, 0.5], [30.0, 0.0]])
    assert not t4.offer(np.array([1.0, 1.0]), cov, 1, mapped)  # fused at (0.5, 0.5): a copy
    assert t4.n_copies == 1


def test_jcbb_with_the_learnt_scale_leaves_a_new_tree_unpaired() -> None:
    """A mapped tree at (5, 0) and a sighting of an unmapped tree 1.5 m away, with a
    stated covariance (pose 0.5 m, sensor 0.3 m sigma) whose real scatter is 0.1 of it:
    at the stated covariance JCBB pairs the sighting with the mapped tree (d2 = 6.6
    < 9.21); with the joint covariance scaled by the learnt 0.1
    (:class:`lampsam.backend.innovation_scale.InnovationScale`) it stays unpaired (66)."""
    tree = np.array([5.0, 0.0])
    z = np.array([5.0, 1.5])
    s_stated = (0.5**2 + 0.3**2) * np.eye(2)
    cfg = AssociationConfig(use_known_ids=False)
    for scale, expect in ((1.0, [(0, 7)]), (0.1, [])):
        def joint(hyp: list[tuple[int, int]], scale: float = scale
                  ) -> tuple[np.ndarray, np.ndarray]:
            return np.concatenate([z - tree for _ in hyp]), scale * np.kron(
                np.eye(len(hyp)), s_stated)
        assert jcbb({0: [7]}, joint, cfg) == expect
