"""Paper 2's Table 1 on the simulated ``office`` world: the trials (``lampsam table1``).

1. **Mapping**: the Kinect zig-zag drive of the office
   (:func:`lampsam.datasets.kinect_sim.simulate_kinect_run`) and the environment
   map built from it with the true poses (:func:`lampsam.localization.map_build.build_map`),
   both cached in ``work``.
2. **Trials** in the *changed* office (all of the world's ``changes``: furniture
   moved and removed, pictures taken down): random start poses with at least
   ``clearance`` m of free space; the steerable robot
   (:class:`lampsam.datasets.steerable_robot.SimulatedRobot`) renders the Kinect
   (Open3D ray casting) while it turns and sees the ceiling's true lamps and
   corners in the upward camera's image while it drives.
3. Every configuration (:class:`lampsam.localization.filter_config.Mode`) runs on
   the same start poses with the same sensor noise seed.

Success (the paper's criterion, :func:`trial_success`): localisation time at
most 60 s and final error at most 30 cm and 10 deg. Localisation time = robot
time (turning + verification driving) + compute time, added serially.

Output in ``out``: ``trials.w<k>.jsonl`` (one line per finished trial and
configuration, appended as it finishes; a rerun resumes), and the report of
:mod:`lampsam.evaluation.table1_report`. Results and history: docs/table1.md.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Sequence
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from lampsam.arrays import Float32Array, FloatArray
from lampsam.datasets.kinect_sim import KinectConfig, KinectRenderer, simulate_kinect_run
from lampsam.datasets.logrun import read_run
from lampsam.datasets.rgbd import RgbdCamera, camera_from_yaml
from lampsam.datasets.scene3d import Scene3D, apply_changes, load_scene, obstacle_footprints
from lampsam.datasets.steerable_robot import CeilingLandmarkSensor, SimulatedRobot
from lampsam.errors import DatasetError
from lampsam.evaluation.table1_report import read_rows, write_report
from lampsam.factors.geometry import wrap_angle
from lampsam.localization.filter_config import GlobalLocalizerConfig, Mode
from lampsam.localization.grid import OccupancyGrid
from lampsam.localization.localizer import localize
from lampsam.localization.map_build import build_map
from lampsam.localization.map_layers import EnvironmentMaps
from lampsam.localization.map_quality import footprint_mask
from lampsam.localization.map_store import load_env_map
from lampsam.localization.raycast import cast_rays, distance_field
from lampsam.localization.replay import kinect_turn_data
from lampsam.localization.result import LocalizationResult, json_safe
from lampsam.localization.spatial_map import make_sift
from lampsam.safe_io import append_json_line, read_json_lines

log = logging.getLogger(__name__)

WORLD = "office"
#: the paper's success bounds: metres, radians, seconds of localisation time
SUCCESS_XY, SUCCESS_THETA, SUCCESS_TIME = 0.30, math.radians(10.0), 60.0


def build_maps(work: Path, seed: int) -> Path:
    """Simulate the mapping drive and build the environment map, cached in ``work``."""
    run, out = work / "map_run", work / "map"
    if (out / "manifest.yaml").is_file():
        return out
    if not (run / "kinect").is_dir():
        simulate_kinect_run(WORLD, run, seed=seed)
    build_map(run, out)
    return out


def truth_grid(scene_now: Scene3D, resolution: float = 0.05) -> OccupancyGrid:
    """Occupancy of the changed office (obstacles 0.05-1.8 m high), log-odds +-4."""
    g = OccupancyGrid.empty(-0.5, -0.5, 10.5, 10.5, resolution)
    occ = footprint_mask(g, obstacle_footprints(scene_now, 0.05, 1.8))
    g.log_odds = np.where(occ, 4.0, -4.0)
    return g


def random_starts(
    grid: OccupancyGrid, n: int, clearance: float, rng: np.random.Generator
) -> FloatArray:
    """(n, 3) start poses with ``clearance`` m to the nearest obstacle, uniform heading."""
    dist = distance_field(grid.log_odds > 0) * grid.resolution
    iy, ix = np.nonzero(dist > clearance)
    k = rng.choice(len(ix), n, replace=False)
    xy = grid.cell_to_world(np.column_stack([ix[k], iy[k]]))
    return np.column_stack([xy, rng.uniform(-np.pi, np.pi, n)])


def trial_success(
    claimed: bool, error_xy: float, error_theta: float, total_s: float
) -> bool:
    """The paper's criterion: accepted, within 30 cm and 10 deg, in at most 60 s."""
    return bool(
        claimed and error_xy <= SUCCESS_XY and error_theta <= SUCCESS_THETA
        and total_s <= SUCCESS_TIME
    )  # fmt: skip


