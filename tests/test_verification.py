"""Ceiling verification: R_loc (paper 2, eq. 10), the sequential test, kidnapping."""

from __future__ import annotations

import numpy as np
import pytest

from lampsam.factors.ceiling import project_point
from lampsam.frontend.measurements import CeilingFrame, CornerObservation
from lampsam.localization.verification import (
    CeilingChecker,
    RlocVerifier,
    SequentialVerifier,
    Verdict,
    VerificationConfig,
    VerificationError,
    frame_match,
    observed_points,
)

CAM = np.array([0.1, 0.0, 0.3])  # ceiling camera offset and height (m)
FOV = 0.6  # |m| visible in the image (about 62 deg half-angle)


def _ceiling(rng: np.random.Generator) -> np.ndarray:
    """A 10 m x 10 m ceiling at 2.8 m: 30 irregular lamps and 40 corners."""
    lamps = np.column_stack([rng.uniform(0, 10, 30), rng.uniform(0, 10, 30), np.full(30, 2.8)])
    corners = np.column_stack([rng.uniform(0, 10, 40), rng.uniform(0, 10, 40), np.full(40, 2.8)])
    return np.vstack([lamps, corners])


def _observe(rng: np.random.Generator, landmarks: np.ndarray, pose: np.ndarray) -> np.ndarray:
    ms = [project_point(pose, p, CAM)[0] for p in landmarks]
    m = np.array(ms)
    m = m[np.hypot(m[:, 0], m[:, 1]) < FOV]
    return m + rng.normal(0, 0.01, m.shape)


def _drive(
    rng: np.random.Generator, n: int, start: np.ndarray, speed: float = 0.3, dt: float = 0.1
) -> np.ndarray:
    """Poses of a gentle arc at ``speed`` m/s sampled at 1/dt Hz."""
    poses = [start]
    for _ in range(n - 1):
        x, y, th = poses[-1]
        poses.append(
            np.array([x + speed * dt * np.cos(th), y + speed * dt * np.sin(th), th + 0.01])
        )
    return np.array(poses)


def _run(
    verifier: RlocVerifier | SequentialVerifier,
    checker: CeilingChecker,
    truth: np.ndarray,
    estimate: np.ndarray,
    landmarks: np.ndarray,
    rng: np.random.Generator,
) -> list[Verdict]:
    verdicts = []
    for k in range(len(truth)):
        ds = 0.0 if k == 0 else float(np.hypot(*(truth[k, :2] - truth[k - 1, :2])))
        obs = _observe(rng, landmarks, truth[k])
        verdicts.append(verifier.update(ds, checker.outcome(estimate[k], obs)))
    return verdicts


@pytest.fixture
def world(rng: np.random.Generator) -> tuple[np.ndarray, CeilingChecker]:
    lm = _ceiling(rng)
    return lm, CeilingChecker(lm, CAM, VerificationConfig())


def test_correct_pose_gives_r_loc_near_one(rng: np.random.Generator, world) -> None:
    lm, checker = world
    truth = _drive(rng, 80, np.array([2.0, 3.0, 0.2]))  # 2.4 m
    est = truth + np.array([0.05, -0.05, np.deg2rad(3.0)])  # within the paper's error
    v = RlocVerifier(VerificationConfig())
    verdicts = _run(v, checker, truth, est, lm, rng)
    assert verdicts[-1] is Verdict.ACCEPTED
    assert v.r_loc > 0.9


def test_wrong_pose_gives_r_loc_below_threshold(rng: np.random.Generator, world) -> None:
    lm, checker = world
    truth = _drive(rng, 80, np.array([2.0, 3.0, 0.2]))
    est = truth + np.array([0.8, -0.6, 0.4])
    v = RlocVerifier(VerificationConfig())
    verdicts = _run(v, checker, truth, est, lm, rng)
    assert verdicts[-1] is Verdict.FAILED
    assert v.r_loc < 0.25
    assert Verdict.ACCEPTED not in verdicts


def test_sequential_decides_fast_both_ways(rng: np.random.Generator, world) -> None:
    lm, checker = world
    truth = _drive(rng, 80, np.array([2.0, 3.0, 0.2]))
    good = SequentialVerifier(VerificationConfig())
    _run(good, checker, truth, truth + np.array([0.05, 0.05, 0.03]), lm, rng)
    assert good.verdict is Verdict.ACCEPTED
    assert good.d_decided is not None and good.d_decided < 0.6  # < 2 s at 0.3 m/s
    bad = SequentialVerifier(VerificationConfig())
    _run(bad, checker, truth, truth + np.array([0.8, -0.6, 0.4]), lm, rng)
    assert bad.verdict is Verdict.FAILED
    assert bad.d_decided is not None and bad.d_decided < 0.6


