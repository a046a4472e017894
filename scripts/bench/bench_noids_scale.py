"""No ids on graph logs: the offline pipeline's odometry-scale choice and its passes.

Usage::

    python scripts/bench/bench_noids_scale.py [--logs victoria,synthetic,mrclam,city]
        [--poses N] [--scales 1,4,16,64] [--passes 20] [--set SECTION.KEY=VALUE ...]

For each log and each candidate odometry variance factor ``q``
(:mod:`lampsam.backend.noids_offline`): the no-ids EKF pass at ``q``, then the batch
re-association with the log's stated noise. Printed per pass (pass 0 = the EKF's online
answer): landmarks with 2+ sightings ("mapped"), file ids owning two or more landmarks
("dup"), sightings whose landmark's majority file id is another ("wrong"), and the
position RMS from lampsam's known-id batch (fast path, within 0.02 m of GTSAM's LM on
every log, docs/graph-backend.md). Per candidate: chi-square per dof of the odometry and
the sighting groups at the optimum, the description length ``C`` and which candidate it
picks, CPU s of the EKF pass and of the batch passes. "dup" and "wrong" count trees: file
ids never sighted together and under 1.5 m apart in the known-id map are one tree
(:func:`lampsam.evaluation.twin_ids.twin_map`; Victoria Park has four such pairs). The last pass of a candidate is
the description-length merges and splits (``[reassociation] cost_moves``) when they moved
anything; the chosen candidate's final pass (``[reassociation] final_pass``,
:mod:`lampsam.backend.final_moves`) is one more line when it moved anything, and the
chosen row of the summary is its answer.

Logs: ``victoria`` (GTSAM's ``victoria_park.txt``), ``synthetic``
(:mod:`lampsam.datasets.landmark_log_sim`, seed 0, 3,000 poses), ``mrclam`` (the shared
MRCLAM ds0 robot 1, 300 s, as ``bench_landmark_logs.py`` builds it), ``city`` (GTSAM's
``cityTrees_reduced_1k.g2o``, 1,000 poses, 66 trees), ``vp1k`` (GTSAM's
``victoriaPark_reduced_1k.g2o``, 1,000 poses: held out, nothing was tuned on it), ``grid``,
``loop``, ``odo2x`` (:mod:`lampsam.datasets.landmark_log_heldout`: held out). The file ids are read only to
score the association. CPU figures are process time (the machine may be shared).
"""

from __future__ import annotations

import argparse
import importlib.util
import logging
import os
import sys
import time
from collections import Counter
from pathlib import Path

import gtsam
import numpy as np

from lampsam.backend.config import SlamConfig
from lampsam.backend.graph_log import run_graph_log
from lampsam.backend.noids_offline import PassReport, select_scale
from lampsam.backend.reassociate import Pass, Sightings
from lampsam.datasets.graph_text import GraphLog, read_graph_text
from lampsam.datasets.landmark_log_heldout import HELD_OUT, write_held_out
from lampsam.datasets.landmark_log_sim import LandmarkLogSpec, write_landmark_log
from lampsam.evaluation import twin_ids

_HERE = Path(__file__).resolve().parent


def _bench_module():  # type: ignore[no-untyped-def]
    spec = importlib.util.spec_from_file_location("bench_landmark_logs",
                                                  _HERE / "bench_landmark_logs.py")
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    sys.modules["bench_landmark_logs"] = mod
    spec.loader.exec_module(mod)
    return mod


def load_log(name: str, out: Path) -> GraphLog:
    """One of the named logs (module doc)."""
    data = Path(gtsam.findExampleDataFile("victoria_park.txt")).parent
    if name == "victoria":
        return read_graph_text(data / "victoria_park.txt")
    if name == "city":
        return read_graph_text(data / "cityTrees_reduced_1k.g2o")
    if name == "vp1k":
        return read_graph_text(data / "victoriaPark_reduced_1k.g2o")
    if name == "synthetic":
        out.mkdir(parents=True, exist_ok=True)
        p, _ = write_landmark_log(out / "synthetic.txt", LandmarkLogSpec(), np.random.default_rng(0))
        return read_graph_text(p)
    if name in HELD_OUT:  # held out (datasets/landmark_log_heldout.py): never tuned on
        out.mkdir(parents=True, exist_ok=True)
        p, _ = write_held_out(out / f"heldout_{name}.txt", name)
        return read_graph_text(p)
    if name == "mrclam":
        from lampsam.datasets.mrclam import mrclam_run
        from lampsam.datasets.paths import shared_dataset

        root = shared_dataset("mrclam_ds0")
        if root is None:
            raise SystemExit("mrclam: shared dataset mrclam_ds0 not found")
        g, _ = _bench_module().graph_log_from_run(mrclam_run(root, duration=300.0), SlamConfig())
        return g
    raise SystemExit(f"unknown log {name!r} (victoria, synthetic, mrclam, city, vp1k, "
                     f"{', '.join(HELD_OUT)})")


def file_ids(g: GraphLog, s: Sightings) -> np.ndarray:
    """(S,) the file's landmark id of each sighting (matched by pose and range)."""
    out = np.empty(len(s.k), int)
    for j, (k, z) in enumerate(zip(s.k.tolist(), s.z, strict=True)):
        cand = g.sightings[k]
        out[j] = cand[int(np.argmin([abs(c.range - z[1]) + abs(np.angle(np.exp(1j * (c.bearing - z[0]))))
                                     for c in cand]))].landmark
    return out



