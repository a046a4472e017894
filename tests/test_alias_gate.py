"""The alias test of range-bearing association without ids (backend/alias_gate.py)."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest

from lampsam.backend.alias_gate import map_density, match_log_odds
from lampsam.backend.association import associate
from lampsam.backend.config import AssociationConfig
from lampsam.backend.models import Obs, predict, residual

SPACING = 5.0
R_BR = np.diag([0.02**2, 0.05**2])  # [bearing, range] noise: rad^2, m^2


def _grid() -> dict[int, np.ndarray]:
    """Trees on a 5 m grid, ids 0..48 (7 x 7, -15..15 m)."""
    xs = np.arange(-3, 4) * SPACING
    pts = [np.array([x, y]) for x in xs for y in xs]
    return dict(enumerate(pts))


def _sight(pose: np.ndarray, tree: np.ndarray, rng: np.random.Generator) -> Obs:
    """A ``[bearing, range]`` sighting of ``tree`` from the true ``pose`` with noise ``R_BR``."""
    d = tree - pose[:2]
    z = np.array([math.atan2(d[1], d[0]) - pose[2], math.hypot(*d)])
    z = z + rng.multivariate_normal(np.zeros(2), R_BR)
    z[0] = math.remainder(z[0], math.tau)
    return Obs("point2", z, R_BR)


def _decide(obs: Obs, est: np.ndarray, p_pose: np.ndarray, mapped: dict[int, np.ndarray],
            config: AssociationConfig, density: float) -> tuple[str, int | None]:
    """associate() one sighting from the estimated pose ``est`` (tangent covariance
    ``p_pose``; mapped landmarks exact): ``(status, landmark id)``."""

    def innovation(lid: int, o: Obs) -> tuple[np.ndarray, np.ndarray]:
        z_hat, h_p, _ = predict("point2", est, mapped[lid], o)
        return residual(o, z_hat), h_p @ p_pose @ h_p.T + o.R

    a = associate([obs], {"point2": list(mapped)}, innovation, config, lambda i: i in mapped,
                  alias_density=density)[0]
    return a.status, a.landmark_id


def test_match_log_odds_by_hand() -> None:
    # N(nu; 0, Psi) at d2 = 2, det Psi = 1e-4; rho * r = 0.04 * 5
    expected = math.log(math.exp(-1.0) / (2 * math.pi * 1e-2) / 0.2)
    assert match_log_odds(2.0, math.log(1e-4), 5.0, 0.04) == pytest.approx(expected, rel=1e-12)
    assert match_log_odds(math.inf, 0.0, 5.0, 0.04) == -math.inf
    assert match_log_odds(1.0, math.nan, 5.0, 0.04) == -math.inf


def test_measurement_space_density_is_rho_times_range() -> None:
    """Points scattered uniformly at rho per m^2 have density rho * r in [bearing, range]."""
    rng = np.random.default_rng(11)
    rho, half = 0.5, 15.0
    n_sets = 10000
    pts = rng.uniform(-half, half, size=(int(rho * (2 * half) ** 2 * n_sets), 2))
    b, r = np.arctan2(pts[:, 1], pts[:, 0]), np.hypot(pts[:, 0], pts[:, 1])
    for r0 in (3.0, 8.0, 13.0):
        inside = (np.abs(r - r0) < 0.5) & (np.abs(b - 0.3) < 0.1)
        per_cell = inside.sum() / n_sets / (1.0 * 0.2)  # one scatter's count per rad m
        assert per_cell == pytest.approx(rho * r0, rel=0.06)  # 3,000+ points a cell: 3 sigma


def test_map_density_of_a_grid_and_a_stated_spacing() -> None:
    xy = np.array(list(_grid().values()))
    assert map_density(xy) == pytest.approx(1.0 / SPACING**2, rel=1e-9)
    # two copies of one tree (0.05 m apart) do not shrink the spacing
    assert map_density(np.vstack([xy, xy[:5] + 0.05])) == pytest.approx(1.0 / SPACING**2, rel=1e-9)
    assert map_density(xy[:3]) == 0.0  # too few to tell
    assert map_density(xy[:3], spacing=2.0) == 0.25


def test_gate_alone_takes_the_neighbour_the_alias_test_does_not() -> None:
    """A tree never mapped, seen from a pose 2 m off (sigma 1.6 m): its sighting lands
    3 m from its mapped neighbour (d2 3.1, and 7.6 to the next: both inside the gate
    of 9.21); the alias test starts a landmark."""
    grid = _grid()
    target = 24 + 1  # (0, 5)
    mapped = {k: v for k, v in grid.items() if k != target}
    true_pose = np.array([-4.0, 1.0, 0.3])
    est = true_pose + np.array([2.0, 0.0, 0.0])  # the sighting lands near (2, 5)
    p_pose = np.diag([1.6**2, 1.6**2, 0.07**2])
    obs = _sight(true_pose, grid[target], np.random.default_rng(3))
    density = map_density(np.array(list(mapped.values())))
    off = AssociationConfig(use_known_ids=False)
    on = dataclasses.replace(off, alias_odds=1.0)
    status, lid = _decide(obs, est, p_pose, mapped, off, density)
    assert status == "matched" and lid == 24 + 8  # (5, 5): the neighbour
    assert _decide(obs, est, p_pose, mapped, on, density) == ("new", None)
    held = dataclasses.replace(on, alias_new=False)
    assert _decide(obs, est, p_pose, mapped, held, density)[0] == "dropped"
    # the test is off without a density (too few landmarks mapped)
    assert _decide(obs, est, p_pose, mapped, on, 0.0) == (status, lid)


def test_alias_test_on_random_sightings_of_an_aliased_grid() -> None:
    """Seeded sightings of unmapped trees (any match is wrong) and of mapped trees (the
    right landmark exists) from poses drawn with their stated covariance: the alias
    test removes most wrong matches when the pose is uncertain (1.6 m on a 5 m grid),
    and keeps the right ones when the pose is well known (0.2 m: only those in the
    gate's outer tail, d2 above ~8.8 of 9.21, fail)."""
    rng = np.random.default_rng(2026)
    grid = _grid()
    off = AssociationConfig(use_known_ids=False)
    on = dataclasses.replace(off, alias_odds=1.0)
    counts = {("wide", "off"): [0, 0], ("wide", "on"): [0, 0],
              ("tight", "off"): [0, 0], ("tight", "on"): [0, 0]}  # [wrong, right]
    for trial in range(300):
        target = int(rng.integers(8, 41))  # an inner tree
        unmapped = trial % 2 == 0
        mapped = {k: v for k, v in grid.items() if not (unmapped and k == target)}
        density = map_density(np.array(list(mapped.values())))
        bearing = rng.uniform(-math.pi, math.pi)
        rng_m = rng.uniform(3.0, 8.0)
        true_pose = np.array([*(grid[target] - rng_m * np.array([math.cos(bearing), math.sin(bearing)])),
                              rng.uniform(-math.pi, math.pi)])
        obs = _sight(true_pose, grid[target], rng)
        for name, sig_xy, sig_th in (("wide", 1.6, 0.07), ("tight", 0.2, 0.01)):
            p_pose = np.diag([sig_xy**2, sig_xy**2, sig_th**2])
            est = true_pose + rng.multivariate_normal(np.zeros(3), p_pose)
            for label, cfg in (("off", off), ("on", on)):
                status, lid = _decide(obs, est, p_pose, mapped, cfg, density)
                if status == "matched":
                    counts[(name, label)][0 if lid != target else 1] += 1
    wrong_off, wrong_on = counts[("wide", "off")][0], counts[("wide", "on")][0]
    assert wrong_off >= 20  # the gate alone gives unmapped trees to neighbours
    assert wrong_on <= wrong_off // 3
    assert counts[("tight", "off")][1] >= 140
    assert counts[("tight", "on")][1] >= 0.97 * counts[("tight", "off")][1]
    assert counts[("tight", "on")][0] <= counts[("tight", "off")][0]


def _neighbour_sightings(config_sets: dict[str, object], n_poses: int) -> int:
    """cityTrees_reduced_1k's first ``n_poses`` poses online (iSAM2, no ids): recorded
    sightings whose landmark's
    majority tree stands more than 1.5 m from their own tree (known-id batch positions;
    the file's six twin pairs, 0.05 m apart, are one place)."""
    import gtsam

    from lampsam.backend.config import SlamConfig
    from lampsam.backend.graph_log import run_graph_log, run_graph_log_backend
    from lampsam.backend.online_final import online_association
    from lampsam.datasets.graph_text import read_graph_text
    from lampsam.datasets.odometry import Pose2OdometryLog

    path = Path(gtsam.findExampleDataFile("victoria_park.txt")).parent / "cityTrees_reduced_1k.g2o"
    g = read_graph_text(path)
    od = g.odometry
    g = dataclasses.replace(g, pose_ids=g.pose_ids[:n_poses], sightings=g.sightings[:n_poses],
                            odometry=Pose2OdometryLog(od.t[:n_poses], od.delta[:n_poses],
                                                      od.cov[:n_poses]))
    known = run_graph_log(g, "batch", SlamConfig())
    where = {int(x.id): np.asarray(x.position[:2], float)
             for x in list(known.landmarks) + list(known.provisional)}
    cfg = SlamConfig()
    cfg = dataclasses.replace(cfg, association=dataclasses.replace(cfg.association, **config_sets))
    online, be = run_graph_log_backend(g, "isam2", cfg, known_ids=False)
    assert online.status == "ok" and be is not None
    s = online_association(be, online)
    fid = np.array([min(g.sightings[k], key=lambda c: abs(c.range - z[1])
                        + abs(math.remainder(c.bearing - z[0], math.tau))).landmark
                    for k, z in zip(s.k.tolist(), s.z, strict=True)])
    wrong = 0
    for lid in np.unique(s.lid).tolist():
        ids, n = np.unique(fid[s.lid == lid], return_counts=True)
        owner = where[int(ids[np.argmax(n)])]
        wrong += sum(int(c) for f, c in zip(ids.tolist(), n.tolist(), strict=True)
                     if np.hypot(*(where[f] - owner)) > 1.5)
    return wrong


def test_city_trees_online_gives_no_tree_to_a_neighbour() -> None:
    """GTSAM's cityTrees_reduced_1k (trees on a 5 m grid; the tuning log of the alias
    test), first 500 poses at the stated odometry noise: the gate alone gives 98
    sightings to a neighbouring tree, the alias test none, with JCBB on as well
    (the whole log: 169 against 0 and 0; docs/noids-aliasing.md)."""
    assert _neighbour_sightings({"use_known_ids": False}, 500) > 50
    assert _neighbour_sightings({"use_known_ids": False, "alias_odds": 1.0}, 500) == 0
    assert _neighbour_sightings({"use_known_ids": False, "alias_odds": 1.0,
                                 "joint_compatibility": True}, 500) == 0
