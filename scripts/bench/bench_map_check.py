"""CPU of ``--save-map`` with and without the map's pass-split test (``--no-map-check``).

Usage::

    python scripts/bench/bench_map_check.py RUN_DIR [--backend batch] [--repeats 3]

Runs SLAM once over ``RUN_DIR`` (a simulated or logged run directory), then saves its map
``--repeats`` times each way, alternating (with the test, without), into a temporary
folder: :func:`lampsam.backend.localize_run.save_map` with ``check=True`` (the default:
:mod:`lampsam.backend.map_calibration` runs and its figures go to ``map.yaml``) and
``check=False``. Printed: the SLAM run's CPU (process time, once), the median save CPU of
each way, their difference, the ratio with/without, and the difference as a share of
(SLAM + save with the test), i.e. what ``--no-map-check`` saves of the mapping run's
in-process CPU. The load average at the start and end is printed: CPU times are only
comparable within one invocation.
"""

from __future__ import annotations

import argparse
import logging
import os
import statistics
import tempfile
import time
from pathlib import Path

from lampsam.backend.localize_run import BackendCapture, save_map
from lampsam.backend.slam import run_slam
from lampsam.datasets.logrun import read_run
from lampsam.observe import observing


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("run", type=Path, help="run directory")
    p.add_argument("--backend", default="batch", choices=("batch", "isam2"))
    p.add_argument("--repeats", type=int, default=3, help="saves of each way (median)")
    args = p.parse_args()
    if args.repeats < 1:
        p.error("--repeats must be >= 1")
    logging.basicConfig(level=logging.ERROR)
    load0 = os.getloadavg()[0]
    run = read_run(args.run)
    capture = BackendCapture()
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.process_time()
        with observing(capture):
            result = run_slam(args.run, args.backend, None, Path(tmp) / "slam", run=run)
        slam_s = time.process_time() - t0
        times: dict[bool, list[float]] = {True: [], False: []}
        for _ in range(args.repeats):
            for check in (True, False):
                t0 = time.process_time()
                save_map(Path(tmp) / f"map_{check}", result, run, capture.backend, check=check)
                times[check].append(time.process_time() - t0)
    with_s, without_s = (statistics.median(times[c]) for c in (True, False))
    print(f"{args.run} ({args.backend}, {len(result.times)} steps, status {result.status}): "
          f"SLAM CPU {slam_s:.2f} s (once)")
    print(f"save_map CPU, median of {args.repeats}: with the map check {with_s:.3f} s, "
          f"without {without_s:.3f} s; saved {with_s - without_s:.3f} s "
          f"(with/without {with_s / without_s:.2f}), "
          f"{(with_s - without_s) / (slam_s + with_s):.1%} of SLAM + save")
    print(f"load average {load0:.1f} at the start, {os.getloadavg()[0]:.1f} now, "
          f"on {os.cpu_count()} cores")


if __name__ == "__main__":
    main()
