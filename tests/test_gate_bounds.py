"""Bounds on the eq.-19 distance without the cross term, and the gate decisions they settle."""

from __future__ import annotations

import numpy as np

from lampsam.backend.association import associate
from lampsam.backend.config import AssociationConfig
from lampsam.backend.gate_bounds import d2_interval, resolve_screened
from lampsam.backend.interface import LandmarkKind
from lampsam.backend.models import Obs

Problem = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, float]
Screened = dict[int, dict[int, tuple[float, bool]]]


def _random_problem(rng: np.random.Generator, m: int) -> Problem:
    """A joint (pose 3, landmark 3) covariance, Jacobians, noise and an innovation."""
    g = rng.normal(size=(6, 6)) * rng.uniform(0.1, 3.0, size=6)
    joint = g @ g.T + 1e-3 * np.eye(6)
    h_p, h_l = rng.normal(size=(m, 3)), rng.normal(size=(m, 3))
    r = np.diag(rng.uniform(0.1, 2.0, size=m))
    h = np.hstack([h_p, h_l])
    psi = h @ joint @ h.T + r
    nu = rng.multivariate_normal(np.zeros(m), psi) * rng.uniform(0.3, 3.0)
    a = h_p @ joint[:3, :3] @ h_p.T
    b = h_l @ joint[3:, 3:] @ h_l.T
    return nu, a, b, r, float(nu @ np.linalg.solve(psi, nu))


def test_interval_brackets_exact_distance() -> None:
    rng = np.random.default_rng(7)
    for m in (2, 3):
        probs = [_random_problem(rng, m) for _ in range(400)]
        nu, a, b, r, d2 = (np.array([p[i] for p in probs]) for i in range(5))
        for margin in (1.0, 2.0):
            lo, hi = d2_interval(nu, a, margin * b, r)
            assert np.all(lo <= d2) and np.all(d2 <= hi)
            assert np.all(lo > 0.0)


def test_interval_tight_when_landmark_is_certain() -> None:
    """With a (nearly) certain landmark the cross term vanishes: the bracket closes on d2."""
    rng = np.random.default_rng(3)
    nu = rng.normal(size=(50, 2))
    g = rng.normal(size=(50, 2, 2))
    a = g @ np.transpose(g, (0, 2, 1)) + 0.1 * np.eye(2)
    b = 1e-9 * np.broadcast_to(np.eye(2), (50, 2, 2))
    r = np.broadcast_to(0.5 * np.eye(2), (50, 2, 2))
    d2 = np.einsum("pi,pi->p", nu, np.linalg.solve(a + r, nu[..., None])[..., 0])
    lo, hi = d2_interval(nu, a, b, r)
    np.testing.assert_allclose(lo, d2, rtol=0.02)
    np.testing.assert_allclose(hi, d2, rtol=0.02)


def _lamp(dof: int) -> Obs:
    return Obs(LandmarkKind.LAMP, np.zeros(dof), np.eye(dof), has_axis=dof == 3)


def _associate(obs: list[Obs], n_lm: int, exact: dict[tuple[int, int], float],
               screened: Screened, cfg: AssociationConfig) -> list[tuple[int | None, str]]:
    """:func:`associate` with an innovation that gives the pair's exact distance."""

    def innovation(lid: int, o: Obs) -> tuple[np.ndarray, np.ndarray]:
        i = next(j for j, ob in enumerate(obs) if ob is o)
        nu = np.zeros(len(o.z))
        nu[0] = np.sqrt(exact[(i, lid)])
        return nu, np.eye(len(o.z))

    out = associate(obs, {"lamp": list(range(n_lm))}, innovation, cfg, lambda _: True, None,
                    screened)
    return [(a.landmark_id, a.status) for a in out]


def test_settled_pairs_give_the_exact_gate_decisions() -> None:
    """Random frames: associate with the settled pairs == associate with every exact distance."""
    rng = np.random.default_rng(11)
    cfg = AssociationConfig()
    n_settled = n_pairs = 0
    for _ in range(300):
        n_obs, n_lm = int(rng.integers(1, 5)), int(rng.integers(1, 6))
        obs = [_lamp(int(rng.choice([2, 3]))) for _ in range(n_obs)]
        exact: dict[tuple[int, int], float] = {}
        screened: Screened = {}
        intervals: dict[tuple[int, int], tuple[float, float]] = {}
        for i, o in enumerate(obs):
            gate = cfg.gate(len(o.z))
            screened[i] = {}
            for lid in rng.choice(n_lm, size=int(rng.integers(0, n_lm + 1)), replace=False):
                lid = int(lid)
                d2 = float(rng.uniform(0.0, 2.5 * gate))
                exact[(i, lid)] = d2
                kind = rng.integers(4)
                if kind == 0:  # final screen distance
                    screened[i][lid] = (d2, True)
                elif kind == 1:  # screen only, beyond the gate
                    screened[i][lid] = (max(d2, gate), False)
                    exact[(i, lid)] = max(d2, gate)
                else:  # needs the exact gate; bounded half of the time
                    screened[i][lid] = (min(d2 * 0.5, gate * 0.99), False)
                    if kind == 2:
                        w = rng.uniform(1.0, 3.0)
                        intervals[(i, lid)] = (d2 / w, d2 * w)
                        n_pairs += 1

        before = _associate(obs, n_lm, exact, {i: dict(p) for i, p in screened.items()}, cfg)
        gates = {i: (cfg.gate(len(o.z)), cfg.new_threshold(len(o.z))) for i, o in enumerate(obs)}
        n_settled += resolve_screened(screened, intervals, gates)
        assert _associate(obs, n_lm, exact, screened, cfg) == before
    assert n_settled >= 10 and n_pairs >= 100  # the test exercises the settling
