"""The single command-line entry point: ``lampsam <subcommand> ...``.

Each subcommand is a thin wrapper over a library function that also works from
Python; heavy modules are imported inside the wrappers so ``lampsam --help``
stays fast. Only this module reads configuration files (TOML); it passes
config dataclasses down explicitly.

Exit codes: 0 success, 1 the job ran but failed (e.g. localization failed),
2 bad input or usage (a :class:`lampsam.errors.LampsamError` is printed, no
traceback).
"""

from __future__ import annotations

import argparse
import logging
import sys
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import tomllib

from lampsam.errors import LampsamError

if TYPE_CHECKING:
    from lampsam.backend.config import SlamConfig

log = logging.getLogger("lampsam")


def load_toml(path: Path | None) -> dict[str, Any]:
    """Read a TOML config file; an absent path gives an empty dict.

    Args:
        path: the file, or None.

    Returns:
        The parsed tables. Unknown keys are rejected by the dataclass that
        consumes each table.
    """
    if path is None:
        return {}
    try:
        with open(path, "rb") as fh:
            return tomllib.load(fh)
    except FileNotFoundError as exc:
        raise LampsamError(f"{path}: config file not found") from exc
    except tomllib.TOMLDecodeError as exc:
        raise LampsamError(f"{path}: invalid TOML: {exc}") from exc


# --------------------------------------------------------------------------- simulate
def _cmd_simulate(args: argparse.Namespace) -> int:
    from lampsam.datasets.simulator import simulate_world

    out = simulate_world(args.world, Path(args.out), seed=args.seed, duration=args.duration)
    print(f"run written to {out}")
    return 0


