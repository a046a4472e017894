"""Benchmark: laser global localization seeded by branch and bound vs 100k uniform particles.

On a CARMEN log and its map (``lampsam build-map LOG --scans even --out MAP``),
runs the same trials (held-out odd scans, as ``lampsam localize``) twice per
repeat: the filter seeded from the branch-and-bound candidates (the default)
and the reference, 100,000 particles uniform over the free space. Prints, per
seeding, the median CPU time per trial (``time.process_time``, so comparable on
a loaded machine) over ``--repeats`` runs, the ratio to the reference measured
in the same run, the success counts, and the branch-and-bound search alone
(median CPU time of the search over the trials' first scans, nodes scored).

Usage: ``python scripts/bench/bench_global_search.py LOG MAP [--trials 10] [--repeats 3]``
"""

from __future__ import annotations

import argparse
import dataclasses
import statistics
import time

import numpy as np

from lampsam.datasets.carmen import read_carmen
from lampsam.evaluation.laser_trials import (
    LaserTrialsConfig,
    laser_trials,
    scan_selection,
    usable_scans,
)
from lampsam.localization.correlative import branch_and_bound, scan_points
from lampsam.localization.laser import joined_scans, search_pyramid
from lampsam.localization.likelihood import LikelihoodFieldModel
from lampsam.localization.map_store import load_env_map
from lampsam.localization.map_tables import load_distance_field


def search_only(log: str, map_dir: str, trials: int) -> tuple[float, float, int]:
    """Median CPU seconds of the search alone over the trials' starts, pyramid build seconds, median leaves."""
    cfg = LaserTrialsConfig(trials=trials)
    scans = usable_scans(read_carmen(log).scans)
    grid = load_env_map(map_dir).grid
    model = LikelihoodFieldModel(grid, cfg.localizer.beam, dist_cells=load_distance_field(map_dir, grid))
    c0 = time.process_time()
    pyr = search_pyramid(model, cfg.localizer)
    t_pyr = time.process_time() - c0
    sc = dataclasses.replace(cfg.localizer.search, resolution=pyr.res, max_range=pyr.pad * pyr.res)
    test = scan_selection(len(scans), "odd")
    starts = np.linspace(0, test.size - 4, trials).round().astype(int)
    times, nodes = [], []
    for s in starts:
        idx = test[s : s + 4]
        m = joined_scans(scans.poses[idx], cfg.localizer)
        pts = scan_points(scans.ranges[idx[:m]], scans.angles, scans.poses[idx[:m]], sc.max_range,
                          sc.resolution, sc.max_points)  # fmt: skip
        c0 = time.process_time()
        _, stats = branch_and_bound(pyr, pts, sc)
        times.append(time.process_time() - c0)
        nodes.append(sum(stats.nodes_per_level))
    return statistics.median(times), t_pyr, int(statistics.median(nodes))


def main() -> None:
    """Run and print the comparison."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("log")
    ap.add_argument("map")
    ap.add_argument("--trials", type=int, default=10)
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args()
    base = LaserTrialsConfig(trials=args.trials)
    uniform = dataclasses.replace(base, localizer=dataclasses.replace(base.localizer, seeding="uniform"))
    per: dict[str, list[float]] = {"search": [], "uniform": []}
    ok: dict[str, list[str]] = {"search": [], "uniform": []}
    for _ in range(args.repeats):
        for name, cfg in (("uniform", uniform), ("search", base)):
            res = laser_trials(args.log, cfg, map_dir=args.map)
            s = res["summary"]
            assert isinstance(s, dict)
            per[name].append(float(s["compute_s_mean"]))
            ok[name].append(f"{s['correct']}/{s['trials']} correct, {s['wrong_accepted']} wrong")
    ref = statistics.median(per["uniform"])
    print(f"{args.log}: {args.trials} trials x {args.repeats} repeats (CPU seconds per trial, median of repeats)")
    for name in ("uniform", "search"):
        med = statistics.median(per[name])
        print(f"  {name:8s} {med:7.2f} s  ratio {med / ref:5.2f}  ({'; '.join(ok[name])})")
    t_search, t_pyr, nodes = search_only(args.log, args.map, args.trials)
    print(f"  branch and bound alone: median {t_search:.3f} s CPU, {nodes} nodes scored; "
          f"score pyramid {t_pyr:.2f} s CPU (once per map)")


if __name__ == "__main__":
    main()
