"""The far-lamp bound of the exact gate (issue 19): a lower bound, and the same decisions.

:meth:`~lampsam.backend.gate_shortcuts.LampGateShortcuts._bound_far` carries a lamp's last exact joint
marginal to the current pose by the odometry alone. On a seeded ceiling run where
every lamp pair goes to the exact gate:

- at every exact query that has an earlier record in the window (and no
  relinearisation since), the bound's ``Psi`` is at least the exact one
  (``Psi_bound - Psi_exact`` positive semi-definite, to 1e-4 relative: the odometry
  since the record is composed per keyframe for the bound, per sample for the gate),
  so its distance is at most the exact distance;
- the run with the bound on makes the same association decisions as the run without.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

from lampsam.backend.association import Assignment, mahalanobis2
from lampsam.backend.ceiling import CeilingModel
from lampsam.backend.ceiling_graph import CeilingHandler
from lampsam.backend.config import SlamConfig
from lampsam.backend.graph import Isam2Slam
from lampsam.backend.slam import drive, iter_steps
from tests.test_backend import ceiling_world


def _every_lamp_to_exact_gate(obs: Any, screened: Any) -> Any:
    """Every lamp pair asks for eq. 19 (not only ambiguous ones): many exact queries."""
    return {i: {lid: (d2, obs[i].kind == "corner") for lid, (d2, _) in pairs.items()}
            for i, pairs in screened.items()}


def _backend(bound: bool, world: Any, gate_prob: float = 0.99, new_prob: float = 0.9999
             ) -> Isam2Slam:
    rig, _, _, gt = world
    base = SlamConfig()
    cfg = dataclasses.replace(
        base, association=dataclasses.replace(base.association, use_known_ids=False,
                                              gate_prob=gate_prob, new_prob=new_prob),
        isam2=dataclasses.replace(base.isam2, far_lamp_recheck=0, far_lamp_bound=bound,
                                   bracket_gate=False))  # every pair asks iSAM2
    model = CeilingModel.from_camera(rig.camera)
    be = Isam2Slam(rig.odometry, cfg, gt.poses[0], model, CeilingHandler(model))
    be._mark_ambiguous = _every_lamp_to_exact_gate  # type: ignore[method-assign]
    return be


def test_bound_is_below_every_exact_distance() -> None:
    world = ceiling_world(np.random.default_rng(11), duration=14.0, n_corners=8)
    be = _backend(False, world)
    prev: dict[int, Any] = {}
    checked: list[float] = []
    screen, innovation = be._screen, be._innovation

    def snap_screen(obs: Any, pose: Any, pose_cov: Any) -> Any:
        prev.clear()
        prev.update(be._joint_at)  # the records before this keyframe's queries
        prev["pose"] = pose
        return screen(obs, pose, pose_cov)

    def check_innovation(gate_ctx: Any, lid: int, obs: Any) -> Any:
        pred = innovation(gate_ctx, lid, obs)
        if pred is None or obs.kind != "lamp" or lid not in prev or prev[lid][0] >= gate_ctx[0]:
            return pred
        bound = be._far_bound(prev[lid], lid, obs, prev["pose"], be._relative_covs(), {})
        if bound is None:
            return pred
        nu, psi = pred
        d2_lo, psi_bound = bound
        # Psi^-1/2 Psi_bound Psi^-T/2 >= I: the bound's covariance is the wider
        c = np.linalg.cholesky(psi)
        w = np.linalg.eigvalsh(np.linalg.solve(c, np.linalg.solve(c, psi_bound).T))
        assert w.min() >= 1.0 - 1e-4, (lid, gate_ctx[0], w)  # rounding of the odometry composition
        assert d2_lo <= mahalanobis2(nu, psi) * (1.0 + 1e-4)
        checked.append(w.min())
        return pred

    be._screen = snap_screen  # type: ignore[method-assign]
    be._innovation = check_innovation  # type: ignore[method-assign]
    rig, odo, frames, _ = world
    assert drive(be, iter_steps(odo, frames)).status == "ok"
    assert len(checked) >= 50  # queries with an earlier record in the window
    assert np.median(checked) > 1.0 + 1e-4  # the bound is not trivially equal


def test_decisions_with_and_without_the_bound_are_the_same() -> None:
    world = ceiling_world(np.random.default_rng(11), duration=14.0, n_corners=8)
    decisions: dict[bool, list[list[Assignment]]] = {}
    for bound in (False, True):
        # narrow gates (chi-square 0.5 / 0.7): true lamps fall beyond the new-landmark
        # threshold often enough for the bound to settle pairs (none do at 0.99 here)
        be = _backend(bound, world, gate_prob=0.5, new_prob=0.7)
        import lampsam.backend.graph as graph_module
        assoc = graph_module.associate
        got: list[list[Assignment]] = []

        def recording(*a: Any, _assoc: Any = assoc, _got: list[list[Assignment]] = got,
                      **k: Any) -> list[Assignment]:
            out = _assoc(*a, **k)
            _got.append([(x.obs_index, x.landmark_id, x.status) for x in out])
            return out

        graph_module.associate = recording  # type: ignore[assignment]
        try:
            _, odo, frames, _ = world
            assert drive(be, iter_steps(odo, frames)).status == "ok"
        finally:
            graph_module.associate = assoc  # type: ignore[assignment]
        decisions[bound] = got
        if bound:
            assert be.n_far_bounded >= 20
    assert decisions[True] == decisions[False]
