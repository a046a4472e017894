"""Online no-ids association defaults: defaults against each option against both, per log.

Usage::

    python scripts/bench/bench_noids_defaults.py [--logs vp1k,city,mrclam,...]
        [--variants defaults,unique,check,both] [--out DIR]

For each log (``bench_noids_scale.load_log`` names; ``victoria3500`` = Victoria Park's
first 3,500 poses, ``vp1k16`` = vp1k with ``cov_scale`` 16; every ``victoria*`` run uses
``[pose2_odometry] cov_scale = 16`` as docs/failures.md does) and each variant
(``defaults``; ``unique`` = ``[association] planar_unique``; ``check`` =
``revisit_check``; ``both``), one online iSAM2 run without ids. Printed per run: position RMS from lampsam's known-id
iSAM2 on the same log (fast path) and, for the synthetic logs, from the truth; the
landmarks kept (2+ sightings) against the file ids sighted twice or more; held
sightings (held / given back / by the check / never used); "diverged"
(RMS from the known-id run above :data:`DIVERGED_M`, or a failed run); process CPU
seconds (*loaded* machine: compare within one invocation only).
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
import math
import os
import time
from collections import Counter
from pathlib import Path

import numpy as np
from timing import sibling  # scripts/bench/timing.py, a sibling module

from lampsam.backend.config import SlamConfig
from lampsam.backend.graph_log import run_graph_log
from lampsam.datasets.graph_text import GraphLog, read_vertices

#: A run whose position RMS from the known-id run exceeds this (m) counts as diverged.
DIVERGED_M = 5.0
VARIANTS = {
    "defaults": {},
    "unique": {"planar_unique": True},
    "check": {"revisit_check": True},
    "both": {"planar_unique": True, "revisit_check": True},
}



def load(name: str, out: Path, scale_mod, bench) -> tuple[GraphLog, float, np.ndarray | None]:  # type: ignore[no-untyped-def]
    """``(log, cov_scale, truth (n, 3) or None)`` of a named log."""
    base = {"victoria3500": "victoria", "vp1k16": "vp1k"}.get(name, name)
    g = scale_mod.load_log(base, out)
    if name == "victoria3500":
        g = bench.first_poses(g, 3500)
    cov = 16.0 if name.startswith("victoria") or name == "vp1k16" else 1.0
    truth = None
    stem = {"synthetic": "synthetic"}.get(name, f"heldout_{name}")
    tpath = out / f"{stem}_truth.txt"
    if name in ("synthetic", "grid", "loop", "odo2x") and tpath.exists():
        v = read_vertices(tpath)
        truth = np.array([v[i] for i in g.pose_ids])
    return g, cov, truth


def rms(a: np.ndarray, b: np.ndarray) -> float:
    """Position RMS between two (n, 3) trajectories, m."""
    return float(np.sqrt(np.mean(np.sum((a[:, :2] - b[:, :2]) ** 2, axis=1))))


def main() -> None:
    """Run every log and variant, print one table row per run."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--logs", default="vp1k,vp1k16,city,mrclam,synthetic,grid,loop,odo2x,"
                                      "victoria3500,victoria")
    ap.add_argument("--variants", default="defaults,unique,check,both")
    ap.add_argument("--out", default="/tmp/bench_noids_defaults")
    args = ap.parse_args()
    logging.basicConfig(level=logging.ERROR)
    bench = sibling("bench_landmark_logs")
    scale_mod = sibling("bench_noids_scale")
    out = Path(args.out)
    print("load average (1, 5, 15 min): " + ", ".join(f"{v:.1f}" for v in os.getloadavg()))
    print("| log | variant | RMS vs known id [m] | RMS vs truth [m] | landmarks 2+ / ids 2+ | "
          "held / given back / check / unused | diverged | CPU [s] |")
    print("|---|---|---|---|---|---|---|---|", flush=True)
    for name in args.logs.split(","):
        g, cov, truth = load(name, out, scale_mod, bench)
        base = SlamConfig()
        base = dataclasses.replace(base, pose2_odometry=dataclasses.replace(
            base.pose2_odometry, cov_scale=cov))
        ref = run_graph_log(g, "isam2", base).poses
        seen2 = sum(1 for v in Counter(s.landmark for ss in g.sightings for s in ss).values()
                    if v >= 2)
        if truth is not None:
            print(f"| {name} | known ids | 0 | {rms(ref, truth):.3f} | | | | |", flush=True)
        for var in args.variants.split(","):
            cfg = dataclasses.replace(base, association=dataclasses.replace(
                base.association, **VARIANTS[var]))  # type: ignore[arg-type]
            c0 = time.process_time()
            try:
                r = run_graph_log(g, "isam2", cfg, known_ids=False)
            except Exception as exc:  # noqa: BLE001 (a failed run is a result here)
                print(f"| {name} | {var} | failed: {type(exc).__name__}: {exc} | | | | yes | "
                      f"{time.process_time() - c0:.1f} |", flush=True)
                continue
            cpu = time.process_time() - c0
            e = r.extra
            d = rms(r.poses, ref)
            dt = f"{rms(r.poses, truth):.3f}" if truth is not None else ""
            held = (f"{e.get('n_held', 0):.0f} / {e.get('n_held_given_back', 0):.0f} / "
                    f"{e.get('n_revisit_resolved', 0):.0f} / "
                    f"{e.get('n_held_unused', 0):.0f}")
            div = "yes" if (not math.isfinite(d) or d > DIVERGED_M or r.status != "ok") else ""
            print(f"| {name} | {var} | {d:.4f} | {dt} | {len(r.landmarks)} / {seen2} | {held} | "
                  f"{div} | {cpu:.1f} |", flush=True)


if __name__ == "__main__":
    main()
