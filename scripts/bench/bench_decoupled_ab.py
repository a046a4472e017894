"""Benchmark: the decoupled pipeline of this tree against another tree's, interleaved.

Usage::

    python scripts/bench/bench_decoupled_ab.py --run RUN --ref /path/to/ref-parent \
        [--repeats 3] [--max-lag 15]

with ``RUN`` from ``lampsam simulate lab --seed 3 --out RUN`` and ``--ref`` a directory
whose ``lampsam`` package is the reference (e.g. a checkout of main: its parent
directory, as ``PYTHONPATH``). Each round runs ``lampsam slam --online decoupled`` as
:func:`lampsam.backend.online_run.run_slam_decoupled` does it (frontend and tracking in
one process, the backend in a worker, lazy frames, the final optimisation in the
worker after the timed steps) once with this tree and once with the reference, each
in a fresh interpreter, alternating which goes first; the load hits both alike.

Printed per tree (medians over the rounds) and as ratios this / reference: the wall
clock from the start to the last step's estimate back and its x real time, the
tracking process's CPU, the worker's CPU (whole, and until the stop mark where the
tree reports it), its steps' CPU, the tracked-pose latency (frame arrival -> pose,
p95) and the keyframe latency p95, with the load average of each run.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np

#: Run in a fresh interpreter with the tree on ``PYTHONPATH``: one decoupled run, its figures as JSON.
_CHILD = r"""
import json, os, sys, time
import numpy as np
from lampsam.backend.config import SlamConfig
from lampsam.backend.online_run import online_figures
from lampsam.backend.pipelined import FrameTimes, frame_source
from lampsam.backend.slam import iter_steps, start_pose_of
from lampsam.backend.tracking import run_decoupled
from lampsam.datasets.logrun import read_run
import lampsam
run = read_run(sys.argv[1])
max_lag = None if int(sys.argv[2]) < 0 else int(sys.argv[2])
times = FrameTimes()
w0, c0 = time.perf_counter(), time.process_time()
src = frame_source(run.images, run.rig.camera, mode="sequential", times=times)
tm = run_decoupled(iter_steps(run.odometry, src), "isam2", run.rig.odometry, SlamConfig(),
                   start_pose_of(run), run.rig.camera, max_lag=max_lag, finish=True)
cpu = time.process_time() - c0
duration = float(run.odometry.t[-1] - run.odometry.t[0])
figs = online_figures(tm, np.asarray(times.arrival, float), duration, w0, cpu)
figs["tree"] = os.path.dirname(lampsam.__file__)
figs["load"] = os.getloadavg()[0]
print("RESULT " + json.dumps(figs))
"""

#: (label, summary key) of the printed figures.
FIGURES = (("wall to last step s", "online_wall_s"), ("x real time", "online_x_real_time"),
           ("tracking process CPU s", "online_tracking_cpu_s"),
           ("worker CPU s (all)", "online_backend_cpu_s"),
           ("worker CPU s (to stop mark)", "online_backend_online_cpu_s"),
           ("worker steps CPU s", "online_backend_step_cpu_s"),
           ("tracked latency p95 ms", "online_tracked_latency_ms_p95"),
           ("keyframe latency p95 ms", "online_keyframe_latency_ms_p95"), ("load", "load"))


def one(tree: Path, run: Path, max_lag: int) -> dict[str, float]:
    """One decoupled run with ``tree`` first on the path: its figures."""
    env = dict(os.environ, PYTHONPATH=str(tree), OPENBLAS_NUM_THREADS="1", OMP_NUM_THREADS="1")
    out = subprocess.run([sys.executable, "-c", _CHILD, str(run), str(max_lag)], env=env,
                         capture_output=True, text=True, check=False, cwd="/")
    line = next((s for s in out.stdout.splitlines() if s.startswith("RESULT ")), None)
    if out.returncode != 0 or line is None:
        raise SystemExit(f"run with {tree} failed:\n{out.stderr[-2000:]}")
    return dict(json.loads(line[len("RESULT "):]))


def main() -> None:
    """Alternate the two trees for ``--repeats`` rounds; print medians and ratios."""
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--run", type=Path, required=True, help="a simulated lab run directory")
    p.add_argument("--ref", type=Path, required=True,
                   help="PYTHONPATH entry holding the reference lampsam package")
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--max-lag", type=int, default=15, help="back-pressure, steps (-1: none)")
    args = p.parse_args()
    this = Path(__file__).resolve().parents[3]  # the parent of this tree's lampsam package
    trees = {"this": this, "ref": args.ref.resolve()}
    rows: dict[str, list[dict[str, float]]] = {"this": [], "ref": []}
    for k in range(args.repeats):
        order = ("this", "ref") if k % 2 == 0 else ("ref", "this")
        for name in order:
            r = one(trees[name], args.run, args.max_lag)
            rows[name].append(r)
            print(f"[round {k + 1}] {name} ({r['tree']}): " + ", ".join(
                f"{label} {float(r.get(key, np.nan)):.3g}" for label, key in FIGURES), flush=True)
    print(f"\nmedians of {args.repeats} rounds, max lag {args.max_lag}")
    print("| figure | this | ref | this / ref |\n|---|---:|---:|---:|")
    for label, key in FIGURES:
        a = float(np.median([r.get(key, np.nan) for r in rows["this"]]))
        b = float(np.median([r.get(key, np.nan) for r in rows["ref"]]))
        print(f"| {label} | {a:.3g} | {b:.3g} | {a / b:.3g} |")


if __name__ == "__main__":
    main()
