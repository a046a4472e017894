"""CLI commands of the ceiling-camera SLAM job around ``slam``: ``simulate``, ``demo``,
``compare`` and ``batch`` (parser builders ``add_*`` and their handlers).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from lampsam.commands._args import (
    add_dask_option,
    add_force,
    config_path,
    log,
    nonneg_int,
    num,
    output_dir,
    positive,
    positive_int,
)
from lampsam.interrupt import EXIT_INTERRUPTED, stop_requested


# --------------------------------------------------------------------------- simulate
def _cmd_simulate(args: argparse.Namespace) -> int:
    from lampsam.datasets.simulator import simulate_world
    from lampsam.datasets.world import load_world

    world = load_world(args.world)  # bad world: an error before the output is touched
    out = simulate_world(world, output_dir(args), seed=args.seed, duration=args.duration,
                         png_compression=args.png_compression)
    import yaml

    meta = yaml.safe_load((out / "meta.yaml").read_text(encoding="utf-8")) or {}
    simulated = float(meta.get("duration", 0.0))
    if args.duration is not None and args.duration > simulated + 0.1:
        log.warning("--duration %s s is longer than the world's path: simulated %.1f s "
                    "(the whole path)", num(args.duration), simulated)
    print(f"run written to {out} ({simulated:.1f} s, {meta.get('n_images', '?')} images)")
    return 0


def add_simulate(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("simulate", help="simulate a ceiling-camera run of a world")
    p.add_argument("world", help="built-in world name (lab, corridor, office) or a world YAML file")
    p.add_argument("--out", required=True, help="run directory to write")
    p.add_argument("--seed", type=nonneg_int, default=0, help="random seed (default 0)")
    p.add_argument("--duration", type=positive, default=None,
                   help="seconds to simulate (default: whole path; longer than the path: a warning)")
    p.add_argument("--png-compression", type=int, choices=range(10), default=0, metavar="0-9",
                   help="zlib level of the images (default 0: stored, 5x faster to decode, "
                        "twice the disk; the pixels are the same at every level)")
    add_force(p)
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


def add_demo(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("demo", help="the main job on the built-in default world")
    p.add_argument("--out", default="out/demo", help="output directory (default out/demo)")
    p.set_defaults(func=_cmd_demo)


# --------------------------------------------------------------------------- compare
def _cmd_compare(args: argparse.Namespace) -> int:
    from lampsam.backend.config import SlamConfig
    from lampsam.config_loader import load_config
    from lampsam.evaluation.compare import compare, markdown_table

    backends = tuple(b.strip() for b in args.backends.split(",") if b.strip())
    features = tuple(f.strip() for f in args.features.split(",")) if args.features else None
    config = load_config(SlamConfig, config_path(args))
    out = output_dir(args, allow_resume=True)
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


def add_compare(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("compare", help="compare EKF against smoothing over runs and seeds")
    p.add_argument("runs", nargs="+", help="run directories, world names (simulated per seed), or mrclam / mrclam-gated")
    p.add_argument("--backends", default="ekf,isam2,batch", help="comma-separated (default ekf,isam2,batch)")
    p.add_argument("--seeds", type=positive_int, default=1, help="Monte Carlo seeds per simulated world (default 1)")
    p.add_argument("--out", required=True, help="report directory")
    p.add_argument("--workers", type=positive_int, default=2, help="parallel processes (default 2)")
    p.add_argument("--frames", default="auto", choices=["auto", "images", "truth"],
                   help="measurements: auto (frontend on images / range-bearing), images, truth projections")
    p.add_argument("--features", default=None, help="ceiling features, e.g. lamps,corners (default: backend config)")
    p.add_argument("--duration", type=positive, default=None, help="seconds per simulated run (default whole path)")
    p.add_argument("--config", default=None,
                   help="TOML/YAML file with the SLAM settings of every job (as for `lampsam slam --config`)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument("--resume", action="store_true",
                   help="continue an earlier compare into the same --out: skip its finished jobs")
    add_force(p)
    add_dask_option(p)
    p.set_defaults(func=_cmd_compare, graceful=True)

# --------------------------------------------------------------------------- batch
def _cmd_batch(args: argparse.Namespace) -> int:
    from lampsam.backend.config import SlamConfig
    from lampsam.config_loader import load_config
    from lampsam.evaluation.batch import batch, markdown_table

    features = tuple(f.strip() for f in args.features.split(",")) if args.features else None
    config = load_config(SlamConfig, config_path(args))
    out = output_dir(args)  # before any computing: a non-empty --out needs --force
    rows = batch(args.runs, out, backend=args.backend, workers=args.workers,
                 dask=args.dask, progress=not args.no_progress, config=config,
                 frames=args.frames, features=features)
    print(markdown_table(rows))
    print(f"summary: {Path(args.out) / 'summary.json'} (and summary.csv); one folder per run")
    if stop_requested() is not None:
        return EXIT_INTERRUPTED
    return 1 if any(r["status"] != "ok" for r in rows) else 0


def add_batch(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("batch", help="offline optimisation of many logs: one result folder each")
    p.add_argument("runs", nargs="+", help="run directories")
    p.add_argument("--out", required=True, help="output directory (one folder per run + summary)")
    p.add_argument("--backend", choices=("batch", "isam2", "ekf"), default="batch",
                   help="estimator (default batch: Levenberg-Marquardt over the whole log)")
    p.add_argument("--workers", type=positive_int, default=2, help="parallel processes (default 2)")
    p.add_argument("--frames", default="auto", choices=["auto", "images", "truth", "rangebearing"],
                   help="measurement source (default auto)")
    p.add_argument("--features", default=None, help="ceiling features, e.g. lamps,corners")
    p.add_argument("--config", default=None,
                   help="TOML/YAML file with the SLAM settings of every run (as for `lampsam slam --config`)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    add_force(p)
    add_dask_option(p)
    p.set_defaults(func=_cmd_batch, graceful=True)
