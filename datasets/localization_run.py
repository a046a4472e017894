"""A simulated run for global localization: start at an unknown pose, turn, drive on, repeat.

Paper 2, Fig. 11: a robot that does not know where it is turns in place once
(30 deg/s; the Kinect frames give SIFT candidates and the 360-degree virtual
scan), then drives on while the ceiling camera verifies the estimate; on
failure it turns again. :func:`simulate_localization_run` writes such a run
(``rounds`` times: a full turn, a turn towards open space, a straight drive)
as a logged run (``docs/log-format.md``: ``rig.yaml``, ``odometry.csv`` with
wheel slip, ``groundtruth.tum``, ``landmarks.csv``, ceiling images with their
truth projections, ``meta.yaml``) plus ``kinect/`` (TUM RGB-D, frames during
the full turns only), so that ``lampsam localize RUN --map MAP`` can replay it
(:class:`lampsam.localization.replay.ReplayRobot`). The run is planned on the
true obstacles (the localizer cannot steer a log): each drive heads where the
truth has room for it.

Frames: poses are ``world_T_body`` (m, m, rad), world ``x, y`` on the floor.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from lampsam.arrays import BoolArray, FloatArray
from lampsam.datasets.ceiling_truth import occluders, project_landmarks
from lampsam.datasets.kinect_sim import KinectConfig, add_kinect_meta, write_kinect_frames
from lampsam.datasets.logrun import (
    PROJECTIONS_FILE,
    ImageWriter,
    OdometryLog,
    ProjectionWriter,
    Trajectory,
    write_run,
)
from lampsam.datasets.motion import noisy_wheel_travel
from lampsam.datasets.render_ceiling import CeilingRenderer
from lampsam.datasets.scene3d import Scene3D, apply_changes, obstacle_footprints, scene_from_dict
from lampsam.datasets.tables import encode_png
from lampsam.datasets.world import World, load_world
from lampsam.datasets.world_landmarks import world_landmarks
from lampsam.errors import DatasetError

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class ObstacleMap:
    """The true obstacles of a scene on a floor grid (for planning and start poses).

    Attributes:
        occupied: (H, W) bool, row ``i`` at ``y = origin[1] + (i + 0.5) res``.
        origin: (2,) world ``x, y`` of the grid's lower-left corner (m).
        resolution: cell size (m).
    """

    occupied: BoolArray
    origin: FloatArray
    resolution: float

    @classmethod
    def from_scene(
        cls, scene: Scene3D, resolution: float = 0.05, band: tuple[float, float] = (0.05, 1.8)
    ) -> ObstacleMap:
        """Rasterize the boxes reaching into the height band ``band`` (m) over the scene's bounds."""
        x0, y0, x1, y1 = (float(v) for v in scene.bounds)
        w = int(math.ceil((x1 - x0) / resolution))
        h = int(math.ceil((y1 - y0) / resolution))
        img = np.zeros((h, w), np.uint8)
        for poly in obstacle_footprints(scene, *band):
            pts = np.round((np.asarray(poly)[:, :2] - [x0, y0]) / resolution - 0.5).astype(np.int32)
            cv2.fillPoly(img, [pts], 1)
        img[0, :] = img[-1, :] = img[:, 0] = img[:, -1] = 1  # the scene ends here
        return cls(img.astype(bool), np.array([x0, y0]), resolution)

    def occupied_at(self, xy: FloatArray) -> bool:
        """``xy`` (m) is in an obstacle or outside the grid."""
        j = int(math.floor((xy[0] - self.origin[0]) / self.resolution))
        i = int(math.floor((xy[1] - self.origin[1]) / self.resolution))
        h, w = self.occupied.shape
        return not (0 <= i < h and 0 <= j < w) or bool(self.occupied[i, j])

    def clearance(self) -> FloatArray:
        """(H, W) distance of each cell centre to the nearest obstacle (m)."""
        free = (~self.occupied).astype(np.uint8)
        return cv2.distanceTransform(free, cv2.DIST_L2, 5).astype(float) * self.resolution

    def free_distance(self, xy: FloatArray, heading: float, max_range: float) -> float:
        """Free distance (m) from ``xy`` along ``heading`` (rad), marched at quarter cells."""
        step = 0.25 * self.resolution
        s = np.arange(0.0, max_range + step, step)
        px = xy[0] + s * math.cos(heading)
        py = xy[1] + s * math.sin(heading)
        j = np.floor((px - self.origin[0]) / self.resolution).astype(int)
        i = np.floor((py - self.origin[1]) / self.resolution).astype(int)
        h, w = self.occupied.shape
        hit = (i < 0) | (i >= h) | (j < 0) | (j >= w)
        hit[~hit] = self.occupied[i[~hit], j[~hit]]
        k = int(np.argmax(hit)) if hit.any() else len(s)
        return float(s[k]) if k < len(s) else float(max_range)


