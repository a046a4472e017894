"""Argument helpers shared by ``cli.py`` and the ``commands`` modules: argparse value
types, the common options (``--force``, ``--rerun``, ``--dask``), and the checks of
``--out`` / ``--config`` that run before any computing.
"""

from __future__ import annotations

import argparse
import logging
import math
from pathlib import Path

log = logging.getLogger("lampsam")


def config_path(args: argparse.Namespace) -> Path | None:
    """The ``--config`` file of a command, or None."""
    value = getattr(args, "config", None)
    return Path(value) if value else None


def positive(text: str) -> float:
    """argparse type: a finite number > 0."""
    try:
        value = float(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(f"not a number: {text!r}") from exc
    if not (math.isfinite(value) and value > 0):
        raise argparse.ArgumentTypeError(f"must be a positive number, got {text}")
    return value


def nonneg(text: str) -> float:
    """argparse type: a finite number >= 0."""
    try:
        value = float(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(f"not a number: {text!r}") from exc
    if not (math.isfinite(value) and value >= 0):
        raise argparse.ArgumentTypeError(f"must be a finite number >= 0, got {text}")
    return value


def _integer(text: str) -> int:
    """An argparse value as an integer, or argparse's error naming the text."""
    try:
        return int(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(f"not an integer: {text!r}") from exc


def positive_int(text: str) -> int:
    """argparse type: an integer >= 1."""
    value = _integer(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be at least 1, got {text}")
    return value


def nonneg_int(text: str) -> int:
    """argparse type: an integer >= 0."""
    value = _integer(text)
    if value < 0:
        raise argparse.ArgumentTypeError(f"must be >= 0, got {text}")
    return value


def add_force(p: argparse.ArgumentParser) -> None:
    """``--force``: overwrite a non-empty output directory or an existing file."""
    p.add_argument("--force", action="store_true",
                   help="write into a non-empty output directory / over an existing file")


def add_rerun_option(p: argparse.ArgumentParser) -> None:
    """``--rerun [FILE.rrd|ADDRESS]``: stream the run to a Rerun recording or viewer."""
    p.add_argument("--rerun", nargs="?", const="", default=None, metavar="FILE.rrd|ADDRESS",
                   help="stream the run to Rerun: save FILE.rrd, or send to a viewer at ADDRESS "
                        "(host:port); bare: OUT/live.rrd (needs lampsam[viz])")


def add_dask_option(p: argparse.ArgumentParser) -> None:
    """``--dask ADDRESS``: run a many-job command on a Dask scheduler."""
    p.add_argument("--dask", default=None, metavar="ADDRESS",
                   help="run the jobs on a Dask distributed scheduler (e.g. tcp://10.0.0.5:8786; "
                        "workers need lampsam and the same paths) or 'local' (a LocalCluster "
                        "with --workers processes); default: a local process pool")


def output_dir(args: argparse.Namespace, allow_resume: bool = False) -> Path:
    """``--out`` checked (and created) before any computing; see :mod:`lampsam.safe_io`."""
    from lampsam.safe_io import check_output_dir

    allow = (lambda _p: True) if allow_resume and getattr(args, "resume", False) else None
    return check_output_dir(args.out, force=args.force, what="--out", allow=allow)


def output_file(args: argparse.Namespace) -> Path:
    """``--out`` (a file) checked before any computing."""
    from lampsam.safe_io import check_output_file

    return check_output_file(args.out, force=args.force, what="--out")


def num(value: object) -> str:
    """A number as a user reads it (never ``np.float64(...)``)."""
    from lampsam.config_loader import plain

    return plain(value)


def warn_partial(meta: dict[str, object], run: Path) -> None:
    """Warn when a run's ``meta.yaml`` says it is partial (``complete: false``)."""
    if meta.get("complete") is False:
        log.warning("%s is a partial run (complete: false in meta.yaml: the simulation was "
                    "interrupted): only its finished frames are used, and after the last "
                    "image the estimate is dead reckoning", run)
