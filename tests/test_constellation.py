"""Revisit detection by constellation (backend/constellation.py) on seeded synthetic maps."""

from __future__ import annotations

import math

import numpy as np

from lampsam.backend.constellation import align_constellation
from lampsam.factors.geometry import rigid_fit_2d


def _trees(rng: np.random.Generator, n: int, size: float, min_sep: float) -> np.ndarray:
    """``n`` tree positions in a ``size`` square, at least ``min_sep`` apart."""
    pts: list[np.ndarray] = []
    while len(pts) < n:
        p = rng.uniform(0.0, size, 2)
        if all(np.linalg.norm(p - q) >= min_sep for q in pts):
            pts.append(p)
    return np.array(pts)


def _rot(theta: float) -> np.ndarray:
    return np.array([[math.cos(theta), -math.sin(theta)], [math.sin(theta), math.cos(theta)]])


def test_rigid_fit_recovers_a_known_motion() -> None:
    rng = np.random.default_rng(0)
    src = rng.uniform(-10, 10, (6, 2))
    dst = src @ _rot(0.4).T + np.array([3.0, -2.0])
    fit = rigid_fit_2d(src, dst)
    theta, t = fit[2], fit[:2]
    assert abs(theta - 0.4) < 1e-12
    np.testing.assert_allclose(t, [3.0, -2.0], atol=1e-12)


def test_revisit_copies_are_aligned_to_their_trees() -> None:
    rng = np.random.default_rng(7)
    trees = _trees(rng, 80, 100.0, 3.0)  # the old map, about 10 m apart
    seen = [3, 11, 19, 27, 35, 42]  # trees mapped again at a revisit ...
    theta, shift = 0.25, np.array([14.0, -9.0])  # ... with this drift (beyond any gate)
    copies = (trees[seen] - shift) @ _rot(-theta).T  # dst = R src + shift
    copies += rng.normal(scale=0.2, size=copies.shape)  # the copies' own error
    new = np.array([[150.0, 150.0], [160.0, 140.0]])  # trees not in the old map
    src = np.vstack([copies, new])
    al = align_constellation(src, trees, tol=1.0, min_inliers=4)
    assert al is not None
    assert set(al.pairs) == {(k, t) for k, t in enumerate(seen)}
    assert abs(al.theta - theta) < 0.02
    np.testing.assert_allclose(al.shift, shift, atol=0.5)
    assert al.rms < 0.4 and al.runner_up <= len(seen) - 2


def test_unrelated_constellation_is_not_aligned() -> None:
    rng = np.random.default_rng(8)
    trees = _trees(rng, 80, 100.0, 3.0)
    src = _trees(rng, 5, 100.0, 3.0) + 300.0  # another place: no rigid motion fits 4
    assert align_constellation(src, trees, tol=1.0, min_inliers=4) is None
    # a grid is ambiguous: every shift by one cell fits as well
    grid = np.array([[x, y] for x in range(0, 50, 10) for y in range(0, 50, 10)], float)
    assert align_constellation(grid[:6] + 0.1, grid, tol=1.0, min_inliers=4) is None
