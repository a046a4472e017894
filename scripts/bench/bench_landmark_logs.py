"""lampsam's EKF / iSAM2 / batch against GTSAM's own iSAM2 and LM on planar landmark logs.

Usage::

    python scripts/bench/bench_landmark_logs.py [--logs victoria,mrclam,synthetic] [--repeats 1]
        [--backends ekf,isam2,batch] [--no-ids] [--file LOG.txt [--truth TRUTH.txt]]
        [--mrclam-duration 600] [--set association.planar_noise_adapt=true ...] [--general]

(``--backends`` also takes ``ekf-batch``, without ids only: the EKF's online pass at each
``[reassociation] scales`` factor re-associated in batch, the least description length
kept (:func:`ekf_then_batch`, :mod:`lampsam.backend.noids_offline`); ``ekf-paper``: the EKF with the paper's Jacobians,
``ekf-invariant``: the right-invariant EKF, ``ekf.right_invariant``, and ``ekf-fej``:
plain first-estimates Jacobians without the observability constraint,
``ekf.observability_constrained = false``.)

For each log (``victoria``: GTSAM's ``victoria_park.txt``; ``mrclam``: the shared
MRCLAM ds0 robot 1, its first ``--mrclam-duration`` s, turned into one pose per step
of :func:`lampsam.backend.slam.iter_steps` (a step at every measurement time, else
every 0.5 s) with the wheel model's increment and covariance (eqs. 13-15, from the
commanded ``(v, w)`` as :mod:`lampsam.datasets.mrclam` does) and the default
range-bearing noise, Vicon truth interpolated at the steps; ``synthetic``: a log made by
:mod:`lampsam.datasets.landmark_log_sim`, 3,000 poses, Pose2 odometry with sideways
noise 3x forward, stops of 200 poses, range-dependent bearing noise; ``--file``: any
iSAM/g2o text log) the same graph is built in GTSAM from the parsed records: a prior
on the start pose, one ``BetweenFactorPose2`` per odometry record with the file's
covariance, one ``BearingRangeFactor2D`` per sighting with its own noise. GTSAM's
iSAM2 runs it with one ``update()`` per pose (as ``Pose2ISAM2Example.py``), then LM
from that estimate gives the reference optimum. Each lampsam backend then runs the
log one step per pose (:func:`lampsam.backend.graph_log.run_graph_log`); with known ids
lampsam's iSAM2 and batch take the fast path (:mod:`lampsam.backend.dense_log`),
``--general`` also runs their general per-step path and prints the largest pose
difference between the two (``max_dpose_general``, 0.0: a pure speed-up).

What is timed: GTSAM's loop from its first factor (the ``ISAM2`` object made
before) to ``calculateEstimate()`` after the last update, building every factor
and noise model from the parsed log inside the loop; lampsam's from the call of
``run_graph_log`` to its result: building the factors from the same parsed log, the
iSAM2 object, every update, the final estimate (batch: LM over the whole graph and
``gtsam.Marginals``), each step's pose and each landmark's marginal covariance.
Both make one ``update()`` and one ``calculateEstimatePose2`` per pose with
sightings, with the same ``ISAM2Params`` (``Isam2Config.to_gtsam()``). lampsam's graph
has a pose only where there are sightings (GTSAM's has every pose: MRCLAM 300 s,
1,079 against 1,169 updates) and a separate start pose ``X(0)`` (one more update).

Printed per log: for each solution the position RMS difference from GTSAM's LM
trajectory, from GTSAM iSAM2's online poses (``rms_vs_online_m``: the fair figure for a
filter) and at the final pose, the map's RMS from LM's landmarks (by id; without ids to
the nearest LM landmark) (``gtsam-isam2-online``: iSAM2's estimate of each pose right after its
own update, the fair reference for a filter's online poses), the chi-square (``2 x error``) of the solution on GTSAM's graph (known
ids; landmarks a backend did not map take LM's value, counted), failures (iSAM2
rebuilds that dropped measurements / GTSAM exceptions), ``qr_rebuilds`` (iSAM2 rebuilt
with QR after an ill-conditioned clique, nothing dropped), mapped landmarks against those in the file, total time
and per-step median / p95, and the ratio of total time to GTSAM's iSAM2 measured in
the same run, wall (``x_gtsam_isam2``) and process CPU (``x_gtsam_isam2_cpu``, the
figure to compare on a shared machine). Times are medians over ``--repeats`` runs;
other engineers' jobs may share the machine: compare ratios, not absolute times.
GTSAM's loop computes no covariance; lampsam's smoothers compute landmark covariances
and, with ``--pose-covariances``, every pose's (online and final) as well.
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
import math
import time
from pathlib import Path
from typing import Any

import gtsam
import numpy as np
from gtsam.symbol_shorthand import L, X
from scipy.spatial import cKDTree
from timing import print_rows  # scripts/bench/timing.py, a sibling module

from lampsam.backend.config import SlamConfig
from lampsam.backend.graph_log import run_graph_log
from lampsam.backend.odometry import WheelMotion
from lampsam.backend.slam import frames_from_range_bearing, iter_steps
from lampsam.datasets.graph_text import GraphLog, Sighting, read_graph_text, read_vertices
from lampsam.datasets.landmark_log_sim import LandmarkLogSpec, write_landmark_log
from lampsam.datasets.logrun import LoggedRun
from lampsam.datasets.odometry import Pose2OdometryLog
from lampsam.evaluation.twin_ids import file_graph
from lampsam.frontend.measurements import RangeBearingFrame


def graph_log_from_run(run: LoggedRun, config: SlamConfig, max_dt: float = 0.5
                       ) -> tuple[GraphLog, np.ndarray]:
    """A wheel-odometry range-bearing run as a graph log (one pose per step) and its truth.

    Each step's wheel travel becomes a Pose2 increment with the wheel model's
    covariance (eqs. 13-15 composed) plus the Pose2 model's floor (a step at rest
    would give GTSAM a singular covariance; lampsam adds the floor once more); each
    sighting gets ``config.noise``'s range-bearing covariance.

    Returns:
        ``(log, truth poses (N, 3))``: the run's ground truth interpolated at the steps.
    """
    assert run.range_bearing is not None and run.groundtruth is not None
    wheel = WheelMotion(run.rig.odometry)
    r = np.diag([config.noise.sigma_bearing ** 2, config.noise.sigma_range ** 2])
    ts: list[float] = []
    deltas: list[np.ndarray] = []
    covs: list[np.ndarray] = []
    sightings: list[list[Sighting]] = []
    for t, u, frame in iter_steps(run.odometry, frames_from_range_bearing(run.range_bearing), max_dt):
        if ts and t <= ts[-1]:  # same time stamp as the previous step: merge
            t = ts[-1] + 1e-6
        d, c = wheel.relative(np.asarray(u, float).reshape(-1, 2), 1e-14) if len(u) else (
            np.zeros(3), np.zeros((3, 3)))
        ts.append(t)
        deltas.append(np.asarray(d, float) if ts[1:] else np.zeros(3))
        covs.append(config.pose2_odometry.sample_cov(d, c) if ts[1:] else np.zeros((3, 3)))
        obs = frame.observations if isinstance(frame, RangeBearingFrame) else ()
        sightings.append([Sighting(int(o.landmark_id), float(o.bearing), float(o.range), r)
                          for o in obs if o.landmark_id is not None])
    gt = run.groundtruth
    th = np.unwrap(gt.poses[:, 2])
    truth = np.column_stack([np.interp(ts, gt.t, gt.poses[:, 0]), np.interp(ts, gt.t, gt.poses[:, 1]),
                             np.interp(ts, gt.t, th)])
    odo = Pose2OdometryLog(np.asarray(ts), np.array(deltas), np.array(covs))
    g = GraphLog(path=Path(run.path), pose_ids=list(range(len(ts))), odometry=odo,
                 sightings=sightings, vertices={0: truth[0]})
    return g, truth


def gtsam_graph(g: GraphLog, config: SlamConfig) -> gtsam.NonlinearFactorGraph:
    """The log's graph in GTSAM: prior, odometry and bearing-range factors
    (:func:`lampsam.evaluation.twin_ids.file_graph`)."""
    return file_graph(g, config)


def gtsam_isam2(g: GraphLog, config: SlamConfig
                ) -> tuple[gtsam.Values, float, list[float], int, np.ndarray, float]:
    """GTSAM's iSAM2, one update per pose.

    Returns:
        ``(final estimate, total s, step times, failures, online poses (N, 3), total
        CPU s)``; the online pose of step ``k`` is iSAM2's estimate of ``X(k)`` right
        after its update (what a filter can give at that time).
    """
    online: list[list[float]] = []
    isam = gtsam.ISAM2(config.isam2.to_gtsam())
    c = config.isam2
    start = gtsam.Pose2(*g.start_pose())
    t_steps: list[float] = []
    failures = 0
    known: set[int] = set()
    pose = start
    t0 = time.perf_counter()
    c0 = time.process_time()
    for k in range(len(g.pose_ids)):
        ts = time.perf_counter()
        graph = gtsam.NonlinearFactorGraph()
        values = gtsam.Values()
        if k == 0:
            graph.add(gtsam.PriorFactorPose2(X(0), start, gtsam.noiseModel.Diagonal.Sigmas(
                np.array([c.sigma_start_xy, c.sigma_start_xy, c.sigma_start_theta]))))
        else:
            d = gtsam.Pose2(*g.odometry.delta[k])
            graph.add(gtsam.BetweenFactorPose2(X(k - 1), X(k), d,
                                               gtsam.noiseModel.Gaussian.Covariance(g.odometry.cov[k])))
            pose = pose.compose(d)
        values.insert(X(k), pose)
        for s in g.sightings[k]:
            if s.landmark not in known:
                known.add(s.landmark)
                a = pose.theta() + s.bearing
                values.insert(L(s.landmark), np.array([pose.x() + s.range * math.cos(a),
                                                       pose.y() + s.range * math.sin(a)]))
            graph.add(gtsam.BearingRangeFactor2D(X(k), L(s.landmark), gtsam.Rot2(s.bearing), s.range,
                                                 gtsam.noiseModel.Gaussian.Covariance(s.cov)))
        try:
            isam.update(graph, values)
        except RuntimeError:
            failures += 1
        pose = isam.calculateEstimatePose2(X(k))
        online.append([pose.x(), pose.y(), pose.theta()])
        t_steps.append(time.perf_counter() - ts)
    est = isam.calculateEstimate()
    return (est, time.perf_counter() - t0, t_steps, failures, np.array(online),
            time.process_time() - c0)


def poses_of(values: gtsam.Values, n: int) -> np.ndarray:
    """(n, 3) ``X(0..n-1)`` from ``values``."""
    return np.array([[p.x(), p.y(), p.theta()] for p in (values.atPose2(X(k)) for k in range(n))])


def chi2_of(graph: gtsam.NonlinearFactorGraph, ref: gtsam.Values, poses: np.ndarray,
            landmarks: dict[int, np.ndarray]) -> tuple[float, int]:
    """``2 x error`` of a solution on the graph; landmarks missing take ``ref``'s (counted)."""
    v = gtsam.Values()
    for k, p in enumerate(poses):
        v.insert(X(k), gtsam.Pose2(*p))
    missing = 0
    for key in ref.keys():
        if gtsam.Symbol(key).chr() == ord("l"):
            lid = gtsam.Symbol(key).index()
            if lid in landmarks:
                v.insert(key, landmarks[lid])
            else:
                v.insert(key, ref.atPoint2(key))
                missing += 1
    return 2.0 * graph.error(v), missing


