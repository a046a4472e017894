"""Speed-up of ``lampsam batch`` on Dask from 1 to 2 (or more) workers.

Usage::

    python scripts/bench/bench_fleet.py RUN [RUN ...] [--workers 1,2] [--repeats 2]
        [--backend batch] [--out out/bench_fleet]
    python scripts/bench/bench_fleet.py --simulate 4 [--duration 30]   # issue 19, one command

``--simulate N``: without run directories, N lab runs (seeds 0..N-1, ``--duration``
seconds each) are simulated once into ``OUT/runs`` (reused when present) and make
the batch: the 1- vs 2-worker speed-up on a 4-log batch is then one command.

For each worker count a ``distributed.LocalCluster`` (single-threaded worker
processes on 127.0.0.1) is started once; then, repeat by repeat, the same batch of
runs (:func:`lampsam.evaluation.batch.batch_job` per run through
:func:`lampsam.evaluation.fleet.run_dask`) is timed on each cluster in turn
(interleaved, so a change of machine load hits every count alike). Cluster start-up
is not timed; each timed batch includes the workers' first imports only in the
first repeat (which is why at least two repeats are advised; the table shows the
median and the minimum). Printed: wall time per batch, speed-up against the first
worker count measured in the same run, and the load average before and after (the
machine may be shared: the speed-up is only meaningful when there are idle cores).
"""

from __future__ import annotations

# ruff: noqa: E402
import os

for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse
import contextlib
import json
import logging
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from lampsam.evaluation.batch import BatchJob, BatchResult, batch_job, folder_names
from lampsam.evaluation.fleet import dask_client, run_dask
from lampsam.safe_io import write_text_atomic


def _failed(job: BatchJob, reason: str) -> BatchResult:
    return BatchResult(job, reason)


def simulated_runs(root: Path, n: int, duration: float) -> list[str]:
    """``n`` lab runs (seeds 0..n-1, ``duration`` s) under ``root``; existing ones are reused."""
    from lampsam.datasets.simulator import simulate_world

    runs = []
    for seed in range(n):
        run = root / f"lab-seed{seed}-{duration:g}s"
        if not (run / "meta.yaml").exists():
            print(f"simulating {run} ...", flush=True)
            simulate_world("lab", run, seed=seed, duration=duration)
        runs.append(str(run.resolve()))
    return runs


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("runs", nargs="*", help="run directories (the batch)")
    p.add_argument("--simulate", type=int, default=0,
                   help="no runs given: simulate this many lab runs (seeds 0..N-1) as the batch")
    p.add_argument("--duration", type=float, default=30.0,
                   help="--simulate: seconds per run (default 30)")
    p.add_argument("--workers", default="1,2", help="comma-separated worker counts")
    p.add_argument("--repeats", type=int, default=2)
    p.add_argument("--backend", default="batch")
    p.add_argument("--out", default="out/bench_fleet")
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.WARNING)
    logging.getLogger("distributed").setLevel(logging.ERROR)
    counts = [int(x) for x in args.workers.split(",")]
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    if not args.runs:
        if args.simulate < 1:
            p.error("give run directories or --simulate N")
        args.runs = simulated_runs(out / "runs", args.simulate, args.duration)
    load0 = os.getloadavg()
    times: dict[int, list[float]] = {c: [] for c in counts}
    statuses: dict[int, list[str]] = {}
    with contextlib.ExitStack() as stack:
        clients = {c: stack.enter_context(dask_client("local", c)) for c in counts}
        for rep in range(args.repeats):
            for c in counts:
                jobs = [BatchJob(name, run, str(out / f"w{c}-r{rep}" / name), args.backend)
                        for name, run in zip(folder_names(args.runs), args.runs, strict=True)]
                t0 = time.perf_counter()
                res, _ = run_dask(clients[c], batch_job, jobs, _failed, progress=False)
                dt = time.perf_counter() - t0
                times[c].append(dt)
                statuses[c] = [r.status for r in res]
                print(f"repeat {rep} workers {c}: {dt:.1f} s ({os.getloadavg()[0]:.1f} load)",
                      flush=True)
    load1 = os.getloadavg()
    ref = counts[0]
    print(f"\n{len(args.runs)} runs, backend {args.backend}; wall time per batch (Dask LocalCluster)")
    print(f"{'workers':>7} {'median s':>9} {'min s':>7} {'speed-up (median)':>18} {'speed-up (min)':>15}")
    rows: list[dict[str, Any]] = []
    for c in counts:
        med, mn = float(np.median(times[c])), float(np.min(times[c]))
        su_med = float(np.median(times[ref])) / med
        su_min = float(np.min(times[ref])) / mn
        rows.append({"workers": c, "times_s": times[c], "median_s": med, "min_s": mn,
                     "speedup_median": su_med, "speedup_min": su_min, "statuses": statuses[c]})
        print(f"{c:7d} {med:9.1f} {mn:7.1f} {su_med:18.2f} {su_min:15.2f}")
    print(f"load average {load0[0]:.1f} -> {load1[0]:.1f} on {os.cpu_count()} cores "
          "(other processes share the cores: speed-ups are then below what idle cores give)")
    write_text_atomic(out / "fleet.json", json.dumps(
        {"runs": args.runs, "backend": args.backend, "load_average": [load0, load1],
         "cpu_count": os.cpu_count(), "rows": rows}, indent=2))
    return 0 if all(s == "ok" for r in rows for s in r["statuses"]) else 1


if __name__ == "__main__":
    sys.exit(main())
