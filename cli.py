"""The single command-line entry point: ``lampsam <subcommand> ...``.

Each subcommand is a thin wrapper over a library function that also works from
Python; heavy modules are imported inside the wrappers so ``lampsam --help``
stays fast. Only this module reads configuration files (TOML or YAML, through
the strict loader :func:`lampsam.config_loader.load_config`: unknown keys,
wrong types and values out of range are errors naming the file and the dotted
key); it passes config dataclasses down explicitly.

Exit codes: 0 success, 1 the job ran but failed (e.g. localization failed, or the
final optimisation failed and the online estimate was written), 2 bad input or
usage (a :class:`lampsam.errors.LampsamError` is printed, no traceback; checked
before any computing, including the ``--out`` path), 3 interrupted by SIGINT or
SIGTERM (finished work written with status ``interrupted``; ``docs/failures.md``).
"""

from __future__ import annotations

import argparse
import logging
import math
import re
import sys
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from lampsam.errors import LampsamError
from lampsam.interrupt import EXIT_FAILED, EXIT_INTERRUPTED, EXIT_USAGE, stop_requested
from lampsam.safe_io import atomic_path, check_output_file

if TYPE_CHECKING:
    from lampsam.backend.config import SlamConfig
    from lampsam.backend.interface import SlamResult
    from lampsam.datasets.kinect_sim import KinectConfig
    from lampsam.datasets.logrun import LoggedRun

log = logging.getLogger("lampsam")


def _config_path(args: argparse.Namespace) -> Path | None:
    """The ``--config`` file of a command, or None."""
    value = getattr(args, "config", None)
    return Path(value) if value else None


