"""CLI command ``slam``: EKF / iSAM2 / batch over a logged run, an iSAM/g2o text log or
MRCLAM, with ``--save-map`` and ``--localize-only`` on a ceiling map.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any

from lampsam.commands._args import (
    add_force,
    add_rerun_option,
    config_path,
    log,
    output_dir,
    positive,
    warn_partial,
)
from lampsam.errors import LampsamError
from lampsam.interrupt import EXIT_INTERRUPTED
from lampsam.safe_io import atomic_path, check_output_file

if TYPE_CHECKING:
    from lampsam.backend.config import SlamConfig
    from lampsam.backend.interface import SlamResult
    from lampsam.datasets.logrun import LoggedRun


# --------------------------------------------------------------------------- slam
def _cmd_slam(args: argparse.Namespace) -> int:
    import dataclasses

    from lampsam.backend.config import SlamConfig
    from lampsam.backend.slam import run_slam
    from lampsam.config_loader import load_config

    config = load_config(SlamConfig, config_path(args))
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
    if args.online == "decoupled" and (Path(args.run).is_file() or args.mrclam or args.g2o
                                       or args.save_map or args.localize_only
                                       or args.rerun is not None):
        raise LampsamError("--online decoupled is for a run directory with wheel odometry, "
                           "without --g2o / --save-map / --localize-only / --rerun")
    if args.max_lag is not None and args.online != "decoupled":
        raise LampsamError("--max-lag applies only with --online decoupled")
    if Path(args.run).is_file():
        return _slam_graph_text(args, config, output_dir(args))
    if args.duration is not None and not args.mrclam:
        raise LampsamError("--duration applies only with --mrclam (a logged run is used whole)")
    if args.robot is not None and not args.mrclam:
        raise LampsamError("--robot applies only with --mrclam")
    if args.mrclam:
        from lampsam.datasets.mrclam import mrclam_run

        run = (mrclam_run(Path(args.run), duration=args.duration) if args.robot is None else
               mrclam_run(Path(args.run), duration=args.duration, robot=args.robot))
    else:
        from lampsam.datasets.logrun import read_run

        run = read_run(args.run)
        warn_partial(run.meta, Path(args.run))
    out = output_dir(args)
    if args.localize_only:
        return _slam_localize_only(args, config, features, run, out)
    if args.online == "decoupled":
        return _slam_decoupled(args, config, features, run, out)
    if args.save_map:
        from lampsam.safe_io import check_output_dir

        if run.images is None or args.frames == "rangebearing" or (
                args.frames == "auto" and run.range_bearing is not None):
            raise LampsamError(f"--save-map writes a ceiling map (lamps, corners) from the "
                               f"run's images; {args.run} is used through its range-bearing "
                               "measurements, so the map would be empty (the landmarks are in "
                               "OUT/landmarks.csv)")
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

        cmap = save_map(args.save_map, result, run, capture.backend,
                        check=not args.no_map_check)
        print(f"ceiling map written to {args.save_map}: {len(cmap.by_kind('lamp'))} lamps, "
              f"{len(cmap.by_kind('corner'))} corners")
    elif args.save_map:
        print(f"{args.backend}: {result.status}: no map written to {args.save_map}", file=sys.stderr)
    if args.g2o:
        from lampsam.backend.g2o_export import write_result_g2o

        g2o = write_result_g2o(Path(args.g2o), result, run)
        print(f"g2o graph written to {args.g2o}: {g2o.text()}")
    return _report_run(args.backend, args.backend, result, run, out)


def _report_run(backend: str, label: str, result: SlamResult, run: LoggedRun, out: Path) -> int:
    """The end of a ``slam`` run on a run directory: where a stopped run's finished steps
    are (exit 3), else ``slam.png`` and the one-line summary as ``label``, and the status
    when it is not ok (exit 1)."""
    if result.status == "interrupted":
        print(f"{backend}: interrupted after {len(result.times)} steps; the finished steps are "
              f"written to {out} (status interrupted)", file=sys.stderr)
        return EXIT_INTERRUPTED
    s = _plot_and_summarize(out, result, run)
    print(f"{label}: {s['steps']} steps, {s['keyframes']} keyframes, {s['landmarks']} "
          f"landmarks ({s['landmarks_pruned']} pruned){_damped_text(result)}{_error_text(s)}; "
          f"written to {out}")
    if result.status != "ok":
        print(f"{backend}: {result.status}; the {result.backend} estimate is written "
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


def _damped_text(result: SlamResult) -> str:
    """``"; N diverging iSAM2 step(s) damped ..."`` when the smoother damped any
    (``extra["n_damped_rebuilds"]``, :meth:`~lampsam.backend.isam2_update.Isam2Updates._damp_divergence`),
    else ""."""
    n = int(result.extra.get("n_damped_rebuilds", 0))
    if not n:
        return ""
    return (f"; {n} diverging iSAM2 step{'s' if n > 1 else ''} damped (Levenberg-Marquardt "
            "solve, then dogleg steps)")


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
    if (args.map_priors or args.map_mode) and not args.localize_only:
        raise LampsamError("--map-priors / --map-mode apply only with --localize-only")
    if args.map_priors and args.map_mode not in (None, "priors"):
        raise LampsamError(f"--map-priors contradicts --map-mode {args.map_mode}")
    if args.release is not None and not args.localize_only:
        raise LampsamError("--release / --no-release apply only with --localize-only")
    if (args.start or args.start_from) and not args.localize_only:
        raise LampsamError("--start / --start-from apply only with --localize-only")
    if args.start and args.start_from:
        raise LampsamError("give --start or --start-from, not both")
    if args.no_map_check and not args.save_map:
        raise LampsamError("--no-map-check applies only with --save-map")
    if (args.map or args.save_map) and (Path(args.run).is_file() or args.mrclam):
        raise LampsamError("--save-map / --map are for ceiling runs (a run directory)")


def _slam_localize_only(args: argparse.Namespace, config: SlamConfig, features: tuple[str, ...],
                        run: LoggedRun, out: Path) -> int:
    """``lampsam slam RUN --map MAP --localize-only``: track the run on the fixed map."""
    import dataclasses

    from lampsam.backend.ceiling_map_io import read_map
    from lampsam.backend.localize_only import LocalizeConfig
    from lampsam.backend.localize_run import parse_start, run_localize_only, start_from_result
    from lampsam.backend.map_merge import merge_all
    from lampsam.backend.map_smoother import MapSmootherConfig

    maps = [read_map(p) for p in args.map]  # a bad map: an error before any computing
    cmap = maps[0]
    if len(maps) > 1:
        cmap, counts = merge_all(maps)
        print(f"merged {len(maps)} maps jointly: {counts['fused']} landmarks fused, "
              f"{counts['alone']} in one map only; scale per map (ppm): "
              + ", ".join(f"{1e6 * s[3]:+.0f}" for s in counts["similarity"]))
    start = (parse_start(args.start) if args.start
             else start_from_result(args.start_from) if args.start_from else None)
    if features:
        config = dataclasses.replace(config, features=features)
    smooth = args.map_mode == "smooth"
    result = run_localize_only(run, cmap, out, config, frames=args.frames, start=start,
                               loc=LocalizeConfig(map_mode="priors" if smooth
                                                  else args.map_mode or "priors",
                                                  **({} if args.release is None
                                                     else {"release": args.release})),
                               smooth=MapSmootherConfig() if smooth else None)
    s = _plot_and_summarize(out, result, run)
    print(f"localize-only: {s['steps']} steps, {int(result.extra['observations_used'])} "
          f"observations of {len(cmap.landmarks)} map landmarks used, none added"
          f"{_error_text(s)}; written to {out}")
    return 0 if result.status == "ok" else (EXIT_INTERRUPTED if result.status == "interrupted" else 1)


def _slam_decoupled(args: argparse.Namespace, config: SlamConfig, features: tuple[str, ...],
                    run: LoggedRun, out: Path) -> int:
    """``lampsam slam RUN --online decoupled``: tracked poses here, the backend in a worker."""
    import dataclasses

    from lampsam.backend.online_run import DEFAULT_MAX_LAG, run_slam_decoupled

    if features:
        config = dataclasses.replace(config, features=features)
    lag = DEFAULT_MAX_LAG if args.max_lag is None else (None if args.max_lag < 0 else args.max_lag)
    result, _ = run_slam_decoupled(run, args.backend, out, config, frames=args.frames,
                                   frontend=args.frontend, max_lag=lag)
    e = result.extra
    print(f"tracked poses: latency median / p95 {e['online_tracked_latency_ms_median']:.1f} / "
          f"{e['online_tracked_latency_ms_p95']:.1f} ms; keyframe updates: latency median / p95 "
          f"{e['online_keyframe_latency_ms_median']:.1f} / "
          f"{e['online_keyframe_latency_ms_p95']:.1f} ms; {e['online_x_real_time']:.1f}x real "
          f"time; tracked.tum beside trajectory.tum")
    return _report_run(args.backend, f"{args.backend} (decoupled)", result, run, out)


def _slam_graph_text(args: argparse.Namespace, config: SlamConfig, out: Path) -> int:
    """``lampsam slam FILE``: an iSAM / g2o text log, one step per pose."""
    import numpy as np

    from lampsam.backend.graph_log import run_graph_log
    from lampsam.backend.pose_graph import closure_summary
    from lampsam.backend.slam import summary, write_landmarks, write_trajectory
    from lampsam.datasets.graph_text import read_graph_text, read_vertices
    from lampsam.datasets.logrun import Trajectory
    from lampsam.errors import DatasetError
    from lampsam.safe_io import write_json_atomic

    glog = read_graph_text(args.run)
    no_landmarks = None
    if glog.n_landmarks == 0 and not glog.closures:
        no_landmarks = ("no landmark sightings and no loop closures: the trajectory is the "
                        "odometry chained (dead reckoning)")
        log.warning("%s: %s", glog.path, no_landmarks)
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
    offline = not known and args.backend in ("ekf", "batch") and config.reassociation.passes > 0
    try_final = (not known and not offline and config.reassociation.online_final
                 and glog.n_landmarks > 0)
    online = None  # the online run, when a final solve of its association is the result
    picker: dict[str, Any] | None = None  # the candidates, with [reassociation] online_candidates
    if offline:  # the EKF's no-ids pass at each [reassociation] scales, re-associated in batch
        from lampsam.backend.noids_offline import run_offline

        result = run_offline(glog, config)
    elif try_final:  # each online candidate's association re-solved in batch at the stated noise
        from lampsam.backend.online_final import run_online_picker

        result, online, cands, chosen = run_online_picker(glog, args.backend, config)
        if config.reassociation.online_candidates:
            picker = {"chosen": cands[chosen].name,
                      "rule": ("least C plus label entropy at each candidate's noise scale "
                               "(picker_cost)" if config.reassociation.online_label_entropy
                               else "least C") + " of the final solves (candidates that did "
                              "not finish one lose)",
                      "candidates": [c.row() for c in cands]}
    else:
        result = run_graph_log(glog, args.backend, config, known_ids=known)
    write_trajectory(out / "trajectory.tum", result)
    write_landmarks(out / "landmarks.csv", result)
    if online is not None:
        write_trajectory(out / "online.tum", online)
    s = summary(result, truth)
    if online is not None:
        s["backend"] = args.backend  # the online run's; the written answer is the batch's
        s["final_solve"] = result.backend
        s["trajectory"] = {
            "trajectory.tum": "the final solve: the online run's association re-solved in "
                              "batch at the log's stated noise ([reassociation] online_final)",
            "online.tum": f"the poses of the online {args.backend} run as it made them"}
        if truth is not None:
            s["online_error"] = summary(online, truth).get("error")
    if picker is not None:
        s["online_picker"] = picker
    s["input"] = {"file": str(glog.path), "poses": len(glog.pose_ids),
                  "landmarks_in_file": glog.n_landmarks, "known_ids": known,
                  "start_pose": ("the first pose's VERTEX" if glog.pose_ids[0] in glog.vertices
                                 else "the origin (no VERTEX for the first pose)"),
                  **closure_summary(glog, result, args.backend, config, known)}
    if no_landmarks:
        s["input"]["warning"] = no_landmarks
    # unused loop closures (EKF, no ids) were warned by backend/graph_log.py as the run
    # started; summary.json keeps the reason as input.closures_warning
    write_json_atomic(out / "summary.json", s)
    if args.g2o:
        from lampsam.backend.g2o_export import write_result_g2o

        print(f"g2o graph written to {args.g2o}: "
              f"{write_result_g2o(Path(args.g2o), result, None).text()}")
    msg = (f"{args.backend}: {s['steps']} steps (one per pose), {s['landmarks']} landmarks "
           f"(file: {glog.n_landmarks}), start pose {s['input']['start_pose']}")
    if offline:
        msg += (f"; no ids offline: EKF pass with odometry variance x{s['noids_scale']:g} (chosen "
                f"of {', '.join(f'{q:g}' for q in config.reassociation.scales)}), "
                f"{int(s['reassociation_passes'])} batch re-association passes")
    if picker is not None:
        rows = picker["candidates"]
        by = "picker cost" if config.reassociation.online_label_entropy else "C"
        msg += ("; online candidates: " + ", ".join(
            f"{r['name']} " + (f"C {r['C']:.1f}" + (f" cost {r['picker_cost']:.1f}"
                                                     if r["picker_cost"] is not None else "")
                               if r["status"] == "ok" else f"({r['status'][:40]})")
            for r in rows) + f"; chosen {picker['chosen']} (least {by})")
    if online is not None:
        msg += (f"; final solve of the online {args.backend} run's association at the stated "
                f"noise ({int(s['reassociation_passes'])} re-association passes, "
                f"{int(s['noids_merges'])} merges, {int(s['noids_splits'])} splits, "
                f"{int(s['noids_sighting_moves'])} sighting moves; online: "
                f"{len(online.landmarks)} landmarks, poses in online.tum)")
        if s.get("noids_stopped_by_budget"):
            msg += ("; the final solve was STOPPED by its CPU budget ([reassociation] "
                    "final_solve_cpu_per_sighting): the answer is the last state it finished")
    elif not known and not offline and config.reassociation.online_final:
        msg += "; no final solve (the online run did not finish or mapped nothing, or it failed)"
    if result.extra.get("n_held"):
        msg += (f"; {int(result.extra['n_held'])} sightings held as ambiguous, "
                f"{int(result.extra['n_held_unused'])} of them never used online")
    if result.extra.get("noids_held_placed"):
        msg += (f"; {int(result.extra['noids_held_placed'])} left-out sightings placed in the "
                "final solve (max-mixture)")
    if glog.closures:
        msg += (f"; {s['input']['loop_closures_used']} of {len(glog.closures)} loop closures used")
    msg += _damped_text(result)
    err = s.get("error")
    if err:
        msg += f"; position error RMS {err['position_rms_m']:.3f} m"
    print(msg + f"; written to {out}")
    return 0 if result.status == "ok" else 1


def add_slam(sub: argparse._SubParsersAction) -> None:
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
    p.add_argument("--online", choices=("sequential", "decoupled"), default="sequential",
                   help="sequential: each frame's pose is the backend's (default); decoupled: "
                        "the backend in a worker process, each frame's pose at once from its "
                        "newest estimate plus odometry, also written to tracked.tum "
                        "(docs/speed.md)")
    p.add_argument("--max-lag", type=int, default=None, metavar="STEPS",
                   help="with --online decoupled: wait for the backend when the tracked pose "
                        "runs this many steps ahead of its newest estimate (default 15; -1: "
                        "never wait, as a robot's camera)")
    p.add_argument("--gate-only", "--no-ids", action="store_true",
                   help="ignore known landmark ids: associate by the Mahalanobis gate alone (a "
                        "text log with --backend ekf/batch and [reassociation] passes > 0: the "
                        "offline pipeline of backend/noids_offline.py)")
    p.add_argument("--truth", default=None,
                   help="with a text log: a file of VERTEX2/VERTEX_SE2 true poses")
    p.add_argument("--mrclam", action="store_true",
                   help="RUN is an MRCLAM folder: the resampled ds0_RS_ copy, or MRCLAM_DatasetN "
                        "as distributed (Robot1_Odometry.dat ...: robot 1, or --robot N)")
    p.add_argument("--robot", type=int, default=None, metavar="N",
                   help="with --mrclam on a MRCLAM_DatasetN folder as distributed: robot N "
                        "(1-5; default 1)")
    p.add_argument("--g2o", default=None, metavar="OUT.g2o",
                   help="also write the final graph as g2o: poses, landmarks and every factor "
                        "(custom LAMPSAM_* lines for the ceiling model; backend/g2o_export.py)")
    p.add_argument("--duration", type=positive, default=None,
                   help="with --mrclam: use only the first seconds (an error without --mrclam)")
    add_rerun_option(p)
    p.add_argument("--save-map", default=None, metavar="MAP",
                   help="also write the ceiling map (landmarks, covariances, lamp axes, corner "
                        "patches, rig) to the folder MAP (docs/ceiling-map.md)")
    p.add_argument("--no-map-check", action="store_true",
                   help="with --save-map: skip the map's pass-split consistency test "
                        "(backend/map_calibration.py, ~15%% of a batch mapping run's CPU); "
                        "map.yaml then has no 'calibration' figures and says "
                        "'map_check: not run' under 'source' (default: the test runs)")
    p.add_argument("--map", default=None, metavar="MAP", action="append",
                   help="with --localize-only: the ceiling map folder to track against; given "
                        "twice or more, the maps of separate mapping drives are merged "
                        "jointly, a shift, turn and scale per drive fitted (backend/map_merge.py)")
    p.add_argument("--map-priors", action="store_true",
                   help="with --localize-only: the map's landmarks are priors updated during "
                        "the run (joint EKF over pose and map landmarks; the default, same as "
                        "--map-mode priors)")
    p.add_argument("--map-mode", default=None, choices=("fixed", "priors", "consider", "smooth"),
                   help="with --localize-only: the map as priors (default), fixed values "
                        "(pose-only EKF), a consider (Schmidt) filter, or smooth: the priors "
                        "filter, then a smoother over the whole run with the map's frame "
                        "model; trajectory.tum then holds the smoothed poses "
                        "(docs/ceiling-map.md)")
    p.add_argument("--release", default=None, action=argparse.BooleanOptionalAction,
                   help="with --localize-only and the map as priors (or smooth): release map "
                        "landmarks that the run's sightings contradict (a chi-square test "
                        "against the rest of the map; summary.json lists them; default on: "
                        "LocalizeConfig.release, docs/ceiling-map.md)")
    p.add_argument("--localize-only", action="store_true",
                   help="track the run against --map without adding landmarks (--map-mode)")
    p.add_argument("--start", default=None, metavar="X,Y,THETA",
                   help="with --localize-only: start pose in the map's frame (m, m, rad; "
                        "default the run's known start)")
    p.add_argument("--start-from", default=None, metavar="RESULT.json",
                   help="with --localize-only: start from a `lampsam localize` answer")
    add_force(p)
    p.set_defaults(func=_cmd_slam, graceful=True)