@pytest.mark.parametrize("kind", ["rloc", "sequential"])
def test_kidnapped_robot_is_detected(rng: np.random.Generator, world, kind: str) -> None:
    lm, checker = world
    before = _drive(rng, 80, np.array([2.0, 3.0, 0.2]))
    # kidnapped: the robot is carried to another place; the estimate keeps
    # dead-reckoning from where it was (same odometry increments)
    after = _drive(rng, 80, np.array([7.0, 6.0, -2.0]))
    est_after = _drive(rng, 80, before[-1])
    truth = np.vstack([before, after])
    est = np.vstack([before, est_after])
    cfg = VerificationConfig()
    v = RlocVerifier(cfg) if kind == "rloc" else SequentialVerifier(cfg)
    verdicts = []
    for k in range(len(truth)):
        ds = 0.0 if k in (0, 80) else 0.03
        obs = _observe(rng, lm, truth[k])
        verdicts.append(v.update(ds, checker.outcome(est[k], obs)))
    assert verdicts[79] is Verdict.ACCEPTED  # converged and accepted before the jump
    assert verdicts[-1] is Verdict.FAILED
    first_fail = verdicts.index(Verdict.FAILED)
    assert first_fail >= 80
    d_after = 0.03 * (first_fail - 80)
    # paper verifier: the 2 m window must be < 25 % good -> about 1.5 m;
    # sequential: a few tenths of a metre
    assert d_after < (1.8 if kind == "rloc" else 0.6)


def test_frame_match_and_observed_points() -> None:
    pred = np.array([[0.0, 0.0], [0.3, 0.1]])
    assert frame_match(np.array([[0.02, 0.0], [0.5, 0.5]]), pred, 0.1) == (1, 2)
    assert frame_match(np.zeros((0, 2)), pred, 0.1) == (0, 0)
    corner = CornerObservation(
        m=np.array([0.1, 0.2]),
        cov_m=np.eye(2) * 1e-4,
        pixel=np.zeros(2),
        patch=np.zeros((5, 5), np.float32),
        score=1.0,
        landmark_id=None,
    )
    np.testing.assert_allclose(observed_points(CeilingFrame(0.0, 0, (), (corner,))), [[0.1, 0.2]])
    with pytest.raises(VerificationError):
        RlocVerifier(VerificationConfig()).update(-1.0, True)


def test_lamps_decide_on_a_periodic_corner_lattice() -> None:
    # 0.6 m tiles: a pose off by one tile matches every corner, but not the lamp
    gx, gy = np.meshgrid(np.arange(0, 6.01, 0.6), np.arange(0, 6.01, 0.6))
    corners = np.column_stack([gx.ravel(), gy.ravel(), np.full(gx.size, 2.7)])
    lamps = np.array([[2.1, 2.9, 2.7], [4.5, 1.2, 2.7]])
    lm = np.vstack([lamps, corners])
    kinds = np.arange(len(lm)) < 2
    truth = np.array([2.0, 2.5, 0.0])
    m = np.array([project_point(truth, p, CAM)[0] for p in lm])
    vis = np.hypot(m[:, 0], m[:, 1]) < FOV
    obs, obs_kind = m[vis], kinds[vis]
    assert obs_kind.any()
    wrong = truth + np.array([0.6, 0.0, 0.0])
    typed = CeilingChecker(lm, CAM, VerificationConfig(), is_lamp=kinds)
    untyped = CeilingChecker(lm, CAM, VerificationConfig())
    assert typed.outcome(truth, obs, obs_kind) is True
    assert untyped.outcome(wrong, obs) is True  # fooled by the lattice
    assert typed.outcome(wrong, obs, obs_kind) is False


def test_lamp_axes_reject_a_pose_turned_by_90_degrees() -> None:
    # strip lamps on a 2 m square lattice, long axes along world x
    gx, gy = np.meshgrid(np.arange(1.0, 9.1, 2.0), np.arange(1.0, 9.1, 2.0))
    lamps = np.column_stack([gx.ravel(), gy.ravel(), np.full(gx.size, 2.7)])
    phi = np.zeros(len(lamps))
    truth = np.array([5.0 - CAM[0], 5.0, 0.3])  # camera above the lattice point (5, 5)
    m = np.array([project_point(truth, p, CAM)[0] for p in lamps])
    vis = np.hypot(m[:, 0], m[:, 1]) < FOV
    obs = m[vis]
    obs_axis = np.full(len(obs), -0.3)  # the image axis: wrap_axis(phi - theta)
    # turned by 90 deg about the camera centre: same lamp positions in the image
    c = np.array([5.0, 5.0])
    th = truth[2] + np.pi / 2
    turned = np.array([*(c - CAM[0] * np.array([np.cos(th), np.sin(th)])), th])
    no_axes = CeilingChecker(lamps, CAM, VerificationConfig(), is_lamp=np.ones(len(lamps), bool))
    axes = CeilingChecker(
        lamps, CAM, VerificationConfig(), is_lamp=np.ones(len(lamps), bool), phi=phi
    )
    kinds = np.ones(len(obs), bool)
    assert no_axes.outcome(turned, obs, kinds) is True  # the lattice fools positions alone
    assert axes.outcome(truth, obs, kinds, obs_axis) is True
    assert axes.outcome(turned, obs, kinds, obs_axis) is False


