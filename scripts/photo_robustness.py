"""The lamp detector on the labelled photos under known geometric and photometric transforms.

Usage::

    python scripts/photo_robustness.py ../shared/data/ceiling_photos \\
        tests/data/ceiling_photo_labels.json --samples 4 --seed 0 [--out robustness.json]

Prints, per transform family, precision, recall, splits, centroid and axis
RMS pooled over the ``tune`` photos and over the ``report`` photos apart
(module :mod:`lampsam.evaluation.photo_augment`; docs/photo-labels.md), and
the trials that lost a lamp or gained a false detection. ``--no-second-look``
and ``--width N`` run the older policies for comparison.
"""

from __future__ import annotations

import argparse
import json
import math
import time
from pathlib import Path

from lampsam.evaluation.photo_augment import (
    FAMILIES,
    AugmentSettings,
    TrialScore,
    family_totals,
    format_families,
    run_trials,
)
from lampsam.frontend.resolution import ResolutionPolicy
from lampsam.safe_io import write_text_atomic


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("photos", type=Path)
    ap.add_argument("labels", type=Path)
    ap.add_argument("--samples", type=int, default=4, help="transforms per photo and family")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--families", default=",".join(FAMILIES))
    ap.add_argument("--photos-only", default=None, help="comma-separated photo names or numbers")
    ap.add_argument("--width", type=int, default=None, help="fixed working width (default: rule)")
    ap.add_argument("--no-second-look", action="store_true")
    ap.add_argument("--out", type=Path, default=None, help="JSON of every trial")
    args = ap.parse_args()

    policy = ResolutionPolicy(
        width=args.width or 320, auto=args.width is None, second_look=not args.no_second_look
    )
    settings = AugmentSettings(
        families=tuple(args.families.split(",")), samples=args.samples, seed=args.seed,
        policy=policy,
    )
    only = tuple(args.photos_only.split(",")) if args.photos_only else None

    def show(t: TrialScore) -> None:
        s = t.score
        lost = s.n_lamps - s.n_found
        false = s.n_detections - s.n_true
        if lost or false:
            print(f"  {s.name} {t.family} {t.value:.3g} (width {s.width}): {lost} of {s.n_lamps} "
                  f"lamps missed, {false} false {s.false_by_kind}", flush=True)

    t0 = time.process_time()
    trials = run_trials(args.photos, args.labels, settings, photos=only, progress=show)
    cpu = time.process_time() - t0
    for uses in (("tune",), ("report",)):
        tot = family_totals(trials, uses)
        if any(s.n_lamps for s in tot.values()):
            print(f"\n{'/'.join(uses)} photos (seed {args.seed}, {args.samples} per family):")
            print(format_families(tot))
    print(f"\n{len(trials)} trials, {cpu:.1f} s CPU")
    if args.out is not None:
        rows = [{"family": t.family, "value": t.value, **t.score.row()} for t in trials]
        for r in rows:
            r.update({k: None for k, v in r.items() if isinstance(v, float) and math.isnan(v)})
        write_text_atomic(args.out, json.dumps({"settings": vars(args) | {
            "photos": str(args.photos), "labels": str(args.labels),
            "out": str(args.out)}, "trials": rows}, indent=1) + "\n")


if __name__ == "__main__":
    main()
