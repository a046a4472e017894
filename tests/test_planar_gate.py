"""The smoothers' vectorised gate for range-bearing landmarks without ids (backend/gating.py)."""

import math

import numpy as np

from lampsam.backend.association import mahalanobis2
from lampsam.backend.planar_gate import bearing_range_d2, range_bearing_many
from lampsam.factors.range_bearing import range_bearing


def test_range_bearing_many_matches_the_scalar_model() -> None:
    rng = np.random.default_rng(3)
    pose = np.array([1.0, -2.0, 2.9])
    pts = rng.uniform(-20.0, 20.0, (25, 2))
    z, h_p, h_l = range_bearing_many(pose, pts)
    for j, p in enumerate(pts):
        z1, hp1, hl1 = range_bearing(pose, p)
        assert abs(math.remainder(z[j, 0] - z1[0], 2 * math.pi)) < 1e-12
        assert abs(z[j, 1] - z1[1]) < 1e-12
        np.testing.assert_allclose(h_p[j], hp1, atol=1e-12)
        np.testing.assert_allclose(h_l[j], hl1, atol=1e-12)


def test_bearing_range_d2_wraps_the_bearing_and_equals_eq20() -> None:
    rng = np.random.default_rng(4)
    z = np.array([[math.pi - 0.01, 10.0], [0.3, 5.0]])
    r = np.array([np.diag([0.01, 0.04]), np.diag([0.02, 0.09])])
    z_hat = np.array([[-math.pi + 0.02, 10.1], [0.2, 5.5], [1.0, 3.0]])
    a = rng.normal(size=(3, 2, 2))
    s = a @ np.transpose(a, (0, 2, 1)) * 0.01
    d2 = bearing_range_d2(z, r, z_hat, s)
    for i in range(2):
        for j in range(3):
            nu = z[i] - z_hat[j]
            nu[0] = math.remainder(nu[0], 2 * math.pi)
            assert abs(d2[i, j] - mahalanobis2(nu, s[j] + r[i])) < 1e-9 * max(1.0, d2[i, j])
    assert d2[0, 0] < 2.0  # 0.03 rad apart across +-pi, not 2 pi