def _add_simulate(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("simulate", help="simulate a ceiling-camera run of a world")
    p.add_argument("world", help="built-in world name (lab, corridor, office) or a world YAML file")
    p.add_argument("--out", required=True, help="run directory to write")
    p.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    p.add_argument("--duration", type=float, default=None, help="seconds to simulate (default: whole path)")
    p.set_defaults(func=_cmd_simulate)


# --------------------------------------------------------------------------- demo
def _cmd_demo(args: argparse.Namespace) -> int:
    from lampsam.evaluation.compare import markdown_table
    from lampsam.evaluation.demo import run_demo

    result = run_demo(Path(args.out))
    print()
    print(markdown_table(result.rows))
    print()
    print(f"simulated run:      {result.run}")
    print(f"contact sheet:      {result.contact_sheet}")
    print(f"comparison report:  {result.report} (and report.html, summary.json, figures/)")
    print(f"per-backend output: {result.out / 'compare' / 'jobs'} (trajectory.tum, landmarks.csv, summary.json)")
    return 1 if any(r["failed"] for r in result.rows) else 0


def _add_demo(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("demo", help="the main job on the built-in default world")
    p.add_argument("--out", default="out/demo", help="output directory (default out/demo)")
    p.set_defaults(func=_cmd_demo)


# --------------------------------------------------------------------------- stereo
def _cmd_stereo_sim(args: argparse.Namespace) -> int:
    from lampsam.datasets.stereo_sim import simulate_stereo_run

    out = simulate_stereo_run(args.scenario, Path(args.out), seed=args.seed)
    print(f"stereo run written to {out}")
    return 0


def _add_stereo_sim(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("stereo-sim", help="simulate a stereo two-point run (paper 3)")
    p.add_argument("--scenario", required=True, choices=["straight", "turn"],
                   help="drive toward and past the target, or turn in place")
    p.add_argument("--out", required=True, help="run directory to write")
    p.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    p.set_defaults(func=_cmd_stereo_sim)


def _cmd_stereo(args: argparse.Namespace) -> int:
    from lampsam.evaluation.stereo_report import stereo_job

    summary = stereo_job(Path(args.run), args.estimator, Path(args.out))
    rms = summary.get("rms")
    line = f"{args.estimator}: {summary['status_counts']}"
    if rms:
        line += (f"; RMS x {rms['x_m']:.4f} m, y {rms['y_m']:.4f} m, "
                 f"heading {rms['heading_rad']:.5f} rad over {rms['frames']} frames")
    print(line)
    return 0


def _add_stereo(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("stereo", help="estimate the relative pose to a stereo target")
    p.add_argument("run", help="stereo run directory (from stereo-sim)")
    p.add_argument("--estimator", required=True, choices=["raw", "ekf", "isam2", "batch"],
                   help="raw triangulation, the paper's EKF, iSAM2 online, batch smoother")
    p.add_argument("--out", required=True, help="output directory")
    p.set_defaults(func=_cmd_stereo)


# --------------------------------------------------------------------------- kinect-sim, build-map, show-map
def _cmd_kinect_sim(args: argparse.Namespace) -> int:
    from lampsam.datasets.kinect_sim import KinectConfig, simulate_kinect_run

    cfg = KinectConfig(width=args.width, height=args.height, rate_hz=args.rate)
    out = simulate_kinect_run(args.world, Path(args.out), seed=args.seed, config=cfg, duration=args.duration,
                              ceiling_images=args.ceiling)
    print(f"Kinect mapping run written to {out}")
    return 0


def _add_kinect_sim(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("kinect-sim", help="simulate the zig-zag Kinect mapping drive of a world with scene3d")
    p.add_argument("world", help="built-in world name (office) or a world YAML file with a scene3d section")
    p.add_argument("--out", required=True, help="run directory to write (RGB-D frames in OUT/kinect)")
    p.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    p.add_argument("--duration", type=float, default=None, help="seconds to simulate (default: whole drive)")
    p.add_argument("--width", type=int, default=320, help="image width (default 320; 640 for full Kinect)")
    p.add_argument("--height", type=int, default=240, help="image height (default 240)")
    p.add_argument("--rate", type=float, default=3.0, help="Kinect frame rate, Hz (default 3)")
    p.add_argument("--ceiling", action="store_true", help="also render the ceiling camera (the ceiling simulator)")
    p.set_defaults(func=_cmd_kinect_sim)


def _cmd_build_map(args: argparse.Namespace) -> int:
    import dataclasses

    from lampsam.localization.envmap import EnvMapConfig, build_map

    cfg = EnvMapConfig()
    table = load_toml(Path(args.config) if args.config else None).get("envmap", {})
    try:
        cfg = dataclasses.replace(
            cfg,
            depth=dataclasses.replace(cfg.depth, **table.get("depth", {})),
            laser=dataclasses.replace(cfg.laser, **table.get("laser", {})),
            spatial=dataclasses.replace(cfg.spatial, **table.get("spatial", {})),
            **{k: v for k, v in table.items() if k not in ("depth", "laser", "spatial")},
        )
    except TypeError as exc:
        raise LampsamError(f"{args.config}: bad [envmap] table: {exc}") from exc
    if args.resolution is not None:
        cfg = dataclasses.replace(cfg, depth=dataclasses.replace(cfg.depth, resolution=args.resolution),
                                  laser=dataclasses.replace(cfg.laser, resolution=args.resolution))
    if args.feature_every is not None:
        cfg = dataclasses.replace(cfg, feature_every=args.feature_every)
    report = build_map(Path(args.run), Path(args.out), poses=args.poses, config=cfg)
    print(f"environment map written to {report.out} ({report.source}, {report.n_frames} frames, "
          f"{report.timings.get('total', 0.0):.1f} s)")
    for name, figures in report.checks.items():
        print(f"  {name}: {figures}")
    return 0


def _add_build_map(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("build-map", help="build the environment map (grid, spatial and ceiling feature maps) of a run")
    p.add_argument("run", help="run directory with kinect/, a TUM RGB-D or slambook2 folder, or a CARMEN log")
    p.add_argument("--out", required=True, help="map directory to write")
    p.add_argument("--poses", default="groundtruth",
                   help="mapping poses: 'groundtruth' (default) or 'slam:PATH_TO_TUM' (a SLAM trajectory)")
    p.add_argument("--resolution", type=float, default=None, help="grid cell size, m (default 0.05 depth, 0.1 laser)")
    p.add_argument("--feature-every", type=int, default=None, help="SIFT on every n-th frame (default 1)")
    p.add_argument("--config", default=None, help="TOML file with an [envmap] table ([envmap.depth], ...)")
    p.set_defaults(func=_cmd_build_map)


def _cmd_show_map(args: argparse.Namespace) -> int:
    from lampsam.evaluation.map_plots import show_map

    out = show_map(Path(args.map), Path(args.out))
    print(f"map figure written to {out}")
    return 0


def _add_show_map(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("show-map", help="draw an environment map's three layers in one figure")
    p.add_argument("map", help="map directory written by build-map")
    p.add_argument("--out", required=True, help="PNG file to write")
    p.set_defaults(func=_cmd_show_map)


# --------------------------------------------------------------------------- slam
def _cmd_slam(args: argparse.Namespace) -> int:
    import dataclasses

    from lampsam.backend.config import SlamConfig
    from lampsam.backend.slam import run_slam, summary
    from lampsam.evaluation.slam_report import write_slam_plot

    config = SlamConfig.from_dict(load_toml(Path(args.config) if args.config else None))
    if args.gate_only:
        config = dataclasses.replace(
            config, association=dataclasses.replace(config.association, use_known_ids=False))
    features = tuple(f.strip() for f in args.features.split(",") if f.strip())
    out = Path(args.out)
    if Path(args.run).is_file():
        return _slam_graph_text(args, config, out)
    if args.mrclam:
        from lampsam.datasets.mrclam import mrclam_run

        run = mrclam_run(Path(args.run), duration=args.duration)
    else:
        from lampsam.datasets.logrun import read_run

        run = read_run(args.run)
    result = run_slam(args.run, args.backend, features, out, config, frames=args.frames, run=run)
    write_slam_plot(out / "slam.png", result, run.groundtruth)
    s = summary(result, run.groundtruth)
    err = s.get("error")
    msg = f"{args.backend}: {s['steps']} steps, {s['keyframes']} keyframes, {s['landmarks']} landmarks"
    if err:
        msg += (f"; position error RMS {err['position_rms_m']:.3f} m, max {err['position_max_m']:.3f} m;"
                f" heading RMS {err['heading_rms_deg']:.2f} deg")
    print(msg + f"; written to {out}")
    return 0 if result.status == "ok" else 1


def _slam_graph_text(args: argparse.Namespace, config: SlamConfig, out: Path) -> int:
    """``lampsam slam FILE``: an iSAM / g2o text log, one step per pose."""
    import json

    import numpy as np

    from lampsam.backend.slam import run_graph_log, summary, write_landmarks, write_trajectory
    from lampsam.datasets.graph_text import read_graph_text, read_vertices
    from lampsam.datasets.logrun import Trajectory
    from lampsam.errors import DatasetError

    glog = read_graph_text(args.run)
    truth = None
    if args.truth:
        verts = read_vertices(args.truth)
        missing = [i for i in glog.pose_ids if i not in verts]
        if missing:
            raise DatasetError(f"no VERTEX for pose {missing[0]} ({len(missing)} missing)",
                               Path(args.truth))
        truth = Trajectory(t=glog.odometry.t.copy(),
                           poses=np.array([verts[i] for i in glog.pose_ids]))
    known = not args.gate_only
    result = run_graph_log(glog, args.backend, config, known_ids=known)
    out.mkdir(parents=True, exist_ok=True)
    write_trajectory(out / "trajectory.tum", result)
    write_landmarks(out / "landmarks.csv", result)
    s = summary(result, truth)
    s["input"] = {"file": str(glog.path), "poses": len(glog.pose_ids),
                  "landmarks_in_file": glog.n_landmarks, "known_ids": known,
                  "start_pose": ("the first pose's VERTEX" if glog.pose_ids[0] in glog.vertices
                                 else "the origin (no VERTEX for the first pose)"),
                  "skipped_non_odometry_edges": glog.n_skipped_edges}
    with open(out / "summary.json", "w") as fh:
        json.dump(s, fh, indent=2, default=float)
    msg = (f"{args.backend}: {s['steps']} steps (one per pose), {s['landmarks']} landmarks "
           f"(file: {glog.n_landmarks}), start pose {s['input']['start_pose']}")
    err = s.get("error")
    if err:
        msg += f"; position error RMS {err['position_rms_m']:.3f} m"
    print(msg + f"; written to {out}")
    return 0 if result.status == "ok" else 1


def _add_slam(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("slam", help="run EKF / iSAM2 / batch SLAM over a logged run")
    p.add_argument("run", help="run directory, an iSAM/g2o text log (.txt/.g2o/.graph: one "
                   "step per pose), or the mrclam_ds0 folder with --mrclam")
    p.add_argument("--backend", choices=("ekf", "isam2", "batch"), default="isam2",
                   help="estimator (default isam2)")
    p.add_argument("--features", default="lamps,corners",
                   help="ceiling features to use: lamps,corners (default both)")
    p.add_argument("--out", required=True, help="output directory")
    p.add_argument("--config", default=None, help="TOML config ([association], [ekf], [isam2], ...)")
    p.add_argument("--frames", choices=("auto", "images", "truth", "rangebearing"), default="auto",
                   help="measurement source (default auto: range-bearing log, else images)")
    p.add_argument("--gate-only", "--no-ids", action="store_true",
                   help="ignore known landmark ids: associate by the Mahalanobis gate alone")
    p.add_argument("--truth", default=None,
                   help="with a text log: a file of VERTEX2/VERTEX_SE2 true poses")
    p.add_argument("--mrclam", action="store_true", help="RUN is the MRCLAM ds0 folder")
    p.add_argument("--duration", type=float, default=None,
                   help="with --mrclam: use only the first seconds")
    p.set_defaults(func=_cmd_slam)


# --------------------------------------------------------------------------- compare
def _cmd_compare(args: argparse.Namespace) -> int:
    from lampsam.backend.config import SlamConfig
    from lampsam.evaluation.compare import compare, markdown_table

    backends = tuple(b.strip() for b in args.backends.split(",") if b.strip())
    features = tuple(f.strip() for f in args.features.split(",")) if args.features else None
    config = SlamConfig.from_dict(load_toml(Path(args.config) if args.config else None))
    rows = compare(args.runs, backends=backends, seeds=args.seeds, out=Path(args.out),
                   workers=args.workers, frames=args.frames, features=features,
                   duration=args.duration, progress=not args.no_progress, config=config)
    print(markdown_table(rows))
    print(f"report: {Path(args.out) / 'report.md'} (also report.html, summary.json, figures/)")
    return 1 if any(r["failed"] for r in rows) else 0


def _add_compare(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("compare", help="compare EKF against smoothing over runs and seeds")
    p.add_argument("runs", nargs="+", help="run directories, world names (simulated per seed), or mrclam / mrclam-gated")
    p.add_argument("--backends", default="ekf,isam2,batch", help="comma-separated (default ekf,isam2,batch)")
    p.add_argument("--seeds", type=int, default=1, help="Monte Carlo seeds per simulated world (default 1)")
    p.add_argument("--out", required=True, help="report directory")
    p.add_argument("--workers", type=int, default=2, help="parallel processes (default 2)")
    p.add_argument("--frames", default="auto", choices=["auto", "images", "truth"],
                   help="measurements: auto (frontend on images / range-bearing), images, truth projections")
    p.add_argument("--features", default=None, help="ceiling features, e.g. lamps,corners (default: backend config)")
    p.add_argument("--duration", type=float, default=None, help="seconds per simulated run (default whole path)")
    p.add_argument("--config", default=None,
                   help="TOML file with the SLAM settings of every job (as for `lampsam slam --config`)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=_cmd_compare)


# --------------------------------------------------------------------------- localize
def _cmd_localize(args: argparse.Namespace) -> int:
    import dataclasses

    from lampsam.localization.global_localizer import GlobalLocalizerConfig, Mode, localize_run

    table = load_toml(Path(args.config) if args.config else None).get("localize", {})
    try:
        cfg = dataclasses.replace(GlobalLocalizerConfig(), **table)
    except TypeError as exc:
        raise LampsamError(f"{args.config}: bad [localize] table: {exc}") from exc
    cfg = dataclasses.replace(cfg, mode=Mode(args.mode))
    result = localize_run(Path(args.run), Path(args.map), Path(args.out), cfg, seed=args.seed)
    x, y, th = result.pose
    print(f"localization {'succeeded' if result.success else 'FAILED'} after {result.restarts} "
          f"restart(s): x {x:.3f} m, y {y:.3f} m, theta {th:.3f} rad; {Path(args.out) / 'result.json'}")
    return 0 if result.success else 1


def _add_localize(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("localize", help="global localization of a run on an environment map")
    p.add_argument("run", help="run directory with odometry, kinect/ and ceiling images")
    p.add_argument("--map", required=True, help="environment map directory (build-map)")
    p.add_argument("--out", required=True, help="output directory for result.json")
    p.add_argument("--mode", default="proposed", choices=["grid_only", "no_ceiling", "proposed", "ours"],
                   help="configuration of the paper's Table 1, or ours (default proposed)")
    p.add_argument("--seed", type=int, default=0, help="seed of RANSAC and the particle filter (default 0)")
    p.add_argument("--config", default=None, help="TOML file with a [localize] table (scalar settings)")
    p.set_defaults(func=_cmd_localize)


# --------------------------------------------------------------------------- frontend-eval
def _cmd_frontend_eval(args: argparse.Namespace) -> int:
    from lampsam.evaluation.frontend_eval import evaluate_run

    res = evaluate_run(Path(args.run), out=args.out, max_frames=args.max_frames)
    print(res.summary())
    return 0 if all(res.targets_met.values()) else 1


def _add_frontend_eval(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "frontend-eval", help="measure the ceiling frontend against a simulated run's truth"
    )
    p.add_argument("run", help="simulated run directory (with truth/projections.csv)")
    p.add_argument("--out", default=None, help="JSON file (default RUN/frontend_eval.json)")
    p.add_argument("--max-frames", type=int, default=None, help="only the first N images")
    p.set_defaults(func=_cmd_frontend_eval)


# --------------------------------------------------------------------------- gallery
def _cmd_gallery(args: argparse.Namespace) -> int:
    from lampsam.evaluation.gallery import make_gallery

    entries = make_gallery(Path(args.photos), Path(args.out), full_size=not args.small_only)
    for e in entries:
        print(
            f"{e.name} {e.width}x{e.height}: {e.n_lamps} lamps ({e.n_oriented} oriented), "
            f"{e.n_border} at the border, {e.n_corners} corners, {e.time_ms:.1f} ms"
        )
    print(f"gallery written to {args.out}")
    return 0


def _add_gallery(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("gallery", help="ceiling frontend overlays on a folder of photos")
    p.add_argument("photos", help="folder of .jpg/.png ceiling photos")
    p.add_argument("--out", required=True, help="gallery PNG to write")
    p.add_argument("--small-only", action="store_true", help="only 320x240, not full size")
    p.set_defaults(func=_cmd_gallery)


_ADDERS: list[Callable[[argparse._SubParsersAction], None]] = [
    _add_simulate,
    _add_demo,
    _add_stereo_sim,
    _add_stereo,
    _add_kinect_sim,
    _add_build_map,
    _add_show_map,
    _add_slam,
    _add_compare,
    _add_localize,
    _add_frontend_eval,
    _add_gallery,
]


def build_parser() -> argparse.ArgumentParser:
    """The argument parser with every subcommand registered."""
    parser = argparse.ArgumentParser(prog="lampsam", description=__doc__.splitlines()[0])
    parser.add_argument("-v", "--verbose", action="count", default=0, help="more logging (-v, -vv)")
    sub = parser.add_subparsers(dest="command", required=True, metavar="SUBCOMMAND")
    for add in _ADDERS:
        add(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Run the CLI; returns the process exit code."""
    parser = build_parser()
    args = parser.parse_args(argv)
    level = [logging.WARNING, logging.INFO, logging.DEBUG][min(args.verbose, 2)]
    logging.basicConfig(level=level, format="%(levelname)s %(name)s: %(message)s")
    try:
        return int(args.func(args))
    except LampsamError as exc:
        print(f"lampsam {args.command}: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    raise SystemExit(main())
