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
from lampsam.backend.gate_exact import RELATIVE_GATE_KEYFRAMES
from lampsam.backend.gating import Gating
from lampsam.backend.graph import Isam2Slam
from lampsam.backend.interface import LandmarkKind
from lampsam.backend.models import Obs
from lampsam.backend.pose_cov import compose_cov
from lampsam.backend.slam import drive, iter_steps
from lampsam.factors.gtsam_factors import pose_array
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
    """Every lamp pair is sent to the exact gate here, so each keyframe prefetches several."""
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

    def every_lamp_to_exact_gate(obs, screened, axis_d2=None):  # every lamp pair asks for eq. 19
        return {i: {lid: (d2, o_kind == "corner") for lid, (d2, _) in pairs.items()}
                for i, pairs in screened.items() for o_kind in [obs[i].kind]}

    be._prefetch_joint = check  # type: ignore[method-assign]
    be._mark_ambiguous = every_lamp_to_exact_gate  # type: ignore[method-assign]
    result = drive(be, iter_steps(odo, frames))
    assert result.status == "ok"
    assert len(checked) >= 5
    assert 4 in checked  # an oriented lamp: position and axis rows


def _triangulate_loop(model: CeilingModel, poses: np.ndarray, ms: np.ndarray, covs: np.ndarray
                      ) -> tuple[np.ndarray, np.ndarray]:
    """Reference: eqs. 17-18 stacked one sight at a time, weighted normal equations summed."""
    o = model.body_t_camera
    rows, rhs, w = [], [], []
    for (x, y, th), m, cov in zip(poses, ms, covs, strict=True):
        rt = np.array([[np.cos(th), np.sin(th)], [-np.sin(th), np.cos(th)]])
        rows.append(np.column_stack([rt, -m]))
        rhs.append(rt @ np.array([x, y]) + o[:2])
        w.append(np.linalg.inv(cov))
    sol = np.linalg.lstsq(np.vstack(rows), np.concatenate(rhs), rcond=None)[0]
    info = sum(a.T @ (wk / sol[2] ** 2) @ a for a, wk in zip(rows, w, strict=True))
    return np.array([sol[0], sol[1], sol[2] + o[2]]), np.linalg.inv(info)


def test_vectorised_triangulation_matches_per_sight_sum() -> None:
    rng = np.random.default_rng(2)
    rig, _, _, _ = ceiling_world(rng, duration=1.0, n_corners=0)
    model = CeilingModel.from_camera(rig.camera)
    point = np.array([1.0, 0.5, 2.8])
    poses = np.column_stack([rng.uniform(0, 1.5, 6), rng.uniform(-0.5, 0.5, 6), rng.uniform(-3, 3, 6)])
    ms = np.array([model.predict(p, point, with_axis=False)[0] for p in poses])
    ms += rng.normal(0, 1e-3, ms.shape)
    covs = np.array([np.diag(rng.uniform(0.5, 2.0, 2)) * 1e-6 for _ in poses])
    got_p, got_c = model.triangulate(poses, ms, covs)
    ref_p, ref_c = _triangulate_loop(model, poses, ms, covs)
    np.testing.assert_allclose(got_p, ref_p, rtol=0, atol=1e-12)
    np.testing.assert_allclose(got_c, ref_c, rtol=1e-9, atol=0)
    assert np.linalg.norm(got_p - point) < 0.05


def test_vectorised_reprojection_chi2_matches_per_sight_solve() -> None:
    """The corner consistency test: one vectorised sum against predict + solve per sight."""
    rng = np.random.default_rng(3)
    rig, _, _, _ = ceiling_world(rng, duration=1.0, n_corners=0)
    model = CeilingModel.from_camera(rig.camera)
    point = np.array([0.7, -0.2, 2.9])
    poses = np.column_stack([rng.uniform(0, 1.5, 7), rng.uniform(-0.5, 0.5, 7), rng.uniform(-3, 3, 7)])
    ms = np.array([model.predict(p, point, with_axis=False)[0] for p in poses])
    ms += rng.normal(0, 2e-3, ms.shape)
    covs = []
    for _ in poses:  # correlated, unequal noise
        a = rng.normal(size=(2, 2)) * 1e-3
        covs.append(a @ a.T + 1e-7 * np.eye(2))
    covs_a = np.array(covs)
    ref = 0.0
    for p, m, c in zip(poses, ms, covs_a, strict=True):
        r = m - model.predict(p, point, with_axis=False)[0]
        ref += float(r @ np.linalg.solve(c, r))
    got = model.reprojection_chi2(poses, point, ms, covs_a)
    assert ref > 1.0  # the noise makes it non-trivial
    np.testing.assert_allclose(got, ref, rtol=1e-9)
    bad = covs_a.copy()
    bad[2] = -bad[2]
    assert model.reprojection_chi2(poses, point, ms, bad) == float("inf")