def _rms_diff(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.sum((a[:, :2] - b[:, :2]) ** 2, axis=1))))


def with_overrides(config: SlamConfig, pairs: list[str]) -> SlamConfig:
    """``config`` with ``section.key=value`` overrides (value parsed as the field's type)."""
    for item in pairs:
        key, sep, text = item.partition("=")
        section, _, name = key.partition(".")
        sub = getattr(config, section, None)
        if not sep or sub is None or not hasattr(sub, name):
            raise SystemExit(f"--set {item!r}: expected section.key=value of SlamConfig")
        cur = getattr(sub, name)
        value: Any = (text.lower() in ("1", "true", "yes")) if isinstance(cur, bool) else (
            type(cur)(text) if cur is not None else float(text))
        config = dataclasses.replace(config, **{section: dataclasses.replace(sub, **{name: value})})
    return config


def first_poses(g: GraphLog, n: int) -> GraphLog:
    """The log cut after its first ``n`` poses (odometry and sightings)."""
    od = g.odometry
    return dataclasses.replace(
        g, pose_ids=g.pose_ids[:n], sightings=g.sightings[:n],
        odometry=Pose2OdometryLog(od.t[:n], od.delta[:n], od.cov[:n]))


def ekf_then_batch(g: GraphLog, config: SlamConfig) -> tuple[np.ndarray, dict[int, np.ndarray],
                                                                float, float, int, float]:
    """Batch without ids started from the EKF's online pass (no ids), then re-associated:
    :func:`lampsam.backend.noids_offline.select_scale` (the EKF's pass at each
    ``reassociation.scales`` factor, the batch with the log's stated odometry covariance,
    the least description length kept; ``config.reassociation``, 20 passes when it says
    0). Returns ``(poses (N, 3), landmarks seen twice or more, wall s, CPU s, passes,
    chosen factor)``.
    """
    from lampsam.backend.noids_offline import select_scale

    t0, c0 = time.perf_counter(), time.process_time()
    rc = config.reassociation if config.reassociation.passes else dataclasses.replace(
        config.reassociation, passes=20)
    best, _ = select_scale(g, dataclasses.replace(config, reassociation=rc))
    found = best.mapped(config.association.min_observations)
    return (best.poses, found, time.perf_counter() - t0, time.process_time() - c0,
            len(best.passes), best.scale)