def test_missing_lamps_fail_when_the_view_is_known(rng: np.random.Generator) -> None:
    lm = _ceiling(rng)
    kinds = np.arange(len(lm)) < 30  # _ceiling: 30 lamps, then corners

    def in_view(m: np.ndarray) -> np.ndarray:
        return np.hypot(m[:, 0], m[:, 1]) < FOV - 0.05

    pose = np.array([5.0, 5.0, 0.0])
    m = np.array([project_point(pose, p, CAM)[0] for p in lm])
    vis = np.hypot(m[:, 0], m[:, 1]) < FOV
    assert (vis & kinds).any()
    corners_only = m[vis & ~kinds]
    chk = CeilingChecker(lm, CAM, VerificationConfig(), is_lamp=kinds, in_view=in_view)
    assert chk.outcome(pose, m[vis], kinds[vis]) is True
    # the lamps overhead were not seen: the corners alone must not accept the pose
    assert chk.outcome(pose, corners_only, np.zeros(len(corners_only), bool)) is False
    assert chk.outcome(pose, np.zeros((0, 2))) is False
    blind = CeilingChecker(lm, CAM, VerificationConfig(), is_lamp=kinds)
    assert blind.outcome(pose, corners_only, np.zeros(len(corners_only), bool)) is True


def _twin_ceiling() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A small periodic ceiling with a twin, like the office: 0.6 m tiles, strip lamps on 3 m.

    Lamp positions and tile corners are symmetric under a quarter turn about
    (4.5, 4.5); the lamps' long axes (two of them across) only partly so.
    """
    gx, gy = np.meshgrid(np.arange(0.3, 8.71, 0.6), np.arange(0.3, 8.71, 0.6))
    corners = np.column_stack([gx.ravel(), gy.ravel(), np.full(gx.size, 2.7)])
    lx, ly = np.meshgrid([1.5, 4.5, 7.5], [1.5, 4.5, 7.5])
    lamps = np.column_stack([lx.ravel(), ly.ravel(), np.full(lx.size, 2.7)])
    phi = np.zeros(len(lamps))
    phi[[2, 5]] = np.pi / 2  # (7.5, 1.5) and (7.5, 4.5) across
    lm = np.vstack([lamps, corners])
    kinds = np.arange(len(lm)) < len(lamps)
    return lm, kinds, np.concatenate([phi, np.full(len(corners), np.nan)])


def test_self_similarity_flags_a_tile_lattice_not_sparse_lamps() -> None:
    lm, kinds, _ = _twin_ceiling()
    gate = 0.1 * (2.7 - CAM[2])
    from lampsam.localization.verification import self_similarity

    assert self_similarity(lm[~kinds, :2], gate, 1.0, 0.3) > 0.85  # lattice: its own twin
    assert self_similarity(lm[kinds, :2], gate, 1.0, 0.3) == 0.0  # lamps 3 m apart
    rng = np.random.default_rng(5)
    assert self_similarity(rng.uniform(0, 9, (60, 2)), gate, 1.0, 0.3) < 0.3


def test_twin_pose_on_a_periodic_ceiling_is_rejected() -> None:
    # the robot between lamps (1.5, 1.5), (4.5, 1.5), (1.5, 4.5), (4.5, 4.5); its
    # twin (quarter turn about the ceiling centre, office trial 12) sees the
    # turned lamps: the corner lattice matches everywhere, two of four lamps
    # match with their axes, the others are across
    lm, kinds, phi = _twin_ceiling()
    truth = np.array([2.7, 2.6, 0.4])
    c = np.array([4.5, 4.5])
    d = truth[:2] - c
    twin = np.array([c[0] - d[1], c[1] + d[0], truth[2] + np.pi / 2])
    fov = 1.2  # a wide-angle ceiling camera (|m| < 1.2 is about 50 deg half-angle)
    rng = np.random.default_rng(12)
    m = np.array([project_point(truth, p, CAM)[0] for p in lm])
    vis = np.hypot(m[:, 0], m[:, 1]) < fov
    obs = m[vis] + rng.normal(0, 0.005, (int(vis.sum()), 2))
    obs_kind = kinds[vis]
    obs_axis = np.where(obs_kind, np.mod(phi[vis] - truth[2], np.pi), np.nan)
    assert obs_kind.sum() >= 3 and (~obs_kind).sum() > 20
    cfg = VerificationConfig()
    # the checker before this fix: lamps at 0.5, corners vote
    old = CeilingChecker(
        lm, CAM, VerificationConfig(lamp_match_fraction=0.5, max_self_similarity=1.0),
        is_lamp=kinds, phi=phi,
    )  # fmt: skip
    new = CeilingChecker(lm, CAM, cfg, is_lamp=kinds, phi=phi)
    assert new.votes == {True: True, False: False}
    n_ok, n = frame_match(
        obs[obs_kind],
        np.array([project_point(twin, p, CAM)[0] for p in lm[kinds]]),
        cfg.gate,
        obs_axis[obs_kind],
        np.mod(phi[kinds] - twin[2], np.pi),
        cfg.axis_gate,
    )
    assert 0.5 <= n_ok / n < 1.0  # the twin: some, not all, lamps match
    assert old.outcome(twin, obs, obs_kind, obs_axis) is True  # the bug: twin accepted
    assert new.outcome(twin, obs, obs_kind, obs_axis) is False
    assert new.outcome(truth, obs, obs_kind, obs_axis) is True
    # corners alone cannot discriminate: no evidence either way
    only = ~obs_kind
    assert new.outcome(twin, obs[only], obs_kind[only]) is None
    # a whole drive at the twin fails both verifiers
    for v in (RlocVerifier(cfg), SequentialVerifier(cfg)):
        verdict = Verdict.PENDING
        for _ in range(80):
            verdict = v.update(0.03, new.outcome(twin, obs, obs_kind, obs_axis))
        assert verdict is Verdict.FAILED


def test_rigid_fit_2d_recovers_a_known_transform() -> None:
    from lampsam.factors.geometry import rigid_fit_2d

    rng = np.random.default_rng(21)
    src = rng.uniform(-2, 2, (20, 2))
    th, t = 0.7, np.array([1.5, -0.4])
    R = np.array([[np.cos(th), -np.sin(th)], [np.sin(th), np.cos(th)]])
    np.testing.assert_allclose(rigid_fit_2d(src, src @ R.T + t), [*t, th], atol=1e-9)


def test_refine_pose_corrects_a_biased_pose_on_a_tiled_ceiling() -> None:
    from lampsam.localization.verification import refine_pose

    rng = np.random.default_rng(33)
    lm, kinds, _ = _twin_ceiling()
    truth = np.array([3.3, 3.1, 0.7])
    m = np.array([project_point(truth, p, CAM)[0] for p in lm])
    vis = np.hypot(m[:, 0], m[:, 1]) < 1.2
    obs = m[vis] + rng.normal(0, 0.005, (int(vis.sum()), 2))
    # a scan-fitted pose off by 0.2 m and 7 deg (the office's changed furniture)
    start = truth + np.array([0.2, -0.15, np.deg2rad(7.0)])
    fixed, n_lamps = refine_pose(start, obs, kinds[vis], lm, kinds, CAM)
    assert n_lamps >= 2
    assert np.hypot(*(fixed[:2] - truth[:2])) < 0.02  # m
    assert abs(fixed[2] - truth[2]) < np.deg2rad(0.5)
    # corners alone (no lamp) cannot be trusted on a lattice: pose unchanged
    only = ~kinds[vis]
    same, n0 = refine_pose(start, obs[only], kinds[vis][only], lm, kinds, CAM)
    assert n0 == 0
    np.testing.assert_array_equal(same, start)


def test_rloc_early_decision_gives_the_full_drive_verdict() -> None:
    """Deciding as soon as the 2 m verdict is certain changes only when, never what."""
    rng = np.random.default_rng(31)
    late = VerificationConfig(early_decision=False)
    early = VerificationConfig()
    decided_at = []
    for p_match in (0.05, 0.2, 0.3, 0.5, 0.9):
        for _ in range(40):
            outcomes = [None if rng.uniform() < 0.1 else bool(rng.uniform() < p_match)
                        for _ in range(120)]  # fmt: skip
            full, quick = RlocVerifier(late), RlocVerifier(early)
            v_full = v_quick = Verdict.PENDING
            d = 0.0
            for o in outcomes:
                if v_full is Verdict.PENDING:
                    v_full = full.update(0.03, o)
                if v_quick is Verdict.PENDING:
                    v_quick = quick.update(0.03, o)
                    d += 0.03
            assert v_quick is v_full
            if v_full is not Verdict.PENDING:
                decided_at.append(d)
    # all-match drives accept after 0.5 m of matches (0.25 x 2 m), all-fail ones fail after 1.5 m
    assert min(decided_at) == pytest.approx(0.51, abs=0.031)
    assert max(decided_at) < 3.6
