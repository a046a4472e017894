"""Benchmark: iSAM2 against GTSAM's IncrementalFixedLagSmoother on the same keyframe factors.

Usage::

    python scripts/bench/bench_fixed_lag.py --lab RUN [--lags 50,200]

with ``RUN`` from ``lampsam simulate lab --seed 3 --out RUN``. The iSAM2 backend runs
once over the run's frames (frontend on the images) and each keyframe's new factors
and values, as sent to ``ISAM2.update``, are recorded. They are then replayed, in the
same process, into a fresh ``gtsam.ISAM2`` and into
``gtsam.IncrementalFixedLagSmoother`` (lag in keyframes: each keyframe's timestamp
is its index) with the same ``ISAM2Params``:

* every variable is stamped when it enters and re-stamped whenever a factor of the
  keyframe touches it, so what is still observed stays in the window;
* lamps (``L(j)``, ``A(j)`` of every lamp) are re-stamped at every keyframe, so they
  are never marginalised: they are few (11 on the lab path) and carry the loop
  closures of the revisits;
* a factor that touches a variable already marginalised (a corner seen again after
  the lag) is dropped and counted.

The association is the full iSAM2 run's (fixed), so the fixed-lag figures show the
smoother's cost and accuracy, not an online backend's with its own gate. Printed per
smoother: the CPU of ``update`` plus the keyframe's pose estimate (total, median / p95
/ max per keyframe), and the keyframe position / heading RMS against ground truth,
online (each keyframe's estimate right after its update) and final (the fixed-lag
smoother's estimate of a pose when it left the window, else at the end).
"""

from __future__ import annotations

import argparse
import os
import time

import gtsam
import numpy as np
from gtsam.symbol_shorthand import X

from lampsam.arrays import FloatArray
from lampsam.backend.ceiling import CeilingModel
from lampsam.backend.ceiling_graph import CeilingHandler
from lampsam.backend.config import SlamConfig
from lampsam.backend.graph import Isam2Slam
from lampsam.backend.slam import iter_steps, make_frames, start_pose_of
from lampsam.datasets.logrun import read_run

Batch = tuple[int, gtsam.NonlinearFactorGraph, gtsam.Values]


def record(run_dir: str, config: SlamConfig) -> tuple[list[Batch], set[int], dict[int, float], Isam2Slam]:
    """Run iSAM2 over the run; each keyframe's update batch, the lamps' keys, keyframe times."""
    run = read_run(run_dir)
    frames, _ = make_frames(run, "images")
    model = CeilingModel.from_camera(run.rig.camera)
    be = Isam2Slam(run.rig.odometry, config, start_pose_of(run), model, CeilingHandler(model))
    g0 = gtsam.NonlinearFactorGraph()
    g0.add(be.graph.at(0))  # the start prior, sent by the constructor
    v0 = gtsam.Values()
    v0.insert(X(0), be.initial.atPose2(X(0)))
    batches: list[Batch] = [(0, g0, v0)]
    flush = be._flush

    def recording_flush() -> None:
        batches.append((be._k, be._new_graph, gtsam.Values(be._new_values)))
        flush()

    be._flush = recording_flush  # type: ignore[method-assign]
    kf_t = {0: float(run.odometry.t[0])}
    for t, u, f in iter_steps(run.odometry, list(frames)):
        k0 = be._k
        be.step(t, u, f)
        if be._k != k0:
            kf_t[be._k] = t
    lamps: set[int] = set()
    for lm in be._landmarks.values():
        if lm.kind == "lamp" and lm.in_graph:
            lamps.update(be.handlers[lm.kind].keys(lm))
    return batches, lamps, kf_t, be


def _xyt(p: gtsam.Pose2) -> list[float]:
    return [p.x(), p.y(), p.theta()]


