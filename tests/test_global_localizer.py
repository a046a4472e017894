"""Global localizer end to end on a small synthetic world (grid + features + ceiling)."""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import pytest

from lampsam.datasets.steerable_robot import SimulatedRobot
from lampsam.factors.ceiling import project_point
from lampsam.factors.geometry import compose, wrap_angle
from lampsam.localization.filter_config import FilterConfig, GlobalLocalizerConfig, Mode
from lampsam.localization.grid import OccupancyGrid, occupied_mask
from lampsam.localization.localizer import localize
from lampsam.localization.map_layers import EnvironmentMaps
from lampsam.localization.raycast import cast_rays
from lampsam.localization.result import write_result

RES = 0.05
CAM = np.array([0.1, 0.0, 0.3])
KINECT_FOV = np.deg2rad(57.0)
KINECT_RANGE = 4.5


def _grid(
    boxes: Sequence[tuple[float, float, float, float]], w: float = 8.0, h: float = 6.0
) -> OccupancyGrid:
    """A walled room with rectangular obstacles (x0, y0, x1, y1), log-odds +-4."""
    g = OccupancyGrid.empty(0.0, 0.0, w, h, RES)
    lo = np.full((g.height, g.width), -4.0)
    lo[:2, :] = lo[-2:, :] = 4.0
    lo[:, :2] = lo[:, -2:] = 4.0
    for x0, y0, x1, y1 in boxes:
        lo[int(y0 / RES) : int(y1 / RES), int(x0 / RES) : int(x1 / RES)] = 4.0
    g.log_odds = lo
    return g


MAP_BOXES = [(1.0, 1.0, 2.0, 1.6), (5.0, 3.5, 5.6, 5.0), (3.0, 4.6, 3.4, 6.0), (6.5, 0.0, 8.0, 1.2)]
# the environment changed after mapping: one box moved, a new one appeared
NOW_BOXES = [
    (1.0, 1.0, 2.0, 1.6),
    (5.0, 3.8, 5.6, 5.0),
    (3.0, 4.6, 3.4, 6.0),
    (6.5, 0.0, 8.0, 1.2),
    (2.5, 2.6, 2.8, 2.9),
]


class SyntheticWorld:
    """Map layers and a simulated robot (Kinect by ray casting, ceiling by projection).

    The robot is the library's :class:`SimulatedRobot` with sensors of this world.
    """

    def __init__(self, rng: np.random.Generator, start: np.ndarray) -> None:
        self.map_grid = _grid(MAP_BOXES)
        self.now_grid = _grid(NOW_BOXES)
        occ = occupied_mask(self.map_grid)
        iy, ix = np.nonzero(occ)
        pick = rng.choice(len(ix), 1500, replace=False)
        xy = np.column_stack([(ix[pick] + 0.5) * RES, (iy[pick] + 0.5) * RES])
        self.spatial_xyz = np.column_stack([xy, rng.uniform(0.2, 1.6, len(xy))])
        self.spatial_desc = rng.uniform(0, 1, (len(xy), 128)).astype(np.float32)
        self.ceiling = np.column_stack(
            [rng.uniform(0, 8, 60), rng.uniform(0, 6, 60), np.full(60, 2.8)]
        )
        self.robot = SimulatedRobot(
            self._kinect, self._ceiling_obs, self._free_ahead, start, rng,
            speed=0.3, blocked_within=0.8, avoid_rate=1.0,
        )  # fmt: skip

    @property
    def pose(self) -> np.ndarray:
        return self.robot.pose

    def maps(self) -> EnvironmentMaps:
        return EnvironmentMaps(
            self.map_grid, self.spatial_xyz, self.spatial_desc, self.ceiling, CAM
        )

    def _free_ahead(self, pose: np.ndarray) -> float:
        return float(cast_rays(self.now_grid, pose[None], np.array([0.0]), 3.0)[0, 0])

    def _kinect(
        self, pose: np.ndarray, rng: np.random.Generator
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        angles = np.linspace(-KINECT_FOV / 2, KINECT_FOV / 2, 58)
        r = cast_rays(self.now_grid, pose[None], angles, KINECT_RANGE)[0]
        ok = r < KINECT_RANGE - 1e-6
        r = r[ok] + rng.normal(0, 0.01, ok.sum())
        depth = np.column_stack(
            [r * np.cos(angles[ok]), r * np.sin(angles[ok]), np.full(ok.sum(), 0.5)]
        )
        c, s = np.cos(pose[2]), np.sin(pose[2])
        d = self.spatial_xyz[:, :2] - pose[:2]
        bx, by = c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1]
        bearing = np.arctan2(by, bx)
        dist = np.hypot(bx, by)
        vis = (bx > 0.3) & (np.abs(bearing) < KINECT_FOV / 2) & (dist < KINECT_RANGE)
        idx = np.nonzero(vis)[0]
        if len(idx):  # line of sight in the current world
            rr = cast_rays(self.now_grid, pose[None], bearing[idx], KINECT_RANGE)[0]
            idx = idx[rr > dist[idx] - 0.15]
        pts = np.column_stack([bx[idx], by[idx], self.spatial_xyz[idx, 2]]) + rng.normal(
            0, 0.01, (len(idx), 3)
        )
        desc = self.spatial_desc[idx] + rng.normal(0, 0.02, (len(idx), 128)).astype(np.float32)
        return pts, desc, depth

    def _ceiling_obs(
        self, pose: np.ndarray, rng: np.random.Generator
    ) -> tuple[np.ndarray, None, None]:
        m = np.array([project_point(pose, p, CAM)[0] for p in self.ceiling])
        m = m[np.hypot(m[:, 0], m[:, 1]) < 0.6]
        return m + rng.normal(0, 0.01, m.shape), None, None

    def kidnap(self, pose: np.ndarray) -> None:
        self.robot.pose = np.asarray(pose, dtype=float)


