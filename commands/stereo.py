"""CLI commands of paper 3's stereo two-point pose: ``stereo-sim``, ``stereo`` and
``stereo-experiment``.
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

from lampsam.commands._args import (
    add_force,
    add_rerun_option,
    config_path,
    log,
    nonneg_int,
    num,
    output_dir,
    positive_int,
)
from lampsam.errors import LampsamError


# --------------------------------------------------------------------------- stereo
def _cmd_stereo_sim(args: argparse.Namespace) -> int:
    from lampsam.datasets.stereo_sim import simulate_stereo_run

    out = simulate_stereo_run(args.scenario, output_dir(args), seed=args.seed)
    print(f"stereo run written to {out}")
    return 0


def add_stereo_sim(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("stereo-sim", help="simulate a stereo two-point run (paper 3)")
    p.add_argument("--scenario", required=True, choices=["straight", "turn"],
                   help="drive toward and past the target, or turn in place")
    p.add_argument("--out", required=True, help="run directory to write")
    p.add_argument("--seed", type=nonneg_int, default=0, help="random seed (default 0)")
    add_force(p)
    p.set_defaults(func=_cmd_stereo_sim)


def _cmd_stereo(args: argparse.Namespace) -> int:
    from lampsam.backend.stereo import StereoEstimatorConfig
    from lampsam.config_loader import load_config
    from lampsam.datasets.stereo_sim import read_stereo_run
    from lampsam.evaluation.live import live_view, rerun_target
    from lampsam.evaluation.stereo_report import stereo_job, summary_table

    cfg = load_config(StereoEstimatorConfig, config_path(args), table="stereo")
    run = read_stereo_run(Path(args.run))
    for name in ("baseline", "focal_length", "pixel_pitch"):
        value = getattr(run.rig, name)
        if not (math.isfinite(value) and value > 0):
            raise LampsamError(f"{Path(args.run) / 'stereo_run.yaml'}: rig.{name}: must be a "
                               f"positive number, got {num(value)}")
    out = output_dir(args)
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


def add_stereo(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("stereo", help="estimate the relative pose to a stereo target")
    p.add_argument("run", help="stereo run directory (from stereo-sim)")
    p.add_argument("--estimator", required=True, choices=["raw", "ekf", "isam2", "batch"],
                   help="raw triangulation, the paper's EKF, iSAM2 online, batch smoother")
    p.add_argument("--out", required=True, help="output directory")
    p.add_argument("--config", default=None,
                   help="TOML/YAML file with a [stereo] table (StereoEstimatorConfig)")
    add_force(p)
    add_rerun_option(p)
    p.set_defaults(func=_cmd_stereo)


def _cmd_stereo_experiment(args: argparse.Namespace) -> int:
    from lampsam.datasets.paths import shared_dataset
    from lampsam.evaluation.stereo_experiment import stereo_experiment

    if args.kitti and args.no_kitti:
        raise LampsamError("--kitti and --no-kitti: give one")
    out = output_dir(args)  # before the seeds run: a non-empty --out needs --force
    if args.kitti:
        from lampsam.datasets.kitti import read_kitti_sequence

        kitti: Path | None = Path(args.kitti)
        read_kitti_sequence(Path(args.kitti))  # a bad folder is refused before the seeds run
    else:
        kitti = None if args.no_kitti else shared_dataset("kitti_stereo_seq1")
    if kitti is None and not args.no_kitti:
        log.warning("shared dataset kitti_stereo_seq1 not found (set LAMPSAM_DATA): "
                    "the KITTI check is skipped")
    print(stereo_experiment(out, args.seeds, kitti))
    return 0


def add_stereo_experiment(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("stereo-experiment",
                       help="paper 3's experiment: seeds x scenarios x estimators, and KITTI")
    p.add_argument("--out", required=True, help="output directory (stereo_rms.md/.json, figures)")
    p.add_argument("--seeds", type=positive_int, default=20, help="seeds per scenario (default 20)")
    p.add_argument("--no-kitti", action="store_true", help="skip the KITTI real-data check")
    p.add_argument("--kitti", default=None, metavar="DIR",
                   help="KITTI stereo sequence for the real-data check (default: the shared "
                        "kitti_stereo_seq1; image_l/image_r or the odometry benchmark's "
                        "image_0..3 with calib.txt, or calib_cam_to_cam.txt, and poses.txt)")
    add_force(p)
    p.set_defaults(func=_cmd_stereo_experiment)
