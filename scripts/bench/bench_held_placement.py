"""Where the final solve's distance from GTSAM's LM comes from, and what placing the
sightings an online run left out does to it (issue 15, docs/noids-offline.md "Placing
the held sightings").

Usage::

    python scripts/bench/bench_held_placement.py [--log victoria] [--spec both+cov_scale=16]
        [--out /tmp/bench_held_placement] [--plot PREFIX]

One online run without ids (iSAM2, the ``[reassociation] online_candidates`` entry
``--spec``; cached in ``--out`` as a pickle, so the final solves can be iterated on),
then the final solve of its association (:func:`lampsam.backend.online_final.final_solve`)
and, on the same answer:

- **oracle**: each left-out sighting (held and never used, or dropped) given to the
  landmark whose majority tree is its file id's (twin ids as one tree), none where that
  tree has no landmark; scoring only;
- **max-mixture**: :func:`lampsam.backend.held_placement.place_into` over the mapped
  landmarks, and with new landmarks (clusters of left-out sightings);
- the known-id batch of lampsam on the file's ids (all sightings), with each pair of
  twin ids (``lampsam.evaluation.twin_ids.twin_map``: known-id landmarks within 1.5 m) as one
  landmark, all pairs and one pair at a time: the known-association optimum a no-ids
  answer that merges the twins is aiming at (its ``chi2`` against the file's ids says
  whether the data pays for the second landmark).

Printed per row: position RMS from GTSAM's LM on the file's graph and from the twin-merged
known-id optimum, landmarks seen 2+ against trees seen 2+, duplicated trees, wrong
sightings (``bench_noids_scale.score``), the description length ``C`` and the CPU of the
step (process s, *loaded*). ``--plot PREFIX`` writes ``PREFIX_lm.png`` and
``PREFIX_twins.png``: per-pose error along the drive from each reference, with where the
left-out sightings were made (:mod:`lampsam.evaluation.held_plots`).
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
import os
import pickle
import time
from collections import Counter
from pathlib import Path
from typing import Any

import gtsam
import numpy as np
from timing import sibling  # scripts/bench/timing.py, a sibling module

from lampsam.backend.config import SlamConfig
from lampsam.backend.graph_log import run_graph_log, run_graph_log_backend
from lampsam.backend.held_placement import place_into
from lampsam.backend.landmark_moves import solve_association
from lampsam.backend.noids_offline import (
    association_cost,
    batch_graph_inputs,
    dropped_sightings,
    group_chi2,
)
from lampsam.backend.online_final import (
    candidate_config,
    final_config,
    final_solve,
    online_association,
)
from lampsam.backend.reassociate import Sightings, first_sight_positions, read_estimate
from lampsam.evaluation import twin_ids
from lampsam.evaluation.held_plots import write_pose_error_plot


def _rms(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.sum((a[:, :2] - b[:, :2]) ** 2, axis=1))))


def main() -> None:  # noqa: PLR0915 (one study, printed in order)
    """Parse arguments, run the study, print one table."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--log", default="victoria")
    ap.add_argument("--spec", default="both+cov_scale=16")
    ap.add_argument("--out", default="/tmp/bench_held_placement")
    ap.add_argument("--plot", default="", help="figure path prefix (none: no figure)")
    args = ap.parse_args()
    logging.basicConfig(level=logging.ERROR)
    bench = sibling("bench_online_final")
    scale = sibling("bench_noids_scale")
    marks = sibling("bench_landmark_logs")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    g = bench.load_log(scale, args.log, out)
    n = len(g.pose_ids)
    print("load average (1, 5, 15 min): " + ", ".join(f"{v:.1f}" for v in os.getloadavg()))
    lm = marks.poses_of(gtsam.LevenbergMarquardtOptimizer(
        marks.gtsam_graph(g, SlamConfig()), marks.gtsam_isam2(g, SlamConfig())[0],
        gtsam.LevenbergMarquardtParams()).optimize(), n)
    known = run_graph_log(g, "batch", SlamConfig())
    twins = twin_ids.twin_map(g, {int(x.id): np.asarray(x.position[:2], float)
                               for x in list(known.landmarks) + list(known.provisional)})
    trees = Counter(twins.get(x.landmark, x.landmark) for ss in g.sightings for x in ss)
    n_trees2 = sum(1 for v in trees.values() if v >= 2)

    cache = out / f"{args.log}_{args.spec.replace('/', '_')}.pkl"
    if cache.exists():
        online_poses, online_extra, s, lm_on, lm_prov = pickle.loads(cache.read_bytes())
    else:
        online, be = run_graph_log_backend(g, "isam2", candidate_config(SlamConfig(), args.spec),
                                           known_ids=False)
        if online.status != "ok" or be is None:
            raise SystemExit(f"online run {args.spec}: {online.status}")
        s = online_association(be, online)
        online_poses, online_extra = online.poses, dict(online.extra)
        lm_on, lm_prov = list(online.landmarks), list(online.provisional)
        cache.write_bytes(pickle.dumps((online_poses, online_extra, s, lm_on, lm_prov)))

    @dataclasses.dataclass
    class _Online:  # what final_solve reads of the online result
        poses: np.ndarray
        extra: dict[str, float]
        landmarks: list[Any]
        provisional: list[Any]

    cfg16 = candidate_config(SlamConfig(), args.spec)
    solve_cfg = dataclasses.replace(SlamConfig(), pose2_odometry=cfg16.pose2_odometry)
    cfg = final_config(solve_cfg)
    c_new = cfg.association.new_threshold(2)
    prior, odo = batch_graph_inputs(g, cfg)

    # the twin-merged known-id optimum (all sightings at the file's ids, each twin pair one)
    k = np.array([kk for kk, ss in enumerate(g.sightings) for _ in ss], int)
    zz = np.array([[x.bearing, x.range] for ss in g.sightings for x in ss])
    rr = np.array([np.asarray(x.cov, float)[:2, :2] for ss in g.sightings for x in ss])
    fid = np.array([x.landmark for ss in g.sightings for x in ss], int)

    def known_solve(lid: np.ndarray) -> tuple[np.ndarray, float]:
        s_k = Sightings(k, zz, rr, lid)
        g2, v2, _ = solve_association(prior, odo, s_k, lid, lm,
                                      first_sight_positions(lm, s_k), {}, c_new)
        co, cs, _, _ = group_chi2(g2, v2)
        return read_estimate(v2, n, [])[0], co + cs

    file_poses, file_chi2 = known_solve(fid)
    merged = np.array([twins.get(int(f), int(f)) for f in fid])
    ref, ref_chi2 = known_solve(merged)
    print(f"\n{args.log}: the file's ids, all sightings: {_rms(file_poses, lm):.3f} m from LM, "
          f"chi2 {file_chi2:.1f}; twin pairs merged: {_rms(ref, lm):.3f} m, chi2 "
          f"{ref_chi2:.1f} (c_new {c_new:.2f} per landmark)")
    for a, b in sorted((a, b) for a, b in twins.items() if a != b):
        p1, c1 = known_solve(np.where(fid == a, b, fid))
        print(f"  merging only {a} into {b} ({np.sum(fid == a)} + {np.sum(fid == b)} "
              f"sightings): {_rms(p1, lm):.3f} m from LM, chi2 +{c1 - file_chi2:.1f}")

    print("\n| log | run | RMS from LM (from the twin-merged optimum) [m] | 2+ / trees 2+ "
          "| dup | wrong / sightings | C | CPU [s] |")
    print("|---|---|---|---|---|---|---|---|")
    runs: dict[str, np.ndarray] = {}

    def row(label: str, ss: Sightings, poses: np.ndarray, cost: float, cpu: float) -> None:
        mapped, dup, wrong = scale.score(ss, scale.tree_ids(g, ss, twins))
        runs[label] = poses
        print(f"| {args.log} | {label} | {_rms(poses, lm):.3f} ({_rms(poses, ref):.3f}) | "
              f"{mapped} / {n_trees2} | {dup} | {wrong} / {len(ss.k)} | {cost:.1f} | "
              f"{cpu:.1f} |", flush=True)

    def cost_of(ss: Sightings, graph: gtsam.NonlinearFactorGraph, values: gtsam.Values
                ) -> tuple[np.ndarray, float]:
        poses, lms = read_estimate(values, n, np.unique(ss.lid).tolist())
        co, cs, _, _ = group_chi2(graph, values)
        return poses, association_cost(co + cs, len(lms),
                                       sum(len(x) for x in g.sightings) - len(ss.k), c_new)

    c0 = time.process_time()
    run = final_solve(g, solve_cfg, _Online(online_poses, online_extra, lm_on, lm_prov),  # type: ignore[arg-type]
                      Sightings(s.k.copy(), s.z, s.r, s.lid.copy()))
    row("final solve", run.sightings, run.poses, run.cost, time.process_time() - c0)
    dk, dz, dr = dropped_sightings(g, run.sightings)
    print(f"| {args.log} | ({len(dk)} sightings left out) | | | | | | |")

    # oracle: each left-out sighting to the landmark of its tree
    rid = scale.tree_ids(g, run.sightings, twins)
    owner: dict[int, tuple[int, int]] = {}
    for i in np.unique(run.sightings.lid).tolist():
        t, c = Counter(rid[run.sightings.lid == i].tolist()).most_common(1)[0]
        if t not in owner or c > owner[t][1]:
            owner[t] = (i, c)
    held_tree = scale.tree_ids(g, Sightings(dk, dz, dr, np.zeros(len(dk), int)), twins)
    seen = {(int(a), int(b)) for a, b in zip(run.sightings.k, run.sightings.lid, strict=True)}
    to = np.array([owner.get(int(t), (-1, 0))[0] for t in held_tree.tolist()], int)
    to = np.array([i if (int(kk), int(i)) not in seen else -1
                   for kk, i in zip(dk.tolist(), to.tolist(), strict=True)], int)
    t = to >= 0
    s_or = Sightings(np.r_[run.sightings.k, dk[t]], np.r_[run.sightings.z, dz[t]],
                     np.r_[run.sightings.r, dr[t]], np.r_[run.sightings.lid, to[t]])
    c0 = time.process_time()
    g_or, v_or, _ = solve_association(prior, odo, s_or, s_or.lid, run.poses, run.landmarks, {},
                                      c_new)
    row(f"+ oracle: {int(t.sum())} to their tree's landmark", s_or,
        *cost_of(s_or, g_or, v_or), time.process_time() - c0)

    for label, gate in (("max-mixture", None), ("max-mixture + new landmarks",
                                                 cfg.association.gate(2))):
        c0 = time.process_time()
        s_m = Sightings(run.sightings.k, run.sightings.z, run.sightings.r,
                        run.sightings.lid.copy())
        placed = place_into(prior, odo, s_m, run.graph, run.values, dk, dz, dr, c_new, gate)
        if placed is None:
            print(f"| {args.log} | + {label}: nothing placed | | | | | | |")
            continue
        s2, g2, v2, n_placed = placed
        row(f"+ {label}: {n_placed} placed", s2, *cost_of(s2, g2, v2),
            time.process_time() - c0)
    row("known ids, twin pairs merged", Sightings(k, zz, rr, merged), ref, float("nan"), 0.0)

    if args.plot:
        base = {x: runs[x] for x in list(runs)[:4]}
        write_pose_error_plot(
            Path(f"{args.plot}_lm.png"), lm, {**base, "known ids, twin pairs merged": ref}, dk,
            f"{args.log} (no ids, {args.spec}): error from GTSAM's LM on the file's ids",
            "GTSAM's LM (file ids)")
        write_pose_error_plot(
            Path(f"{args.plot}_twins.png"), ref, base, dk,
            f"{args.log}: error from the known-id optimum with the twin pairs merged",
            "known ids, twins merged")
        print(f"figures: {args.plot}_lm.png, {args.plot}_twins.png")


if __name__ == "__main__":
    main()