@dataclass(frozen=True)
class LocalizationDrive:
    """How the simulated robot searches for its pose.

    Attributes:
        rounds: full turns (each followed by a drive). Default 4 (the
            localizer's first attempt plus 3 restarts).
        turn_rate: in-place turning rate (rad/s). Default 30 deg/s (paper).
        turn_angle: each full turn (rad): one turn plus 10 degrees, so that the
            odometry (with slip) has turned by a full turn before the Kinect
            frames of the turn end.
        speed: forward speed (m/s). Default 0.4 (paper).
        drive_distance: each drive (m), shorter when the truth has less room.
            Default 2.5 (the 2 m verification plus the decision step).
        open_need: free distance wanted ahead of a drive (m). Default 2.7.
        corridor: half-width of the drive corridor checked (rad). Default 15 deg.
        clearance: free space around a random start (m). Default 0.6.
    """

    rounds: int = 4
    turn_rate: float = math.radians(30.0)
    turn_angle: float = 2 * math.pi + math.radians(10.0)
    speed: float = 0.4
    drive_distance: float = 2.5
    open_need: float = 2.7
    corridor: float = math.radians(15.0)
    clearance: float = 0.6


def random_start(obstacles: ObstacleMap, clearance: float, rng: np.random.Generator) -> FloatArray:
    """(3,) a start pose at least ``clearance`` m from every obstacle, uniform heading."""
    iy, ix = np.nonzero(obstacles.clearance() > clearance)
    if len(ix) == 0:
        raise DatasetError(f"no free place with {clearance} m clearance")
    k = int(rng.integers(len(ix)))
    xy = obstacles.origin + (np.array([ix[k], iy[k]]) + 0.5) * obstacles.resolution
    return np.array([xy[0], xy[1], rng.uniform(-math.pi, math.pi)])


def _open_heading(obstacles: ObstacleMap, pose: FloatArray, drive: LocalizationDrive) -> tuple[float, float]:
    """The heading to drive on (nearest to the current one with ``open_need`` free) and its room."""
    rays = np.deg2rad(np.arange(-15.0, 15.1, 5.0)) * (drive.corridor / math.radians(15.0))
    best, best_free = float(pose[2]), -1.0
    for turn in sorted(np.deg2rad(np.arange(-180.0, 180.0, 5.0)), key=abs):
        head = float(pose[2] + turn)
        free = min(obstacles.free_distance(pose[:2], head + r, drive.open_need + 0.5) for r in rays)
        if free >= drive.open_need:
            return head, free
        if free > best_free:
            best, best_free = head, free
    return best, best_free


def plan_search(
    obstacles: ObstacleMap, start: FloatArray, drive: LocalizationDrive, rate_hz: float
) -> tuple[FloatArray, FloatArray, list[tuple[str, float, float]]]:
    """The true motion: ``rounds`` x (full turn, turn towards open space, drive).

    Returns:
        ``poses (N, 3)`` at ``rate_hz``, the commanded body increments per sample
        ``(N, 3)`` (row 0 zero), and the phases ``(kind, t_start, t_end)`` with
        kind ``"turn"``, ``"face"`` or ``"drive"``.
    """
    dt = 1.0 / rate_hz
    poses = [np.asarray(start, dtype=float)]
    steps = [np.zeros(3)]
    phases: list[tuple[str, float, float]] = []

    def move(kind: str, deltas: list[FloatArray]) -> None:
        t0 = (len(poses) - 1) * dt
        for d in deltas:
            p = poses[-1]
            c, s = math.cos(p[2]), math.sin(p[2])
            poses.append(np.array([p[0] + c * d[0], p[1] + s * d[0], p[2] + d[2]]))
            steps.append(d)
        if deltas:
            phases.append((kind, t0, (len(poses) - 1) * dt))

    def turn(kind: str, angle: float) -> None:
        n = int(math.ceil(abs(angle) / (drive.turn_rate * dt) - 1e-9))
        move(kind, [np.array([0.0, 0.0, angle / n])] * n if n else [])

    for _ in range(drive.rounds):
        turn("turn", drive.turn_angle)
        head, free = _open_heading(obstacles, poses[-1], drive)
        turn("face", math.remainder(head - poses[-1][2], 2 * math.pi))
        dist = max(0.0, min(drive.drive_distance, free - 0.7))
        n = int(math.ceil(dist / (drive.speed * dt) - 1e-9))
        move("drive", [np.array([dist / n, 0.0, 0.0])] * n if n else [])
    out = np.array(poses)
    out[:, 2] = np.mod(out[:, 2] + math.pi, 2 * math.pi) - math.pi
    return out, np.array(steps), phases


