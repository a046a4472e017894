"""CLI commands of global localization on environment maps (paper 2): ``kinect-sim``,
``build-map``, ``show-map``, ``localize`` and ``table1``.
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path
from typing import TYPE_CHECKING

from lampsam.commands._args import (
    add_force,
    add_rerun_option,
    config_path,
    log,
    nonneg_int,
    output_dir,
    output_file,
    positive,
    positive_int,
)
from lampsam.errors import LampsamError
from lampsam.interrupt import EXIT_INTERRUPTED

if TYPE_CHECKING:
    from lampsam.datasets.kinect_sim import KinectConfig


# --------------------------------------------------------------------------- kinect-sim, build-map, show-map
def _kinect_localization_run(args: argparse.Namespace, cfg: KinectConfig, out: Path) -> Path:
    import numpy as np

    from lampsam.datasets.localization_run import LocalizationDrive, simulate_localization_run

    start = None
    if args.localize_from != "random":
        try:
            start = np.array([float(v) for v in args.localize_from.split(",")])
            if len(start) != 3:
                raise ValueError("need three values")
        except ValueError as exc:
            raise LampsamError(f"--localize-from {args.localize_from!r}: X,Y,THETA or random ({exc})") from exc
    if args.rounds < 1:
        raise LampsamError(f"--rounds must be at least 1, got {args.rounds}")
    return simulate_localization_run(args.world, out, start, seed=args.seed, config=cfg,
                                     drive=LocalizationDrive(rounds=args.rounds), changed=args.changed)


def _cmd_kinect_sim(args: argparse.Namespace) -> int:
    import dataclasses

    from lampsam.config_loader import load_config
    from lampsam.datasets.kinect_sim import KinectConfig, simulate_kinect_run

    cfg = load_config(KinectConfig, config_path(args), table="kinect")
    given = {"width": args.width, "height": args.height, "rate_hz": args.rate}
    cfg = dataclasses.replace(cfg, **{k: v for k, v in given.items() if v is not None})
    if args.localize_from is not None:
        print(f"Kinect localization run written to {_kinect_localization_run(args, cfg, output_dir(args))}")
        return 0
    out = simulate_kinect_run(args.world, output_dir(args), seed=args.seed, config=cfg, duration=args.duration,
                              ceiling_images=args.ceiling)
    print(f"Kinect mapping run written to {out}")
    return 0


def add_kinect_sim(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("kinect-sim", help="simulate the zig-zag Kinect mapping drive of a world with scene3d")
    p.add_argument("world", help="built-in world name (office) or a world YAML file with a scene3d section")
    p.add_argument("--out", required=True, help="run directory to write (RGB-D frames in OUT/kinect)")
    p.add_argument("--seed", type=nonneg_int, default=0, help="random seed (default 0)")
    p.add_argument("--duration", type=positive, default=None, help="seconds to simulate (default: whole drive)")
    p.add_argument("--width", type=positive_int, default=None, help="image width (default 320; 640 for full Kinect)")
    p.add_argument("--height", type=positive_int, default=None, help="image height (default 240)")
    p.add_argument("--rate", type=positive, default=None, help="Kinect frame rate, Hz (default 3)")
    add_force(p)
    p.add_argument("--config", default=None,
                   help="TOML/YAML file with a [kinect] table (KinectConfig; the options above override it)")
    p.add_argument("--ceiling", action="store_true", help="also render the ceiling camera (the ceiling simulator)")
    p.add_argument("--localize-from", default=None, metavar="X,Y,THETA|random",
                   help="instead of the mapping drive: a global-localization run from this true start (m, m, rad) "
                        "or a random one: full turns in place, each followed by a drive (for `lampsam localize`)")
    p.add_argument("--rounds", type=positive_int, default=4,
                   help="with --localize-from: full turns, each followed by a drive (default 4: 3 restarts)")
    p.add_argument("--changed", action="store_true",
                   help="with --localize-from: apply the world's scene changes (moved furniture, as in Table 1)")
    p.set_defaults(func=_cmd_kinect_sim)


def _cmd_build_map(args: argparse.Namespace) -> int:
    import dataclasses

    from lampsam.config_loader import load_config
    from lampsam.localization.map_build import build_map
    from lampsam.localization.map_config import EnvMapConfig

    cfg = load_config(EnvMapConfig, config_path(args), table="envmap")
    if args.resolution is not None:
        cfg = dataclasses.replace(cfg, depth=dataclasses.replace(cfg.depth, resolution=args.resolution),
                                  laser=dataclasses.replace(cfg.laser, resolution=args.resolution))
    if args.feature_every is not None:
        cfg = dataclasses.replace(cfg, feature_every=args.feature_every)
    if args.no_tables:
        cfg = dataclasses.replace(cfg, tables=dataclasses.replace(
            cfg.tables, range_table=False, laser_range_table=False, distance_field=False))
    if not Path(args.run).exists():
        raise LampsamError(f"{args.run}: run not found")
    out = output_dir(args)
    from lampsam.evaluation.map_truth import floor_plan_of_run

    truth = floor_plan_of_run(Path(args.run), cfg.depth.height_band)
    report = build_map(Path(args.run), out, poses=args.poses, config=cfg, truth=truth, scans=args.scans)
    print(f"environment map written to {report.out} ({report.source}, {report.n_frames} frames, "
          f"{report.timings.get('total', 0.0):.1f} s)")
    for name, figures in report.checks.items():
        print(f"  {name}: {figures}")
    return 0


def add_build_map(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("build-map", help="build the environment map (grid, spatial and ceiling feature maps) of a run "
                       "or a CARMEN laser log, with the localizer's precomputed lookups")
    p.add_argument("run", help="run directory with kinect/, a TUM RGB-D or slambook2 folder, or a CARMEN log")
    p.add_argument("--out", required=True, help="map directory to write")
    p.add_argument("--poses", default="groundtruth",
                   help="mapping poses: 'groundtruth' (default) or 'slam:PATH_TO_TUM' (a SLAM trajectory)")
    p.add_argument("--resolution", type=positive, default=None, help="grid cell size, m (default 0.05 depth, 0.1 laser)")
    p.add_argument("--feature-every", type=positive_int, default=None, help="SIFT on every n-th frame (default 1)")
    p.add_argument("--scans", choices=("all", "even", "odd"), default="all",
                   help="laser logs: map from all, the even or the odd scans (the others left for localization)")
    p.add_argument("--no-tables", action="store_true",
                   help="do not precompute the localizer's range table and distance field")
    add_force(p)
    p.add_argument("--config", default=None,
                   help="TOML/YAML file with an [envmap] table ([envmap.depth], [envmap.laser], [envmap.tables], ...)")
    p.set_defaults(func=_cmd_build_map)


def _cmd_show_map(args: argparse.Namespace) -> int:
    from lampsam.evaluation.map_plots import show_map

    if not Path(args.map).is_dir():
        raise LampsamError(f"{args.map}: map directory not found")
    out = show_map(Path(args.map), output_file(args))
    print(f"map figure written to {out}")
    return 0


def add_show_map(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("show-map", help="draw an environment map's three layers in one figure")
    p.add_argument("map", help="map directory written by build-map")
    p.add_argument("--out", required=True, help="PNG file to write")
    add_force(p)
    p.set_defaults(func=_cmd_show_map)


# --------------------------------------------------------------------------- localize
def _warn_map_sensor(map_dir: Path, laser_log: bool) -> None:
    """Warn when ``map_dir`` was built from another sensor than the one localized.

    A laser log localized on a map from RGB-D depth (or a Kinect run on a laser map) runs,
    and fails on maps of different places the same way; this says why it may fail.
    """
    from lampsam.localization.map_store import MANIFEST_FILE

    manifest = map_dir / MANIFEST_FILE
    if not manifest.is_file():
        return  # load_env_map names a missing or bad manifest
    try:
        from lampsam.datasets.textio import read_yaml

        doc = read_yaml(manifest)
        sensor = str(doc["layers"]["grid"]["sensor"])
        source = doc.get("source", {}).get("path", "?")
    except (LampsamError, KeyError, TypeError, AttributeError):
        return
    if laser_log != (sensor == "planar laser"):
        log.warning("%s was built from %s (%s); localizing %s on it matches scans of one sensor "
                    "against the other's grid", map_dir, sensor, source,
                    "a laser log" if laser_log else "a run's Kinect scans")


def _localize_laser_log(args: argparse.Namespace) -> int:
    import dataclasses

    from lampsam.evaluation.laser_trials import LaserTrialsConfig, laser_trials, write_json

    if args.scans not in ("odd", "even", "all"):
        raise LampsamError(f"--scans must be odd, even or all, not {args.scans!r}")
    if args.trials < 1 or args.updates < 1:
        raise LampsamError("--trials and --updates must be at least 1")
    if not Path(args.run).is_file():
        raise LampsamError(f"{args.run}: CARMEN log not found")
    if not Path(args.map).is_dir():
        raise LampsamError(f"{args.map}: map directory not found")
    _warn_map_sensor(Path(args.map), laser_log=True)
    out = output_dir(args)
    cfg = dataclasses.replace(LaserTrialsConfig(), trials=args.trials, updates=args.updates,
                              seed=args.seed, scans=args.scans)
    result = laser_trials(Path(args.run), cfg, progress=args.verbose > 0, map_dir=Path(args.map))
    path = write_json(result, out / "result.json")
    s = result["summary"]
    assert isinstance(s, dict)
    if result["status"] == "interrupted":
        print(f"interrupted after {s['trials']} of {args.trials} trials: {s['localized']} "
              f"localized ({s['correct']} correct, {s['wrong_accepted']} wrong); the finished "
              f"trials are written to {path} (status interrupted)", file=sys.stderr)
        return EXIT_INTERRUPTED
    print(f"{s['trials']} trials: {s['localized']} localized ({s['correct']} correct, "
          f"{s['wrong_accepted']} wrong), {s['ambiguous']} ambiguous, {s['failed']} failed; "
          f"success rate {s['success_rate']:.2f}, compute {s['compute_s_mean']:.2f} s CPU per trial; {path}")
    return 0 if s["wrong_accepted"] == 0 else 1


def _cmd_localize(args: argparse.Namespace) -> int:
    import dataclasses

    if args.run.endswith((".log", ".log.gz")) or Path(args.run).is_file():
        return _localize_laser_log(args)  # a file: a CARMEN log, whatever its suffix (.clf ...)

    from lampsam.config_loader import load_config
    from lampsam.localization.filter_config import GlobalLocalizerConfig, Mode
    from lampsam.localization.replay import localize_run

    cfg = load_config(GlobalLocalizerConfig, config_path(args), table="localize")
    if args.mode is not None:
        cfg = dataclasses.replace(cfg, mode=Mode(args.mode))
    if not Path(args.run).is_dir():
        raise LampsamError(f"{args.run}: run directory not found")
    _warn_map_sensor(Path(args.map), laser_log=False)
    from lampsam.evaluation.live import live_view, rerun_target

    out = output_dir(args)
    target = rerun_target(args.rerun, out)
    run = None
    if target:
        from lampsam.datasets.logrun import read_run

        run = read_run(args.run)
    with live_view(target, f"localize {cfg.mode.value} {args.run}", run=run, kind="localize"):
        result = localize_run(Path(args.run), Path(args.map), out, cfg, seed=args.seed)
    x, y, th = result.pose
    print(f"{result.status} after {result.restarts} restart(s): x {x:.3f} m, y {y:.3f} m, "
          f"heading {math.degrees(th):.1f} deg; {out / 'result.json'}")
    return 0 if result.status == "localized" else 1


def add_localize(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("localize", help="global localization of a run on an environment map")
    p.add_argument("run", help="run directory with odometry, kinect/ and ceiling images, or a CARMEN log (.log, .log.gz)")
    p.add_argument("--map", required=True, help="environment map directory (build-map)")
    p.add_argument("--out", required=True, help="output directory for result.json")
    p.add_argument("--mode", default=None, choices=["grid_only", "no_ceiling", "proposed", "ours"],
                   help="configuration of the paper's Table 1, or ours (default: the config's "
                        "[localize] mode, else proposed)")
    p.add_argument("--seed", type=nonneg_int, default=0, help="seed of RANSAC and the particle filter (default 0)")
    add_force(p)
    p.add_argument("--config", default=None, help="TOML/YAML file with a [localize] table (nested tables too: "
                        "[localize.filter], [localize.verification], ...)")
    add_rerun_option(p)
    p.add_argument("--scans", default="odd", help="CARMEN log: scans the trials use: odd (default), even or all")
    p.add_argument("--trials", type=positive_int, default=50,
                   help="CARMEN log: trials from evenly spread scans (default 50)")
    p.add_argument("--updates", type=positive_int, default=4,
                   help="CARMEN log: scans before the first acceptance test (more follow while ambiguous; default 4)")
    p.set_defaults(func=_cmd_localize)


# --------------------------------------------------------------------------- table1
def _cmd_table1(args: argparse.Namespace) -> int:
    from lampsam.evaluation.table1 import run_table1
    from lampsam.localization.filter_config import Mode

    try:
        modes = [Mode(m.strip()) for m in args.modes.split(",") if m.strip()]
        only = {int(v) for v in args.trials_list.split(",") if v.strip()} or None
    except ValueError as exc:
        raise LampsamError(f"--modes / --trials-list: {exc}") from exc
    md = run_table1(Path(args.out), args.trials, Path(args.work) if args.work else None, args.seed,
                    args.clearance, modes, args.jobs, only, args.report_only)
    print(md)
    return 0


def add_table1(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("table1", help="paper 2's Table 1 on the simulated office (global localization trials)")
    p.add_argument("--out", required=True, help="output directory (trials, table1.md, table1.png); a rerun resumes")
    p.add_argument("--trials", type=positive_int, default=50, help="start poses (default 50)")
    p.add_argument("--work", default=None, help="cache of the mapping run and map (default OUT/work)")
    p.add_argument("--seed", type=nonneg_int, default=1, help="seed of the map, starts and noise (default 1)")
    p.add_argument("--clearance", type=positive, default=0.6, help="free space around start poses, m (default 0.6)")
    p.add_argument("--modes", default="grid_only,no_ceiling,proposed,ours", help="comma-separated configurations")
    p.add_argument("--trials-list", default="", help="comma-separated trial indices to run (same starts as a full run)")
    p.add_argument("--jobs", type=positive_int, default=1, help="worker processes (trial i goes to worker i %% jobs)")
    p.add_argument("--report-only", action="store_true", help="only rebuild the report from OUT/trials.w*.jsonl")
    p.set_defaults(func=_cmd_table1)
