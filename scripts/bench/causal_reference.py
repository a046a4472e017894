"""The causal optimum of a planar landmark log, against GTSAM iSAM2's online poses and the EKF.

Usage::

    python scripts/bench/causal_reference.py [--log victoria|synthetic|FILE] [--stride 25]
        [--variants ekf,ekf-invariant,ekf-paper,ekf-fej]

A filter's pose at step ``k`` can only use the data up to ``k``; the best any causal
estimator can give there is the optimum of the graph of poses ``0..k`` and the
sightings so far, at ``X(k)``. This script solves that graph with GTSAM's
Levenberg-Marquardt every ``--stride`` poses (warm-started from the previous prefix's
optimum extended by odometry, as an exact incremental smoother would be) and prints the
position RMS over those steps of GTSAM iSAM2's online poses (``bench_landmark_logs``'s
``gtsam-isam2-online`` reference) and of each EKF variant (known ids). Cost: one LM per stride on a growing graph
(Victoria Park, stride 25: ~10 min of CPU).
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import time
from pathlib import Path

import gtsam
import numpy as np
from bench_landmark_logs import gtsam_isam2
from gtsam.symbol_shorthand import L, X

from lampsam.backend.config import SlamConfig
from lampsam.backend.graph_log import run_graph_log
from lampsam.datasets.graph_text import GraphLog, read_graph_text
from lampsam.datasets.landmark_log_sim import LandmarkLogSpec, write_landmark_log

VARIANTS: dict[str, dict[str, bool]] = {"ekf": {}, "ekf-invariant": {"right_invariant": True},
            "ekf-paper": {"first_estimate_jacobians": False},
            "ekf-fej": {"observability_constrained": False}}


def prefix_optima(g: GraphLog, config: SlamConfig, steps: list[int]) -> np.ndarray:
    """(len(steps), 3) the LM optimum's pose ``X(k)`` of the graph of poses ``0..k``."""
    c = config.isam2
    prior = gtsam.noiseModel.Diagonal.Sigmas(np.array([c.sigma_start_xy, c.sigma_start_xy,
                                                       c.sigma_start_theta]))
    graph = gtsam.NonlinearFactorGraph()
    graph.add(gtsam.PriorFactorPose2(X(0), gtsam.Pose2(*g.start_pose()), prior))
    values = gtsam.Values()
    values.insert(X(0), gtsam.Pose2(*g.start_pose()))
    seen: set[int] = set()
    out = []
    j = 0
    for k in steps:
        while j <= k:
            pose = values.atPose2(X(j))
            for s in g.sightings[j]:
                graph.add(gtsam.BearingRangeFactor2D(X(j), L(s.landmark), gtsam.Rot2(s.bearing),
                                                     s.range, gtsam.noiseModel.Gaussian.Covariance(s.cov)))
                if s.landmark not in seen:
                    seen.add(s.landmark)
                    a = pose.theta() + s.bearing
                    values.insert(L(s.landmark), np.array([pose.x() + s.range * math.cos(a),
                                                           pose.y() + s.range * math.sin(a)]))
            if j + 1 <= k:
                d = gtsam.Pose2(*g.odometry.delta[j + 1])
                graph.add(gtsam.BetweenFactorPose2(X(j), X(j + 1), d,
                                                   gtsam.noiseModel.Gaussian.Covariance(g.odometry.cov[j + 1])))
                values.insert(X(j + 1), pose.compose(d))
            j += 1
        values = gtsam.LevenbergMarquardtOptimizer(graph, values,
                                                   gtsam.LevenbergMarquardtParams()).optimize()
        p = values.atPose2(X(k))
        out.append([p.x(), p.y(), p.theta()])
        # the next prefix extends this optimum by odometry
        if k + 1 < len(g.pose_ids):
            d = gtsam.Pose2(*g.odometry.delta[k + 1])
            graph.add(gtsam.BetweenFactorPose2(X(k), X(k + 1), d,
                                               gtsam.noiseModel.Gaussian.Covariance(g.odometry.cov[k + 1])))
            values.insert(X(k + 1), p.compose(d))
            j = k + 1
    return np.array(out)


def _rms(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.sum((a[:, :2] - b[:, :2]) ** 2, axis=1))))


def main() -> None:
    """Parse arguments, compute the references, print one line per estimator."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--log", default="victoria")
    ap.add_argument("--stride", type=int, default=25)
    ap.add_argument("--variants", default="ekf,ekf-invariant")
    args = ap.parse_args()
    if args.log == "victoria":
        path = Path(gtsam.findExampleDataFile("victoria_park.txt"))
    elif args.log == "synthetic":
        path, _ = write_landmark_log(Path("/tmp/causal_reference_synthetic.txt"), LandmarkLogSpec(),
                                     np.random.default_rng(0))
    else:
        path = Path(args.log)
    g = read_graph_text(path)
    config = SlamConfig()
    n = len(g.pose_ids)
    steps = list(range(args.stride, n, args.stride)) + [n - 1]
    t0 = time.process_time()
    _, _, _, _, online = gtsam_isam2(g, config)
    causal = prefix_optima(g, config, steps)
    print(f"{path.name}: {n} poses, causal optimum at {len(steps)} steps "
          f"({time.process_time() - t0:.0f} s CPU)")
    print(f"gtsam-isam2-online vs causal optimum: {_rms(online[steps], causal):.3f} m RMS")
    for v in [x for x in args.variants.split(",") if x]:
        cfg = dataclasses.replace(config, ekf=dataclasses.replace(config.ekf, **VARIANTS[v]))
        res = run_graph_log(g, "ekf", cfg)
        print(f"lampsam-{v} vs causal optimum: {_rms(res.poses[steps], causal):.3f} m RMS, "
              f"vs gtsam-isam2-online (all steps): {_rms(res.poses, online):.3f} m RMS")


if __name__ == "__main__":
    main()