def bench_log(name: str, g: GraphLog, truth: np.ndarray | None, backends: list[str],
              repeats: int, no_ids: bool, config: SlamConfig | None = None,
              pose_covariances: bool = False, general: bool = False) -> list[dict[str, Any]]:
    """Rows of the table for one log (``pose_covariances``: lampsam's smoothers also
    compute every pose covariance, which GTSAM's loop does not; ``general``: the
    smoothers also run their general per-step path, ``-general`` rows, and both rows
    give the largest pose coordinate difference between the two in
    ``max_dpose_general``)."""
    config = config or SlamConfig()
    graph = gtsam_graph(g, config)
    n = len(g.pose_ids)
    runs = [gtsam_isam2(g, config) for _ in range(repeats)]
    est, _, steps, fails, online, _ = runs[0]
    t_isam = float(np.median([r[1] for r in runs]))
    cpu_isam = float(np.median([r[5] for r in runs]))
    t0 = time.perf_counter()
    lm = gtsam.LevenbergMarquardtOptimizer(graph, est, gtsam.LevenbergMarquardtParams()).optimize()
    t_lm = time.perf_counter() - t0
    ref = poses_of(lm, n)
    n_lm_file = g.n_landmarks
    rows: list[dict[str, Any]] = []
    lm_pts = {gtsam.Symbol(k).index(): lm.atPoint2(k) for k in lm.keys()
              if gtsam.Symbol(k).chr() == ord("l")}
    lm_tree = cKDTree(np.array(list(lm_pts.values())))

    def map_rms(lms: dict[int, np.ndarray] | None, ids: bool) -> float:
        """Landmark RMS from LM's: by id, or (no ids) to the nearest LM landmark."""
        if not lms:
            return math.nan
        if ids:
            d = [np.linalg.norm(p - lm_pts[i]) for i, p in lms.items() if i in lm_pts]
        else:
            d = list(lm_tree.query(np.array(list(lms.values())))[0])
        return float(np.sqrt(np.mean(np.square(d)))) if d else math.nan

    def row(solver: str, poses: np.ndarray, lms: dict[int, np.ndarray] | None, total: float,
            step_s: np.ndarray, failures: int, n_map: int, ids: bool,
            map_lms: dict[int, np.ndarray] | None = None, cpu: float = math.nan,
            qr: int = 0) -> None:
        map_lms = lms if map_lms is None else map_lms
        chi2, missing = chi2_of(graph, lm, poses, lms) if lms is not None else (math.nan, 0)
        rows.append({"log": name, "solver": solver, "ids": "known" if ids else "none",
                     "rms_vs_lm_m": _rms_diff(poses, ref),
                     "rms_vs_online_m": _rms_diff(poses, online),
                     "final_vs_lm_m": float(np.linalg.norm(poses[-1, :2] - ref[-1, :2])),
                     "map_vs_lm_m": map_rms(map_lms, ids),
                     "rms_vs_truth_m": _rms_diff(poses, truth) if truth is not None else math.nan,
                     "chi2": chi2, "lm_missing": missing, "failures": failures,
                     "qr_rebuilds": qr,
                     "mapped": n_map, "in_file": n_lm_file, "total_s": total,
                     "step_median_ms": float(np.median(step_s) * 1e3),
                     "step_p95_ms": float(np.percentile(step_s, 95) * 1e3),
                     "x_gtsam_isam2": total / t_isam, "cpu_s": cpu,
                     "x_gtsam_isam2_cpu": cpu / cpu_isam, "max_dpose_general": math.nan})

    row("gtsam-isam2", poses_of(est, n),
        {gtsam.Symbol(k).index(): est.atPoint2(k) for k in est.keys() if gtsam.Symbol(k).chr() == ord("l")},
        t_isam, np.asarray(steps), fails, n_lm_file, True, cpu=cpu_isam)
    row("gtsam-isam2-online", online, None, t_isam, np.asarray(steps), fails, n_lm_file, True,
        cpu=cpu_isam)
    row("gtsam-lm", ref, {gtsam.Symbol(k).index(): lm.atPoint2(k) for k in lm.keys()
                          if gtsam.Symbol(k).chr() == ord("l")},
        t_isam + t_lm, np.asarray(steps), 0, n_lm_file, True)
    for ids in ([True, False] if no_ids else [True]):
        for b in backends:
            if b == "ekf-batch":  # no ids only: the EKF's pass re-associated in batch
                if not ids:
                    poses_b, found_b, wall_b, cpu_b, n_pass, q_b = ekf_then_batch(g, config)
                    row(f"lampsam-ekf-batch (q={q_b:g}, {n_pass} passes)", poses_b, None, wall_b,
                        np.array([wall_b / n]), 0, len(found_b), False, found_b, cpu_b)
                continue
            # "ekf-paper": the EKF with the paper's Jacobians (at the latest estimate)
            # instead of first estimates (docs/graph-backend.md).
            variant = {"ekf-paper": {"first_estimate_jacobians": False},
                       "ekf-invariant": {"right_invariant": True},
                       "ekf-fej": {"observability_constrained": False}}.get(b, {})
            cfg_b = dataclasses.replace(config, ekf=dataclasses.replace(config.ekf, **variant))
            backend = "ekf" if b.startswith("ekf") else b
            paths = [True, False] if general and backend != "ekf" else [True]
            results = {}
            for fast in paths:
                res_runs = [run_graph_log(g, backend, cfg_b, known_ids=ids,
                                          pose_covariances=pose_covariances, fast=fast)
                            for _ in range(repeats)]
                res = results[fast] = res_runs[0]
                total = float(np.median([r.extra["total_time_s"] for r in res_runs]))
                cpu = float(np.median([r.extra["total_cpu_s"] for r in res_runs]))
                found = {int(x.id): x.position[:2] for x in res.landmarks}
                row(f"lampsam-{b}" + ("" if fast else "-general"), res.poses, found if ids else None,
                    total, res.step_times_s, int(res.extra.get("n_recoveries", 0)),
                    len(res.landmarks), ids, found, cpu, int(res.extra.get("n_qr_rebuilds", 0)))
                if not res.status == "ok":
                    rows[-1]["solver"] += f" ({res.status[:40]})"
                if not fast:  # what the fast path changed (a pure speed-up: 0.0)
                    d = float(np.abs(results[True].poses - res.poses).max()) if len(
                        res.poses) == len(results[True].poses) else math.inf
                    rows[-2]["max_dpose_general"] = rows[-1]["max_dpose_general"] = d
    return rows


