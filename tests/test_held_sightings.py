"""Held sightings (``association.planar_unique``, backend/held_sightings.py) on a seeded
row of trees whose odometry is stated 10x noisier than it is, so that every tree ahead
is first sighted with a mapped neighbour inside the new-landmark threshold and held.

Before 2026-11-24 a held sighting was re-gated only against the landmarks screened when
it was held: a tree mapped later (by a later, unambiguous sighting) never got its held
sightings back, and they expired unused (docs/failures.md, the vp1k trace)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from lampsam.backend.config import AssociationConfig, SlamConfig
from lampsam.backend.graph_log import run_graph_log
from lampsam.datasets.graph_text import read_graph_text
from lampsam.datasets.landmark_log_heldout import HELD_OUT, simulate_held_out


def _row_log(path: Path, rng: np.random.Generator, n: int = 80, stated: float = 0.2,
             spacing: float = 5.0) -> np.ndarray:
    """A robot driving 0.5 m per pose along x between two rows of trees (y = +-3 m,
    ``spacing`` apart, 0.3 m jitter); odometry noise 2 cm, 5 mrad, stated ``stated``
    (m, m, rad); sightings 1-10 m (0.01 rad, 0.05 m, as stated). Returns the truth."""
    trees = np.array([[x, s * 3.0] for x in np.arange(0.0, n * 0.5 + 10.0, spacing)
                      for s in (-1.0, 1.0)])
    trees += rng.normal(0.0, 0.3, trees.shape)
    pose = np.zeros(3)
    truth = [pose.copy()]
    lines = []
    for k in range(n):
        if k:
            pose = pose + np.array([0.5, 0.0, 0.0])
            truth.append(pose.copy())
            m = np.array([0.5, 0.0, 0.0]) + rng.normal(0.0, 1.0, 3) * np.array([0.02, 0.02, 0.005])
            lines.append(f"ODOMETRY {k - 1} {k} {float(m[0])!r} {float(m[1])!r} {float(m[2])!r} "
                         f"{stated**2} 0 0 {stated**2} 0 {stated**2}")
        for lid, p in enumerate(trees):
            r = float(np.hypot(*(p - pose[:2])))
            if 1.0 < r < 10.0:
                b = math.remainder(math.atan2(p[1] - pose[1], p[0] - pose[0]) - pose[2], math.tau)
                lines.append(f"BR {k} {lid} {float(b + rng.normal(0, 0.01))!r} "
                             f"{float(r + rng.normal(0, 0.05))!r} 0.01 0.05")
    path.write_text("\n".join(lines) + "\n")
    return np.array(truth)


def _rms(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.sum((a[:, :2] - b[:, :2]) ** 2, axis=1))))


def test_held_sightings_go_to_a_tree_mapped_after_they_were_held(tmp_path: Path) -> None:
    """Seed 0: 116 sightings held. Measured with the fix: 106 given back, 10 unused, the
    trajectory 0.1713 m from the truth against the known-id 0.1711 m; before it (held
    sightings re-gated against their first candidates only) 89 given back, 27 unused,
    0.1865 m."""
    truth = _row_log(tmp_path / "row.txt", np.random.default_rng(0))
    g = read_graph_text(tmp_path / "row.txt")
    known = run_graph_log(g, "isam2", SlamConfig())
    res = run_graph_log(g, "isam2", SlamConfig(association=AssociationConfig(planar_unique=True)),
                        known_ids=False)
    e = res.extra
    assert e["n_held"] >= 100
    assert e["n_held_unused"] <= 0.12 * e["n_held"]  # before: 27 of 116
    assert abs(_rms(res.poses, truth) - _rms(known.poses, truth)) < 0.005  # before: 0.015
    assert len(res.landmarks) == len(known.landmarks)


def test_held_out_logs_are_seeded_and_have_their_properties() -> None:
    """The held-out generator is deterministic per seed and each log has what it is for:
    ``grid`` trees 6 m apart on a grid, ``loop`` few trees in view (median <= 4), ``odo2x``
    odometry residuals twice the stated sigma."""
    grid, seed = HELD_OUT["grid"]
    a = simulate_held_out(grid, np.random.default_rng(seed))
    b = simulate_held_out(grid, np.random.default_rng(seed))
    assert a[0] == b[0]
    marks = a[2]
    d = np.hypot(*(marks[:, None, :] - marks[None, :, :]).transpose(2, 0, 1))
    np.fill_diagonal(d, np.inf)
    assert abs(float(np.median(d.min(axis=1))) - grid.spacing) < 1.0
    loop, seed = HELD_OUT["loop"]
    lines, truth, _ = simulate_held_out(loop, np.random.default_rng(seed))
    per_pose = np.bincount([int(x.split()[1]) for x in lines if x.startswith("BR")],
                           minlength=len(truth))
    assert np.median(per_pose) <= 4
    odo, seed = HELD_OUT["odo2x"]
    lines, truth, _ = simulate_held_out(odo, np.random.default_rng(seed))
    odo_lines = [x.split() for x in lines if x.startswith("ODOMETRY")]
    dth = np.array([float(x[5]) for x in odo_lines]) - np.diff(np.unwrap(truth[:, 2]))
    assert 1.7 < float(np.std(dth)) / odo.sigma_theta < 2.3
