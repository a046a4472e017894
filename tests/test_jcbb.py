"""JCBB on a hand-made ambiguous case where nearest neighbour takes the wrong tree."""

from __future__ import annotations

import numpy as np

from lampsam.backend.association import associate, jcbb
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
