"""The single command-line entry point: ``lampsam <subcommand> ...``.

Each subcommand is a thin wrapper over a library function that also works from
Python; heavy modules are imported inside the wrappers so ``lampsam --help``
stays fast. Only the CLI (this module and :mod:`lampsam.commands`) reads
configuration files (TOML or YAML, through
the strict loader :func:`lampsam.config_loader.load_config`: unknown keys,
wrong types and values out of range are errors naming the file and the dotted
key); it passes config dataclasses down explicitly.

Exit codes: 0 success, 1 the job ran but failed (e.g. localization failed, or the
final optimisation failed and the online estimate was written), 2 bad input or
usage (a :class:`lampsam.errors.LampsamError` is printed, no traceback; checked
before any computing, including the ``--out`` path), 3 interrupted by SIGINT or
SIGTERM (finished work written with status ``interrupted``; ``docs/failures.md``).

The subcommands live in :mod:`lampsam.commands` (one module per command family, each
with its parser builder ``add_*`` and handler); this module builds the parser from
them, sets up logging and signals, and turns errors into exit codes.
"""

from __future__ import annotations

import argparse
import logging
import re
import sys
from collections.abc import Callable, Sequence

from lampsam.commands import bags, ceiling, localization, photos, slam, stereo
from lampsam.errors import LampsamError
from lampsam.interrupt import EXIT_FAILED, EXIT_INTERRUPTED, EXIT_USAGE

log = logging.getLogger("lampsam")

_ADDERS: list[Callable[[argparse._SubParsersAction], None]] = [
    ceiling.add_simulate,
    ceiling.add_demo,
    stereo.add_stereo_sim,
    stereo.add_stereo,
    stereo.add_stereo_experiment,
    localization.add_kinect_sim,
    localization.add_build_map,
    localization.add_show_map,
    slam.add_slam,
    ceiling.add_compare,
    ceiling.add_batch,
    localization.add_localize,
    localization.add_table1,
    photos.add_frontend_eval,
    photos.add_gallery,
    bags.add_import_bag,
    bags.add_export_bag,
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


_NUMPY_SCALAR = re.compile(r"np\.(?:float|int|uint|bool_?)\d*\(([^()]*)\)")


def _plain_text(message: str) -> str:
    """A message with numpy scalar reprs (``np.float64(5.0)``) shown as plain numbers."""
    return _NUMPY_SCALAR.sub(r"\1", message)


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
