"""Speed-up of ``lampsam batch`` on Dask from 1 to 2 (or more) workers.

Usage::

    python scripts/bench/bench_fleet.py RUN [RUN ...] [--workers 1,2] [--repeats 3]
        [--backend batch] [--out out/bench_fleet]
    python scripts/bench/bench_fleet.py --simulate 4 [--duration 30]   # one command: the 1- vs 2-worker speed-up

``--simulate N``: without run directories, N lab runs (seeds 0..N-1, ``--duration``
seconds each) are simulated once into ``OUT/runs`` (reused when present) and make
the batch: the 1- vs 2-worker speed-up on a 4-log batch is then one command.

For each worker count a ``distributed.LocalCluster`` (single-threaded worker
processes on 127.0.0.1) is started and timed (**start-up**: cluster and workers up).
Then, round by round, the same batch of runs
(:func:`lampsam.evaluation.batch.batch_job` per run through
:func:`lampsam.evaluation.fleet.run_dask`) is timed on each cluster in turn
(interleaved, so a change of machine load hits every count alike):

* round 0, **cold**: the workers' first jobs import lampsam, GTSAM and OpenCV
  (what ``--dask local`` costs a user, with the start-up);
* rounds 1.., **warm**: the same cluster, already warmed up (what a user with a
  running cluster, ``--dask ADDRESS``, sees from the second batch on).

Printed per worker count: start-up, cold batch, start-up + cold batch, warm batch
(median and minimum over the warm rounds), and each as a speed-up against the first
count; then, from each job's own clock (process CPU and wall time, taken inside the
job), where a warm batch's wall time goes: the busiest worker's busy time (the
floor set by how the jobs split), the mean busy time per worker (the floor with a
perfect split) and the rest (scheduling, transfer, result gathering, the client's
polling), the CPU seconds of all jobs (which grow when two jobs share the
machine: caches, memory bandwidth, other processes), and a CPU-time speed-up (all
jobs' CPU with the first count over the busiest worker's; robust to machine load). Load average before and after
(the machine may be shared: the speed-up is only meaningful with idle cores).
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

Timed = tuple[BatchResult, dict[str, float]]


def timed_batch_job(job: BatchJob) -> Timed:
    """:func:`batch_job` with the job's own clock: worker pid, start/end (wall, s), CPU s."""
    w0, c0 = time.time(), time.process_time()
    res = batch_job(job)
    return res, {"pid": float(os.getpid()), "start": w0, "end": time.time(),
                 "cpu": time.process_time() - c0}


def _failed(job: BatchJob, reason: str) -> Timed:
    return BatchResult(job, reason), {}


def _warm_up() -> None:
    """The imports a batch job's first call pays (run on every worker of a warm cluster)."""
    import cv2  # noqa: F401
    import gtsam  # noqa: F401

    import lampsam.backend.slam  # noqa: F401
    import lampsam.datasets.logrun  # noqa: F401


