"""CLI commands on ceiling images: ``frontend-eval`` (simulated run or labelled
photos) and ``gallery`` (frontend overlays on a photo folder).
"""

from __future__ import annotations

import argparse
from pathlib import Path

from lampsam.commands._args import add_force, config_path, output_file, positive_int
from lampsam.errors import LampsamError


# --------------------------------------------------------------------------- frontend-eval
def _cmd_frontend_eval(args: argparse.Namespace) -> int:
    from lampsam.config_loader import load_config
    from lampsam.frontend.pipeline import FrontendConfig

    photos = args.photos is not None or args.labels is not None
    if (photos and (args.photos is None or args.labels is None or args.run is not None)) or (
        not photos and args.run is None
    ):
        raise LampsamError("frontend-eval: give RUN, or both --photos DIR and --labels FILE")
    cfg = load_config(FrontendConfig, config_path(args), table="frontend")
    if photos:
        from lampsam.evaluation.photo_eval import (
            PhotoEvalSettings,
            evaluate_photos,
            format_table,
            write_scores,
        )

        settings = PhotoEvalSettings(
            width=args.width or 320,
            auto_width=args.width is None,
            second_look=args.second_look,
        )
        out_file = output_file(args) if args.out is not None else None
        scores = evaluate_photos(Path(args.photos), Path(args.labels), settings, cfg.lamps)
        print(format_table(scores))
        if out_file is not None:
            write_scores(scores, out_file, settings)
        return 0
    from lampsam.evaluation.frontend_eval import evaluate_run

    if not Path(args.run).is_dir():
        raise LampsamError(f"{args.run}: run directory not found")
    out = output_file(args) if args.out is not None else None
    res = evaluate_run(
        Path(args.run), out=out, config=cfg, max_frames=args.max_frames, lamp_models=args.lamp_models
    )
    print(res.summary())
    return 0 if all(res.targets_met.values()) else 1


def add_frontend_eval(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "frontend-eval",
        help="measure the ceiling frontend against a simulated run's truth or labelled photos",
    )
    p.add_argument("run", nargs="?", default=None,
                   help="simulated run directory (with truth/projections.csv)")
    p.add_argument("--photos", default=None, help="folder of real ceiling photos")
    p.add_argument("--labels", default=None,
                   help="label file of those photos (tests/data/ceiling_photo_labels.json)")
    p.add_argument("--width", type=positive_int, default=None,
                   help="photos: working image width in px (default: per photo, from its lamps; "
                        "docs/photo-labels.md)")
    p.add_argument("--second-look", action=argparse.BooleanOptionalAction, default=True,
                   help="photos: look at full resolution inside long or border-cut blobs "
                        "(default on)")
    p.add_argument("--out", default=None,
                   help="JSON file (default RUN/frontend_eval.json; photos: none)")
    p.add_argument("--max-frames", type=int, default=None, help="only the first N images")
    p.add_argument("--lamp-models", action="store_true",
                   help="RUN: reject blobs whose size and shape fit none of the run's lamps")
    add_force(p)
    p.add_argument("--config", default=None,
                   help="TOML/YAML file with a [frontend] table ([frontend.lamps], [frontend.corners])")
    p.set_defaults(func=_cmd_frontend_eval)


# --------------------------------------------------------------------------- gallery
def _cmd_gallery(args: argparse.Namespace) -> int:
    from lampsam.evaluation.gallery import make_gallery

    if not Path(args.photos).is_dir():
        raise LampsamError(f"{args.photos}: " + ("not a folder (give the folder of photos)"
                                                 if Path(args.photos).exists() else "photo folder not found"))
    entries = make_gallery(Path(args.photos), output_file(args), full_size=not args.small_only)
    for e in entries:
        print(
            f"{e.name} {e.width}x{e.height}: {e.n_lamps} lamps ({e.n_oriented} oriented), "
            f"{e.n_border} at the border, {e.n_corners} corners, {e.time_ms:.1f} ms"
        )
    print(f"gallery written to {args.out}")
    return 0


def add_gallery(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("gallery", help="ceiling frontend overlays on a folder of photos")
    p.add_argument("photos", help="folder of .jpg/.png ceiling photos")
    p.add_argument("--out", required=True, help="gallery PNG to write")
    p.add_argument("--small-only", action="store_true",
                   help="only 320x240, not the working width (frontend-eval --photos' width rule "
                        "and second look)")
    add_force(p)
    p.set_defaults(func=_cmd_gallery)