def replay(batches: list[Batch], params: gtsam.ISAM2Params, lag: float | None, lamps: set[int]
           ) -> tuple[FloatArray, dict[int, list[float]], dict[int, list[float]], int]:
    """Replay into iSAM2 (``lag`` None) or the fixed-lag smoother.

    Returns:
        ``(CPU per keyframe (s), online pose per keyframe, final pose per keyframe,
        dropped factors)``.
    """
    isam = gtsam.ISAM2(params) if lag is None else None
    smoother = gtsam.IncrementalFixedLagSmoother(lag, params) if lag is not None else None
    alive: set[int] = set()
    gone: set[int] = set()
    left: dict[int, list[float]] = {}
    online: dict[int, list[float]] = {}
    cpu: list[float] = []
    dropped = 0
    for k, graph, values in batches:
        c = time.process_time()
        if isam is not None:
            isam.update(graph, values)
            online[k] = _xyt(isam.calculateEstimatePose2(X(k)))
            cpu.append(time.process_time() - c)
            continue
        assert smoother is not None
        stamps = {key: float(k) for key in values.keys()}
        keep = gtsam.NonlinearFactorGraph()
        for i in range(graph.size()):
            f = graph.at(i)
            if f is None:
                continue
            keys = list(f.keys())
            if any(key in gone for key in keys):
                dropped += 1
                continue
            keep.add(f)
            stamps.update({key: float(k) for key in keys})
        stamps.update({key: float(k) for key in lamps if key in alive or values.exists(key)})
        smoother.update(keep, values, stamps)  # type: ignore[arg-type]  # (dict invariance)
        online[k] = _xyt(smoother.calculateEstimatePose2(X(k)))
        cpu.append(time.process_time() - c)
        alive.update(values.keys())
        now = set(smoother.timestamps().keys())
        for key in [key for key in alive if key not in now]:
            alive.discard(key)
            gone.add(key)
            sym = gtsam.Symbol(key)
            if sym.chr() == ord("x"):
                left[sym.index()] = online[sym.index()]
    est = isam.calculateEstimate() if isam is not None else smoother.calculateEstimate()  # type: ignore[union-attr]
    final = {k: left[k] if k in left else _xyt(est.atPose2(X(k))) for k in online}
    return np.asarray(cpu), online, final, dropped


def main() -> None:
    """Record, replay, print."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--lab", required=True, help="a simulated run directory")
    ap.add_argument("--lags", default="50,200", help="fixed-lag windows, keyframes")
    args = ap.parse_args()
    config = SlamConfig()
    batches, lamps, kf_t, _ = record(args.lab, config)
    run = read_run(args.lab)
    ks = sorted(kf_t)
    gt = run.groundtruth.interpolate(np.array([kf_t[k] for k in ks])) if run.groundtruth else None

    def rms(poses: dict[int, list[float]]) -> str:
        if gt is None:
            return "no ground truth"
        p = np.array([poses[k] for k in ks])
        e = np.hypot(p[:, 0] - gt[:, 0], p[:, 1] - gt[:, 1])
        h = np.angle(np.exp(1j * (p[:, 2] - gt[:, 2])))
        return f"{np.sqrt(np.mean(e**2)) * 1e3:.2f} mm / {np.degrees(np.sqrt(np.mean(h**2))):.4f} deg"

    print(f"{args.lab}: {len(batches)} keyframe batches, {len(lamps)} lamp keys kept in the "
          f"window; load average {os.getloadavg()[0]:.1f}")
    ref_total = None
    for lag in [None, *(float(s) for s in args.lags.split(","))]:
        cpu, online, final, dropped = replay(batches, config.isam2.to_gtsam(), lag, lamps)
        ms = cpu * 1e3
        ref_total = ref_total or float(cpu.sum())
        name = "iSAM2" if lag is None else f"fixed lag {lag:g} kf"
        print(f"  {name:18s} CPU {cpu.sum():6.2f} s ({cpu.sum() / ref_total:.2f}x iSAM2), per "
              f"keyframe median / p95 / max {np.median(ms):.1f} / {np.percentile(ms, 95):.1f} / "
              f"{ms.max():.0f} ms; dropped factors {dropped}; keyframe RMS online {rms(online)}, "
              f"final {rms(final)}", flush=True)
    print(f"load average {os.getloadavg()[0]:.1f} at the end")


if __name__ == "__main__":
    main()
