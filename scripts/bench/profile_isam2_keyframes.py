"""Where the slow iSAM2 keyframes' time goes: update, exact-gate joint marginals, first estimate read.

Usage::

    python scripts/bench/profile_isam2_keyframes.py --lab RUN_DIR [--no-prefetch]

Runs :class:`~lampsam.backend.graph.Isam2Slam` over a run's frames (the frontend on the
images, made once before timing) with iSAM2 wrapped so that each ``update``,
``jointMarginalCovariance`` and ``calculateEstimatePose2`` call is timed in process CPU
time. Prints, per keyframe, the share of the backend's CPU in each, then the slowest 5 %
of keyframes (those at or above the p95) against the faster half: mean CPU per part,
variables relinearised and re-eliminated by the update, new factors, and the keyframe
indices of the slow ones (clusters show revisits). ``--exact-gate`` turns the gate's
bracket off (``[isam2] bracket_gate = false``: every undecided lamp pair asks iSAM2, as
before it). ``--no-prefetch`` asks one joint
marginal per landmark instead of one per keyframe (:meth:`Gating._prefetch_joint` off),
to tell the Bayes tree's cost from the batching's. Per update it also records what
iSAM2 re-eliminated for: whether it relinearised, how many poses its new factors touch
(a corner entering the graph brings sights from up to ``corner_pending_keyframes``
keyframes back) and whether a landmark last in an update more than :data:`OLD_KF`
keyframes before is observed again (a revisit); printed for the slowest 5 % against
the faster half. ``--constrain-recent W`` passes GTSAM's ``constrainedKeys`` with the
new factors' keys and the last ``W`` keyframes' poses in the last group (eliminated
last, near the root), to test whether keeping recent poses at the top shortens the
slow updates (docs/speed.md: it does not). Joint-marginal calls are also
binned by their number of keys, and the landmarks of the calls over 20 ms are counted
(a prefetched call names all its lamps, though its cost is its deepest one's: on the
lab path, lamp 1, rejected at every revisit keyframe; docs/speed.md), and for slow and
cheap calls alike the keyframes since their least recently observed lamp (a lamp not
observed at the last keyframe has left the root clique: docs/speed.md). The Python
phases of a keyframe are timed too (inclusive CPU: the screen with its point reads,
association with the exact gate, observing and starting landmarks, the pose marginal),
in all and per slow keyframe. CPU figures
are inflated on a loaded machine: compare the shares and the slow/fast ratios.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import time
from collections import Counter
from typing import Any

import gtsam
import numpy as np
from gtsam.symbol_shorthand import X

from lampsam.backend.ceiling import CeilingModel
from lampsam.backend.ceiling_graph import CeilingHandler
from lampsam.backend.config import SlamConfig
from lampsam.backend.gating import Gating
from lampsam.backend.graph import Isam2Slam
from lampsam.backend.slam import iter_steps, make_frames, start_pose_of
from lampsam.datasets.logrun import read_run

#: A joint-marginal call slower than this (s CPU) has its landmarks counted.
SLOW_CALL_S = 0.02
#: ... and one faster than this is counted as a cheap call (near the Bayes tree's root).
FAST_CALL_S = 0.001
#: A landmark observed again after this many keyframes out of the updates counts as a revisit.
OLD_KF = 20


class _TimedIsam:
    """Delegates to a ``gtsam.ISAM2``, timing three of its calls into ``rec``."""

    def __init__(self, isam: Any, rec: dict[str, float], joint_calls: list[tuple[int, float]],
                 slow_ids: Counter[int]) -> None:
        self._isam = isam
        self._rec = rec
        self._joint = joint_calls
        self._slow_ids = slow_ids
        #: the backend (set by the caller) and, per slow / fast joint call, the most
        #: keyframes since one of its lamps was last observed
        self.backend: Any = None
        self.slow_since: list[int] = []
        self.fast_since: list[int] = []
        #: keyframe of each landmark key's last update; ``constrain_recent``: see the module doc
        self.last_update: dict[int, int] = {}
        self.constrain_recent: int | None = None

    def __getattr__(self, name: str) -> Any:
        return getattr(self._isam, name)

    def update(self, *args: Any) -> Any:
        k = self.backend._k if self.backend is not None else 0
        if self.constrain_recent is not None and len(args) >= 2:
            groups = gtsam.KeyGroupMap()  # one group: GTSAM 4.3 failed with two ("not involved")
            for key in args[0].keyVector():
                groups.insert2(key, 1)
            for j in range(max(0, k - self.constrain_recent), k + 1):
                groups.insert2(X(j), 1)
            params = gtsam.ISAM2UpdateParams()
            params.constrainedKeys = groups
            args = (args[0], args[1], params)
        c = time.process_time()
        result = self._isam.update(*args)
        self._rec["update"] += time.process_time() - c
        poses, revisit = 0, False
        for key in result.getObservedKeys():
            if gtsam.Symbol(key).chr() == ord("x"):
                poses += 1
            else:
                revisit |= k - self.last_update.get(key, k) > OLD_KF
                self.last_update[key] = k
        self._rec["poses touched"] += poses
        self._rec["revisit"] += revisit
        self._rec["relinearising"] += result.getVariablesRelinearized() > 0
        self._rec["relinearized"] += result.getVariablesRelinearized()
        self._rec["reeliminated"] += result.getVariablesReeliminated()
        if args:
            self._rec["factors"] += args[0].size()
        return result

    def jointMarginalCovariance(self, keys: Any) -> Any:  # noqa: N802 (GTSAM's name)
        c = time.process_time()
        out = self._isam.jointMarginalCovariance(keys)
        dt = time.process_time() - c
        self._rec["joint"] += dt
        self._joint.append((len(keys), dt))
        if dt > SLOW_CALL_S:  # name the landmarks (L(j), A(j) -> j) of a slow call
            ids = {gtsam.Symbol(key).index() for key in list(keys)[1:]}
            self._slow_ids.update(ids)
            if self.backend is not None:  # keyframes since its lamps were last observed
                lms = self.backend._landmarks
                self.slow_since.append(max(self.backend._k - lms[i].last_kf for i in ids if i in lms))
        elif dt < FAST_CALL_S and len(keys) > 1 and self.backend is not None:
            lms = self.backend._landmarks
            ids = {gtsam.Symbol(key).index() for key in list(keys)[1:]}
            self.fast_since.append(max(self.backend._k - lms[i].last_kf for i in ids if i in lms))
        return out

    def calculateEstimatePose2(self, key: int) -> Any:  # noqa: N802
        c = time.process_time()
        out = self._isam.calculateEstimatePose2(key)
        self._rec["estimate"] += time.process_time() - c
        return out

    def calculateEstimatePoint3(self, key: int) -> Any:  # noqa: N802
        c = time.process_time()
        out = self._isam.calculateEstimatePoint3(key)
        self._rec["point reads"] += time.process_time() - c
        return out

    def marginalCovariance(self, key: int) -> Any:  # noqa: N802
        c = time.process_time()
        out = self._isam.marginalCovariance(key)
        self._rec["pose marginal"] += time.process_time() - c
        return out


def _timed(obj: Any, name: str, rec: dict[str, float], part: str) -> None:
    """Replace the bound method ``obj.name`` by one that adds its CPU time to ``rec[part]``."""
    fn = getattr(obj, name)

    def wrapper(*args: Any, **kwargs: Any) -> Any:
        c = time.process_time()
        try:
            return fn(*args, **kwargs)
        finally:
            rec[part] += time.process_time() - c

    setattr(obj, name, wrapper)


def main() -> None:
    """Parse arguments, run, print the breakdown."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--lab", required=True, help="a simulated run directory")
    ap.add_argument("--no-prefetch", action="store_true", help="one joint marginal per landmark")
    ap.add_argument("--constrain-recent", type=int, default=None, metavar="W",
                    help="constrain the new factors' keys and the last W poses last")
    ap.add_argument("--exact-gate", action="store_true",
                    help="[isam2] bracket_gate = false: every undecided lamp pair asks iSAM2")
    args = ap.parse_args()
    if args.no_prefetch:
        Gating._prefetch_joint = lambda *a, **k: 0  # type: ignore[method-assign]
    run = read_run(args.lab)
    frames, _ = make_frames(run, "images")
    frames = list(frames)
    model = CeilingModel.from_camera(run.rig.camera)
    cfg = SlamConfig()
    if args.exact_gate:
        cfg = dataclasses.replace(cfg, isam2=dataclasses.replace(cfg.isam2, bracket_gate=False))
    be = Isam2Slam(run.rig.odometry, cfg, start_pose_of(run), model, CeilingHandler(model))
    parts = ("update", "joint", "estimate", "relinearized", "reeliminated", "factors",
             "poses touched", "revisit", "relinearising")
    # Python phases of a keyframe (inclusive: the screen contains the point reads,
    # association the exact gate's joint marginals)
    phases = ("screen", "associate", "observe", "new landmarks", "point reads", "pose marginal")
    rec = dict.fromkeys(parts + phases, 0.0)
    _timed(be, "_screen", rec, "screen")
    _timed(be, "_observe", rec, "observe")
    _timed(be, "_start_landmark", rec, "new landmarks")
    import lampsam.backend.graph as graph_module
    assoc = graph_module.associate

    def timed_associate(*a: Any, **k: Any) -> Any:
        c = time.process_time()
        try:
            return assoc(*a, **k)
        finally:
            rec["associate"] += time.process_time() - c

    graph_module.associate = timed_associate  # type: ignore[assignment]
    joint_calls: list[tuple[int, float]] = []
    slow_ids: Counter[int] = Counter()
    timed = _TimedIsam(be.isam, rec, joint_calls, slow_ids)
    timed.backend = be
    timed.constrain_recent = args.constrain_recent
    be.isam = timed  # type: ignore[assignment]
    rows = []
    for t, wheel, frame in iter_steps(run.odometry, frames):
        for key in rec:
            rec[key] = 0.0
        c = time.process_time()
        est = be.step(t, wheel, frame)
        if est.keyframe:
            rows.append([time.process_time() - c, *(rec[p] for p in parts), be._k,
                         *(rec[p] for p in phases)])
    r = np.array(rows)
    total = r[:, 0]
    p95 = float(np.percentile(total, 95))
    print(f"{len(r)} keyframes, CPU median / p95 {np.median(total) * 1e3:.1f} / {p95 * 1e3:.1f} ms, "
          f"load average {os.getloadavg()[0]:.1f}; lamp pairs settled by the gate's bracket "
          f"inside / outside {be.n_bracket_inside} / {be.n_bracket_outside}, joint-marginal "
          f"calls {len(joint_calls)}")
    print("share of keyframe CPU: " + ", ".join(
        f"{p} {r[:, 1 + i].sum() / total.sum():.2f}" for i, p in enumerate(parts[:3])))
    for name, sel in (("slowest 5 %", total >= p95), ("faster half", total < np.median(total))):
        s = r[sel]
        print(f"{name} (n={len(s)}): mean CPU {s[:, 0].mean() * 1e3:.1f} ms = update "
              f"{s[:, 1].mean() * 1e3:.1f} + joint marginals {s[:, 2].mean() * 1e3:.1f} + first "
              f"estimate {s[:, 3].mean() * 1e3:.1f} + rest; relinearised {s[:, 4].mean():.0f}, "
              f"re-eliminated {s[:, 5].mean():.0f}, new factors {s[:, 6].mean():.0f}; poses "
              f"touched by the new factors {s[:, 7].mean():.1f}, share revisiting a landmark "
              f"unseen for > {OLD_KF} keyframes {s[:, 8].mean():.2f}, share relinearising "
              f"{s[:, 9].mean():.2f}")
    kcol = 1 + len(parts)
    print("slow keyframes:", r[total >= p95, kcol].astype(int).tolist())
    print(f"keyframe CPU in all, s: total {total.sum():.2f} = " + ", ".join(
        f"{p} {r[:, 1 + i].sum():.2f}" for i, p in enumerate(parts[:3])) + "; Python phases "
        "(inclusive): " + ", ".join(f"{p} {r[:, kcol + 1 + i].sum():.2f}" for i, p in enumerate(phases)))
    slow = total >= p95
    print("slowest 5 %, mean ms per phase: " + ", ".join(
        f"{p} {r[slow, kcol + 1 + i].mean() * 1e3:.1f}" for i, p in enumerate(phases)))
    print(f"landmarks in joint-marginal calls over {SLOW_CALL_S * 1e3:.0f} ms (id: calls): "
          + ", ".join(f"{i}: {n}" for i, n in slow_ids.most_common(8)))
    for name, since in (("over", timed.slow_since), ("under", timed.fast_since)):
        if since:
            lim = SLOW_CALL_S if name == "over" else FAST_CALL_S
            print(f"joint-marginal calls {name} {lim * 1e3:g} ms: n={len(since)}, keyframes since "
                  f"their least recently observed lamp median {np.median(since):.0f}, "
                  f"min {min(since)}, share with every lamp seen at the last keyframe "
                  f"{np.mean(np.array(since) <= 1):.2f}")
    j = np.array(joint_calls).reshape(-1, 2)
    for lo, hi in ((1, 5), (5, 9), (9, 1000)):
        m = (j[:, 0] >= lo) & (j[:, 0] < hi)
        if m.any():
            print(f"joint marginals over {lo}-{min(hi, int(j[:, 0].max()) + 1) - 1} keys: n={m.sum()}, "
                  f"CPU median {np.median(j[m, 1]) * 1e3:.2f} ms, max {j[m, 1].max() * 1e3:.1f} ms")


if __name__ == "__main__":
    main()
