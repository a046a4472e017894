"""Placing the sightings an online run left out, by max-mixture factors
(factors/max_mixture.py, backend/held_placement.py, ``online_final_held_mixture``)."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import gtsam
import numpy as np
import pytest
from gtsam.symbol_shorthand import L, X

from lampsam.backend.config import SlamConfig
from lampsam.backend.graph_log import run_graph_log_backend
from lampsam.backend.held_placement import held_clusters, place_held
from lampsam.backend.noids_offline import dropped_sightings
from lampsam.backend.online_final import final_solve, online_association
from lampsam.backend.reassociate import Sightings, build_graph
from lampsam.datasets.graph_text import read_graph_text
from lampsam.datasets.landmark_log_sim import LandmarkLogSpec, write_landmark_log
from lampsam.factors.gtsam_factors import pose_array
from lampsam.factors.max_mixture import max_mixture_choice, max_mixture_factor
from lampsam.factors.range_bearing import range_bearing

#: sightings' noise: bearing 0.05 rad, range 0.2 m (sigma)
R = np.diag([0.05**2, 0.2**2])
#: the new-landmark threshold chi2_2^-1(0.9999) and the gate chi2_2^-1(0.99)
C_NEW = SlamConfig().association.new_threshold(2)
GATE = SlamConfig().association.gate(2)

#: The config with the held sightings' placement off (``online_final_held_mixture``, on by
#: default): these tests check the final solve of the association the online run made.
NO_PLACE = dataclasses.replace(SlamConfig(), reassociation=dataclasses.replace(
    SlamConfig().reassociation, online_final_held_mixture=False))
N_POSES = 12


def _z(pose: np.ndarray, xy: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """``[bearing, range]`` of ``xy`` from ``pose`` with a tenth of the stated noise."""
    z, _, _ = range_bearing(pose, xy)
    return z + rng.normal(0.0, 0.1 * np.sqrt(np.diag(R)))


def _scene(lms: dict[int, tuple[float, float]], rec: list[tuple[int, int]],
           held: list[tuple[int, tuple[float, float]]], seed: int = 0):  # type: ignore[no-untyped-def]
    """Poses ``(k, 0, 0)``, k < 12, odometry 1 m (sigma 1 cm, 0.001 rad); ``rec`` the
    recorded sightings ``(pose, landmark)``; ``held`` the left-out ones ``(pose, true
    point)``. Returns ``(graph, truth values, s, dk, dz, dr, poses)``."""
    rng = np.random.default_rng(seed)
    poses = np.array([[float(k), 0.0, 0.0] for k in range(N_POSES)])
    odo = [(np.zeros(3), np.eye(3))] + [
        (np.array([1.0, 0.0, 0.0]), np.diag([1e-4, 1e-4, 1e-6])) for _ in range(1, N_POSES)]
    prior = gtsam.PriorFactorPose2(X(0), gtsam.Pose2(0, 0, 0),
                                   gtsam.noiseModel.Diagonal.Sigmas(np.array([1e-3, 1e-3, 1e-4])))
    s = Sightings(np.array([k for k, _ in rec]),
                  np.array([_z(poses[k], np.array(lms[i]), rng) for k, i in rec]),
                  np.repeat(R[None], len(rec), 0), np.array([i for _, i in rec]))
    graph = build_graph(prior, odo, s)
    v = gtsam.Values()
    for k in range(N_POSES):
        v.insert(X(k), gtsam.Pose2(*poses[k]))
    for i, xy in lms.items():
        v.insert(L(i), gtsam.Point2(*xy))
    dk = np.array([k for k, _ in held], int)
    dz = np.array([_z(poses[k], np.array(xy), rng) for k, xy in held]).reshape(-1, 2)
    dr = np.repeat(R[None], len(held), 0)
    return graph, v, s, dk, dz, dr, poses


def _residual_at(f: gtsam.CustomFactor, pose: np.ndarray, lm: list[np.ndarray],
                 d: np.ndarray) -> np.ndarray:
    """``f``'s residual with the pose retracted by ``d[:3]`` (right tangent) and the two
    landmarks moved by ``d[3:5]``, ``d[5:7]``."""
    w = gtsam.Values()
    w.insert(X(0), gtsam.Pose2(*pose).retract(d[:3]))
    w.insert(L(0), gtsam.Point2(*(lm[0] + d[3:5])))
    w.insert(L(1), gtsam.Point2(*(lm[1] + d[5:7])))
    return np.asarray(f.unwhitenedError(w))


def test_max_mixture_jacobians_match_numerical_derivatives() -> None:
    """Each component's Jacobians (pose on GTSAM's right tangent, landmarks) against
    central differences of the factor's own residual, at seeded random states; the other
    landmarks' Jacobians and, when "none" wins, all of them are zero; the chosen
    component's error equals ``BearingRangeFactor2D``'s."""
    rng = np.random.default_rng(7)
    for trial in range(6):
        pose = np.array([*rng.uniform(-5, 5, 2), rng.uniform(-np.pi, np.pi)])
        lm = [pose[:2] + rng.uniform(2, 6) * np.array([np.cos(a), np.sin(a)])
              for a in rng.uniform(-np.pi, np.pi, 2)]
        target = trial % 3  # 0, 1: a sighting of that landmark; 2: of neither
        xy = lm[target] if target < 2 else pose[:2] + np.array([30.0, 0.0])
        z, _, _ = range_bearing(pose, xy)
        z = z + rng.normal(0.0, 0.5 * np.sqrt(np.diag(R)))
        f = max_mixture_factor(X(0), [L(0), L(1)], z, R, C_NEW)
        v = gtsam.Values()
        v.insert(X(0), gtsam.Pose2(*pose))
        v.insert(L(0), gtsam.Point2(*lm[0]))
        v.insert(L(1), gtsam.Point2(*lm[1]))
        a, b = f.linearize(v).jacobian()
        e = f.unwhitenedError(v)
        assert np.allclose(-b, e)
        j, c2 = max_mixture_choice(pose, lm, z, R, C_NEW)
        assert j == (target if target < 2 else -1)
        assert np.isclose(2.0 * f.error(v), c2)
        if j < 0:
            assert np.isclose(c2, C_NEW) and np.all(a == 0.0)
            continue
        br = gtsam.BearingRangeFactor2D(X(0), L(j), gtsam.Rot2(float(z[0])), float(z[1]),
                                        gtsam.noiseModel.Gaussian.Covariance(R))
        assert np.isclose(f.error(v), br.error(v), rtol=1e-9)
        h = 1e-6
        num = np.zeros((2, 7))
        for col in range(7):
            d = np.zeros(7)
            d[col] = h
            num[:, col] = (_residual_at(f, pose, lm, d) - _residual_at(f, pose, lm, -d)) / (2 * h)
        assert np.allclose(a, num, atol=1e-5), (trial, a, num)
        other = slice(5, 7) if j == 0 else slice(3, 5)
        assert np.all(a[:, other] == 0.0)


def test_an_ambiguous_held_sighting_goes_to_its_own_landmark() -> None:
    """Two trees 0.8 m apart, both mapped; pose 6 recorded nothing and its sighting of
    ``B`` was held. At the start the pose is 0.5 m behind (odometry pins it back): there
    the sighting fits ``A`` better (a hard choice at this estimate takes ``A``); the
    mixture re-chooses at each linearisation and ends on ``B``, pose 6 within 2 cm."""
    lms = {0: (4.6, 3.0), 1: (5.4, 3.0)}
    rec = [(k, i) for k in range(N_POSES) if k != 6 for i in lms]
    graph, v, s, dk, dz, dr, poses = _scene(lms, rec, [(6, lms[1])])
    start = gtsam.Values(v)
    start.update(X(6), gtsam.Pose2(5.5, 0.0, 0.0))
    at_start = max_mixture_choice(np.array([5.5, 0.0, 0.0]),
                                  [np.array(lms[0]), np.array(lms[1])], dz[0], R, C_NEW)
    assert at_start[0] == 0 and at_start[1] < C_NEW  # A, by a hard choice here
    p = place_held(graph, start, s, dk, dz, dr, C_NEW)
    assert p.n_candidates.tolist() == [2]
    assert p.lid.tolist() == [1]
    assert np.hypot(*(pose_array(p.values.atPose2(X(6)))[:2] - poses[6, :2])) < 0.02


def test_a_held_sighting_of_an_unmapped_tree_stays_out() -> None:
    """One held sighting of a tree no landmark is near (no candidate): it stays out,
    with or without new landmarks (a landmark of one sighting does not pay)."""
    lms = {0: (4.6, 3.0), 1: (5.4, 3.0)}
    rec = [(k, i) for k in range(N_POSES) for i in lms]
    graph, v, s, dk, dz, dr, _ = _scene(lms, rec, [(6, (6.0, -3.0))])
    for gate in (None, GATE):
        p = place_held(graph, v, s, dk, dz, dr, C_NEW, gate)
        assert p.lid.tolist() == [-1]
    assert place_held(graph, v, s, dk, dz, dr, C_NEW).n_candidates.tolist() == [0]


def test_held_sightings_of_an_unmapped_tree_start_a_landmark() -> None:
    """An unmapped tree 0.5 m from a mapped one, sighted (held) from poses 6, 7 and 8: each
    sighting is inside the new-landmark threshold of the mapped tree, so the mixture over
    mapped landmarks alone puts all three on its neighbour; with new landmarks they form
    one, within 0.1 m of the tree, and none goes to the neighbour."""
    lms = {0: (8.0, 3.0)}
    rec = [(k, 0) for k in range(N_POSES) if k not in (6, 7, 8)]
    tree = (7.5, 3.0)
    graph, v, s, dk, dz, dr, poses = _scene(lms, rec, [(k, tree) for k in (6, 7, 8)])
    assert held_clusters(poses, dk, dz, dr, GATE).tolist() == [0, 0, 0]
    only_mapped = place_held(graph, v, s, dk, dz, dr, C_NEW)
    assert only_mapped.lid.tolist() == [0, 0, 0]  # the neighbour: what a hard rule does
    p = place_held(graph, v, s, dk, dz, dr, C_NEW, GATE)
    assert len(set(p.lid.tolist())) == 1 and p.lid[0] not in (0, -1)
    assert np.hypot(*(np.asarray(p.values.atPoint2(L(int(p.lid[0])))) - tree)) < 0.1


def test_final_solve_with_the_mixture_places_the_left_out_sightings(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """``online_final_held_mixture`` on a seeded 200-pose log (the online run at 16x the
    odometry variance leaves some sightings out): the final solve with it holds every
    sighting it held before with the same landmark, its ``C`` is lower, and every
    sighting it placed on a mapped landmark is of that landmark's tree (file ids); new
    landmarks only with ``online_final_held_new_landmarks``. When GTSAM fails on the
    mixture graph the final solve without the placement is the answer."""
    spec = LandmarkLogSpec(n_poses=200, n_landmarks=30, extent=40.0, stop_every=0)
    g = read_graph_text(write_landmark_log(tmp_path / "log.txt", spec,
                                           np.random.default_rng(1))[0])
    cfg = NO_PLACE
    cfg16 = dataclasses.replace(cfg, pose2_odometry=dataclasses.replace(cfg.pose2_odometry,
                                                                        cov_scale=16.0))
    online, be = run_graph_log_backend(g, "isam2", cfg16, known_ids=False)
    assert be is not None and online.status == "ok"
    s = online_association(be, online)
    base = final_solve(g, cfg16, online, Sightings(s.k, s.z, s.r, s.lid.copy()))
    left = len(dropped_sightings(g, base.sightings)[0])
    assert left > 0
    for new in (True, False):
        on = dataclasses.replace(cfg16, reassociation=dataclasses.replace(
            cfg16.reassociation, online_final_held_mixture=True,
            online_final_held_new_landmarks=new))
        mix = final_solve(g, on, online, Sightings(s.k, s.z, s.r, s.lid.copy()))
        n0 = len(base.sightings.k)
        assert len(mix.sightings.k) > n0 and mix.cost < base.cost
        assert np.array_equal(mix.sightings.lid[:n0], base.sightings.lid)
        assert sum(m.kind == "held" for m in mix.moves) == len(mix.sightings.k) - n0
        fid = np.array([min(g.sightings[k], key=lambda c: abs(c.range - z[1])).landmark
                        for k, z in zip(mix.sightings.k.tolist(), mix.sightings.z,
                                        strict=True)])
        for j in range(n0, len(mix.sightings.k)):
            lid = mix.sightings.lid[j]
            own = fid[:n0][base.sightings.lid == lid]
            if len(own):
                assert np.bincount(own).argmax() == fid[j]
            else:
                assert new  # a new landmark only with the option

    import lampsam.backend.online_final as of

    def fails(*_: object, **__: object) -> None:
        raise RuntimeError("Indeterminant linear system")

    monkeypatch.setattr(of, "place_into", fails)
    kept = final_solve(g, on, online, Sightings(s.k, s.z, s.r, s.lid.copy()))
    assert np.array_equal(kept.sightings.lid, base.sightings.lid) and kept.cost == base.cost


@pytest.mark.parametrize("bad", [0.0, -1.0])
def test_max_mixture_refuses_a_non_positive_null_cost(bad: float) -> None:
    """The "none" component's cost must be positive (its residual is its square root)."""
    from lampsam.factors.geometry import FactorError

    with pytest.raises(FactorError, match="null_chi2"):
        max_mixture_factor(X(0), [L(0)], np.array([0.1, 3.0]), R, bad)
