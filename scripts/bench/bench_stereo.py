"""Per-frame cost of the stereo two-point estimators (raw, EKF, iSAM2, batch).

One simulated run per scenario (seed 0); each estimator runs ``--repeats`` times;
printed: the median over repeats of the mean per-frame wall time (ms), and its
ratio to the EKF measured in the same process (the reference). Batch: total
time / frames. Timings on a shared machine are inflated; compare the ratios.

Usage: ``python scripts/bench/bench_stereo.py [--repeats 5]``
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from lampsam.backend.stereo import ESTIMATORS, estimate
from lampsam.datasets.stereo_sim import SCENARIOS, simulate_stereo


def main() -> int:
    """Run the benchmark; returns the exit code."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=5, help="runs per estimator (default 5)")
    args = ap.parse_args()
    for scenario in SCENARIOS:
        run = simulate_stereo(scenario, np.random.default_rng(0))
        per_frame: dict[str, float] = {}
        for name in ESTIMATORS:
            samples = []
            for _ in range(args.repeats):
                t0 = time.perf_counter()
                estimate(run, name)
                samples.append((time.perf_counter() - t0) / len(run))
            per_frame[name] = float(np.median(samples))
        ref = per_frame["ekf"]
        print(f"{scenario}: {len(run)} frames, median of {args.repeats} runs")
        for name in ESTIMATORS:
            ms = 1e3 * per_frame[name]
            print(f"  {name:6s} {ms:8.3f} ms/frame   x{per_frame[name] / ref:6.1f} EKF")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
