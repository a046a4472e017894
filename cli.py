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
import tomllib
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from lampsam.errors import LampsamError

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
    from lampsam.evaluation.demo import run_demo

    run_demo(Path(args.out))
    return 0


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


_ADDERS: list[Callable[[argparse._SubParsersAction], None]] = [
    _add_simulate,
    _add_demo,
    _add_stereo_sim,
    _add_stereo,
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
