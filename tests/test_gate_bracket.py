"""The bracket of the exact gate distance without the cross term (issue 19).

- :func:`bracket_d2` on random joint covariances (seeded): ``lo <= d2 <= hi`` for the
  exact eq.-19 distance, with the landmark part from the true marginal and from an
  inflated one (an upper bound), and the bracket is not the trivial ``[0, nu^T R^-1 nu]``;
- :func:`settle_bracketed` settles only pairs whose association outcome the bracket fixes;
- on a seeded ceiling run with every lamp pair sent to the exact gate, the run with
  the bracket makes the same association decisions as the run without, having
  settled pairs.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

from lampsam.backend.association import Assignment
from lampsam.backend.ceiling import CeilingModel
from lampsam.backend.ceiling_graph import CeilingHandler
from lampsam.backend.config import SlamConfig
from lampsam.backend.gate_bracket import bracket_d2, settle_bracketed, sole_candidates
from lampsam.backend.graph import Isam2Slam
from lampsam.backend.slam import drive, iter_steps
from tests.test_backend import ceiling_world


def _random_pairs(rng: np.random.Generator, n: int, m: int, d: int, corr: float,
                  lm_scale: float = 1.0) -> tuple[np.ndarray, ...]:
    """n random pairs: joint covariance of (pose 3, landmark d), the landmark's first
    three states partly a copy of the pose (``corr``: as when initialised from it),
    its standard deviations scaled by ``lm_scale``."""
    nus, a, b, r, psi = [], [], [], [], []
    for _ in range(n):
        g = rng.normal(size=(3 + d, 3 + d))
        joint = g @ g.T / (3 + d) + 1e-3 * np.eye(3 + d)
        mix = np.eye(3 + d)
        mix[3:6, :3] = corr * np.eye(3)
        scale = np.diag([1.0] * 3 + [lm_scale] * d)
        joint = scale @ mix @ joint @ mix.T @ scale
        h_p, h_l = rng.normal(size=(m, 3)), rng.normal(size=(m, d))
        h = np.hstack([h_p, h_l])
        rr = np.diag(rng.uniform(0.01, 0.5, m))
        s = h @ joint @ h.T + rr
        nu = rng.multivariate_normal(np.zeros(m), s) * rng.uniform(0.5, 3.0)
        nus.append(nu)
        a.append(h_p @ joint[:3, :3] @ h_p.T)
        b.append(h_l @ joint[3:, 3:] @ h_l.T)
        r.append(rr)
        psi.append(s)
    return tuple(np.array(x) for x in (nus, a, b, r, psi))


def test_bracket_contains_the_exact_distance() -> None:
    rng = np.random.default_rng(19)
    for m, d, corr, lm_scale in ((2, 3, 0.9, 1.0), (3, 4, -0.8, 1.0), (3, 4, 0.0, 1.0),
                                 (3, 4, 0.5, 0.1)):
        nu, a, b, r, psi = _random_pairs(rng, 400, m, d, corr, lm_scale)
        exact = np.einsum("ni,ni->n", nu, np.linalg.solve(psi, nu[..., None])[..., 0])
        for scale in (1.0, 1.7):  # the landmark marginal itself, and an upper bound of it
            lo, hi = bracket_d2(nu, a, scale * b, r)
            assert np.all(lo <= exact * (1 + 1e-9)), (m, d, scale)
            assert np.all(hi >= exact * (1 - 1e-9)), (m, d, scale)
            # t = 1 (2 (A + B) + R, the plain Cauchy-Schwarz bound) is never tighter
            s1 = 2.0 * (a + scale * b) + r
            lo1 = np.einsum("ni,ni->n", nu, np.linalg.solve(s1, nu[..., None])[..., 0])
            assert np.all(lo >= lo1 * (1 - 1e-9))
        hi_r = np.einsum("ni,ni->n", nu, np.linalg.solve(r, nu[..., None])[..., 0])
        lo, hi = bracket_d2(nu, a, b, r)
        assert np.median(lo / exact) > 0.05  # the lower distance is not 0
        if lm_scale < 1.0:  # a well-known landmark seen from an uncertain pose:
            assert np.mean(hi < 0.5 * hi_r) > 0.5  # the lower covariance bound helps
    lo, hi = bracket_d2(nu, a, None, r)  # no landmark bound: [0, nu^T R^-1 nu]
    assert np.all(lo == 0.0) and np.allclose(hi, hi_r)
    mask = np.arange(len(nu)) % 2 == 0  # rows asking only for R's end
    lo_m, hi_m = bracket_d2(nu, a, b, r, mask)
    lo_f, hi_f = bracket_d2(nu, a, b, r)
    assert np.all(lo_m[mask] == 0.0) and np.allclose(hi_m[mask], hi_r[mask])
    assert np.allclose(lo_m[~mask], lo_f[~mask]) and np.allclose(hi_m[~mask], hi_f[~mask])


def test_settle_only_what_the_bracket_decides() -> None:
    gate, new = {0: 11.3, 1: 11.3, 2: 11.3}, {0: 21.1, 1: 21.1, 2: 21.1}
    pairs = {0: {5: 3.0}, 1: {6: 4.0, 7: 30.0}, 2: {8: 2.0, 9: 5.0}}
    bracket = {(0, 5): (1.0, 9.0), (1, 6): (25.0, 80.0), (2, 8): (0.1, 3.0),
               (2, 9): (0.1, 3.0)}
    sole = sole_candidates(pairs, gate)
    assert sole == {(0, 5), (1, 6)}
    got = settle_bracketed(sole, bracket, gate, new, None)
    # 0: sole candidate, surely inside; 1: beyond the new-landmark threshold;
    # 2: two candidates inside: the exact distances pick the winner
    assert got == {(0, 5): (9.0, "inside"), (1, 6): (25.0, "outside")}
    # a landmark wanted by two observations is not settled inside
    assert sole_candidates({0: {5: 3.0}, 1: {5: 4.0}}, gate) == set()
    assert settle_bracketed(set(), {(0, 5): (1.0, 9.0)}, gate, new, None) == {}
    # hi above the gate: undecided; lo beyond new but not beyond the far-reuse threshold
    one = {(0, 5)}
    assert settle_bracketed(one, {(0, 5): (1.0, 12.0)}, gate, new, None) == {}
    far = {0: 42.2}
    assert settle_bracketed(one, {(0, 5): (30.0, 90.0)}, gate, new, far) == {}
    assert settle_bracketed(one, {(0, 5): (50.0, 90.0)}, gate, new, far) == {
        (0, 5): (50.0, "outside")}


def _every_lamp_to_exact_gate(obs: Any, screened: Any) -> Any:
    """Every lamp pair asks for eq. 19 (not only ambiguous ones): many exact queries."""
    return {i: {lid: (d2, obs[i].kind == "corner") for lid, (d2, _) in pairs.items()}
            for i, pairs in screened.items()}


def test_decisions_with_and_without_the_bracket_are_the_same() -> None:
    world = ceiling_world(np.random.default_rng(11), duration=14.0, n_corners=8)
    rig, odo, frames, gt = world
    import lampsam.backend.graph as graph_module
    assoc = graph_module.associate
    decisions: dict[bool, list[list[tuple[int, int | None, str]]]] = {}
    poses: dict[bool, np.ndarray] = {}
    for on in (False, True):
        base = SlamConfig()
        cfg = dataclasses.replace(
            base, association=dataclasses.replace(base.association, use_known_ids=False),
            isam2=dataclasses.replace(base.isam2, bracket_gate=on))
        model = CeilingModel.from_camera(rig.camera)
        be = Isam2Slam(rig.odometry, cfg, gt.poses[0], model, CeilingHandler(model))
        be._mark_ambiguous = _every_lamp_to_exact_gate  # type: ignore[method-assign]
        got: list[list[tuple[int, int | None, str]]] = []

        def recording(*a: Any, _got: list[list[tuple[int, int | None, str]]] = got,
                      **k: Any) -> list[Assignment]:
            out = assoc(*a, **k)
            _got.append([(x.obs_index, x.landmark_id, x.status) for x in out])
            return out

        graph_module.associate = recording  # type: ignore[assignment]
        try:
            result = drive(be, iter_steps(odo, frames))
        finally:
            graph_module.associate = assoc  # type: ignore[assignment]
        assert result.status == "ok"
        decisions[on] = got
        poses[on] = result.poses
        if on:
            assert be.n_bracket_inside >= 50  # pairs that asked iSAM2 without the bracket
        else:
            assert be.n_bracket_inside == 0
    assert decisions[True] == decisions[False]
    np.testing.assert_allclose(poses[True], poses[False], atol=1e-9)
