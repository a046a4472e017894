"""Environment map: grid logic from depth, feature merging, build_map end to end, bad input."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from lampsam.cli import main
from lampsam.datasets.kinect_sim import (
    KinectConfig,
    KinectRenderer,
    simulate_kinect_run,
    world_T_camera,
)
from lampsam.datasets.logrun import Trajectory, read_tum, write_tum
from lampsam.datasets.rgbd import RgbdCamera
from lampsam.datasets.scene3d import scene_from_dict
from lampsam.evaluation.map_truth import floor_plan_of_run
from lampsam.localization.ceiling_map import CeilingFeatureMap, read_landmark_csv
from lampsam.localization.depth_grid import integrate_depth_frame, split_by_height
from lampsam.localization.grid import OccupancyGrid, free_mask, occupied_mask
from lampsam.localization.map_build import build_map
from lampsam.localization.map_config import DepthGridConfig, EnvMapConfig
from lampsam.localization.map_poses import planar_poses_at
from lampsam.localization.map_quality import FloorPlan, grid_precision_recall
from lampsam.localization.map_store import EnvMapError, load_env_map
from lampsam.localization.map_tables import TableConfig
from lampsam.localization.pointcloud import depth_to_points
from lampsam.localization.spatial_map import SpatialMapConfig, merge_duplicates

CFG = KinectConfig(width=160, height=120)
#: The office builds skip the range table (tests/test_laser_map.py tests it on a small map).
NO_TABLE = EnvMapConfig(tables=TableConfig(range_table=False))


def _camera(cfg: KinectConfig) -> RgbdCamera:
    return RgbdCamera(
        cfg.width,
        cfg.height,
        cfg.fx,
        cfg.fy,
        cfg.cx,
        cfg.cy,
        cfg.depth_scale,
        cfg.min_depth,
        cfg.max_depth,
        cfg.body_T_camera(),
    )


def test_grid_free_and_occupied_from_one_depth_frame() -> None:
    """A wall 2.95 m ahead: its face cells occupied, the floor before it free, behind it unknown."""
    scene = scene_from_dict(
        {"walls": [{"id": "w", "start": [3.0, -3.0], "end": [3.0, 3.0], "thickness": 0.1}]},
        bounds=[-1, -3, 4, 3],
    )
    pose = np.zeros(3)
    T = world_T_camera(pose, CFG)
    _, depth = KinectRenderer(scene, CFG).render(T)
    pts = depth_to_points(depth, _camera(CFG), T)
    obst, floor = split_by_height(pts, 0.0, (0.08, 1.8))
    assert len(obst) > 100 and len(floor) > 100
    np.testing.assert_allclose(obst[:, 0], 2.95, atol=0.01)  # wall face
    grid = OccupancyGrid.empty(
        -1.025, -3.025, 4.0, 3.0, 0.05
    )  # the wall face at 2.95 m is mid-cell
    for _ in range(4):  # a robot standing still: 4 frames take cells past the map_server thresholds
        integrate_depth_frame(grid, T[:2, 3], obst, floor, CFG.max_depth, DepthGridConfig())
    occ, free = occupied_mask(grid), free_mask(grid)
    assert not np.any(occ & free)
    on_axis = grid.world_to_cell(
        np.array([[2.95, 0.0], [2.0, 0.0], [1.0, 0.0], [3.5, 0.0], [0.5, 2.5]])
    )
    ix, iy = on_axis[:, 0], on_axis[:, 1]
    assert occ[iy[0], ix[0]]  # wall face cell
    assert free[iy[1], ix[1]] and free[iy[2], ix[2]]  # in front of the wall
    assert grid.log_odds[iy[3], ix[3]] == 0.0  # behind the wall: unknown
    assert grid.log_odds[iy[4], ix[4]] == 0.0  # outside the field of view
    # every occupied cell is within one cell of the wall face
    cells = np.argwhere(occ)
    centres = grid.cell_to_world(cells[:, ::-1])
    assert np.all(np.abs(centres[:, 0] - 2.95) <= 0.05 + 1e-9)


def test_precision_recall_on_hand_made_masks() -> None:
    truth = np.zeros((5, 5), bool)
    truth[2, :] = True
    surface = truth.copy()
    occ = np.zeros((5, 5), bool)
    occ[2, :3] = True  # 3 of 5 true cells found
    occ[0, 0] = True  # one false positive two cells away
    p, r = grid_precision_recall(occ, truth, surface, 0)
    assert p == pytest.approx(3 / 4) and r == pytest.approx(3 / 5)
    occ[3, 4] = True  # one cell off the truth: counts with tolerance 1
    p, r = grid_precision_recall(occ, truth, surface, 1)
    assert p == pytest.approx(4 / 5) and r == pytest.approx(5 / 5)


def test_duplicates_merged_by_position_and_descriptor(rng: np.random.Generator) -> None:
    d_a = rng.uniform(0, 100, 128)
    d_b = rng.uniform(0, 100, 128)
    xyz = np.array(
        [[1.0, 2.0, 1.0], [1.01, 2.0, 1.0], [1.0, 2.02, 1.01], [1.0, 2.0, 1.0], [3.0, 2.0, 1.0]]
    )
    desc = np.stack([d_a, d_a + 1, d_a - 1, d_b, d_a]).astype(np.float32)
    m = merge_duplicates(
        xyz,
        desc,
        np.ones(5),
        np.zeros(5),
        SpatialMapConfig(merge_radius=0.05, merge_descriptor_dist=100.0),
    )
    order = np.argsort(-m.n_obs)
    np.testing.assert_array_equal(m.n_obs[order], [3, 1, 1])
    np.testing.assert_allclose(m.xyz[order[0]], xyz[:3].mean(axis=0), atol=1e-12)
    np.testing.assert_allclose(m.descriptors[order[0]], d_a, atol=1e-4)


def test_missing_pose_is_a_clear_error() -> None:
    t = np.array([0.0, 1.0, 2.0])
    poses = np.array([[0, 0, 0], [1, 0, 0], [2, 0, 3.0]])
    got = planar_poses_at(t, poses, np.array([0.5, 2.1]), 0.2, "traj.tum")
    np.testing.assert_allclose(got[0], [0.5, 0.0, 0.0])
    with pytest.raises(EnvMapError, match=r"traj\.tum: no pose for frame 1 at t=2\.500"):
        planar_poses_at(t, poses, np.array([0.5, 2.5]), 0.2, "traj.tum")


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """An 8-second office drive at 160x120 (25 frames)."""
    out = tmp_path_factory.mktemp("office") / "run"
    return simulate_kinect_run(
        "office", out, seed=5, config=KinectConfig(width=160, height=120), duration=8.0
    )


def _truth(run: Path) -> FloorPlan:
    plan = floor_plan_of_run(run, DepthGridConfig().height_band)
    assert plan is not None  # the office world has a scene3d section
    return plan


def test_build_map_on_simulated_office(tiny_run: Path, tmp_path: Path) -> None:
    report = build_map(tiny_run, tmp_path / "map", config=NO_TABLE, truth=_truth(tiny_run))
    assert report.source == "run" and report.n_frames == 25
    env = load_env_map(tmp_path / "map")
    assert env.manifest["format"] == "lampsam-envmap"
    assert env.manifest["units"]["length"] == "m"
    assert env.grid.resolution == pytest.approx(0.05)
    assert occupied_mask(env.grid).sum() > 50
    checks = report.checks["grid_vs_world"]
    assert checks["precision_tol1"] > 0.95  # occupied cells lie on true obstacles
    assert env.spatial is not None and len(env.spatial) > 20
    # SIFT points lie on walls/furniture: inside the room, below the ceiling
    assert np.all((env.spatial.xyz[:, :2] > -0.2) & (env.spatial.xyz[:, :2] < 10.2))
    assert np.all((env.spatial.xyz[:, 2] > -0.05) & (env.spatial.xyz[:, 2] < 2.75))
    assert env.ceiling is not None and int(env.ceiling.is_lamp().sum()) == 11


def test_build_map_with_slam_poses_and_missing_pose(tiny_run: Path, tmp_path: Path) -> None:
    gt = read_tum(tiny_run / "groundtruth.tum")
    slam_dir = tmp_path / "slam"
    slam_dir.mkdir()
    write_tum(slam_dir / "trajectory.tum", gt)
    (slam_dir / "landmarks.csv").write_text(  # the backend's columns (backend/slam.py)
        "id,type,x,y,z,phi,n_obs,cov_xx,cov_xy,cov_xz,cov_yy,cov_yz,cov_zz,var_phi\n"
        "1,lamp,2.0,2.0,2.38,0.1,9,0.01,0.002,0,0.02,0,0.03,0.001\n"
        "1000,corner,0.2,0.2,2.4,nan,4,0.04,0,0,0.05,0,0.06,nan\n"
    )
    report = build_map(
        tiny_run,
        tmp_path / "map",
        poses=f"slam:{slam_dir / 'trajectory.tum'}",
        config=NO_TABLE,
        truth=_truth(tiny_run),
    )
    env = load_env_map(tmp_path / "map")
    assert report.checks["grid_vs_world"]["precision_tol1"] > 0.95
    assert env.ceiling is not None and len(env.ceiling) == 2
    # the backend's z is above the floor: kept as is
    np.testing.assert_allclose(env.ceiling.xyz[0], [2.0, 2.0, 2.38])
    np.testing.assert_allclose(env.ceiling.cov_xy[0], [[0.01, 0.002], [0.002, 0.02]])
    assert math.isnan(env.ceiling.phi[1])
    short = Trajectory(gt.t[gt.t < 4.0], gt.poses[gt.t < 4.0])
    write_tum(slam_dir / "short.tum", short)
    with pytest.raises(EnvMapError, match="no pose for frame"):
        build_map(tiny_run, tmp_path / "map2", poses=f"slam:{slam_dir / 'short.tum'}")
    with pytest.raises(EnvMapError, match="groundtruth"):
        build_map(tiny_run, tmp_path / "map3", poses="odometry")


def test_cli_build_and_show_map(tiny_run: Path, tmp_path: Path) -> None:
    assert (
        main(["build-map", str(tiny_run), "--out", str(tmp_path / "m"), "--resolution", "0.1",
              "--no-tables"]) == 0
    )
    assert load_env_map(tmp_path / "m").grid.resolution == pytest.approx(0.1)
    assert main(["show-map", str(tmp_path / "m"), "--out", str(tmp_path / "m.png")]) == 0
    assert (tmp_path / "m.png").stat().st_size > 10_000
    assert main(["build-map", str(tmp_path / "nowhere"), "--out", str(tmp_path / "x")]) == 2
    assert main(["show-map", str(tmp_path / "nowhere"), "--out", str(tmp_path / "x.png")]) == 2


def test_ceiling_map_round_trip(tmp_path: Path) -> None:
    cm = CeilingFeatureMap(
        np.array([1, 1000]), ("lamp_rect", "corner"), np.array([[1.0, 2.0, 2.7], [3.0, 4.0, 2.7]]),
        np.array([0.5, math.nan]), np.array([1.2, 0.0]), np.array([0.3, 0.0]),
        np.full((2, 2, 2), math.nan), "groundtruth",
    )  # fmt: skip
    back = CeilingFeatureMap.load(cm.save(tmp_path / "c.csv"))
    np.testing.assert_array_equal(back.ids, cm.ids)
    np.testing.assert_allclose(back.xyz, cm.xyz)
    assert back.phi[0] == pytest.approx(0.5) and math.isnan(back.phi[1])
    (tmp_path / "bad.csv").write_text("id,type,x,y,z\n1,lamp,1.0,oops,2.0\n")
    with pytest.raises(Exception, match=r"bad\.csv:2: column 'y'"):
        read_landmark_csv(tmp_path / "bad.csv")


def test_laser_grid_of_a_square_room() -> None:
    """Scans from inside a 6 m x 4 m room: walls occupied, the inside free, outside unknown."""
    from lampsam.datasets.carmen import LaserScans, carmen_beam_angles
    from lampsam.localization.laser_grid import build_laser_grid
    from lampsam.localization.map_config import LaserGridConfig

    angles = carmen_beam_angles(180)
    four = [[2.0, 2.0, 0.0], [2.0, 2.0, math.pi], [4.0, 2.0, math.pi / 2], [4.0, 2.0, -math.pi / 2]]
    poses = np.array(four * 4)  # each view 4 times: enough evidence to pass the thresholds
    ranges = np.empty((len(poses), len(angles)))
    for k, (x, y, th) in enumerate(poses):
        phi = th + angles
        c, s = np.cos(phi), np.sin(phi)
        with np.errstate(divide="ignore"):
            tx = np.where(c > 0, (6.0 - x) / c, np.where(c < 0, -x / c, np.inf))
            ty = np.where(s > 0, (4.0 - y) / s, np.where(s < 0, -y / s, np.inf))
        ranges[k] = np.minimum(tx, ty)
    scans = LaserScans(
        np.arange(16.0), ranges, angles, poses, poses.copy(), np.arange(1, 17), max_range=80.0
    )
    grid, used = build_laser_grid(
        scans, poses, LaserGridConfig(resolution=0.1, min_move=0.0, min_turn=0.0)
    )
    assert used == 16
    occ, free = occupied_mask(grid), free_mask(grid)
    centres = grid.cell_centres()
    on_wall = (np.abs(centres[..., 0]) < 0.05) | (np.abs(centres[..., 0] - 6.0) < 0.05)
    on_wall |= (np.abs(centres[..., 1]) < 0.05) | (np.abs(centres[..., 1] - 4.0) < 0.05)
    # every occupied cell touches a wall line (within one cell)
    near_wall = (
        np.minimum.reduce([np.abs(centres[..., 0]), np.abs(centres[..., 0] - 6.0)]) < 0.11
    ) | (np.minimum.reduce([np.abs(centres[..., 1]), np.abs(centres[..., 1] - 4.0)]) < 0.11)
    assert occ.sum() > 100 and np.all(near_wall[occ])
    inside = (
        (centres[..., 0] > 0.5)
        & (centres[..., 0] < 5.5)
        & (centres[..., 1] > 0.5)
        & (centres[..., 1] < 3.5)
    )
    assert free[inside].mean() > 0.95
    outside = (centres[..., 0] < -0.3) | (centres[..., 1] < -0.3)
    assert not np.any(free[outside] | occ[outside])