@dataclass
class OfficeWorld:
    """Everything the trials share: the map, the changed office and its sensors."""

    maps: EnvironmentMaps
    renderer: KinectRenderer
    kinect_camera: RgbdCamera
    grid_now: OccupancyGrid
    ceiling: CeilingLandmarkSensor

    @classmethod
    def load(cls, work: Path, seed: int) -> OfficeWorld:
        """Build (or read from ``work``) the map; the changed office's truth."""
        map_dir = build_maps(work, seed)
        env = load_env_map(map_dir)
        run = read_run(work / "map_run")
        cam = run.rig.camera
        body_t_cam = np.asarray(cam.body_t_camera, dtype=float)
        maps = EnvironmentMaps.from_env_map(env, body_t_cam, cam)
        scene = load_scene(WORLD)
        scene_now = apply_changes(scene, list(scene.changes))
        renderer = KinectRenderer(scene_now, KinectConfig())
        camera = camera_from_yaml(work / "map_run" / "kinect" / "kinect.yaml")
        lm = run.landmarks
        if lm is None:
            raise DatasetError("the mapping run has no landmarks", work / "map_run")
        rect = np.array([str(k) == "lamp_rect" for k in lm.types])
        ceiling = CeilingLandmarkSensor(
            np.asarray(lm.xyz, dtype=float),
            lm.is_lamp(),
            np.where(rect, np.asarray(lm.phi, dtype=float), np.nan),
            body_t_cam,
            cam,
        )
        return cls(maps, renderer, camera, truth_grid(scene_now), ceiling)

    def robot(self, start: FloatArray, rng: np.random.Generator) -> SimulatedRobot:
        """A steerable robot at the true pose ``start`` in the changed office."""
        sift = make_sift()

        def kinect(
            pose: FloatArray, g: np.random.Generator
        ) -> tuple[FloatArray, Float32Array, FloatArray]:
            rgb, depth = self.renderer.render_pose(pose, g)
            return kinect_turn_data(rgb, depth, self.kinect_camera, sift)

        def free_ahead(pose: FloatArray) -> float:
            rays = cast_rays(self.grid_now, pose[None], np.array([-0.3, 0.0, 0.3]), 3.0)
            return float(rays[0].min())

        return SimulatedRobot(kinect, self.ceiling, free_ahead, start.copy(), rng,
                              kinect_rate=KinectConfig().rate_hz)  # fmt: skip


def trial_row(
    i: int, mode: Mode, start: FloatArray, robot: SimulatedRobot, res: LocalizationResult,
    wall: float,
) -> dict[str, object]:
    """The JSON record of one finished (trial, configuration)."""
    e_xy = float(np.hypot(*(res.pose[:2] - robot.pose[:2])))
    e_th = float(abs(wrap_angle(res.pose[2] - robot.pose[2])))
    compute = float(sum(res.compute_time.values()))
    robot_s = float(sum(res.robot_time.values()))
    total = compute + robot_s
    return {
        "trial": i,
        "mode": mode.value,
        "start": start.tolist(),
        "truth": robot.pose.tolist(),
        "pose": [float(v) for v in res.pose],
        "claimed_success": res.success,
        "status": res.status,
        "correct_pose": bool(e_xy <= SUCCESS_XY and e_th <= SUCCESS_THETA),
        "evidence": json_safe(res.evidence),
        "success": trial_success(res.success, e_xy, e_th, total),
        "error_m": e_xy,
        "error_deg": math.degrees(e_th),
        "compute_s": compute,
        "robot_s": robot_s,
        "turn_s": res.robot_time["turn"],
        "total_s": total,
        "restarts": res.restarts,
        "wall_s": wall,
        "compute_stages_s": dict(res.compute_time),
        "compute_after_turn_s": compute - float(res.compute_time["candidates"]),
        "attempts": [
            {"n_candidates": a.n_candidates, "verdict": a.verdict, "pose": a.pose,
             "verify_m": a.verify_distance}
            for a in res.attempts
        ],  # fmt: skip
        "turn_starts": robot.turn_starts,
    }