def _error(pose: np.ndarray, truth: np.ndarray) -> tuple[float, float]:
    return float(np.hypot(*(pose[:2] - truth[:2]))), float(abs(wrap_angle(pose[2] - truth[2])))


@pytest.mark.parametrize("mode", [Mode.PROPOSED, Mode.OURS])
def test_end_to_end_small_world(rng: np.random.Generator, mode: Mode, tmp_path: Path) -> None:
    world = SyntheticWorld(rng, np.array([3.7, 2.2, 0.9]))
    cfg = GlobalLocalizerConfig(mode=mode)
    res = localize(world.robot, world.maps(), cfg, np.random.default_rng(11))
    e_xy, e_th = _error(res.pose, world.pose)
    assert res.success
    assert e_xy < 0.15 and e_th < np.deg2rad(5.0)
    assert res.restarts == 0
    # one full turn, plus at most half a turn towards open space (the start faces a box)
    assert 12.0 - 0.5 <= res.robot_time["turn"] <= 18.0 + 0.5
    data = json.loads(write_result(res, tmp_path).read_text())
    assert data["success"] and len(data["covariance"]) == 3


def test_kidnapped_after_convergence_is_detected_and_recovered(rng: np.random.Generator) -> None:
    world = SyntheticWorld(rng, np.array([3.7, 2.2, 0.9]))
    cfg = GlobalLocalizerConfig(mode=Mode.OURS)
    res = localize(world.robot, world.maps(), cfg, np.random.default_rng(11))
    assert res.success
    world.kidnap(np.array([6.0, 2.5, 2.5]))
    res2 = localize(world.robot, world.maps(), cfg, np.random.default_rng(12), initial=res)
    assert res2.attempts[0].verdict == "failed"  # the kidnapping is detected
    assert res2.success and res2.restarts >= 1  # and the robot is found again
    e_xy, e_th = _error(res2.pose, world.pose)
    assert e_xy < 0.15 and e_th < np.deg2rad(5.0)


def test_modes_without_verification_do_not_drive(rng: np.random.Generator) -> None:
    world = SyntheticWorld(rng, np.array([3.7, 2.2, 0.9]))
    cfg = GlobalLocalizerConfig(mode=Mode.GRID_ONLY, filter=FilterConfig(n_uniform=4000))
    res = localize(world.robot, world.maps(), cfg, np.random.default_rng(3))
    assert res.robot_time["verification"] == 0.0 and res.restarts == 0
    assert res.attempts[0].n_candidates == 0  # grid map only: no spatial features used
    assert res.compute_time["filter"] > 0.0
    assert np.allclose(res.covariance, res.covariance.T)