def test_pairwise_d2_matches_per_pair_mahalanobis() -> None:
    from lampsam.backend.association import mahalanobis2, pairwise_d2

    rng = np.random.default_rng(4)
    z, z_hat = rng.normal(size=(5, 2)), rng.normal(size=(7, 2))
    r = np.array([(lambda a: a @ a.T + 0.1 * np.eye(2))(rng.normal(size=(2, 2))) for _ in z])
    s = np.array([(lambda a: a @ a.T)(rng.normal(size=(2, 2))) for _ in z_hat])
    s[3] = -np.eye(2) * 10.0  # R + S not positive definite: no distance
    got = pairwise_d2(z, r, z_hat, s)
    for i in range(len(z)):
        for j in range(len(z_hat)):
            if j == 3:
                assert got[i, j] == np.inf
            else:
                np.testing.assert_allclose(got[i, j], mahalanobis2(z[i] - z_hat[j], r[i] + s[j]),
                                           rtol=1e-9)


def test_keyframe_odometry_factor_equals_composition_of_its_samples() -> None:
    """The factor reuses the first step's composition when no samples follow (exactly)."""
    from lampsam.backend.odometry import Pose2Motion
    from lampsam.datasets.odometry import Pose2OdometryModel
    from lampsam.frontend.measurements import RangeBearingFrame, RangeBearingObservation

    rng = np.random.default_rng(6)
    cfg = SlamConfig()
    model = Pose2OdometryModel()
    be = Isam2Slam(model, cfg, np.zeros(3))
    motion = Pose2Motion(model)
    chunks: list[np.ndarray] = []
    # keyframes after one step's samples, after three steps' samples, and after none
    for t, n_samples, with_frame in [(0.1, 2, True), (0.2, 1, False), (0.3, 3, False),
                                     (0.4, 1, True), (0.5, 0, True)]:
        rows = np.full((n_samples, 12), np.nan)
        rows[:, :3] = np.column_stack([rng.uniform(0.05, 0.1, n_samples),
                                       rng.normal(0, 0.01, n_samples), rng.normal(0, 0.05, n_samples)])
        chunks.append(rows)
        frame = (RangeBearingFrame(t, (RangeBearingObservation(4.0, 0.3, 7),)) if with_frame else None)
        k_before = be._k
        be.step(t, rows, frame)
        if be._k > k_before:
            u = np.concatenate(chunks)
            delta, cov = motion.relative(u, cfg.isam2.odometry_floor_var)
            factor = next(f for f in (be.graph.at(i) for i in range(be.graph.size()))
                          if isinstance(f, gtsam.BetweenFactorPose2)
                          and list(f.keys()) == [X(be._k - 1), X(be._k)])
            assert isinstance(factor, gtsam.BetweenFactorPose2)
            # through GTSAM's square-root information: equal to rounding
            np.testing.assert_allclose(factor.noiseModel().covariance(), cov, rtol=1e-12, atol=0)
            np.testing.assert_array_equal(pose_array(factor.measured()), pose_array(gtsam.Pose2(*delta)))
            chunks = []