def _done_pairs(sink: Path | None) -> set[tuple[int, str]]:
    done: set[tuple[int, str]] = set()
    if sink is not None and sink.is_file():
        for r in read_json_lines(sink):
            done.add((int(str(r["trial"])), str(r["mode"])))
    return done


def run_trials(
    trials: int,
    work: Path,
    seed: int,
    clearance: float,
    modes: Sequence[Mode],
    worker: int = 0,
    n_workers: int = 1,
    sink: Path | None = None,
    only: set[int] | None = None,
) -> list[dict[str, object]]:
    """Trials ``i`` with ``i % n_workers == worker``, every mode; one dict per (trial, mode).

    Args:
        trials: start poses drawn (seeded by ``seed``): trial ``i`` has the
            same start and noise in every run.
        work: cache of the mapping run and map.
        seed: seed of the mapping run, the starts and the noise.
        clearance: free space around the start poses (m).
        modes: the configurations to run.
        worker, n_workers: this process's share of the trials.
        sink: JSON-lines file: every finished (trial, mode) is appended at once
            (an interrupted run keeps what finished); pairs already in it are
            not run again (resume).
        only: run just these trial indices.
    """
    done = _done_pairs(sink)
    world = OfficeWorld.load(work, seed)
    starts = random_starts(world.grid_now, trials, clearance, np.random.default_rng(seed))
    rows: list[dict[str, object]] = []
    for i, start in enumerate(starts):
        if i % n_workers != worker or (only is not None and i not in only):
            continue
        for mode in modes:
            if (i, mode.value) in done:
                continue
            robot = world.robot(start, np.random.default_rng(seed * 1000 + i))
            t0 = time.perf_counter()
            res = localize(robot, world.maps, GlobalLocalizerConfig(mode=mode),
                           np.random.default_rng(seed * 7 + i))  # fmt: skip
            row = trial_row(i, mode, start, robot, res, time.perf_counter() - t0)
            rows.append(row)
            if sink is not None:
                append_json_line(sink, row)
            log.info("trial %d %-10s ok=%s err %.3f m %.1f deg compute %.1f s robot %.1f s",
                     i, mode.value, row["success"], row["error_m"], row["error_deg"],
                     row["compute_s"], row["robot_s"])  # fmt: skip
    return rows


def run_table1(
    out: Path,
    trials: int = 50,
    work: Path | None = None,
    seed: int = 1,
    clearance: float = 0.6,
    modes: Sequence[Mode] = tuple(Mode),
    jobs: int = 1,
    only: set[int] | None = None,
    report_only: bool = False,
) -> str:
    """Run (or resume) the experiment and write the report; returns the Markdown table.

    Args:
        out: output directory (``trials.w<k>.jsonl``, ``table1.md``, ``table1.png``,
            ``trials.json``).
        trials: number of start poses.
        work: cache of the mapping run and map (default ``out/work``).
        seed: seed of everything.
        clearance: free space around the start poses (m).
        modes: configurations.
        jobs: worker processes (trial ``i`` goes to worker ``i % jobs``).
        only: just these trial indices (same starts as a full run).
        report_only: only rebuild the report from ``out/trials.w*.jsonl``.
    """
    out.mkdir(parents=True, exist_ok=True)
    work = out / "work" if work is None else work
    modes = list(modes)
    if not report_only:
        build_maps(work, seed)  # once, before the workers share the cache
        if jobs <= 1:
            run_trials(trials, work, seed, clearance, modes, 0, 1, out / "trials.w0.jsonl", only)
        else:
            with ProcessPoolExecutor(jobs) as pool:
                futures = [
                    pool.submit(run_trials, trials, work, seed, clearance, modes, k, jobs,
                                out / f"trials.w{k}.jsonl", only)
                    for k in range(jobs)
                ]  # fmt: skip
                for f in futures:
                    f.result()
    return write_report(read_rows(out), [m.value for m in modes], out)