def main() -> None:
    """Parse arguments, run every log, print the table."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--logs", default="victoria,mrclam,synthetic")
    ap.add_argument("--mrclam-duration", type=float, default=600.0,
                    help="seconds of MRCLAM robot 1 (default 600)")
    ap.add_argument("--backends", default="ekf,isam2,batch")
    ap.add_argument("--repeats", type=int, default=1)
    ap.add_argument("--no-ids", action="store_true", help="also run without ids")
    ap.add_argument("--file", default=None, help="an iSAM/g2o text log instead of --logs")
    ap.add_argument("--truth", default=None, help="VERTEX2 truth for --file")
    ap.add_argument("--out", default="/tmp/bench_landmark_logs", help="synthetic logs go here")
    ap.add_argument("--set", nargs="*", default=[], metavar="SECTION.KEY=VALUE",
                    help="config overrides for lampsam's backends (e.g. association.planar_merge=true)")
    ap.add_argument("--poses", type=int, default=0, help="only the first N poses of each log")
    ap.add_argument("--pose-covariances", action="store_true",
                    help="lampsam's smoothers also compute every pose covariance (online and "
                         "final), which GTSAM's loop does not (run_graph_log's default: off)")
    ap.add_argument("--general", action="store_true",
                    help="also run lampsam's smoothers by their general per-step path (with known "
                         "ids they take the fast path, lampsam.backend.dense_log) and print the "
                         "largest pose difference between the two")
    args = ap.parse_args()
    logging.basicConfig(level=logging.ERROR)
    backends = [b for b in args.backends.split(",") if b]
    logs: list[tuple[str, Path | GraphLog, Path | np.ndarray | None]] = []
    if args.file:
        logs.append((Path(args.file).name, Path(args.file), Path(args.truth) if args.truth else None))
    else:
        for name in args.logs.split(","):
            if name == "victoria":
                logs.append((name, Path(gtsam.findExampleDataFile("victoria_park.txt")), None))
            elif name == "mrclam":
                from lampsam.datasets.mrclam import mrclam_run
                from lampsam.datasets.paths import shared_dataset

                root = shared_dataset("mrclam_ds0")
                if root is None:
                    raise SystemExit("mrclam: shared dataset mrclam_ds0 not found (set LAMPSAM_DATA)")
                glog, gtruth = graph_log_from_run(
                    mrclam_run(root, duration=args.mrclam_duration), SlamConfig())
                logs.append((name, glog, gtruth))
            elif name == "synthetic":
                out = Path(args.out)
                out.mkdir(parents=True, exist_ok=True)
                p, t = write_landmark_log(out / "synthetic.txt", LandmarkLogSpec(),
                                          np.random.default_rng(0))
                logs.append((name, p, t))
            else:
                raise SystemExit(f"unknown log {name!r} (victoria, mrclam, synthetic)")
    rows: list[dict[str, Any]] = []
    for name, src, tsrc in logs:
        g = src if isinstance(src, GraphLog) else read_graph_text(src)
        truth = tsrc if isinstance(tsrc, np.ndarray) else None
        if isinstance(tsrc, Path):
            v = read_vertices(tsrc)
            truth = np.array([v[i] for i in g.pose_ids])
        if args.poses:
            g, truth = first_poses(g, args.poses), (truth[: args.poses] if truth is not None else None)
        rows += bench_log(name, g, truth, backends, args.repeats, args.no_ids,
                          with_overrides(SlamConfig(), args.set), args.pose_covariances,
                          args.general)
        print_rows(rows)


if __name__ == "__main__":
    main()
