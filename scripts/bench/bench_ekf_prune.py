"""The EKF without ids: the absolute prune rule against the relative one (issue #15).

Usage::

    python scripts/bench/bench_ekf_prune.py [--logs vp1k,city,example,mrclam,synthetic]
        [--repeats 3] [--set SECTION.KEY=VALUE ...]

For each log: the EKF without ids (defaults, ``run_graph_log(known_ids=False)``) with
``association.prune_relative`` false (the absolute horizontal sigma, the rule before
issue #15) and true (the sigma conditional on the pose of the landmark's last
sighting), in the same invocation. Printed: landmarks seen twice or more ("mapped")
against the file's ids sighted twice or more ("true"), the prune counts by reason, the
position RMS against lampsam's known-id batch on the same log, and the median process
CPU time of the EKF over ``--repeats`` runs with its ratio (relative / absolute; the
machine may be shared: compare within one run only). Logs as in
``bench_noids_scale.py``, plus ``example`` (GTSAM's ``example.graph``).
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
import statistics
import time
from collections import Counter
from pathlib import Path

import gtsam
import numpy as np
from timing import sibling  # scripts/bench/timing.py, a sibling module

from lampsam.backend.config import SlamConfig
from lampsam.backend.graph_log import run_graph_log
from lampsam.datasets.graph_text import GraphLog, read_graph_text


def load(name: str, out: Path) -> GraphLog:
    """A named log (module doc)."""
    if name == "example":
        return read_graph_text(Path(gtsam.findExampleDataFile("example.graph")))
    return sibling("bench_noids_scale").load_log(name, out)  # type: ignore[no-any-return]


def main() -> None:
    """Parse arguments, run every log, print one table."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--logs", default="vp1k,city,example,mrclam,synthetic")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--out", default="/tmp/bench_ekf_prune")
    ap.add_argument("--set", nargs="*", default=[], metavar="SECTION.KEY=VALUE")
    args = ap.parse_args()
    logging.basicConfig(level=logging.ERROR)
    base = sibling("bench_landmark_logs").with_overrides(SlamConfig(), args.set)
    print("| log | rule | mapped / true | pruned | RMS vs known-id batch [m] | CPU s (median) | ratio |")
    print("|---|---|---|---|---|---|---|")
    for name in args.logs.split(","):
        g = load(name, Path(args.out))
        seen = Counter(s.landmark for ss in g.sightings for s in ss)
        true = sum(c >= 2 for c in seen.values())
        ref = run_graph_log(g, "batch", base).poses[:, :2]
        c_abs = 0.0
        for rel in (False, True):
            cfg = dataclasses.replace(base, association=dataclasses.replace(
                base.association, prune_relative=rel))
            cpu = []
            for _ in range(args.repeats):
                t0 = time.process_time()
                res = run_graph_log(g, "ekf", cfg, known_ids=False)
                cpu.append(time.process_time() - t0)
            c = statistics.median(cpu)
            c_abs = c if not rel else c_abs
            rms = float(np.sqrt(np.mean(np.sum((res.poses[:, :2] - ref) ** 2, axis=1))))
            print(f"| {name} | {'relative' if rel else 'absolute'} | {len(res.landmarks)} / {true} | "
                  f"{dict(sorted(res.pruned.items()))} | {rms:.3f} | {c:.2f} | "
                  f"{c / c_abs:.3f} |", flush=True)


if __name__ == "__main__":
    main()