def _positive(text: str) -> float:
    """argparse type: a finite number > 0."""
    try:
        value = float(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(f"not a number: {text!r}") from exc
    if not (math.isfinite(value) and value > 0):
        raise argparse.ArgumentTypeError(f"must be a positive number, got {text}")
    return value


def _positive_int(text: str) -> int:
    """argparse type: an integer >= 1."""
    try:
        value = int(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(f"not an integer: {text!r}") from exc
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be at least 1, got {text}")
    return value


def _nonneg_int(text: str) -> int:
    """argparse type: an integer >= 0."""
    try:
        value = int(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(f"not an integer: {text!r}") from exc
    if value < 0:
        raise argparse.ArgumentTypeError(f"must be >= 0, got {text}")
    return value


def _add_force(p: argparse.ArgumentParser) -> None:
    p.add_argument("--force", action="store_true",
                   help="write into a non-empty output directory / over an existing file")


def _out_dir(args: argparse.Namespace, allow_resume: bool = False) -> Path:
    """``--out`` checked (and created) before any computing; see :mod:`lampsam.safe_io`."""
    from lampsam.safe_io import check_output_dir

    allow = (lambda _p: True) if allow_resume and getattr(args, "resume", False) else None
    return check_output_dir(args.out, force=args.force, what="--out", allow=allow)


def _out_file(args: argparse.Namespace) -> Path:
    """``--out`` (a file) checked before any computing."""
    from lampsam.safe_io import check_output_file

    return check_output_file(args.out, force=args.force, what="--out")


# --------------------------------------------------------------------------- simulate
def _cmd_simulate(args: argparse.Namespace) -> int:
    from lampsam.datasets.simulator import simulate_world
    from lampsam.datasets.world import load_world

    world = load_world(args.world)  # bad world: an error before the output is touched
    out = simulate_world(world, _out_dir(args), seed=args.seed, duration=args.duration,
                         png_compression=args.png_compression)
    import yaml

    meta = yaml.safe_load((out / "meta.yaml").read_text(encoding="utf-8")) or {}
    simulated = float(meta.get("duration", 0.0))
    if args.duration is not None and args.duration > simulated + 0.1:
        log.warning("--duration %s s is longer than the world's path: simulated %.1f s "
                    "(the whole path)", _num(args.duration), simulated)
    print(f"run written to {out} ({simulated:.1f} s, {meta.get('n_images', '?')} images)")
    return 0


def _add_simulate(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("simulate", help="simulate a ceiling-camera run of a world")
    p.add_argument("world", help="built-in world name (lab, corridor, office) or a world YAML file")
    p.add_argument("--out", required=True, help="run directory to write")
    p.add_argument("--seed", type=_nonneg_int, default=0, help="random seed (default 0)")
    p.add_argument("--duration", type=_positive, default=None,
                   help="seconds to simulate (default: whole path; longer than the path: a warning)")
    p.add_argument("--png-compression", type=int, choices=range(10), default=0, metavar="0-9",
                   help="zlib level of the images (default 0: stored, 5x faster to decode, "
                        "twice the disk; the pixels are the same at every level)")
    _add_force(p)
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
    if result.recording is not None:
        print(f"live recording:     {result.recording} (open with: rerun {result.recording})")
    return 1 if any(r["failed"] for r in result.rows) else 0


def _add_demo(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("demo", help="the main job on the built-in default world")
    p.add_argument("--out", default="out/demo", help="output directory (default out/demo)")
    p.set_defaults(func=_cmd_demo)


# --------------------------------------------------------------------------- stereo
def _cmd_stereo_sim(args: argparse.Namespace) -> int:
    from lampsam.datasets.stereo_sim import simulate_stereo_run

    out = simulate_stereo_run(args.scenario, _out_dir(args), seed=args.seed)
    print(f"stereo run written to {out}")
    return 0


def _add_stereo_sim(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("stereo-sim", help="simulate a stereo two-point run (paper 3)")
    p.add_argument("--scenario", required=True, choices=["straight", "turn"],
                   help="drive toward and past the target, or turn in place")
    p.add_argument("--out", required=True, help="run directory to write")
    p.add_argument("--seed", type=_nonneg_int, default=0, help="random seed (default 0)")
    _add_force(p)
    p.set_defaults(func=_cmd_stereo_sim)


def _cmd_stereo(args: argparse.Namespace) -> int:
    from lampsam.backend.stereo import StereoEstimatorConfig
    from lampsam.config_loader import load_config
    from lampsam.datasets.stereo_sim import read_stereo_run
    from lampsam.evaluation.live import live_view, rerun_target
    from lampsam.evaluation.stereo_report import stereo_job, summary_table

    cfg = load_config(StereoEstimatorConfig, _config_path(args), table="stereo")
    run = read_stereo_run(Path(args.run))
    for name in ("baseline", "focal_length", "pixel_pitch"):
        value = getattr(run.rig, name)
        if not (math.isfinite(value) and value > 0):
            raise LampsamError(f"{Path(args.run) / 'stereo_run.yaml'}: rig.{name}: must be a "
                               f"positive number, got {_num(value)}")
    out = _out_dir(args)
    target = rerun_target(args.rerun, out)
    with live_view(target, f"stereo {args.estimator} {args.run}",
                   stereo_truth=run.truth if target else None, kind="stereo"):
        summary = stereo_job(Path(args.run), args.estimator, out, cfg)
    counts = summary["status_counts"]
    if not any(n for status, n in counts.items() if status == "ok"):
        log.warning("no frame gave a measurement the %s estimator could use (%s): the "
                    "estimate is empty", args.estimator, counts)
        print(f"{args.estimator}: {counts}; no usable frame", file=sys.stderr)
        return 1
    print(summary_table(summary))
    print(f"written to {out} (estimate.tum, status.csv, summary.json, errors.png)")
    return 0


def _add_stereo(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("stereo", help="estimate the relative pose to a stereo target")
    p.add_argument("run", help="stereo run directory (from stereo-sim)")
    p.add_argument("--estimator", required=True, choices=["raw", "ekf", "isam2", "batch"],
                   help="raw triangulation, the paper's EKF, iSAM2 online, batch smoother")
    p.add_argument("--out", required=True, help="output directory")
    p.add_argument("--config", default=None,
                   help="TOML/YAML file with a [stereo] table (StereoEstimatorConfig)")
    _add_force(p)
    p.add_argument("--rerun", nargs="?", const="", default=None, metavar="FILE.rrd|ADDRESS",
                   help="stream the run to Rerun: save FILE.rrd, or send to a viewer at ADDRESS "
                        "(host:port); bare: OUT/live.rrd (needs lampsam[viz])")
    p.set_defaults(func=_cmd_stereo)


def _cmd_stereo_experiment(args: argparse.Namespace) -> int:
    from lampsam.datasets.paths import shared_dataset
    from lampsam.evaluation.stereo_experiment import stereo_experiment

    kitti = None if args.no_kitti else shared_dataset("kitti_stereo_seq1")
    if kitti is None and not args.no_kitti:
        log.warning("shared dataset kitti_stereo_seq1 not found (set LAMPSAM_DATA): "
                    "the KITTI check is skipped")
    print(stereo_experiment(Path(args.out), args.seeds, kitti))
    return 0


def _add_stereo_experiment(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("stereo-experiment",
                       help="paper 3's experiment: seeds x scenarios x estimators, and KITTI")
    p.add_argument("--out", required=True, help="output directory (stereo_rms.md/.json, figures)")
    p.add_argument("--seeds", type=int, default=20, help="seeds per scenario (default 20)")
    p.add_argument("--no-kitti", action="store_true", help="skip the KITTI real-data check")
    p.set_defaults(func=_cmd_stereo_experiment)


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

    cfg = load_config(KinectConfig, _config_path(args), table="kinect")
    given = {"width": args.width, "height": args.height, "rate_hz": args.rate}
    cfg = dataclasses.replace(cfg, **{k: v for k, v in given.items() if v is not None})
    if args.localize_from is not None:
        print(f"Kinect localization run written to {_kinect_localization_run(args, cfg, _out_dir(args))}")
        return 0
    out = simulate_kinect_run(args.world, _out_dir(args), seed=args.seed, config=cfg, duration=args.duration,
                              ceiling_images=args.ceiling)
    print(f"Kinect mapping run written to {out}")
    return 0


def _add_kinect_sim(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("kinect-sim", help="simulate the zig-zag Kinect mapping drive of a world with scene3d")
    p.add_argument("world", help="built-in world name (office) or a world YAML file with a scene3d section")
    p.add_argument("--out", required=True, help="run directory to write (RGB-D frames in OUT/kinect)")
    p.add_argument("--seed", type=_nonneg_int, default=0, help="random seed (default 0)")
    p.add_argument("--duration", type=_positive, default=None, help="seconds to simulate (default: whole drive)")
    p.add_argument("--width", type=_positive_int, default=None, help="image width (default 320; 640 for full Kinect)")
    p.add_argument("--height", type=_positive_int, default=None, help="image height (default 240)")
    p.add_argument("--rate", type=_positive, default=None, help="Kinect frame rate, Hz (default 3)")
    _add_force(p)
    p.add_argument("--config", default=None,
                   help="TOML/YAML file with a [kinect] table (KinectConfig; the options above override it)")
    p.add_argument("--ceiling", action="store_true", help="also render the ceiling camera (the ceiling simulator)")
    p.add_argument("--localize-from", default=None, metavar="X,Y,THETA|random",
                   help="instead of the mapping drive: a global-localization run from this true start (m, m, rad) "
                        "or a random one: full turns in place, each followed by a drive (for `lampsam localize`)")
    p.add_argument("--rounds", type=int, default=4,
                   help="with --localize-from: full turns, each followed by a drive (default 4: 3 restarts)")
    p.add_argument("--changed", action="store_true",
                   help="with --localize-from: apply the world's scene changes (moved furniture, as in Table 1)")
    p.set_defaults(func=_cmd_kinect_sim)


def _cmd_build_map(args: argparse.Namespace) -> int:
    import dataclasses

    from lampsam.config_loader import load_config
    from lampsam.localization.map_build import build_map
    from lampsam.localization.map_config import EnvMapConfig

    cfg = load_config(EnvMapConfig, _config_path(args), table="envmap")
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
    out = _out_dir(args)
    from lampsam.evaluation.map_truth import floor_plan_of_run

    truth = floor_plan_of_run(Path(args.run), cfg.depth.height_band)
    report = build_map(Path(args.run), out, poses=args.poses, config=cfg, truth=truth, scans=args.scans)
    print(f"environment map written to {report.out} ({report.source}, {report.n_frames} frames, "
          f"{report.timings.get('total', 0.0):.1f} s)")
    for name, figures in report.checks.items():
        print(f"  {name}: {figures}")
    return 0


def _add_build_map(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("build-map", help="build the environment map (grid, spatial and ceiling feature maps) of a run "
                       "or a CARMEN laser log, with the localizer's precomputed lookups")
    p.add_argument("run", help="run directory with kinect/, a TUM RGB-D or slambook2 folder, or a CARMEN log")
    p.add_argument("--out", required=True, help="map directory to write")
    p.add_argument("--poses", default="groundtruth",
                   help="mapping poses: 'groundtruth' (default) or 'slam:PATH_TO_TUM' (a SLAM trajectory)")
    p.add_argument("--resolution", type=_positive, default=None, help="grid cell size, m (default 0.05 depth, 0.1 laser)")
    p.add_argument("--feature-every", type=_positive_int, default=None, help="SIFT on every n-th frame (default 1)")
    p.add_argument("--scans", choices=("all", "even", "odd"), default="all",
                   help="laser logs: map from all, the even or the odd scans (the others left for localization)")
    p.add_argument("--no-tables", action="store_true",
                   help="do not precompute the localizer's range table and distance field")
    _add_force(p)
    p.add_argument("--config", default=None,
                   help="TOML/YAML file with an [envmap] table ([envmap.depth], [envmap.laser], [envmap.tables], ...)")
    p.set_defaults(func=_cmd_build_map)


def _cmd_show_map(args: argparse.Namespace) -> int:
    from lampsam.evaluation.map_plots import show_map

    if not Path(args.map).is_dir():
        raise LampsamError(f"{args.map}: map directory not found")
    out = show_map(Path(args.map), _out_file(args))
    print(f"map figure written to {out}")
    return 0


def _add_show_map(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("show-map", help="draw an environment map's three layers in one figure")
    p.add_argument("map", help="map directory written by build-map")
    p.add_argument("--out", required=True, help="PNG file to write")
    _add_force(p)
    p.set_defaults(func=_cmd_show_map)


# --------------------------------------------------------------------------- slam
def _cmd_slam(args: argparse.Namespace) -> int:
    import dataclasses

    from lampsam.backend.config import SlamConfig
    from lampsam.backend.slam import run_slam
    from lampsam.config_loader import load_config

    config = load_config(SlamConfig, _config_path(args))
    if args.gate_only:
        config = dataclasses.replace(
            config, association=dataclasses.replace(config.association, use_known_ids=False))
    features = tuple(f.strip() for f in args.features.split(",") if f.strip())
    if args.g2o:
        check_output_file(args.g2o, force=args.force, what="--g2o")
        if args.backend == "ekf" and Path(args.run).is_file():
            raise LampsamError("--g2o with the EKF needs a run directory (its odometry gives the "
                               "factors); use --backend isam2 or batch for a text log")
    _check_map_flags(args)
    if Path(args.run).is_file():
        return _slam_graph_text(args, config, _out_dir(args))
    if args.duration is not None and not args.mrclam:
        raise LampsamError("--duration applies only with --mrclam (a logged run is used whole)")
    if args.mrclam:
        from lampsam.datasets.mrclam import mrclam_run

        run = mrclam_run(Path(args.run), duration=args.duration)
    else:
        from lampsam.datasets.logrun import read_run

        run = read_run(args.run)
        _warn_partial(run.meta, Path(args.run))
    out = _out_dir(args)
    if args.localize_only:
        return _slam_localize_only(args, config, features, run, out)
    if args.save_map:
        from lampsam.safe_io import check_output_dir

        check_output_dir(args.save_map, force=args.force, what="--save-map")
    from lampsam.backend.localize_run import BackendCapture
    from lampsam.evaluation.live import live_view, rerun_target
    from lampsam.observe import observing

    with live_view(rerun_target(args.rerun, out), f"slam {args.backend} {args.run}", run=run) as view:
        capture = BackendCapture(view)
        with observing(capture if args.save_map else None):
            result = run_slam(args.run, args.backend, features, out, config, frames=args.frames,
                              run=run, frontend=args.frontend)
    if args.save_map and result.status == "ok":
        from lampsam.backend.localize_run import save_map

        cmap = save_map(args.save_map, result, run, capture.backend)
        print(f"ceiling map written to {args.save_map}: {len(cmap.by_kind('lamp'))} lamps, "
              f"{len(cmap.by_kind('corner'))} corners")
    elif args.save_map:
        print(f"{args.backend}: {result.status}: no map written to {args.save_map}", file=sys.stderr)
    if args.g2o:
        from lampsam.backend.g2o_export import write_result_g2o

        g2o = write_result_g2o(Path(args.g2o), result, run)
        print(f"g2o graph written to {args.g2o}: {g2o.text()}")
    if result.status == "interrupted":
        print(f"{args.backend}: interrupted after {len(result.times)} steps; the finished steps "
              f"are written to {out} (status interrupted)", file=sys.stderr)
        return EXIT_INTERRUPTED
    s = _plot_and_summarize(out, result, run)
    print(f"{args.backend}: {s['steps']} steps, {s['keyframes']} keyframes, {s['landmarks']} "
          f"landmarks ({s['landmarks_pruned']} pruned){_error_text(s)}; written to {out}")
    if result.status != "ok":
        print(f"{args.backend}: {result.status}; the {result.backend} estimate is written "
              f"to {out}", file=sys.stderr)
        return 1
    return 0


def _plot_and_summarize(out: Path, result: SlamResult, run: LoggedRun) -> dict[str, Any]:
    """Write ``out/slam.png`` (path, map, error over time) and return the run's summary."""
    from lampsam.backend.slam import summary
    from lampsam.evaluation.slam_report import write_slam_plot

    with atomic_path(out / "slam.png") as tmp:
        write_slam_plot(tmp, result, run.groundtruth)
    return summary(result, run.groundtruth)


def _error_text(s: dict[str, Any]) -> str:
    """``"; position error RMS .., max ..; heading RMS .."`` of a summary, or "" without truth."""
    err = s.get("error")
    if not err:
        return ""
    return (f"; position error RMS {err['position_rms_m']:.3f} m, max {err['position_max_m']:.3f} m;"
            f" heading RMS {err['heading_rms_deg']:.2f} deg")


def _check_map_flags(args: argparse.Namespace) -> None:
    """``--save-map`` / ``--map`` / ``--localize-only`` / ``--start*``: only sensible combinations."""
    if args.localize_only and not args.map:
        raise LampsamError("--localize-only needs --map MAP (a folder written by --save-map)")
    if args.map and not args.localize_only:
        raise LampsamError("--map is used with --localize-only (SLAM that extends a map is not "
                           "implemented)")
    if args.localize_only and args.save_map:
        raise LampsamError("--save-map and --localize-only exclude each other: localize-only "
                           "does not change the map")
    if args.map_priors and not args.localize_only:
        raise LampsamError("--map-priors applies only with --localize-only")
    if (args.start or args.start_from) and not args.localize_only:
        raise LampsamError("--start / --start-from apply only with --localize-only")
    if args.start and args.start_from:
        raise LampsamError("give --start or --start-from, not both")
    if (args.map or args.save_map) and (Path(args.run).is_file() or args.mrclam):
        raise LampsamError("--save-map / --map are for ceiling runs (a run directory)")


def _slam_localize_only(args: argparse.Namespace, config: SlamConfig, features: tuple[str, ...],
                        run: LoggedRun, out: Path) -> int:
    """``lampsam slam RUN --map MAP --localize-only``: track the run on the fixed map."""
    import dataclasses

    from lampsam.backend.ceiling_map_io import read_map
    from lampsam.backend.localize_only import LocalizeConfig
    from lampsam.backend.localize_run import parse_start, run_localize_only, start_from_result
    from lampsam.backend.map_merge import merge_maps

    cmap = read_map(args.map[0])  # a bad map: an error before any computing
    for more in args.map[1:]:
        cmap, counts = merge_maps(cmap, read_map(more))
        print(f"merged {more}: {counts['fused']} landmarks fused, {counts['only_b']} added, "
              f"{counts['only_a']} kept alone")
    start = (parse_start(args.start) if args.start
             else start_from_result(args.start_from) if args.start_from else None)
    if features:
        config = dataclasses.replace(config, features=features)
    result = run_localize_only(run, cmap, out, config, frames=args.frames, start=start,
                               loc=LocalizeConfig(map_mode="priors" if args.map_priors else "fixed"))
    s = _plot_and_summarize(out, result, run)
    print(f"localize-only: {s['steps']} steps, {int(result.extra['observations_used'])} "
          f"observations of {len(cmap.landmarks)} map landmarks used, none added"
          f"{_error_text(s)}; written to {out}")
    return 0 if result.status == "ok" else (EXIT_INTERRUPTED if result.status == "interrupted" else 1)


def _slam_graph_text(args: argparse.Namespace, config: SlamConfig, out: Path) -> int:
    """``lampsam slam FILE``: an iSAM / g2o text log, one step per pose."""
    import numpy as np

    from lampsam.backend.slam import run_graph_log, summary, write_landmarks, write_trajectory
    from lampsam.datasets.graph_text import read_graph_text, read_vertices
    from lampsam.datasets.logrun import Trajectory
    from lampsam.errors import DatasetError
    from lampsam.safe_io import write_json_atomic

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
    with atomic_path(out / "trajectory.tum") as tmp:
        write_trajectory(tmp, result)
    with atomic_path(out / "landmarks.csv") as tmp:
        write_landmarks(tmp, result)
    s = summary(result, truth)
    s["input"] = {"file": str(glog.path), "poses": len(glog.pose_ids),
                  "landmarks_in_file": glog.n_landmarks, "known_ids": known,
                  "start_pose": ("the first pose's VERTEX" if glog.pose_ids[0] in glog.vertices
                                 else "the origin (no VERTEX for the first pose)"),
                  "skipped_non_odometry_edges": glog.n_skipped_edges}
    write_json_atomic(out / "summary.json", s)
    if args.g2o:
        from lampsam.backend.g2o_export import write_result_g2o

        print(f"g2o graph written to {args.g2o}: "
              f"{write_result_g2o(Path(args.g2o), result, None).text()}")
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
    p.add_argument("--config", default=None, help="TOML/YAML config ([association], [ekf], [isam2], ...)")
    p.add_argument("--frames", choices=("auto", "images", "truth", "rangebearing"), default="auto",
                   help="measurement source (default auto: range-bearing log, else images)")
    p.add_argument("--frontend", choices=("sequential", "thread", "process"), default="sequential",
                   help="images: run the frontend when each frame is due (default), or ahead of "
                        "the estimator in a worker process / thread (same frames; a process uses "
                        "a second core: docs/frontend-speed.md)")
    p.add_argument("--gate-only", "--no-ids", action="store_true",
                   help="ignore known landmark ids: associate by the Mahalanobis gate alone")
    p.add_argument("--truth", default=None,
                   help="with a text log: a file of VERTEX2/VERTEX_SE2 true poses")
    p.add_argument("--mrclam", action="store_true", help="RUN is the MRCLAM ds0 folder")
    p.add_argument("--g2o", default=None, metavar="OUT.g2o",
                   help="also write the final graph as g2o: poses, landmarks and every factor "
                        "(custom LAMPSAM_* lines for the ceiling model; backend/g2o_export.py)")
    p.add_argument("--duration", type=_positive, default=None,
                   help="with --mrclam: use only the first seconds (an error without --mrclam)")
    p.add_argument("--rerun", nargs="?", const="", default=None, metavar="FILE.rrd|ADDRESS",
                   help="stream the run to Rerun: save FILE.rrd, or send to a viewer at ADDRESS "
                        "(host:port); bare: OUT/live.rrd (needs lampsam[viz])")
    p.add_argument("--save-map", default=None, metavar="MAP",
                   help="also write the ceiling map (landmarks, covariances, lamp axes, corner "
                        "patches, rig) to the folder MAP (docs/ceiling-map.md)")
    p.add_argument("--map", default=None, metavar="MAP", action="append",
                   help="with --localize-only: the ceiling map folder to track against; given "
                        "twice or more, the maps of separate mapping drives are merged "
                        "(backend/map_merge.py)")
    p.add_argument("--map-priors", action="store_true",
                   help="with --localize-only: the map's landmarks are priors updated during "
                        "the run (joint EKF over pose and map landmarks), not fixed values")
    p.add_argument("--localize-only", action="store_true",
                   help="track the run against --map without adding landmarks (pose-only EKF)")
    p.add_argument("--start", default=None, metavar="X,Y,THETA",
                   help="with --localize-only: start pose in the map's frame (m, m, rad; "
                        "default the run's known start)")
    p.add_argument("--start-from", default=None, metavar="RESULT.json",
                   help="with --localize-only: start from a `lampsam localize` answer")
    _add_force(p)
    p.set_defaults(func=_cmd_slam, graceful=True)


# --------------------------------------------------------------------------- compare
def _cmd_compare(args: argparse.Namespace) -> int:
    from lampsam.backend.config import SlamConfig
    from lampsam.config_loader import load_config
    from lampsam.evaluation.compare import compare, markdown_table

    backends = tuple(b.strip() for b in args.backends.split(",") if b.strip())
    features = tuple(f.strip() for f in args.features.split(",")) if args.features else None
    config = load_config(SlamConfig, _config_path(args))
    out = _out_dir(args, allow_resume=True)
    rows = compare(args.runs, backends=backends, seeds=args.seeds, out=out,
                   workers=args.workers, frames=args.frames, features=features,
                   duration=args.duration, progress=not args.no_progress, config=config,
                   resume=args.resume, dask=args.dask)
    print(markdown_table(rows))
    print(f"report: {out / 'report.md'} (also report.html, summary.json, figures/)")
    if stop_requested() is not None:
        print("compare: interrupted; the report covers the finished jobs "
              "(rerun with --resume to run the others)", file=sys.stderr)
        return EXIT_INTERRUPTED
    return 1 if any(r["failed"] for r in rows) else 0


def _add_compare(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("compare", help="compare EKF against smoothing over runs and seeds")
    p.add_argument("runs", nargs="+", help="run directories, world names (simulated per seed), or mrclam / mrclam-gated")
    p.add_argument("--backends", default="ekf,isam2,batch", help="comma-separated (default ekf,isam2,batch)")
    p.add_argument("--seeds", type=_positive_int, default=1, help="Monte Carlo seeds per simulated world (default 1)")
    p.add_argument("--out", required=True, help="report directory")
    p.add_argument("--workers", type=_positive_int, default=2, help="parallel processes (default 2)")
    p.add_argument("--frames", default="auto", choices=["auto", "images", "truth"],
                   help="measurements: auto (frontend on images / range-bearing), images, truth projections")
    p.add_argument("--features", default=None, help="ceiling features, e.g. lamps,corners (default: backend config)")
    p.add_argument("--duration", type=_positive, default=None, help="seconds per simulated run (default whole path)")
    p.add_argument("--config", default=None,
                   help="TOML/YAML file with the SLAM settings of every job (as for `lampsam slam --config`)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument("--resume", action="store_true",
                   help="continue an earlier compare into the same --out: skip its finished jobs")
    _add_force(p)
    _add_dask_option(p)
    p.set_defaults(func=_cmd_compare, graceful=True)


def _add_dask_option(p: argparse.ArgumentParser) -> None:
    p.add_argument("--dask", default=None, metavar="ADDRESS",
                   help="run the jobs on a Dask distributed scheduler (e.g. tcp://10.0.0.5:8786; "
                        "workers need lampsam and the same paths) or 'local' (a LocalCluster "
                        "with --workers processes); default: a local process pool")


# --------------------------------------------------------------------------- batch
def _cmd_batch(args: argparse.Namespace) -> int:
    from lampsam.backend.config import SlamConfig
    from lampsam.config_loader import load_config
    from lampsam.evaluation.batch import batch, markdown_table

    features = tuple(f.strip() for f in args.features.split(",")) if args.features else None
    config = load_config(SlamConfig, _config_path(args))
    rows = batch(args.runs, Path(args.out), backend=args.backend, workers=args.workers,
                 dask=args.dask, progress=not args.no_progress, config=config,
                 frames=args.frames, features=features)
    print(markdown_table(rows))
    print(f"summary: {Path(args.out) / 'summary.json'} (and summary.csv); one folder per run")
    if stop_requested() is not None:
        return EXIT_INTERRUPTED
    return 1 if any(r["status"] != "ok" for r in rows) else 0


def _add_batch(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("batch", help="offline optimisation of many logs: one result folder each")
    p.add_argument("runs", nargs="+", help="run directories")
    p.add_argument("--out", required=True, help="output directory (one folder per run + summary)")
    p.add_argument("--backend", choices=("batch", "isam2", "ekf"), default="batch",
                   help="estimator (default batch: Levenberg-Marquardt over the whole log)")
    p.add_argument("--workers", type=int, default=2, help="parallel processes (default 2)")
    p.add_argument("--frames", default="auto", choices=["auto", "images", "truth", "rangebearing"],
                   help="measurement source (default auto)")
    p.add_argument("--features", default=None, help="ceiling features, e.g. lamps,corners")
    p.add_argument("--config", default=None,
                   help="TOML/YAML file with the SLAM settings of every run (as for `lampsam slam --config`)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    _add_dask_option(p)
    p.set_defaults(func=_cmd_batch, graceful=True)


# --------------------------------------------------------------------------- localize
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
    out = _out_dir(args)
    cfg = dataclasses.replace(LaserTrialsConfig(), trials=args.trials, updates=args.updates,
                              seed=args.seed, scans=args.scans)
    result = laser_trials(Path(args.run), cfg, progress=args.verbose > 0, map_dir=Path(args.map))
    path = write_json(result, out / "result.json")
    s = result["summary"]
    assert isinstance(s, dict)
    print(f"{s['trials']} trials: {s['localized']} localized ({s['correct']} correct, "
          f"{s['wrong_accepted']} wrong), {s['ambiguous']} ambiguous, {s['failed']} failed; "
          f"success rate {s['success_rate']:.2f}, compute {s['compute_s_mean']:.2f} s CPU per trial; {path}")
    return 0 if s["wrong_accepted"] == 0 else 1


def _cmd_localize(args: argparse.Namespace) -> int:
    import dataclasses

    if args.run.endswith((".log", ".log.gz")):
        return _localize_laser_log(args)

    from lampsam.config_loader import load_config
    from lampsam.localization.filter_config import GlobalLocalizerConfig, Mode
    from lampsam.localization.replay import localize_run

    cfg = load_config(GlobalLocalizerConfig, _config_path(args), table="localize")
    if args.mode is not None:
        cfg = dataclasses.replace(cfg, mode=Mode(args.mode))
    if not Path(args.run).is_dir():
        raise LampsamError(f"{args.run}: run directory not found")
    from lampsam.evaluation.live import live_view, rerun_target

    out = _out_dir(args)
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


def _add_localize(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("localize", help="global localization of a run on an environment map")
    p.add_argument("run", help="run directory with odometry, kinect/ and ceiling images, or a CARMEN log (.log, .log.gz)")
    p.add_argument("--map", required=True, help="environment map directory (build-map)")
    p.add_argument("--out", required=True, help="output directory for result.json")
    p.add_argument("--mode", default=None, choices=["grid_only", "no_ceiling", "proposed", "ours"],
                   help="configuration of the paper's Table 1, or ours (default: the config's "
                        "[localize] mode, else proposed)")
    p.add_argument("--seed", type=_nonneg_int, default=0, help="seed of RANSAC and the particle filter (default 0)")
    _add_force(p)
    p.add_argument("--config", default=None, help="TOML/YAML file with a [localize] table (nested tables too: "
                        "[localize.filter], [localize.verification], ...)")
    p.add_argument("--rerun", nargs="?", const="", default=None, metavar="FILE.rrd|ADDRESS",
                   help="stream the run to Rerun: save FILE.rrd, or send to a viewer at ADDRESS "
                        "(host:port); bare: OUT/live.rrd (needs lampsam[viz])")
    p.add_argument("--scans", default="odd", help="CARMEN log: scans the trials use: odd (default), even or all")
    p.add_argument("--trials", type=int, default=50, help="CARMEN log: trials from evenly spread scans (default 50)")
    p.add_argument("--updates", type=int, default=4,
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


def _add_table1(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("table1", help="paper 2's Table 1 on the simulated office (global localization trials)")
    p.add_argument("--out", required=True, help="output directory (trials, table1.md, table1.png); a rerun resumes")
    p.add_argument("--trials", type=int, default=50, help="start poses (default 50)")
    p.add_argument("--work", default=None, help="cache of the mapping run and map (default OUT/work)")
    p.add_argument("--seed", type=int, default=1, help="seed of the map, starts and noise (default 1)")
    p.add_argument("--clearance", type=float, default=0.6, help="free space around start poses, m (default 0.6)")
    p.add_argument("--modes", default="grid_only,no_ceiling,proposed,ours", help="comma-separated configurations")
    p.add_argument("--trials-list", default="", help="comma-separated trial indices to run (same starts as a full run)")
    p.add_argument("--jobs", type=int, default=1, help="worker processes (trial i goes to worker i %% jobs)")
    p.add_argument("--report-only", action="store_true", help="only rebuild the report from OUT/trials.w*.jsonl")
    p.set_defaults(func=_cmd_table1)


# --------------------------------------------------------------------------- frontend-eval
def _cmd_frontend_eval(args: argparse.Namespace) -> int:
    from lampsam.config_loader import load_config
    from lampsam.frontend.pipeline import FrontendConfig

    photos = args.photos is not None or args.labels is not None
    if (photos and (args.photos is None or args.labels is None or args.run is not None)) or (
        not photos and args.run is None
    ):
        raise LampsamError("frontend-eval: give RUN, or both --photos DIR and --labels FILE")
    cfg = load_config(FrontendConfig, _config_path(args), table="frontend")
    if photos:
        from lampsam.evaluation.photo_eval import (
            PhotoEvalSettings,
            evaluate_photos,
            format_table,
            write_scores,
        )

        settings = PhotoEvalSettings(width=args.width)
        out_file = _out_file(args) if args.out is not None else None
        scores = evaluate_photos(Path(args.photos), Path(args.labels), settings, cfg.lamps)
        print(format_table(scores))
        if out_file is not None:
            write_scores(scores, out_file, settings)
        return 0
    from lampsam.evaluation.frontend_eval import evaluate_run

    if not Path(args.run).is_dir():
        raise LampsamError(f"{args.run}: run directory not found")
    out = _out_file(args) if args.out is not None else None
    res = evaluate_run(
        Path(args.run), out=out, config=cfg, max_frames=args.max_frames, lamp_models=args.lamp_models
    )
    print(res.summary())
    return 0 if all(res.targets_met.values()) else 1


def _add_frontend_eval(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "frontend-eval",
        help="measure the ceiling frontend against a simulated run's truth or labelled photos",
    )
    p.add_argument("run", nargs="?", default=None,
                   help="simulated run directory (with truth/projections.csv)")
    p.add_argument("--photos", default=None, help="folder of real ceiling photos")
    p.add_argument("--labels", default=None,
                   help="label file of those photos (tests/data/ceiling_photo_labels.json)")
    p.add_argument("--width", type=int, default=320,
                   help="photos: working image width in px (default 320)")
    p.add_argument("--out", default=None,
                   help="JSON file (default RUN/frontend_eval.json; photos: none)")
    p.add_argument("--max-frames", type=int, default=None, help="only the first N images")
    p.add_argument("--lamp-models", action="store_true",
                   help="RUN: reject blobs whose size and shape fit none of the run's lamps")
    _add_force(p)
    p.add_argument("--config", default=None,
                   help="TOML/YAML file with a [frontend] table ([frontend.lamps], [frontend.corners])")
    p.set_defaults(func=_cmd_frontend_eval)


# --------------------------------------------------------------------------- gallery
def _cmd_gallery(args: argparse.Namespace) -> int:
    from lampsam.evaluation.gallery import make_gallery

    if not Path(args.photos).is_dir():
        raise LampsamError(f"{args.photos}: photo folder not found")
    entries = make_gallery(Path(args.photos), _out_file(args), full_size=not args.small_only)
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
    _add_force(p)
    p.set_defaults(func=_cmd_gallery)


# --------------------------------------------------------------------------- ROS bags
def _cmd_import_bag(args: argparse.Namespace) -> int:
    from lampsam.datasets.rosbag_import import ImportOptions, import_bag
    from lampsam.errors import DatasetError

    topics: dict[str, str] = {}
    for item in args.topic:
        kind, sep, name = item.partition("=")
        if not sep or not kind or not name:
            raise DatasetError(f"--topic expects KIND=NAME, got {item!r}")
        topics[kind.strip()] = name.strip()
    joints = None
    if args.wheel_joints:
        names = [j.strip() for j in args.wheel_joints.split(",")]
        if len(names) != 2 or not all(names):
            raise DatasetError(f"--wheel-joints expects LEFT,RIGHT, got {args.wheel_joints!r}")
        joints = (names[0], names[1])
    opts = ImportOptions(
        topics=topics, wheel_joints=joints, wheel_radius=args.wheel_radius,
        wheel_base=args.wheel_base, k_wheel=args.k_wheel,
        rig=Path(args.rig) if args.rig else None, base_frame=args.base_frame,
    )  # fmt: skip
    report = import_bag(Path(args.bag), Path(args.out), opts)
    for line in report.lines():
        print(line)
    print(f"logged run written to {args.out}")
    return 0


def _add_import_bag(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("import-bag", help="ROS1 .bag / ROS2 bag -> logged run (docs/log-format.md)")
    p.add_argument("bag", help="ROS1 .bag file, or ROS2 bag directory (or its .db3 / .mcap file)")
    p.add_argument("--out", required=True, help="run directory to write")
    p.add_argument("--topic", action="append", default=[], metavar="KIND=NAME",
                   help="use topic NAME for KIND (joints, odometry, image, camera_info, tf_static, "
                        "depth, scan, groundtruth, rig); NAME 'none' skips the kind; repeatable")
    p.add_argument("--wheel-joints", default=None, metavar="L,R",
                   help="odometry from sensor_msgs/JointState: the left and right wheel joints")
    p.add_argument("--wheel-radius", type=float, default=None, help="wheel radius, m (with --wheel-joints)")
    p.add_argument("--wheel-base", type=float, default=None, help="distance between the wheels, m")
    p.add_argument("--k-wheel", type=float, default=None, help="wheel slip constant k_r = k_l, m")
    p.add_argument("--rig", default=None, help="rig.yaml to use instead of the bag's camera_info / tf")
    p.add_argument("--base-frame", default="base_link", help="robot body frame in tf (default base_link)")
    p.set_defaults(func=_cmd_import_bag)


def _cmd_export_bag(args: argparse.Namespace) -> int:
    from lampsam.datasets.rosbag_export import export_bag

    summary = export_bag(Path(args.run), Path(args.out), ros1=args.ros1, compressed=args.compressed,
                         wheel_radius=args.wheel_radius, mcap=args.mcap)  # fmt: skip
    for topic, n in summary.counts.items():
        print(f"{topic}: {n} messages")
    print(f"bag written to {summary.path}")
    return 0


def _add_export_bag(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("export-bag", help="logged run -> ROS1 .bag or ROS2 bag")
    p.add_argument("run", help="run directory")
    p.add_argument("--out", required=True, help="ROS1: the .bag file; ROS2: the bag directory")
    ver = p.add_mutually_exclusive_group()
    ver.add_argument("--ros1", action="store_true", help="ROS1 (Noetic) .bag")
    ver.add_argument("--ros2", action="store_true", help="ROS2 (Humble) bag (the default)")
    p.add_argument("--mcap", action="store_true", help="ROS2 storage MCAP instead of SQLite (.db3)")
    p.add_argument("--compressed", action="store_true",
                   help="images as sensor_msgs/CompressedImage (the run's PNG files)")
    p.add_argument("--wheel-radius", type=float, default=0.05,
                   help="wheel radius for the joint angles, m (default 0.05)")
    p.set_defaults(func=_cmd_export_bag)


_ADDERS: list[Callable[[argparse._SubParsersAction], None]] = [
    _add_simulate,
    _add_demo,
    _add_stereo_sim,
    _add_stereo,
    _add_stereo_experiment,
    _add_kinect_sim,
    _add_build_map,
    _add_show_map,
    _add_slam,
    _add_compare,
    _add_batch,
    _add_localize,
    _add_table1,
    _add_frontend_eval,
    _add_gallery,
    _add_import_bag,
    _add_export_bag,
]


def build_parser() -> argparse.ArgumentParser:
    """The argument parser with every subcommand registered."""
    parser = argparse.ArgumentParser(prog="lampsam", description=__doc__.splitlines()[0])
    parser.add_argument("-v", "--verbose", action="count", default=0, help="more logging (-v, -vv)")
    parser.add_argument("--cv-threads", type=int, default=1, metavar="N",
                        help="OpenCV threads (default 1: the frontend's images are too small for "
                             "OpenCV's pool to pay, +6 %% CPU with 2; 0 keeps OpenCV's default)")
    sub = parser.add_subparsers(dest="command", required=True, metavar="SUBCOMMAND")
    for add in _ADDERS:
        add(sub)
    return parser


def _num(value: object) -> str:
    """A number as a user reads it (never ``np.float64(...)``)."""
    from lampsam.config_loader import plain

    return plain(value)


_NUMPY_SCALAR = re.compile(r"np\.(?:float|int|uint|bool_?)\d*\(([^()]*)\)")


def _plain_text(message: str) -> str:
    """A message with numpy scalar reprs (``np.float64(5.0)``) shown as plain numbers."""
    return _NUMPY_SCALAR.sub(r"\1", message)


def _warn_partial(meta: dict[str, object], run: Path) -> None:
    """Warn when a run's ``meta.yaml`` says it is partial (``complete: false``)."""
    if meta.get("complete") is False:
        log.warning("%s is a partial run (complete: false in meta.yaml: the simulation was "
                    "interrupted): only its finished frames are used, and after the last "
                    "image the estimate is dead reckoning", run)


def main(argv: Sequence[str] | None = None) -> int:
    """Run the CLI; returns the process exit code (:mod:`lampsam.interrupt` lists them).

    SIGINT and SIGTERM are handled alike: ``slam`` and ``compare`` finish the
    current step and write what is finished (status ``interrupted``); the other
    commands stop at once and write nothing half-finished (their outputs are
    written at the end, atomically). Either way the exit code is 3.
    """
    from lampsam.interrupt import stop_on_signals

    parser = build_parser()
    args = parser.parse_args(argv)
    level = [logging.WARNING, logging.INFO, logging.DEBUG][min(args.verbose, 2)]
    logging.basicConfig(level=level, format="%(levelname)s %(name)s: %(message)s")
    if args.cv_threads > 0:  # process-wide OpenCV state: set once, here, not in the library
        import cv2

        cv2.setNumThreads(args.cv_threads)
    with stop_on_signals(graceful=getattr(args, "graceful", False)):
        try:
            return int(args.func(args))
        except KeyboardInterrupt as exc:
            print(f"lampsam {args.command}: interrupted ({exc or 'SIGINT'}); "
                  "see docs/failures.md for what was written", file=sys.stderr)
            return EXIT_INTERRUPTED
        except LampsamError as exc:
            print(f"lampsam {args.command}: error: {_plain_text(str(exc))}", file=sys.stderr)
            return EXIT_USAGE
        except OSError as exc:  # the file system refused (disk full, permissions...)
            where = f"{exc.filename}: " if exc.filename else ""
            print(f"lampsam {args.command}: error: {where}{exc.strerror or exc}", file=sys.stderr)
            return EXIT_USAGE
        except Exception as exc:  # a defect: one line, the traceback with -vv
            log.debug("traceback", exc_info=True)
            print(f"lampsam {args.command}: internal error: {type(exc).__name__}: {exc} "
                  "(a defect; run with -vv for the traceback)", file=sys.stderr)
            return EXIT_FAILED


if __name__ == "__main__":
    raise SystemExit(main())