def split(records: list[dict[str, float]], wall: float) -> dict[str, float]:
    """Where a batch's wall time went, from the jobs' own clocks.

    Returns:
        ``busiest_s`` (the worker with the most job time: the floor set by the split),
        ``mean_busy_s`` (job time per worker: the floor of a perfect split),
        ``other_s`` (wall minus the busiest: scheduling, transfer, gathering, polling),
        ``cpu_s`` (CPU time of all jobs), ``busiest_cpu_s`` (the largest CPU time of
        one worker's jobs), ``jobs_per_worker`` (max), ``workers_used``.
    """
    busy: dict[float, float] = {}
    busy_cpu: dict[float, float] = {}
    count: dict[float, int] = {}
    cpu = 0.0
    for r in records:
        if not r:
            continue
        busy[r["pid"]] = busy.get(r["pid"], 0.0) + r["end"] - r["start"]
        busy_cpu[r["pid"]] = busy_cpu.get(r["pid"], 0.0) + r["cpu"]
        count[r["pid"]] = count.get(r["pid"], 0) + 1
        cpu += r["cpu"]
    if not busy:
        return {}
    busiest = max(busy.values())
    return {"busiest_s": busiest, "mean_busy_s": sum(busy.values()) / len(busy),
            "other_s": wall - busiest, "cpu_s": cpu, "busiest_cpu_s": max(busy_cpu.values()),
            "jobs_per_worker": float(max(count.values())), "workers_used": float(len(busy))}


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
    p.add_argument("--repeats", type=int, default=3,
                   help="rounds per count: one cold, the others warm (default 3)")
    p.add_argument("--backend", default="batch")
    p.add_argument("--out", default="out/bench_fleet")
    args = p.parse_args(argv)
    if args.repeats < 2:
        p.error("--repeats must be >= 2 (one cold round, at least one warm)")
    logging.basicConfig(level=logging.WARNING)
    import distributed  # noqa: F401  (its import sets its loggers' levels: quiet them after it)

    logging.getLogger("distributed").setLevel(logging.ERROR)
    counts = [int(x) for x in args.workers.split(",")]
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    if not args.runs:
        if args.simulate < 1:
            p.error("give run directories or --simulate N")
        args.runs = simulated_runs(out / "runs", args.simulate, args.duration)
    load0 = os.getloadavg()
    startup: dict[int, float] = {}
    times: dict[int, list[float]] = {c: [] for c in counts}
    splits: dict[int, list[dict[str, float]]] = {c: [] for c in counts}
    statuses: dict[int, list[str]] = {}
    with contextlib.ExitStack() as stack:
        clients = {}
        for c in counts:
            t0 = time.perf_counter()
            clients[c] = stack.enter_context(dask_client("local", c))
            clients[c].wait_for_workers(c)
            startup[c] = time.perf_counter() - t0
            print(f"workers {c}: cluster start-up {startup[c]:.1f} s", flush=True)
        for rep in range(args.repeats):
            if rep == 1:  # every worker has run a job by now; make sure of the imports anyway
                for c in counts:
                    clients[c].run(_warm_up)
            for c in counts:
                jobs = [BatchJob(name, run, str(out / f"w{c}-r{rep}" / name), args.backend)
                        for name, run in zip(folder_names(args.runs), args.runs, strict=True)]
                t0 = time.perf_counter()
                res, _ = run_dask(clients[c], timed_batch_job, jobs, _failed, progress=False)
                dt = time.perf_counter() - t0
                times[c].append(dt)
                statuses[c] = [r.status for r, _ in res]
                splits[c].append(split([rec for _, rec in res], dt))
                sp = splits[c][-1]
                print(f"round {rep} ({'cold' if rep == 0 else 'warm'}) workers {c}: {dt:.1f} s; "
                      f"busiest worker {sp.get('busiest_s', float('nan')):.1f} s, jobs' CPU "
                      f"{sp.get('cpu_s', float('nan')):.1f} s ({os.getloadavg()[0]:.1f} load)",
                      flush=True)
    load1 = os.getloadavg()
    ref = counts[0]
    rows: list[dict[str, Any]] = []
    for c in counts:
        warm = times[c][1:]
        med = {k: float(np.median([sp[k] for sp in splits[c][1:] if sp]))
               for k in ("busiest_s", "mean_busy_s", "other_s", "cpu_s", "busiest_cpu_s")}
        rows.append({"workers": c, "startup_s": startup[c], "cold_s": times[c][0],
                     "with_startup_s": startup[c] + times[c][0],
                     "warm_median_s": float(np.median(warm)), "warm_min_s": float(np.min(warm)),
                     "warm_split_median": med, "times_s": times[c], "splits": splits[c],
                     "statuses": statuses[c]})
    base = rows[0]
    print(f"\n{len(args.runs)} runs, backend {args.backend}; wall time per batch "
          f"(Dask LocalCluster), speed-up against {ref} worker(s) in brackets")
    print(f"{'workers':>7} {'start-up s':>11} {'cold batch s':>13} {'start-up + cold s':>18} "
          f"{'warm median s':>14} {'warm min s':>11}")
    for r in rows:
        def su(key: str, r: dict[str, Any] = r) -> str:
            return f"({base[key] / r[key]:.2f}x)"
        print(f"{r['workers']:7d} {r['startup_s']:11.1f} {r['cold_s']:7.1f} {su('cold_s'):>5} "
              f"{r['with_startup_s']:11.1f} {su('with_startup_s'):>6} "
              f"{r['warm_median_s']:7.1f} {su('warm_median_s'):>6} "
              f"{r['warm_min_s']:5.1f} {su('warm_min_s'):>5}")
    print("\nwarm batches, medians, from the jobs' own clocks:")
    print(f"{'workers':>7} {'wall s':>7} {'busiest worker s':>17} {'mean busy s':>12} "
          f"{'other s':>8} {'jobs CPU s':>11} {'CPU x':>6} {'CPU speed-up':>13}")
    for r in rows:
        m = r["warm_split_median"]
        print(f"{r['workers']:7d} {r['warm_median_s']:7.1f} {m['busiest_s']:17.1f} "
              f"{m['mean_busy_s']:12.1f} {m['other_s']:8.1f} {m['cpu_s']:11.1f} "
              f"{m['cpu_s'] / base['warm_split_median']['cpu_s']:6.2f} "
              f"{base['warm_split_median']['busiest_cpu_s'] / m['busiest_cpu_s']:12.2f}x")
    print("(CPU speed-up: the jobs' CPU with the first count over the busiest worker's jobs' CPU;\n"
          " it counts the split and the contention but not the waiting for a core, so it stays\n"
          " meaningful on a loaded machine, unlike the wall-time ratios above)")
    print(f"load average {load0[0]:.1f} -> {load1[0]:.1f} on {os.cpu_count()} cores "
          "(other processes share the cores: speed-ups are then below what idle cores give)")
    write_text_atomic(out / "fleet.json", json.dumps(
        {"runs": args.runs, "backend": args.backend, "load_average": [load0, load1],
         "cpu_count": os.cpu_count(), "rows": rows}, indent=2))
    return 0 if all(s == "ok" for r in rows for s in r["statuses"]) else 1


if __name__ == "__main__":
    sys.exit(main())
