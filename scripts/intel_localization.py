"""Laser global-localization trials on a CARMEN log (default: the shared Intel lab log).

A thin wrapper of :func:`lampsam.evaluation.laser_trials.laser_trials`: map from
the even-numbered scans, trials from the odd-numbered ones, scored against the
corrected poses (30 cm / 10 deg).

Usage: ``python scripts/intel_localization.py [--log LOG] [--trials 50]
[--particles 100000] [--updates 4] [--out out/intel_localization/result.json]``
"""

from __future__ import annotations

import argparse
import json
from dataclasses import replace

from lampsam.datasets.paths import shared_dataset
from lampsam.evaluation.laser_trials import LaserTrialsConfig, laser_trials, write_json


def main() -> None:
    """Parse the options, run the trials, print the summary and write the JSON."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--log", default=None, help="CARMEN log (default: the shared intel-corrected.log.gz)")
    ap.add_argument("--trials", type=int, default=50)
    ap.add_argument("--particles", type=int, default=100_000, help="initial particles")
    ap.add_argument("--updates", type=int, default=4, help="scans per trial")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", default="out/intel_localization/result.json")
    args = ap.parse_args()
    log_path = args.log
    if log_path is None:
        root = shared_dataset("carmen")
        if root is None:
            raise SystemExit("shared dataset 'carmen' not found (set LAMPSAM_DATA) and no --log")
        log_path = root / "intel-corrected.log.gz"
    base = LaserTrialsConfig()
    cfg = replace(base, trials=args.trials, updates=args.updates, seed=args.seed,
                  localizer=replace(base.localizer, particles=args.particles))
    result = laser_trials(log_path, cfg, progress=True)
    print(json.dumps(result["summary"], indent=2))
    print(f"written {write_json(result, args.out)}")


if __name__ == "__main__":
    main()
