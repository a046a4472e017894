"""Pose graphs with loop closures: lampsam's iSAM2 and batch against GTSAM's own LM and iSAM2
on GTSAM's reading of the same file, in the same process.

Usage (from the worktree's parent)::

    PYTHONPATH=.. python scripts/bench/bench_pose_graphs.py [--repeats 3] [FILE ...]

Default files: GTSAM's ``noisyToyGraph.txt``, ``w100.graph``, ``w10000.graph``,
``w20000.txt`` (the development set) and SE-Sync's ``intel.g2o``, ``MIT.g2o``,
``manhattan.g2o`` from ``../shared/data/pose_graphs`` (held out: nothing was tuned on them).

For each file:

- GTSAM reads it (``gtsam.load2D``; ``gtsam.readG2o(path, False)`` for ``.g2o``) and a
  prior on the first pose at lampsam's start with lampsam's start sigmas
  (``[isam2] sigma_start_xy`` / ``sigma_start_theta``) is added: the graph is then the one
  lampsam builds, up to lampsam's odometry floors (``[isam2] odometry_floor_var`` 1e-9,
  the per-sample floor 1e-8) and a zero-length edge from lampsam's start variable ``X(0)``
  to the first pose.
- ``gtsam-lm``: GTSAM's Levenberg-Marquardt (default parameters) from the file's vertices
  when every pose has one, else from ``gtsam.lago.initialize`` of GTSAM's graph (as GTSAM's
  ``Pose2SLAMExample_lago.py``, each covariance cut to its diagonal, which LAGO requires:
  :func:`lampsam.backend.pose_graph.lago_graph`; ``load2D``'s own guess for the poses a file leaves out is
  not used: on a backwards chain LM stops metres away from it). This is the reference of
  the RMS column; its chi-square says whether another solver found a lower minimum.
- ``gtsam-isam2``: GTSAM's ISAM2 with lampsam's parameters (``Isam2Config.to_gtsam()``, and
  ``[graph] isam2_factorization`` on a file with closures, as lampsam's run), one
  ``update`` per pose in chain order with every factor whose later pose it is, the new pose
  predicted from the previous estimate and its odometry edge (as ``Pose2ISAM2Example.py``).
  The time reference of the ratio column.
- ``lampsam-isam2``, ``lampsam-batch``: ``run_graph_log`` on lampsam's reading, default
  config (batch starts from the online iSAM2 pass: ``[graph] batch_init``);
  ``lampsam-batch-chain`` and ``lampsam-batch-lago`` with ``batch_init = "chain"`` /
  ``"lago"``, one run each, for the choice of that default.

Columns: ``rms_vs_lm_m`` (RMS position difference from ``gtsam-lm`` over all poses),
``chi2`` (twice GTSAM's graph error, prior included, at each solution), ``wall_s`` and
``cpu_s`` (medians of ``--repeats`` runs, in one process: the machine is shared, so only the
ratios within one run compare), ``x_gtsam_isam2`` (CPU over ``gtsam-isam2``'s), ``status``.
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
import statistics
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import gtsam
import numpy as np
from timing import print_rows  # scripts/bench/timing.py, a sibling module

from lampsam.backend.config import SlamConfig
from lampsam.backend.graph_log import run_graph_log
from lampsam.backend.pose_graph import lago_graph
from lampsam.datasets.graph_text import GraphLog, read_graph_text

DEV = ("noisyToyGraph.txt", "w100.graph", "w10000.graph", "w20000.txt")
HELD_OUT = ("intel.g2o", "MIT.g2o", "manhattan.g2o")


def default_files() -> list[Path]:
    """GTSAM's development files, then SE-Sync's held-out graphs (those present)."""
    data = Path(gtsam.findExampleDataFile("victoria_park.txt")).parent
    shared = Path(__file__).resolve().parents[3] / "shared" / "data" / "pose_graphs"
    return [data / f for f in DEV] + [shared / f for f in HELD_OUT if (shared / f).exists()]


def gtsam_reading(path: Path, g: GraphLog, config: SlamConfig
                  ) -> tuple[gtsam.NonlinearFactorGraph, gtsam.Values]:
    """GTSAM's graph of the file (plus lampsam's prior on its first pose) and its values."""
    graph, initial = (gtsam.readG2o(str(path), False) if path.suffix == ".g2o"
                      else gtsam.load2D(str(path)))
    c = config.isam2
    graph.add(gtsam.PriorFactorPose2(g.pose_ids[0], gtsam.Pose2(*g.start_pose()),
                                     gtsam.noiseModel.Diagonal.Sigmas(np.array(
                                         [c.sigma_start_xy, c.sigma_start_xy, c.sigma_start_theta]))))
    return graph, initial


def gtsam_lm(graph: gtsam.NonlinearFactorGraph, initial: gtsam.Values, ids: list[int],
             vertices: dict[int, Any]) -> tuple[gtsam.Values, str]:
    """GTSAM's LM from the file's vertices (when it has one for every pose) or from
    GTSAM's LAGO (``load2D`` fills the poses a file leaves out with a guess of its own,
    which is not used)."""
    if all(i in vertices for i in ids):
        start, how = initial, "file vertices"
    else:
        start, how = gtsam.lago.initialize(lago_graph(graph)), "LAGO"
    return gtsam.LevenbergMarquardtOptimizer(graph, start, gtsam.LevenbergMarquardtParams()).optimize(), how


def gtsam_isam2(graph: gtsam.NonlinearFactorGraph, g: GraphLog, config: SlamConfig
                ) -> tuple[gtsam.Values, int]:
    """GTSAM's ISAM2, one update per pose of the chain (module docstring); ``(estimate,
    updates that threw)``."""
    order = {pid: k for k, pid in enumerate(g.pose_ids)}
    by_step: dict[int, list[Any]] = {}
    for n in range(graph.size()):
        f = graph.at(n)
        if f is not None:
            by_step.setdefault(max(order[key] for key in f.keys()), []).append(f)
    params = config.isam2.to_gtsam()
    if g.closures:  # as lampsam's run: [graph] isam2_factorization
        params.setFactorization(config.graph.isam2_factorization)
    isam = gtsam.ISAM2(params)
    pose = prev = gtsam.Pose2(*g.start_pose())
    fails = 0
    for k, pid in enumerate(g.pose_ids):
        new = gtsam.NonlinearFactorGraph()
        for f in by_step.get(k, []):
            new.add(f)
            keys = list(f.keys())
            if k and len(keys) == 2 and set(keys) == {g.pose_ids[k - 1], pid}:
                d = f.measured() if keys[0] == g.pose_ids[k - 1] else f.measured().inverse()
                pose = prev.compose(d)
        values = gtsam.Values()
        values.insert(pid, pose)
        try:
            isam.update(new, values)
        except RuntimeError:
            fails += 1
            continue
        prev = isam.calculateEstimatePose2(pid)
        pose = prev
    return isam.calculateEstimate(), fails


def poses_of(values: gtsam.Values, ids: list[int], keys: Callable[[int], int] = int) -> np.ndarray:
    """(N, 3) poses of ``ids`` (``keys`` maps an id to its key in ``values``)."""
    out = np.full((len(ids), 3), np.nan)
    for k, i in enumerate(ids):
        if values.exists(keys(i)):
            p = values.atPose2(keys(i))
            out[k] = [p.x(), p.y(), p.theta()]
    return out


def chi2_at(graph: gtsam.NonlinearFactorGraph, ids: list[int], poses: np.ndarray) -> float:
    """Twice GTSAM's graph error with the (N, 3) poses as its pose values."""
    if not np.isfinite(poses).all():
        return float("nan")
    v = gtsam.Values()
    for i, p in zip(ids, poses, strict=True):
        v.insert(i, gtsam.Pose2(*p))
    return 2.0 * graph.error(v)


