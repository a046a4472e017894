"""The online iSAM2 hot path (issue 19): the shortcuts give the same numbers as the plain way.

- the relative covariances of the screen, kept incrementally, against composing the
  odometry window backwards (:func:`~lampsam.backend.pose_cov.compose_cov`);
- the joint marginals fetched in one query per keyframe, against one
  ``jointMarginalCovariance`` per landmark, on a gate-only ceiling run.
"""

from __future__ import annotations

import dataclasses
from types import SimpleNamespace

import gtsam
import numpy as np
from gtsam.symbol_shorthand import X

from lampsam.backend.ceiling import CeilingModel
from lampsam.backend.ceiling_graph import CeilingHandler
from lampsam.backend.config import SlamConfig
from lampsam.backend.gating import RELATIVE_GATE_KEYFRAMES, Gating
from lampsam.backend.graph import Isam2Slam
from lampsam.backend.pose_cov import compose_cov, pose_array
from lampsam.backend.slam import drive, iter_steps
from tests.test_backend import ceiling_world


def _backward_relative(odo: list[tuple[np.ndarray, np.ndarray]], k: int) -> dict[int, np.ndarray]:
    """Reference: compose the window backwards from keyframe ``k`` (the plain way)."""
    out = {k: np.zeros((3, 3))}
    delta, cov = np.zeros(3), np.zeros((3, 3))
    for j in range(k - 1, max(k - RELATIVE_GATE_KEYFRAMES, 0) - 1, -1):
        d_j, c_j = odo[j + 1]
        cov = compose_cov(delta, c_j, cov)
        delta = pose_array(gtsam.Pose2(*d_j).compose(gtsam.Pose2(*delta)))
        out[j] = cov
    return out


def test_incremental_relative_covs_match_backward_composition() -> None:
    rng = np.random.default_rng(5)
    odo: list[tuple[np.ndarray, np.ndarray]] = [(np.zeros(3), np.zeros((3, 3)))]
    for _ in range(80):
        a = rng.normal(size=(3, 3)) * 1e-3
        odo.append((np.array([rng.uniform(0.02, 0.08), rng.normal(0, 0.01), rng.normal(0, 0.1)]),
                    a @ a.T + 1e-9 * np.eye(3)))
    w = SimpleNamespace(_odo=odo, _k=0, _rel_cache=None)  # the state the method reads
    # asked at every keyframe, then with gaps (keyframes without a ceiling screen),
    # then after a jump longer than the window
    for k in [*range(0, 40), 43, 44, 50, 51, 80]:
        w._k = k
        got = Gating._relative_covs(w)  # type: ignore[arg-type]
        ref = _backward_relative(odo, k)
        assert sorted(got) == sorted(ref)
        for j in ref:
            np.testing.assert_allclose(got[j], ref[j], rtol=1e-9, atol=1e-15)


def test_joint_marginals_prefetched_per_keyframe_match_per_landmark_queries() -> None:
    rig, odo, frames, gt = ceiling_world(np.random.default_rng(11), duration=14.0, n_corners=8)
    cfg = SlamConfig(association=dataclasses.replace(SlamConfig().association, use_known_ids=False))
    model = CeilingModel.from_camera(rig.camera)
    be = Isam2Slam(rig.odometry, cfg, gt.poses[0], model, CeilingHandler(model))
    checked = []
    orig = be._prefetch_joint

    def check(k: int, obs, screened) -> int:
        n = orig(k, obs, screened)
        for lid, (s_kk, s_kl, s_ll) in list(be._joint_cache.items()) if n else []:
            lm = be._landmarks[lid]
            handler = be.handlers[lm.kind]
            full = np.asarray(be.isam.jointMarginalCovariance([X(k), *handler.keys(lm)]).fullMatrix())
            idx = np.r_[0:3, 3 + np.asarray(handler.state_index(lm), int)]
            full = full[np.ix_(idx, idx)]
            scale = np.abs(full).max()
            np.testing.assert_allclose(s_kk, full[:3, :3], rtol=0, atol=1e-8 * scale)
            np.testing.assert_allclose(s_kl, full[:3, 3:], rtol=0, atol=1e-8 * scale)
            np.testing.assert_allclose(s_ll, full[3:, 3:], rtol=0, atol=1e-8 * scale)
            checked.append(len(s_ll))
        return n

    be._prefetch_joint = check  # type: ignore[method-assign]
    result = drive(be, iter_steps(odo, frames))
    assert result.status == "ok"
    assert len(checked) >= 5
    assert 4 in checked  # an oriented lamp: position and axis rows