def simulate_localization_run(
    world: str | Path,
    out: str | Path,
    start: FloatArray | None = None,
    seed: int = 0,
    config: KinectConfig | None = None,
    drive: LocalizationDrive | None = None,
    changed: bool = False,
) -> Path:
    """Simulate a global-localization run of a world (see the module docstring).

    Args:
        world: built-in world name (``office``) or a world YAML with ``scene3d``.
        out: the run directory.
        start: (3,) the true start pose (m, m, rad); None: random
            (``drive.clearance`` m from obstacles), drawn from ``seed``.
        seed: seed of the start, wheel slip and sensor noise.
        config: the Kinect (default :class:`KinectConfig`).
        drive: the search motion (default :class:`LocalizationDrive`).
        changed: apply all of the scene's ``changes`` (furniture moved, pictures
            removed: the environment changed after mapping, as in paper 2's Table 1).

    Returns:
        The run directory.

    Raises:
        DatasetError: unknown world, no ``scene3d``, a start inside an obstacle.
    """
    config = KinectConfig() if config is None else config
    drive = LocalizationDrive() if drive is None else drive
    w = load_world(world)
    if "scene3d" not in w.extra:
        raise DatasetError("world has no 'scene3d' section", w.source)
    scene = scene_from_dict(w.extra["scene3d"])
    if changed:
        scene = apply_changes(scene, list(scene.changes))
    rng = np.random.default_rng(seed)
    obstacles = ObstacleMap.from_scene(scene)
    if start is None:
        start = random_start(obstacles, drive.clearance, rng)
    start = np.asarray(start, dtype=float).reshape(3)
    if obstacles.occupied_at(start[:2]):
        raise DatasetError(f"start pose {start.tolist()} is inside an obstacle", w.source)
    rate = float(w.simulation.odometry_rate_hz)
    poses, steps, phases = plan_search(obstacles, start, drive, rate)
    t = np.arange(len(poses)) / rate
    b = w.rig.odometry.wheel_base
    wheel = np.column_stack([steps[:, 0] - 0.5 * b * steps[:, 2], steps[:, 0] + 0.5 * b * steps[:, 2]])
    noisy = noisy_wheel_travel(wheel, w.rig.odometry.k_r, w.rig.odometry.k_l, rng)
    out = Path(out)
    meta = {
        "world": w.name,
        "seed": int(seed),
        "simulator": "lampsam.datasets.localization_run",
        "localization_start": [float(v) for v in start],
        "changed": bool(changed),
        "phases": [[k, float(a), float(e)] for k, a, e in phases],
        "duration_s": float(t[-1]),
    }
    write_run(out, w.rig, OdometryLog(t[1:], noisy[1:, 0], noisy[1:, 1]),
              groundtruth=Trajectory(t, poses), landmarks=world_landmarks(w), meta=meta)  # fmt: skip
    add_kinect_meta(out, w.name, config)
    in_turn = np.zeros(len(t), bool)
    in_drive = np.zeros(len(t), bool)
    for kind, a, e in phases:
        sel = (t >= a - 1e-9) & (t <= e + 1e-9)
        (in_turn if kind == "turn" else in_drive)[sel] = True
    k_step = max(1, int(round(rate / config.rate_hz)))
    kinect_idx = [i for i in range(0, len(t), k_step) if in_turn[i]]
    write_kinect_frames(out, scene, config, t, poses, kinect_idx, rng)
    c_step = max(1, int(round(rate / w.simulation.image_rate_hz)))
    ceiling_idx = [i for i in range(0, len(t), c_step) if in_drive[i]]
    _render_ceiling(w, out, t, poses, ceiling_idx, seed)
    log.info("localization run %s: start %s, %.1f s, %d Kinect and %d ceiling frames", out,
             np.round(start, 3).tolist(), t[-1], len(kinect_idx), len(ceiling_idx))  # fmt: skip
    return out


def _render_ceiling(
    world: World, out: Path, t: FloatArray, poses: FloatArray, idx: list[int], seed: int
) -> None:
    """Ceiling images (and their truth projections) at the samples ``idx``."""
    renderer = CeilingRenderer(world)
    landmarks = world_landmarks(world)
    occ = occluders(world)
    images = ImageWriter(out)
    proj = ProjectionWriter(out / PROJECTIONS_FILE)
    try:
        for k, i in enumerate(idx):
            img = renderer.render(poses[i], np.random.default_rng([seed, k]))
            images.write_encoded(float(t[i]), encode_png(img, what=f"ceiling frame {k}"))
            truth = project_landmarks(renderer.camera, poses[i], landmarks, occ, renderer.m_max)
            proj.write_frame(k, float(t[i]), truth)
    finally:
        images.close()
        proj.close()