def test_cli_localize_reports_a_missing_map(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from lampsam.cli import main

    rc = main(
        ["localize", str(tmp_path), "--map", str(tmp_path / "nomap"), "--out", str(tmp_path / "o")]
    )
    assert rc == 2
    err = capsys.readouterr().err
    assert "nomap" in err and "not found" in err


def test_distinct_modes_keeps_the_heaviest_separated_poses() -> None:
    from lampsam.localization.stages import distinct_modes

    rng = np.random.default_rng(3)
    centres = np.array([[1.0, 1.0, 0.0], [1.0, 1.0, np.pi], [4.0, 2.0, 1.0]])
    parts = np.vstack([c + rng.normal(0, [0.05, 0.05, 0.02], (50, 3)) for c in centres])
    logw = np.concatenate([np.full(50, -1.0), np.full(50, -2.0), np.full(50, -3.0)])
    logw = logw + rng.normal(0, 0.01, 150)
    modes = distinct_modes(parts, logw, 5, (0.5, 0.5))
    assert len(modes) == 3  # same place, turned by pi, is a separate mode
    np.testing.assert_allclose(modes[:, :2], centres[:, :2], atol=0.2)
    assert abs(np.cos(modes[1, 2] - np.pi) - 1.0) < 0.01
    assert len(distinct_modes(parts, logw, 2, (0.5, 0.5))) == 2


def test_joint_scan_model_scores_kept_scans_at_the_earlier_pose() -> None:
    """A kept scan is scored at x composed with the odometry back to its turn."""
    from lampsam.factors.geometry import between
    from lampsam.localization.likelihood import BeamModelConfig, RayCastModel
    from lampsam.localization.stages import JointScanModel, KeptScan

    grid = _grid(MAP_BOXES)
    model = RayCastModel(grid, BeamModelConfig(sigma_hit=0.1, max_range=4.5), method="march")
    angles = np.deg2rad(np.arange(0.0, 360.0, 4.0))
    then_true = np.array([2.0, 3.0, 0.4])
    now_true = np.array([4.5, 2.2, -1.0])
    r_then = cast_rays(grid, then_true[None], angles, 4.5)[0]
    r_now = cast_rays(grid, now_true[None], angles, 4.5)[0]
    # odometry with an arbitrary origin: only the relative motion matters
    odom_then = np.array([10.0, -3.0, 2.0])
    odom_now = compose(odom_then, between(then_true, now_true))
    joint = JointScanModel(model, [KeptScan(r_then, angles, odom_then)], odom_now)
    back = between(odom_now, odom_then)
    np.testing.assert_allclose(compose(now_true, back), then_true, atol=1e-9)
    poses = np.array([now_true, now_true + [0.5, 0.0, 0.0], now_true + [0.0, 0.0, 0.3]])
    earlier = np.array([compose(p, back) for p in poses])
    expected = model.log_likelihood(poses, r_now, angles) + model.log_likelihood(
        earlier, r_then, angles
    )
    got = joint.log_likelihood(poses, r_now, angles)
    np.testing.assert_allclose(got, expected, rtol=1e-9, atol=1e-6)
    assert np.argmax(got) == 0  # the true pose explains both scans best
    # the kept scan widens the margin between the truth and a shifted pose
    assert got[0] - got[1] > model.log_likelihood(poses[:2], r_now, angles) @ [1, -1]


def _scan_like_kinect(grid: OccupancyGrid, pose: np.ndarray) -> np.ndarray:
    """(360,) virtual scan: ray-cast ranges, NaN beyond 4.5 m and nearer than 0.5 m."""
    from lampsam.localization.virtual_scan import beam_angles

    r = cast_rays(grid, pose[None], beam_angles(), 6.0)[0]
    return np.where((r > 4.5) | (r < 0.5), np.nan, r)


@pytest.mark.parametrize(
    "pose",
    [
        np.array([0.45, 3.0, np.pi]),  # facing the west wall, 0.35 m off it
        np.array([0.45, 3.0, 2.0]),  # along it, too close to pass
        np.array([7.4, 5.4, 0.8]),  # in the north-east corner
        np.array([4.2, 2.6, -1.2]),  # towards the box at the south wall
    ],
)
def test_open_heading_turns_to_a_free_corridor(pose: np.ndarray) -> None:
    """Blocked ahead: the chosen heading has the needed free distance (true ray casting)."""
    from lampsam.localization.open_space import open_heading

    grid = _grid(MAP_BOXES)
    need = 2.7
    angle = open_heading(_scan_like_kinect(grid, pose), need)
    assert abs(angle) > np.deg2rad(10.0)
    corridor = pose[2] + angle + np.deg2rad(np.arange(-12.0, 13.0, 3.0))
    free = cast_rays(grid, np.repeat(pose[None], len(corridor), 0) * [1, 1, 0], corridor, 6.0)[0]
    assert free.min() >= need - 0.05


def test_open_heading_keeps_a_free_heading_and_handles_an_empty_scan() -> None:
    from lampsam.localization.open_space import open_heading

    grid = _grid(MAP_BOXES)
    pose = np.array([2.5, 3.0, 0.0])  # the box 15 deg to the left is 2.6 m away
    assert open_heading(_scan_like_kinect(grid, pose), 2.4) == 0.0
    assert open_heading(np.full(360, np.nan), 2.7) == 0.0


def test_half_turn_centre_finds_the_symmetry_of_a_lamp_layout() -> None:
    from lampsam.localization.symmetry import half_turn_centre, half_turn_twin

    rng = np.random.default_rng(5)
    half = rng.uniform(0.0, 4.0, (5, 2))
    centre = np.array([4.2, 3.1])
    xy = np.vstack([half, 2.0 * centre - half, centre[None]])  # symmetric pairs + one at the centre
    phi = np.concatenate([rng.uniform(0, np.pi, 5)] * 2 + [[np.nan]])
    noisy = xy + rng.normal(0, 0.02, xy.shape)
    got = half_turn_centre(noisy, phi)
    assert got is not None
    np.testing.assert_allclose(got, centre, atol=0.03)
    # a half turn keeps a lamp's axis mod pi: axes turned by 90 deg break the symmetry
    assert half_turn_centre(xy, np.concatenate([phi[:5], phi[5:10] + np.pi / 2, [np.nan]])) is None
    assert half_turn_centre(np.vstack([xy, [[0.3, 0.2]]])) is None  # an unmatched lamp
    assert half_turn_centre(xy[:1]) is None
    # the twin of a pose sees the ceiling from the mirrored place, turned by pi
    pose = np.array([1.0, 2.0, 0.3])
    twin = half_turn_twin(pose, centre)
    np.testing.assert_allclose(twin[:2], [7.4, 4.2], atol=1e-12)
    assert abs(wrap_angle(twin[2] - 0.3 - np.pi)) < 1e-12
    lamp = xy[0]
    body = lambda p, q: np.array(  # noqa: E731
        [np.cos(p[2]) * (q[0] - p[0]) + np.sin(p[2]) * (q[1] - p[1]),
         -np.sin(p[2]) * (q[0] - p[0]) + np.cos(p[2]) * (q[1] - p[1])]
    )  # fmt: skip
    np.testing.assert_allclose(body(pose, lamp), body(twin, xy[5]), atol=1e-9)


def test_resolve_half_turn_prefers_the_scan_side_and_flags_a_symmetric_room() -> None:
    from lampsam.localization.filter_config import OURS_TWIN_MARGIN
    from lampsam.localization.symmetry import half_turn_twin, resolve_half_turn
    from lampsam.localization.virtual_scan import beam_angles

    cfg = GlobalLocalizerConfig(mode=Mode.OURS, filter=FilterConfig(expected_ranges="march"))
    truth = np.array([2.3, 2.4, 0.6])
    centre = np.array([4.0, 3.0])  # of the 8 m x 6 m room
    for boxes, symmetric in ((MAP_BOXES, False), ([], True)):
        grid = _grid(boxes)
        r = cast_rays(grid, truth[None], beam_angles(), 4.5)[0]
        scan = np.where(r >= 4.5 - 1e-6, np.nan, r)
        maps = EnvironmentMaps(grid, np.zeros((0, 3)), np.zeros((0, 128)), np.zeros((0, 3)), CAM)
        twin = half_turn_twin(truth, centre)
        pose, margin = resolve_half_turn(twin, scan, centre, maps, cfg, np.random.default_rng(2))
        if symmetric:  # an empty rectangle looks the same from both: ambiguous
            assert margin < OURS_TWIN_MARGIN
        else:  # the boxes tell: the truth is chosen although the filter gave its twin
            e_xy, e_th = _error(pose, truth)
            assert e_xy < 0.1 and e_th < np.deg2rad(3.0)
            assert margin > 10.0 * OURS_TWIN_MARGIN
