"""Paper 2's Table 1, reproduced on the simulated ``office`` world, plus ours.

Usage::

    python scripts/table1_experiment.py --trials 50 --out out/table1 [--work /tmp/table1] [--jobs 2]
    python scripts/table1_experiment.py --out out/table1 --report-only

1. Mapping: the Kinect zig-zag drive of the office (``datasets.kinect_sim``),
   the environment map built from it with the true poses (``localization.envmap``);
   both are cached in ``--work``.
2. Localization trials in the *changed* office (all of the world's ``changes``:
   furniture moved and removed, pictures taken down): random start poses with
   at least ``--clearance`` m of free space; the simulated robot renders the
   Kinect (colour + depth, Open3D ray casting) while it turns, and sees the
   ceiling's true lamps and corners (in the upward camera's image, with
   0.005 noise in normalised coordinates) while it drives.
3. Every configuration of :class:`lampsam.localization.global_localizer.Mode`
   runs on the same start poses with the same sensor noise seed.

Failure (paper): localisation time over 60 s, or final error over 30 cm or 10 deg.
Localisation time = robot time (turning + verification driving) + compute time
(serial, i.e. conservative; measured on a shared machine, inflated by the load).

Output: ``OUT/trials.w<k>.jsonl`` (one line per finished trial and
configuration, written as it finishes; a rerun resumes), ``OUT/table1.md``
(the table), ``OUT/table1.png`` (errors, success rates and times,
``lampsam.evaluation.table1_plots``), ``OUT/trials.json``
(every trial). ``--jobs 2`` runs two worker processes on interleaved trials
(each runs every configuration on its trials, so an interrupted run has about
the same number of trials per configuration).
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from lampsam.datasets.kinect_sim import KinectConfig, KinectRenderer, simulate_kinect_run
from lampsam.datasets.logrun import read_run
from lampsam.datasets.rgbd import RgbdCamera, camera_from_yaml
from lampsam.datasets.scene3d import apply_changes, load_scene, obstacle_footprints
from lampsam.evaluation.table1_plots import save_table1_figure
from lampsam.factors.ceiling import project_point
from lampsam.factors.geometry import compose, wrap_angle, wrap_axis
from lampsam.localization.global_localizer import (
    DriveFrame,
    EnvironmentMaps,
    GlobalLocalizerConfig,
    LocalizationResult,
    Mode,
    TurnFrame,
    localize,
)
from lampsam.localization.grid import OccupancyGrid
from lampsam.localization.map_build import build_map
from lampsam.localization.map_quality import footprint_mask
from lampsam.localization.map_store import load_env_map
from lampsam.localization.pointcloud import depth_to_points
from lampsam.localization.raycast import cast_rays, distance_field
from lampsam.localization.spatial_map import frame_features, make_sift

log = logging.getLogger("table1")

WORLD = "office"


def build_maps(work: Path, seed: int) -> Path:
    """Simulate the mapping drive and build the environment map (cached)."""
    run, out = work / "map_run", work / "map"
    if (out / "manifest.yaml").is_file():
        return out
    if not (run / "kinect").is_dir():
        simulate_kinect_run(WORLD, run, seed=seed)
    build_map(run, out)
    return out


def truth_grid(scene_now: object, resolution: float = 0.05) -> OccupancyGrid:
    """Occupancy of the changed office (obstacles 0.05-1.8 m high), log-odds +-4."""
    g = OccupancyGrid.empty(-0.5, -0.5, 10.5, 10.5, resolution)
    occ = footprint_mask(g, obstacle_footprints(scene_now, 0.05, 1.8))  # type: ignore[arg-type]
    g.log_odds = np.where(occ, 4.0, -4.0)
    return g


@dataclass
class OfficeRobot:
    """The simulated robot in the changed office (implements ``global_localizer.Robot``)."""

    renderer: KinectRenderer
    kinect: KinectConfig
    camera: RgbdCamera
    grid: OccupancyGrid
    ceiling_xyz: np.ndarray
    ceiling_is_lamp: np.ndarray
    ceiling_cam: np.ndarray
    ceiling_camera: object
    ceiling_phi: np.ndarray
    pose: np.ndarray
    rng: np.random.Generator
    odom_sigma: float = 0.01
    ceiling_rate: float = 10.0
    speed: float = 0.4  # m/s, the paper's driving speed (400 mm/s; turning 30 deg/s)

    def __post_init__(self) -> None:
        self.odom = np.zeros(3)
        self.t = 0.0
        self.sift = make_sift()
        self.body_T_cam = self.kinect.body_T_camera()
        self.turn_starts: list[list[float]] = []  # true pose at the start of every turn

    def _move(self, delta: np.ndarray) -> None:
        self.pose = compose(self.pose, delta)
        scale = np.abs(delta).sum()
        self.odom = compose(self.odom, delta + self.rng.normal(0, self.odom_sigma * scale, 3))

    def _kinect(self) -> TurnFrame:
        rgb, depth = self.renderer.render_pose(self.pose, self.rng)
        ff = frame_features(rgb, depth, self.camera, self.sift)
        R, t = self.body_T_cam[:3, :3], self.body_T_cam[:3, 3]
        pts = depth_to_points(depth, self.camera, stride=4)
        return TurnFrame(
            self.t, self.odom.copy(), ff.camera_xyz @ R.T + t, ff.descriptors, pts @ R.T + t
        )

    def turn(self, angle: float, rate: float) -> list[TurnFrame]:
        dt = 1.0 / self.kinect.rate_hz
        self.turn_starts.append([float(v) for v in self.pose])
        n = int(math.ceil(abs(angle) / (rate * dt) - 1e-9))
        frames = [self._kinect()]
        for _ in range(n):
            self._move(np.array([0.0, 0.0, math.copysign(rate * dt, angle)]))
            self.t += dt
            frames.append(self._kinect())
        return frames

    def _ceiling(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        ms, idx = [], []
        for i, p in enumerate(self.ceiling_xyz):
            if p[2] - self.ceiling_cam[2] <= 0.1:
                continue
            ms.append(project_point(self.pose, p, self.ceiling_cam)[0])
            idx.append(i)
        m = np.array(ms).reshape(-1, 2)
        sel = np.array(idx, dtype=int)
        px = self.ceiling_camera.pixels_from_normalized(m)  # type: ignore[attr-defined]
        w, h = self.ceiling_camera.width, self.ceiling_camera.height  # type: ignore[attr-defined]
        vis = (px[:, 0] >= 0) & (px[:, 0] < w) & (px[:, 1] >= 0) & (px[:, 1] < h)
        sel = sel[vis]
        axis = np.asarray(wrap_axis(self.ceiling_phi[sel] - self.pose[2]))
        axis = axis + self.rng.normal(0, np.deg2rad(2.0), len(sel))
        noisy = m[vis] + self.rng.normal(0, 0.005, (len(sel), 2))
        return noisy, self.ceiling_is_lamp[sel], axis

    def drive(self, distance: float) -> list[DriveFrame]:
        dt = 1.0 / self.ceiling_rate
        frames, travelled = [], 0.0
        while travelled < distance - 1e-9:
            ahead = cast_rays(self.grid, self.pose[None], np.array([-0.3, 0.0, 0.3]), 3.0)[0].min()
            if ahead > 0.7:
                step = min(self.speed * dt, distance - travelled)
                self._move(np.array([step, 0.0, 0.0]))
                travelled += step
            else:
                self._move(np.array([0.0, 0.0, 0.5 * dt]))
            self.t += dt
            m, kinds, axis = self._ceiling()
            frames.append(DriveFrame(self.t, self.odom.copy(), m, kinds, axis))
        return frames


def random_starts(
    grid: OccupancyGrid, n: int, clearance: float, rng: np.random.Generator
) -> np.ndarray:
    """(n, 3) start poses with ``clearance`` m to the nearest obstacle."""
    dist = distance_field(grid.log_odds > 0) * grid.resolution
    iy, ix = np.nonzero(dist > clearance)
    k = rng.choice(len(ix), n, replace=False)
    xy = grid.cell_to_world(np.column_stack([ix[k], iy[k]]))
    return np.column_stack([xy, rng.uniform(-np.pi, np.pi, n)])


def run_trials(
    trials: int,
    work: Path,
    seed: int,
    clearance: float,
    modes: list[Mode],
    skip: int = 0,
    worker: int = 0,
    n_workers: int = 1,
    sink: Path | None = None,
    only: set[int] | None = None,
) -> list[dict[str, object]]:
    """Trials ``i >= skip`` with ``i % n_workers == worker``, all modes; one dict per (trial, mode).

    ``only``: run just these trial indices (the starts are still drawn for
    ``trials`` trials, so trial ``i`` has the same start as in a full run).

    Every finished (trial, mode) is appended as one JSON line to ``sink`` at
    once (an interrupted run keeps what finished); pairs already in ``sink``
    are not run again (resume).
    """
    done: set[tuple[int, str]] = set()
    if sink is not None and sink.is_file():
        for line in sink.read_text().splitlines():
            if line.strip():
                r = json.loads(line)
                done.add((int(r["trial"]), str(r["mode"])))
    map_dir = build_maps(work, seed)
    env = load_env_map(map_dir)
    run = read_run(work / "map_run")
    cam = run.rig.camera
    body_t_cam = np.asarray(cam.body_t_camera, dtype=float)
    maps = EnvironmentMaps.from_env_map(env, body_t_cam, cam)
    scene = load_scene(WORLD)
    scene_now = apply_changes(scene, list(scene.changes))
    kinect = KinectConfig()
    renderer = KinectRenderer(scene_now, kinect)
    camera = camera_from_yaml(work / "map_run" / "kinect" / "kinect.yaml")
    grid_now = truth_grid(scene_now)
    lm = run.landmarks
    assert lm is not None
    ceiling_xyz = np.asarray(lm.xyz, dtype=float)
    is_lamp = np.array([str(k).startswith("lamp") for k in lm.types])
    rect = np.array([str(k) == "lamp_rect" for k in lm.types])
    phi = np.where(rect, np.asarray(lm.phi, dtype=float), np.nan)
    starts = random_starts(grid_now, trials, clearance, np.random.default_rng(seed))
    rows: list[dict[str, object]] = []
    for i, start in enumerate(starts):
        if i < skip or i % n_workers != worker or (only is not None and i not in only):
            continue
        for mode in modes:
            if (i, mode.value) in done:
                continue
            robot = OfficeRobot(
                renderer,
                kinect,
                camera,
                grid_now,
                ceiling_xyz,
                is_lamp,
                body_t_cam,
                cam,
                phi,
                start.copy(),
                np.random.default_rng(seed * 1000 + i),
            )
            t0 = time.perf_counter()
            res: LocalizationResult = localize(
                robot, maps, GlobalLocalizerConfig(mode=mode), np.random.default_rng(seed * 7 + i)
            )
            wall = time.perf_counter() - t0
            e_xy = float(np.hypot(*(res.pose[:2] - robot.pose[:2])))
            e_th = float(abs(wrap_angle(res.pose[2] - robot.pose[2])))
            compute = float(sum(res.compute_time.values()))
            robot_s = float(sum(res.robot_time.values()))
            total = compute + robot_s
            ok = bool(res.success and e_xy <= 0.30 and e_th <= math.radians(10.0) and total <= 60.0)
            row: dict[str, object] = {
                "trial": i,
                "mode": mode.value,
                "start": start.tolist(),
                "truth": robot.pose.tolist(),
                "pose": [float(v) for v in res.pose],
                "claimed_success": res.success,
                "success": ok,
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
                    {
                        "n_candidates": a.n_candidates,
                        "verdict": a.verdict,
                        "pose": a.pose,
                        "verify_m": a.verify_distance,
                    }
                    for a in res.attempts
                ],  # fmt: skip
                "turn_starts": robot.turn_starts,
            }
            rows.append(row)
            if sink is not None:
                with sink.open("a") as fh:
                    fh.write(json.dumps(row) + "\n")
            log.info(
                "trial %d %-10s ok=%s err %.3f m %.1f deg compute %.1f s robot %.1f s restarts %d",
                i,
                mode.value,
                ok,
                e_xy,
                math.degrees(e_th),
                compute,
                robot_s,
                res.restarts,
            )
    return rows


PAPER = {  # paper 2, Table 1 (DESIGN.md sec. 2): success %, localisation time s, cm, deg
    "grid_only": (68.0, 41.7, 13.4, 9.2),
    "no_ceiling": (82.0, 5.2, 12.6, 8.7),
    "proposed": (98.0, 10.4 + 12.3, 12.0, 8.4),
}


def table(rows: list[dict[str, object]], modes: list[Mode]) -> str:
    """The Markdown table: success, times (means; compute after the turn also median), errors.

    Errors are means over the successful trials (as the paper's); times and
    restarts over all trials.
    """
    lines = [
        "| configuration | trials | success | compute after turn (s), mean / median "
        "| compute total (s) | robot time (s) (turning) | localisation time (s) "
        "| position error (cm) | heading error (deg) | restarts | paper: success, time, error |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]

    def vals(key: str, sel: list[dict[str, object]]) -> np.ndarray:
        return np.array([float(x[key]) for x in sel])  # type: ignore[arg-type]

    def mean(key: str, sel: list[dict[str, object]]) -> float:
        v = vals(key, sel)
        return float(np.mean(v)) if len(v) else float("nan")

    for mode in modes:
        r = [x for x in rows if x["mode"] == mode.value]
        if not r:
            continue
        ok = [x for x in r if x["success"]]
        after = vals("compute_after_turn_s", r)
        paper = PAPER.get(mode.value)
        ptxt = (
            "-" if paper is None
            else f"{paper[0]:.0f} %, {paper[1]:.1f} s, {paper[2]:.1f} cm / {paper[3]:.1f} deg"
        )  # fmt: skip
        lines.append(
            f"| {mode.value} | {len(r)} | {100.0 * len(ok) / len(r):.0f} % ({len(ok)}/{len(r)}) "
            f"| {np.mean(after):.2f} / {np.median(after):.2f} "
            f"| {mean('compute_s', r):.1f} "
            f"| {mean('robot_s', r):.1f} ({mean('turn_s', r):.1f}) | {mean('total_s', r):.1f} "
            f"| {100 * mean('error_m', ok):.1f} | {mean('error_deg', ok):.1f} "
            f"| {mean('restarts', r):.2f} | {ptxt} |"
        )
    return "\n".join(lines)


def write_report(rows: list[dict[str, object]], modes: list[Mode], out: Path) -> str:
    """``OUT/trials.json``, ``OUT/table1.md`` and ``OUT/table1.png`` from the finished rows."""
    rows = sorted(rows, key=lambda x: (int(str(x["trial"])), str(x["mode"])))
    (out / "trials.json").write_text(json.dumps(rows, indent=1))
    md = table(rows, modes)
    (out / "table1.md").write_text(md + "\n")
    save_table1_figure(rows, [m.value for m in modes], out / "table1.png",
                       {k: v[0] for k, v in PAPER.items()})  # fmt: skip
    return md


def read_rows(out: Path) -> list[dict[str, object]]:
    """All rows of the per-worker line files ``OUT/trials.w*.jsonl`` (last one per pair wins)."""
    rows: dict[tuple[int, str], dict[str, object]] = {}
    for f in sorted(out.glob("trials.w*.jsonl")):
        for line in f.read_text().splitlines():
            if line.strip():
                r = json.loads(line)
                rows[(int(r["trial"]), str(r["mode"]))] = r
    return list(rows.values())


def main() -> None:
    """Command-line entry of the experiment."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--trials", type=int, default=50)
    ap.add_argument("--out", default="out/table1")
    ap.add_argument("--work", default="out/table1/work", help="cache of the mapping run and map")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--clearance", type=float, default=0.6, help="free space around start poses, m")
    ap.add_argument("--modes", default=",".join(m.value for m in Mode))
    ap.add_argument("--skip", type=int, default=0, help="skip the first trials (debugging)")
    ap.add_argument("--trials-list", default="",
                    help="comma-separated trial indices to run (same starts as a full run)")  # fmt: skip
    ap.add_argument("--jobs", type=int, default=1,
                    help="worker processes (trials interleaved: worker k runs i %% jobs == k)")  # fmt: skip
    ap.add_argument("--worker", type=int, default=-1, help=argparse.SUPPRESS)
    ap.add_argument("--report-only", action="store_true",
                    help="only rebuild the table and figure from OUT/trials.w*.jsonl")  # fmt: skip
    args = ap.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    modes = [Mode(m) for m in args.modes.split(",")]
    only = {int(v) for v in args.trials_list.split(",") if v.strip()} or None
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    if args.worker >= 0:
        run_trials(args.trials, Path(args.work), args.seed, args.clearance, modes, args.skip,
                   args.worker, args.jobs, out / f"trials.w{args.worker}.jsonl", only)  # fmt: skip
        return
    if not args.report_only:
        build_maps(Path(args.work), args.seed)  # once, before the workers share the cache
        if args.jobs <= 1:
            run_trials(args.trials, Path(args.work), args.seed, args.clearance, modes, args.skip,
                       0, 1, out / "trials.w0.jsonl", only)  # fmt: skip
        else:
            import os
            import subprocess
            import sys

            env = dict(os.environ, OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1")
            procs = []
            for k in range(args.jobs):
                cmd = [sys.executable, __file__, *sys.argv[1:], "--worker", str(k)]
                with (out / f"worker{k}.log").open("w") as fh:
                    procs.append(
                        subprocess.Popen(cmd, stdout=fh, stderr=subprocess.STDOUT, env=env)
                    )
            for p in procs:
                p.wait()
    md = write_report(read_rows(out), modes, out)
    print(md)


if __name__ == "__main__":
    main()
