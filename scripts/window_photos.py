"""The labelled photos with a bright window pasted in: the lamp detector before and after the window rules.

Usage::

    python scripts/window_photos.py ../shared/data/ceiling_photos \\
        tests/data/ceiling_photo_labels.json [--photos 470,560,808] [--old]

For each photo, without a window, with a flat saturated window and with a
textured sky window (:func:`lampsam.evaluation.photo_augment.paste_window`,
seed 0), prints the threshold, the working width (from the photo's lamps, with
the second look, as ``frontend-eval --photos``), detections, false detections
by kind, modules and fittings found. ``--old`` runs the rules before the window
session (``light_share=None``, ``thin_min_length_px=0``).
docs/photo-labels.md, last section, has the figures.
"""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path

import cv2
import numpy as np

from lampsam.evaluation.gallery import detect_photo
from lampsam.evaluation.photo_augment import load_colour, paste_window
from lampsam.evaluation.photo_eval import PhotoEvalSettings, score_photo
from lampsam.evaluation.photo_labels import read_labels
from lampsam.frontend.pipeline import FrontendConfig


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("photos", type=Path)
    ap.add_argument("labels", type=Path)
    ap.add_argument("--photos", dest="which", default="", help="comma-separated photo numbers")
    ap.add_argument("--old", action="store_true", help="the rules before the window session")
    args = ap.parse_args()
    cfg = FrontendConfig().lamps
    if args.old:
        cfg = dataclasses.replace(cfg, light_share=None, thin_min_length_px=0.0)
    which = [w for w in args.which.split(",") if w]
    for name, pl in read_labels(args.labels).items():
        if which and name.split("_")[0] not in which:
            continue
        grey = np.asarray(cv2.cvtColor(load_colour(args.photos / name), cv2.COLOR_BGR2GRAY),
                          dtype=np.uint8)
        for mode in ("none", "flat", "textured"):
            img, lab = (grey, pl) if mode == "none" else paste_window(
                grey, pl, textured=mode == "textured", rng=np.random.default_rng(0))
            det, used = detect_photo(img, cfg)
            h, w = det.mask.shape
            sc = score_photo(det, lab, (w, h), used, PhotoEvalSettings())
            print(f"{name[:3]} {pl.use:6s} {mode:8s} width {w:4d} k {det.threshold} "
                  f"det {sc.n_detections} false {dict(sc.false_by_kind) or '-'} "
                  f"modules {sc.n_found}/{sc.n_lamps} fittings {sc.n_fittings_found}/{sc.n_fittings}")


if __name__ == "__main__":
    main()