def timed(fn: Callable[[], Any], repeats: int) -> tuple[Any, float, float]:
    """``(last result, median wall s, median CPU s)`` of ``repeats`` calls."""
    wall, cpu, out = [], [], None
    for _ in range(repeats):
        w0, c0 = time.perf_counter(), time.process_time()
        out = fn()
        wall.append(time.perf_counter() - w0)
        cpu.append(time.process_time() - c0)
    return out, statistics.median(wall), statistics.median(cpu)


def bench_file(path: Path, repeats: int) -> list[dict[str, Any]]:
    """The rows of one file (module docstring)."""
    config = SlamConfig()
    g = read_graph_text(path)
    ids = list(g.pose_ids)
    graph, initial = gtsam_reading(path, g, config)
    (lm, how), lm_wall, lm_cpu = timed(lambda: gtsam_lm(graph, initial, ids, g.vertices), repeats)
    ref = poses_of(lm, ids)
    (isam, fails), is_wall, is_cpu = timed(lambda: gtsam_isam2(graph, g, config), repeats)
    held = path.name in HELD_OUT
    rows: list[dict[str, Any]] = []

    def row(solver: str, poses: np.ndarray, wall: float, cpu: float, status: str) -> None:
        d = np.hypot(*(poses[:, :2] - ref[:, :2]).T)
        rows.append({"file": path.name, "data": "held-out" if held else "dev",
                     "poses": len(ids), "closures": len(g.closures), "solver": solver,
                     "rms_vs_lm_m": float(np.sqrt(np.mean(d ** 2))),
                     "chi2": chi2_at(graph, ids, poses), "wall_s": wall, "cpu_s": cpu,
                     "x_gtsam_isam2": cpu / is_cpu, "status": status})

    row(f"gtsam-lm ({how})", ref, lm_wall, lm_cpu, "ok")
    row("gtsam-isam2", poses_of(isam, ids), is_wall, is_cpu, f"{fails} updates threw" if fails else "ok")
    runs = [("lampsam-isam2", "isam2", "backend", repeats),
            ("lampsam-batch", "batch", "backend", repeats),
            ("lampsam-batch-chain (1 run)", "batch", "chain", 1),
            ("lampsam-batch-lago (1 run)", "batch", "lago", 1)]
    for label, backend, init, n_runs in runs:
        cfg = dataclasses.replace(config, graph=dataclasses.replace(config.graph, batch_init=init))
        res, wall, cpu = timed(lambda b=backend, c=cfg: run_graph_log(g, b, c), n_runs)
        used = int(res.extra.get("loop_closures_used", 0))
        row(label, res.poses, wall, cpu,
            res.status + ("" if used == len(g.closures) else f"; {used} closures used"))
    return rows


def main() -> None:
    """Parse arguments, bench each file, print the table."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("files", nargs="*", type=Path, help="graph files (default: module docstring)")
    ap.add_argument("--repeats", type=int, default=3, help="runs per solver (median; default 3)")
    args = ap.parse_args()
    logging.basicConfig(level=logging.ERROR)
    rows: list[dict[str, Any]] = []
    for path in args.files or default_files():
        rows += bench_file(path, args.repeats)
        print_rows(rows)


if __name__ == "__main__":
    main()
