"""Cost of iSAM2's divergence check (:meth:`~lampsam.backend.isam2_update.Isam2Updates._damp_divergence`).

Usage::

    python scripts/bench/bench_divergence_check.py --lab RUN_DIR [--repeats 5]

``RUN_DIR`` is a simulated ceiling run (``lampsam simulate lab --seed 3 --out RUN_DIR``:
173 s, 2,601 frames, the speed targets' run of ``bench_backends.py``; ``--duration 30``
for a short one). Its frames are the simulator's truth projections (0.5 px noise, seed
0; no frontend), made once. iSAM2 (defaults, lamps + corners) then runs the whole
run with the check on and off, round-robin (one run of each per round, ``--repeats``
rounds, the same invocation). Printed per variant: median process-CPU seconds of the
run, median summed iSAM2 update wall time, and the ratio to the check-off run (the
reference); for the check-on runs also the calls (relinearising updates checked), the
process-CPU time inside the check (median of the runs' sums) per call and as a share of
the run's CPU. The two variants' trajectories are compared (identical unless the check
damped a step).
"""

from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path
from typing import Any

import numpy as np

from lampsam.backend.config import SlamConfig
from lampsam.backend.isam2_update import Isam2Updates
from lampsam.backend.slam import drive, iter_steps, make_backend, make_frames, start_pose_of
from lampsam.datasets.logrun import read_run


def _timed_check() -> tuple[list[float], Any]:
    """Wrap ``Isam2Updates._damp_divergence`` to record each call's process-CPU time;
    returns ``(times, original)``."""
    times: list[float] = []
    original = Isam2Updates._damp_divergence

    def timed(self: Isam2Updates) -> bool:
        t0 = time.process_time()
        out = original(self)
        times.append(time.process_time() - t0)
        return out

    Isam2Updates._damp_divergence = timed  # type: ignore[method-assign]
    return times, original


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--lab", type=Path, required=True, help="a simulated ceiling run")
    ap.add_argument("--repeats", type=int, default=5)
    args = ap.parse_args()
    run = read_run(args.lab)
    frames = list(make_frames(run, "truth", rng_seed=0)[0])
    steps = list(iter_steps(run.odometry, frames))
    config = SlamConfig()
    times, original = _timed_check()
    rows: dict[bool, dict[str, list[float]]] = {c: {"cpu": [], "update": [], "calls": [],
                                                   "check": [], "damped": []} for c in (True, False)}
    poses: dict[bool, np.ndarray] = {}
    try:
        for _ in range(args.repeats):
            for check in (True, False):
                be = make_backend("isam2", run.rig.odometry, config, start_pose_of(run),
                                  run.rig.camera)
                be.divergence_check = check  # type: ignore[attr-defined]
                times.clear()
                c0 = time.process_time()
                result = drive(be, steps)
                cpu = time.process_time() - c0
                assert result.status == "ok", result.status
                r = rows[check]
                r["cpu"].append(cpu)
                r["update"].append(float(np.sum(be.update_times)))  # type: ignore[attr-defined]
                r["calls"].append(len(times))
                r["check"].append(float(np.sum(times)))
                r["damped"].append(float(result.extra.get("n_damped_rebuilds", 0)))
                poses[check] = result.poses
    finally:
        Isam2Updates._damp_divergence = original  # type: ignore[method-assign]
    ref = statistics.median(rows[False]["cpu"])
    print(f"run {args.lab}: {len(steps)} steps, {len(frames)} frames, "
          f"{args.repeats} rounds (round-robin); load average "
          + ", ".join(f"{v:.1f}" for v in __import__("os").getloadavg()))
    print("| check | run CPU s (median) | ratio to off | iSAM2 update wall s | calls | "
          "check CPU ms/call | check share of run CPU | damped |")
    print("|---|---|---|---|---|---|---|---|")
    for check in (True, False):
        r = rows[check]
        cpu = statistics.median(r["cpu"])
        calls = statistics.median(r["calls"])
        inside = statistics.median(r["check"]) if check else float("nan")
        per = inside / calls if check and calls else float("nan")
        share = inside / cpu if check else float("nan")
        print(f"| {'on' if check else 'off'} | {cpu:.3f} | {cpu / ref:.3f} | "
              f"{statistics.median(r['update']):.3f} | {calls:.0f} | {per * 1e3:.2f} | "
              f"{share:.3%} | {statistics.median(r['damped']):.0f} |")
    same = poses[True].shape == poses[False].shape and np.array_equal(poses[True], poses[False])
    print(f"trajectories identical (check on vs off, last round): {same}")


if __name__ == "__main__":
    main()