def test_reuse_far_keeps_a_recent_far_exact_distance_only() -> None:
    """``isam2.far_lamp_recheck``: which lamp pairs skip the joint marginal."""
    base = SlamConfig()
    cfg = dataclasses.replace(base, isam2=dataclasses.replace(base.isam2, far_lamp_recheck=5))
    far = 2.0 * cfg.association.new_threshold(3)
    lamp = Obs(LandmarkKind.LAMP, np.zeros(3), np.eye(3), has_axis=True)
    corner = Obs(LandmarkKind.CORNER, np.zeros(2), np.eye(2))
    records = {(1, 3): (10, far + 1.0),   # recent and far: reused
               (2, 3): (4, far + 1.0),    # far but 6 keyframes old: asked again
               (3, 3): (10, far - 1.0),   # recent but not far enough
               (4, 2): (10, far + 50.0)}  # recorded for a 2-row sight, not this 3-row one
    w = SimpleNamespace(config=cfg, _far=records, _k=10, n_far_reused=0)
    screened = {0: {1: (3.0, False), 2: (3.0, False), 3: (3.0, False), 4: (3.0, False),
                    5: (1.0, True)},
                1: {1: (3.0, False)}}
    out = Gating._reuse_far(w, [lamp, corner], screened)  # type: ignore[arg-type]
    assert out[0] == {1: (far + 1.0, True), 2: (3.0, False), 3: (3.0, False), 4: (3.0, False),
                      5: (1.0, True)}
    assert out[1] == {1: (3.0, False)}  # corners: never
    assert w.n_far_reused == 1
    w.config = dataclasses.replace(base, isam2=dataclasses.replace(base.isam2, far_lamp_recheck=0))  # 0: always exact
    assert Gating._reuse_far(w, [lamp], {0: {1: (3.0, False)}}) == {0: {1: (3.0, False)}}  # type: ignore[arg-type]


def _mark_ambiguous_copying(cfg, obs, screened):  # type: ignore[no-untyped-def]
    """Reference: the rule rebuilt as a new dict for every observation (the plain way)."""
    out = {}
    for i, pairs in screened.items():
        o = obs[i]
        gate = cfg.gate(len(o.z))
        inside = [lid for lid, (d2, _) in pairs.items() if d2 < gate]
        if o.kind == "corner" or len(inside) <= 1:
            out[i] = {lid: (d2, len(o.z) == 2) for lid, (d2, _) in pairs.items()}
        else:
            out[i] = {lid: (d2, False) for lid, (d2, _) in pairs.items()}
    return out


def test_mark_ambiguous_in_place_matches_the_copying_rule() -> None:
    """Corners, lamps with and without an axis, 0-4 landmarks inside the gate."""
    rng = np.random.default_rng(8)
    cfg = SlamConfig().association
    obs, screened = [], {}
    for i in range(200):
        kind = "corner" if i % 3 == 0 else "lamp"
        dim = 3 if kind == "lamp" and i % 2 else 2
        obs.append(Obs(kind, np.zeros(dim), np.eye(dim), None))
        gate = cfg.gate(dim)
        n = int(rng.integers(0, 5))
        screened[i] = {int(lid): (float(rng.uniform(0.0, 2.0 * gate)), dim == 2)
                       for lid in rng.choice(50, size=n, replace=False)}
    ref = _mark_ambiguous_copying(cfg, obs, {i: dict(p) for i, p in screened.items()})
    assert sum(any(not e for _, e in p.values()) and len(p) > 1 for p in ref.values()) > 10
    w = SimpleNamespace(config=SlamConfig())
    assert Gating._mark_ambiguous(w, obs, screened) == ref  # type: ignore[arg-type]


def test_frames_between_keyframes_are_not_turned_into_observations(monkeypatch) -> None:  # type: ignore[no-untyped-def]
    """Only a frame that becomes a keyframe pays for its observations (same result)."""
    import lampsam.backend.keyframes as keyframes_module

    rig, odo, frames, gt = ceiling_world(np.random.default_rng(12), duration=6.0, n_corners=8)
    model = CeilingModel.from_camera(rig.camera)
    calls = []
    build = keyframes_module.observations_from_frame

    def counted(*a, **k):  # type: ignore[no-untyped-def]
        calls.append(1)
        return build(*a, **k)

    monkeypatch.setattr(keyframes_module, "observations_from_frame", counted)
    be = Isam2Slam(rig.odometry, SlamConfig(), gt.poses[0], model, CeilingHandler(model))
    result = drive(be, iter_steps(odo, frames))
    n_frames = sum(f is not None for f in frames)
    assert result.status == "ok"
    assert int(result.keyframes.sum()) == len(calls) < n_frames