def tree_ids(g: GraphLog, s: Sightings, twins: dict[int, int]) -> np.ndarray:
    """(S,) the tree of each sighting: its file id, twins as one
    (:func:`lampsam.evaluation.twin_ids.twin_map`)."""
    return np.array([twins.get(f, f) for f in file_ids(g, s).tolist()], int)


def score(s: Sightings, fid: np.ndarray) -> tuple[int, int, int]:
    """``(mapped, dup, wrong)``: landmarks with 2+ sightings, file ids that are the
    majority of two or more landmarks, sightings not of their landmark's majority id."""
    major: dict[int, int] = {}
    wrong = 0
    for lid in np.unique(s.lid).tolist():
        c = Counter(fid[s.lid == lid].tolist())
        m, n = c.most_common(1)[0]
        major[lid] = m
        wrong += sum(c.values()) - n
    ids, counts = np.unique(s.lid, return_counts=True)
    mapped = int(np.sum(counts >= 2))
    owners = Counter(major.values())
    return mapped, sum(1 for v in owners.values() if v >= 2), wrong


def main() -> None:
    """Parse arguments, run every log and candidate, print the tables."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--logs", default="victoria,synthetic,mrclam,city")
    ap.add_argument("--poses", type=int, default=0, help="only the first N poses of each log")
    ap.add_argument("--scales", default="", help="candidate factors (default: the config's)")
    ap.add_argument("--passes", type=int, default=20)
    ap.add_argument("--set", nargs="*", default=[], metavar="SECTION.KEY=VALUE")
    ap.add_argument("--out", default="/tmp/bench_noids_scale")
    args = ap.parse_args()
    logging.basicConfig(level=logging.WARNING)
    bench = _bench_module()
    config = bench.with_overrides(SlamConfig(), args.set)
    import dataclasses

    config = dataclasses.replace(config, reassociation=dataclasses.replace(
        config.reassociation, passes=args.passes))
    scales = tuple(float(x) for x in args.scales.split(",")) if args.scales else None
    print("load average (1, 5, 15 min): " + ", ".join(f"{v:.1f}" for v in os.getloadavg()))
    for name in args.logs.split(","):
        g = load_log(name, Path(args.out))
        if args.poses:
            g = bench.first_poses(g, args.poses)
        c0 = time.process_time()
        ref_run = run_graph_log(g, "batch", config)
        ref = ref_run.poses
        twins = twin_ids.twin_map(g, {int(lm.id): np.asarray(lm.position[:2], float)
                             for lm in list(ref_run.landmarks) + list(ref_run.provisional)})
        n_twins = sum(1 for k, v in twins.items() if k != v)
        c_ref = time.process_time() - c0
        n_seen2 = sum(1 for v in Counter(x.landmark for ss in g.sightings for x in ss).values() if v >= 2)
        print(f"\n## {name}: {len(g.pose_ids)} poses, {g.n_landmarks} file ids, {n_seen2} sighted "
              f"twice or more, {n_twins} file ids counted as a twin of another (one tree, "
              f"never sighted together, < 1.5 m apart); known-id batch {c_ref:.1f} s CPU")
        print("| q | pass | mapped | dup | wrong / sightings | RMS vs known-id batch [m] | final [m] |")
        print("|---|---|---|---|---|---|---|")

        def report(q: float, g: GraphLog = g, ref: np.ndarray = ref,
                   twins: dict[int, int] = twins) -> PassReport:
            def f(i: int, p: Pass, poses: np.ndarray, lms: dict[int, np.ndarray], s: Sightings) -> None:
                fid = tree_ids(g, s, twins)
                mapped, dup, wrong = score(s, fid)
                d = np.linalg.norm(poses[:, :2] - ref[:, :2], axis=1)
                print(f"| {q:g} | {i} | {mapped} | {dup} | {wrong} / {len(s.k)} | "
                      f"{float(np.sqrt(np.mean(d**2))):.3f} | {float(d[-1]):.3f} |", flush=True)
            return f

        best, runs = select_scale(g, config, scales, report)
        print("\n| q | passes | landmarks (2+) | dup | wrong | RMS vs known-id batch [m] | dropped | "
              "chi2/dof odometry | chi2/dof sightings | C | chosen | CPU EKF / batch [s] |")
        print("|---|---|---|---|---|---|---|---|---|---|---|---|")
        for r in runs:
            _, dup, wrong = score(r.sightings, tree_ids(g, r.sightings, twins))
            rms = float(np.sqrt(np.mean(np.sum((r.poses[:, :2] - ref[:, :2]) ** 2, 1))))
            print(f"| {r.scale:g} | {len(r.passes)} | {len(r.landmarks)} ({len(r.mapped())}) | {dup} | "
                  f"{wrong} | {rms:.3f} | {r.n_dropped} | "
                  f"{r.chi2_odometry / r.dof_odometry:.3f} | {r.chi2_sightings / r.dof_sightings:.3f} | "
                  f"{r.cost:.1f} | {'**yes**' if r is best else ''} | {r.online_cpu_s:.1f} / "
                  f"{r.batch_cpu_s:.1f} |", flush=True)


if __name__ == "__main__":
    main()
