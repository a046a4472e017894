"""Label ceiling photos by eye: propose numbered bright blobs, then turn decisions into a label file.

Usage::

    python scripts/label_photos.py propose PHOTOS_DIR OUT_DIR
        # writes OUT_DIR/proposals_<photo>.png: look at each, write decisions.txt
    python scripts/label_photos.py finalize PHOTOS_DIR DECISIONS.txt LABELS.json --tune 430 807

Proposals are made on the photo reduced to 1000 px wide (deterministic, so the
numbers in the pictures are those ``finalize`` uses). Format of the decisions
and of the label file: :mod:`lampsam.evaluation.photo_labels`.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import cv2

from lampsam.evaluation.gallery import load_photo
from lampsam.evaluation.photo_labels import (
    Region,
    draw_proposals,
    finalize_labels,
    parse_decisions,
    propose_regions,
    write_labels,
)
from lampsam.safe_io import atomic_path

LABEL_WIDTH = 1000


def _proposals(photos: Path) -> tuple[dict[str, list[Region]], dict[str, tuple[int, int]], dict]:
    props, sizes, small = {}, {}, {}
    for path in sorted(
        p for p in photos.iterdir() if p.suffix.lower() in (".jpg", ".jpeg", ".png")
    ):
        full = load_photo(path, None)
        h, w = full.shape
        img = cv2.resize(
            full, (LABEL_WIDTH, round(LABEL_WIDTH * h / w)), interpolation=cv2.INTER_AREA
        )
        props[path.name] = propose_regions(img, w)
        sizes[path.name] = (w, h)
        small[path.name] = img
    return props, sizes, small


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    p = sub.add_parser("propose")
    p.add_argument("photos", type=Path)
    p.add_argument("out", type=Path)
    f = sub.add_parser("finalize")
    f.add_argument("photos", type=Path)
    f.add_argument("decisions", type=Path)
    f.add_argument("labels", type=Path)
    f.add_argument("--tune", nargs="*", default=[], help="photo prefixes used for tuning")
    args = ap.parse_args()
    props, sizes, small = _proposals(args.photos)
    if args.cmd == "propose":
        args.out.mkdir(parents=True, exist_ok=True)
        for name, regs in props.items():
            png = args.out / f"proposals_{Path(name).stem}.png"
            with atomic_path(png) as tmp:
                cv2.imwrite(str(tmp), draw_proposals(small[name], regs, sizes[name][0]))
            print(f"{name}: {len(regs)} proposals -> {png}")
        return
    labels = finalize_labels(
        props, parse_decisions(args.decisions.read_text()), sizes, set(args.tune)
    )
    write_labels(labels, args.labels)
    print(f"{args.labels}: {sum(len(pl.regions) for pl in labels.values())} regions")


if __name__ == "__main__":
    main()
