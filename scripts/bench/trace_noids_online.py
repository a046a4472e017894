"""Score the smoothers' online association without ids against the file's ids, per window.

Usage::

    python scripts/bench/trace_noids_online.py [--logs victoria,mrclam,synthetic]
        [--poses N] [--backend isam2] [--windows 0,500,2000,3500,4500]
        [--set pose2_odometry.cov_scale=16 ...] [--causes 20]

Each log runs one step per pose without ids (:func:`lampsam.backend.graph_log.graph_log_steps`,
``known_ids=False``); every association decision of every keyframe
(:func:`lampsam.backend.association.associate`, wrapped) is recorded with the exact
eq.-19 distance of each screened candidate. The file's landmark id of each
sighting is used only to score: a landmark's *owner* is the majority file id of its
sightings at the end of the run. Per window of poses: sightings in the file, taken
(matched or new), ``wrong`` (matched to a landmark another tree owns), ``missed``
(dropped as ambiguous, or matched nowhere while its tree's landmark existed), ``dup``
(a new landmark for a tree that already owned one) and the trajectory's position
RMS from lampsam's known-id iSAM2 (fast path) over the window.

Each wrong match is classified by what the gate saw at that keyframe:

- ``unmapped``: the true tree owned no landmark yet (its sighting went to a neighbour
  instead of starting one);
- ``nn``: the true tree's landmark was inside the gate too, farther in Mahalanobis
  distance than the chosen one (nearest neighbour picked the neighbour);
- ``rejected``: the true tree's landmark was screened but beyond the gate;
- ``unseen``: the true tree's landmark was not even screened (beyond the
  new-landmark threshold: drift);
- ``taken``: the true landmark was inside the gate and nearer, but another
  observation of the frame took it (greedy one-to-one);
- ``twin``: the landmark's tree and the sighting's are less than :data:`TWIN_M`
  apart in the known-id solution (the file gives one place two ids: not counted
  in the "not twins" column).

"Owner then" is the majority file id of the landmark's sightings up to that
keyframe; "final owner" the majority at the end (a landmark taken over later counts
all its first tree's sightings as wrong).

A ``dup`` is classified the same way (its true landmark's distance, beyond the
new-landmark threshold or not screened). The first ``--causes`` wrong matches are
(from the first ``--detail`` step on) printed with their keyframe, candidates and
distances.
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
import math
import os
import time
from collections import Counter, defaultdict
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from timing import sibling  # scripts/bench/timing.py, a sibling module

import lampsam.backend.graph as graph_mod
from lampsam.backend.config import SlamConfig
from lampsam.backend.graph_log import graph_log_steps, run_graph_log
from lampsam.backend.slam import drive, make_backend
from lampsam.datasets.graph_text import GraphLog

#: Two file ids whose known-id landmarks are closer than this (m) are one place ("twins").
TWIN_M = 1.5



@dataclass
class Decision:
    """One observation's association at one keyframe."""

    step: int
    kf: int
    fid: int
    status: str
    lid: int | None
    cands: dict[int, float] = field(default_factory=dict)  # lid -> exact d2
    sigma_xy: float = math.nan  # the online pose marginal's largest position sigma, m
    xy: tuple[float, float] = (math.nan, math.nan)  # the online pose estimate then, m
    obs_id: int = 0  # id() of the observation (unique within its keyframe)


def trace_run(g: GraphLog, config: SlamConfig, backend: str = "isam2"
              ) -> tuple[list[Decision], Any, Any]:
    """Run ``backend`` without ids over ``g`` recording every decision; ``(decisions, result, backend)``."""
    cfg = dataclasses.replace(
        config, isam2=dataclasses.replace(config.isam2, every_frame=True),
        association=dataclasses.replace(config.association, use_known_ids=False))
    be = make_backend(backend, cfg.pose2_odometry, cfg, g.start_pose())
    be._trace_revisit = True
    decisions: list[Decision] = []
    cur = {"step": 0}
    real_assoc, real_learn = graph_mod.associate, graph_mod.learn_scale
    inn: dict[str, Any] = {}

    def steps():  # type: ignore[no-untyped-def]
        for n, item in enumerate(graph_log_steps(g, known_ids=False)):
            cur["step"] = n
            yield item

    def assoc(*args, **kw):  # type: ignore[no-untyped-def]
        inn["fn"] = args[2]
        return real_assoc(*args, **kw)

    def learn(scale, obs, out, screened):  # type: ignore[no-untyped-def]
        # called after the association (and JCBB) of a keyframe: its final decisions
        n = cur["step"]
        file_s = g.sightings[n]
        cov = be.current_cov()
        sig = float(np.sqrt(max(np.linalg.eigvalsh(cov[:2, :2])[-1], 0.0)))
        here = be.current_pose()
        for a in out:
            o = obs[a.obs_index]
            j = int(np.argmin([abs(s.range - o.z[1]) + abs(math.remainder(s.bearing - o.z[0], math.tau))
                               for s in file_s]))
            d: dict[int, float] = {}
            for lid, (d2, exact) in (screened or {}).get(a.obs_index, {}).items():
                if not exact:
                    pred = inn["fn"](lid, o)
                    d2 = math.inf if pred is None else _m2(pred)
                d[lid] = float(d2)
            decisions.append(Decision(n, be._k, file_s[j].landmark, a.status, a.landmark_id, d, sig,
                                      (float(here[0]), float(here[1])), id(o)))
        return real_learn(scale, obs, out, screened)

    graph_mod.associate, graph_mod.learn_scale = assoc, learn
    try:
        result = drive(be, steps())
    finally:
        graph_mod.associate, graph_mod.learn_scale = real_assoc, real_learn
    # a new landmark's id is assigned by the backend: the first sighting recorded for it
    return decisions, result, be


def _m2(pred: tuple[np.ndarray, np.ndarray]) -> float:
    nu, psi = pred
    try:
        return float(nu @ np.linalg.solve(psi, nu))
    except np.linalg.LinAlgError:
        return float("inf")


def score(g: GraphLog, decisions: list[Decision], be: Any, windows: list[int], ref: np.ndarray,
          poses: np.ndarray, gate: float, new_t: float, n_causes: int,
          ref_xy: dict[int, np.ndarray], detail: tuple[int, int] = (0, 0),
          detail_csv: Path | None = None) -> tuple[dict[int, int], dict[int, int]]:
    """Print the per-window table and the wrong-match causes; with ``detail``
    ``(first, last)`` steps, a per-keyframe record of that range (``detail_csv``) and
    its summary per 100 steps, and why each revisit check there tied or not. Returns
    ``(owner, first_kf)``: each landmark's final majority file id and first keyframe."""
    # landmark id of each taken sighting (new ones: from the backend's sighting record)
    # (k, z, R, lid) per taken sighting; a keyframe's new landmarks come first, in order
    new_ids: dict[int, list[int]] = defaultdict(list)
    matched_ids: dict[int, set[int]] = defaultdict(set)
    for d in decisions:
        if d.status == "matched" and d.lid is not None:
            matched_ids[d.kf].add(d.lid)
    for k, _, _, lid in be._planar_sightings:
        if int(lid) not in matched_ids[int(k)]:
            new_ids[int(k)].append(int(lid))
    for d in decisions:
        if d.status == "new":
            d.lid = new_ids[d.kf].pop(0) if new_ids[d.kf] else None
    taken = [d for d in decisions if d.lid is not None and d.status in ("matched", "new")]
    by_lid: dict[int, Counter[int]] = defaultdict(Counter)
    for d in taken:
        by_lid[d.lid][d.fid] += 1  # type: ignore[index]
    owner = {lid: c.most_common(1)[0][0] for lid, c in by_lid.items()}
    first_kf: dict[int, int] = {}
    for d in taken:
        first_kf.setdefault(d.lid, d.kf)  # type: ignore[arg-type]
    tree_lids: dict[int, list[int]] = defaultdict(list)
    for lid, f in owner.items():
        tree_lids[f].append(lid)
    bounds = [*windows, len(g.pose_ids)]
    rows = []
    causes: Counter[str] = Counter()
    dup_causes: Counter[str] = Counter()
    shown = 0
    per_win = [Counter() for _ in windows]
    live: dict[int, Counter[int]] = defaultdict(Counter)  # sightings so far per landmark
    last_kf_of: dict[int, int] = {}
    shown_dup = 0

    def owner_now(lid: int) -> int | None:
        c = live.get(lid)
        return c.most_common(1)[0][0] if c else None

    per_kf: dict[int, Counter[str]] = defaultdict(Counter)
    kf_info: dict[int, tuple[int, float, tuple[float, float]]] = {}

    def mark(d: Decision, what: str) -> None:
        if detail[0] <= d.step < detail[1]:
            per_kf[d.kf][what] += 1
            kf_info[d.kf] = (d.step, d.sigma_xy, d.xy)

    for d in decisions:
        w = max(i for i, b in enumerate(windows) if d.step >= b)
        c = per_win[w]
        c["sightings"] += 1
        # the tree's landmarks at this keyframe: those whose sightings so far are mostly it
        true_lids = [lid for lid in live if owner_now(lid) == d.fid]
        if d.status == "dropped" or d.lid is None:
            c["dropped"] += 1
            mark(d, "dropped")
            continue
        c["taken"] += 1
        if d.status == "new":
            mark(d, "dup" if true_lids else "new_tree")
            if true_lids:
                c["dup"] += 1
                best = min((d.cands.get(lid, math.inf) for lid in true_lids), default=math.inf)
                dup_causes["unseen" if math.isinf(best) else "beyond new threshold"] += 1
                if shown_dup < n_causes and d.step >= detail[0]:
                    shown_dup += 1
                    n_true = max(sum(live[lid].values()) for lid in true_lids)
                    print(f"  dup: step {d.step} kf {d.kf} tree {d.fid}: its landmark(s) "
                          f"{true_lids} ({n_true} sightings) at d2 {best:.1f}; idle "
                          f"{d.kf - max(last_kf_of[lid] for lid in true_lids)} keyframes")
            live[d.lid][d.fid] += 1
            last_kf_of[d.lid] = d.kf
            continue
        now = owner_now(d.lid)
        live[d.lid][d.fid] += 1
        last_kf_of[d.lid] = d.kf
        if owner[d.lid] != d.fid:
            c["wrong"] += 1
        if now == d.fid:
            mark(d, "right")
            continue
        c["wrong_now"] += 1
        if now is not None and now in ref_xy and d.fid in ref_xy and float(
                np.hypot(*(ref_xy[now] - ref_xy[d.fid]))) < TWIN_M:
            causes["twin"] += 1
            mark(d, "right")
            continue  # two file ids at one place: not an error the gate could avoid
        c["wrong_far"] += 1
        mark(d, "wrong")
        d_chosen = d.cands.get(d.lid, math.nan)
        d_true = min((d.cands.get(lid, math.inf) for lid in true_lids), default=math.inf)
        if not true_lids:
            why = "unmapped"
        elif d_true < gate:
            why = "nn" if d_true >= d_chosen else "taken"
        elif math.isfinite(d_true):
            why = "rejected" + (" (< new threshold)" if d_true < new_t else "")
        else:
            why = "unseen"
        causes[why] += 1
        n_in = sum(1 for v in d.cands.values() if v < gate)
        causes[f"gated candidates = {min(n_in, 3)}{'+' if n_in >= 3 else ''}"] += 1
        n_lid = sum(live[d.lid].values()) - 1
        causes[f"chosen landmark's sightings before: {min(n_lid, 3)}{'+' if n_lid >= 3 else ''}"] += 1
        if shown < n_causes and d.step >= detail[0]:
            shown += 1
            print(f"  wrong: step {d.step} kf {d.kf} tree {d.fid} -> lm {d.lid} (tree {now} so far, "
                  f"{n_lid} sightings before), {why}; d2 chosen {d_chosen:.2f}, true {d_true:.2f}; "
                  f"candidates {sorted((round(v, 2), k) for k, v in d.cands.items())[:5]}")
    print("\n| poses | sightings | taken | dropped | wrong (final owner) | wrong (owner then) | "
          f"of which not twins (> {TWIN_M} m apart) | dup (new for a mapped tree) | "
          "RMS vs known-id iSAM2 [m] |")
    print("|---|---|---|---|---|---|---|---|---|")
    for w, c in enumerate(per_win):
        lo, hi = bounds[w], bounds[w + 1]
        dd = np.linalg.norm(poses[lo:hi, :2] - ref[lo:hi, :2], axis=1)
        rms = float(np.sqrt(np.mean(dd ** 2))) if len(dd) else math.nan
        rows.append(c)
        print(f"| {lo}-{hi} | {c['sightings']} | {c['taken']} | {c['dropped']} | {c['wrong']} | "
              f"{c['wrong_now']} | {c['wrong_far']} | {c['dup']} | {rms:.2f} |")
    tot = sum(per_win, Counter())
    dd = np.linalg.norm(poses[:, :2] - ref[:, :2], axis=1)
    print(f"| all | {tot['sightings']} | {tot['taken']} | {tot['dropped']} | {tot['wrong']} | "
          f"{tot['wrong_now']} | {tot['wrong_far']} | {tot['dup']} | {float(np.sqrt(np.mean(dd ** 2))):.2f} |")
    seen2 = sum(1 for v in Counter(s.landmark for ss in g.sightings for s in ss).values() if v >= 2)
    n2 = sum(1 for c in by_lid.values() if sum(c.values()) >= 2)
    print(f"landmarks {len(by_lid)} ({n2} with 2+ sightings) for {g.n_landmarks} file ids "
          f"({seen2} sighted 2+); trees owning 2+ landmarks: "
          f"{sum(1 for v in tree_lids.values() if len(v) >= 2)}")
    if detail[1] > detail[0]:
        _detail_report(per_kf, kf_info, ref, poses, detail, detail_csv)
        _revisit_report(be, owner, first_kf, ref_xy, detail, kf_info)
    ties = getattr(be, "revisit_ties", [])
    ok = [owner.get(c) == owner.get(o) or (owner.get(c) in ref_xy and owner.get(o) in ref_xy and float(
        np.hypot(*(ref_xy[owner[c]] - ref_xy[owner[o]]))) < TWIN_M) for _, c, o in ties]
    print(f"revisit ties: {len(ties)}, right (same tree or twins) {sum(ok)}; keyframes "
          f"{sorted({kf for kf, _, _ in ties})}")
    print("wrong-match causes:", dict(sorted(causes.items())))
    print("dup causes:", dict(dup_causes))
    return owner, first_kf


def held_report(be: Any, decisions: list[Decision], owner: dict[int, int],
                first_kf: dict[int, int], gate: float, n_show: int = 0) -> Counter[str]:
    """Every held sighting's fate (``--held``): given back by the re-gate, resolved by
    the revisit check, or never used; for the unused, why every re-gate failed
    (``rival``: another landmark still within the threshold; ``outside``: the best
    beyond the give-back gate; ``no candidate``: none of its candidates in the graph)
    and whether its tree owned a landmark when it was held (else it could only have
    started one). Prints a summary; returns the fate counts."""
    fid_of = {(d.kf, d.obs_id): d for d in decisions if d.status == "dropped"}
    tries: dict[int, list[tuple[int, str, list[tuple[float, int]]]]] = defaultdict(list)
    for k, kk, oid, why, sc in getattr(be, "_held_log", []):
        tries[oid].append((k - kk, why, sc))
    into = {id(z): int(lid) for _, z, _, lid in be._planar_sightings}
    fates: Counter[str] = Counter()
    shown = 0
    for k, o, _ in getattr(be, "_hold_log", []):
        d = fid_of.get((k, id(o)))
        fid = d.fid if d is not None else -1
        tree_lids = [lid for lid, f in owner.items() if f == fid and first_kf.get(lid, 1 << 30) <= k]
        mapped = "tree mapped" if tree_lids else "tree unmapped"
        ds = sorted((v, lid) for lid, v in (d.cands if d is not None else {}).items())
        held_why = ("rival" if len(ds) > 1 and ds[0][0] < gate else "between gate and threshold"
                    if ds and ds[0][0] >= gate else "other")
        t = tries.get(id(o), [])
        if id(o.z) in into:
            lid = into[id(o.z)]
            how = "given back" if any(w == "given" for _, w, _ in t) else "resolved by check"
            fate = f"{how}, {'right' if owner.get(lid) == fid else 'wrong'}"
        else:
            reasons = sorted({w for _, w, _ in t}) or ["never re-gated"]
            fate = f"unused ({'/'.join(reasons)})"
        fates[f"{fate}; {mapped}; held as {held_why}"] += 1
        if fate.startswith("unused") and shown < n_show:
            shown += 1
            print(f"  held kf {k} tree {fid} ({mapped} {tree_lids}): at hold "
                  f"{[(round(v, 1), lid, owner.get(lid)) for v, lid in ds[:3]]}; re-gates "
                  + "; ".join(f"age {a} {w} {[(round(v, 1), lid) for v, lid in sc[:2]]}"
                              for a, w, sc in t))
    print(f"held sightings: {sum(fates.values())}")
    for key, n in sorted(fates.items(), key=lambda kv: -kv[1]):
        print(f"  {n:5d}  {key}")
    return fates


def _detail_report(per_kf: dict[int, Counter[str]],
                   kf_info: dict[int, tuple[int, float, tuple[float, float]]],
                   ref: np.ndarray, poses: np.ndarray, detail: tuple[int, int],
                   csv: Path | None) -> None:
    """Per keyframe of the detail range: the online pose estimate's error against the
    known-id run (and the final one's), the online sigma, the sightings and what
    became of them."""
    keys = ("right", "wrong", "dup", "new_tree", "dropped")
    lines = ["kf,step,online_err_m,final_err_m,sigma_xy_m," + ",".join(keys)]
    fin: dict[int, list[float]] = defaultdict(list)
    bins: dict[int, Counter[str]] = defaultdict(Counter)
    errs: dict[int, list[float]] = defaultdict(list)
    sigs: dict[int, list[float]] = defaultdict(list)
    for kf in sorted(per_kf):
        step, sig, xy = kf_info[kf]
        err = float(np.hypot(xy[0] - ref[step, 0], xy[1] - ref[step, 1]))
        err_final = float(np.hypot(*(poses[step, :2] - ref[step, :2])))
        lines.append(f"{kf},{step},{err:.3f},{err_final:.3f},{sig:.3f},"
                     + ",".join(str(per_kf[kf][x]) for x in keys))
        b = step // 100 * 100
        bins[b].update(per_kf[kf])
        bins[b]["kf"] += 1
        errs[b].append(err)
        fin[b].append(err_final)
        sigs[b].append(sig)
    if csv is not None:
        csv.parent.mkdir(parents=True, exist_ok=True)
        csv.write_text("\n".join(lines) + "\n")
        print(f"per-keyframe record: {csv}")
    print("\n| steps | keyframes | online pose error vs known id, max [m] | final, max [m] | "
          "online sigma_xy, max [m] | right | wrong | mapped again | new tree | dropped |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for b in sorted(bins):
        c = bins[b]
        print(f"| {b}-{b + 100} | {c['kf']} | {max(errs[b]):.2f} | {max(fin[b]):.2f} | "
              f"{max(sigs[b]):.2f} | "
              + " | ".join(str(c[x]) for x in keys) + " |")


def _revisit_report(be: Any, owner: dict[int, int], first_kf: dict[int, int],
                    ref_xy: dict[int, np.ndarray], detail: tuple[int, int],
                    kf_info: dict[int, tuple[int, float, tuple[float, float]]]) -> None:
    """Why the revisit check tied or not at each run in the detail range: outcome, the
    recent landmarks that copy a tree mapped before (possible inliers), how many of
    those have the tree's landmark in the old set, and the best/rival inliers."""
    log = getattr(be, "revisit_log", [])
    kfs = [kf for kf in kf_info]
    if not log or not kfs:
        print("revisit check: no run recorded in the detail range")
        return
    lo, hi = min(kfs), max(kfs)
    tree_first: dict[int, list[tuple[int, int]]] = defaultdict(list)
    for lid, f in owner.items():
        tree_first[f].append((first_kf.get(lid, 0), lid))
    outcomes: Counter[str] = Counter()
    print("\n| keyframe | recent | old | recent copying an older landmark | "
          "of which its landmark in 'old' | best | rival | outcome |")
    print("|---|---|---|---|---|---|---|---|")
    shown = 0
    for r in log:
        if not lo <= r.k <= hi:
            continue
        outcomes[r.outcome] += 1
        old = set(r.old)
        copies = in_old = 0
        for lid in r.recent:
            f = owner.get(lid)
            olders = [x for fk, x in tree_first.get(f, []) if fk < first_kf.get(lid, 0)]
            if olders:
                copies += 1
                in_old += any(x in old for x in olders)
        if r.outcome != "few" or copies:
            outcomes[f"{r.outcome}, copies {min(copies, 4)}{'+' if copies >= 4 else ''}"] += 1
            if shown < 40 and copies:
                shown += 1
                print(f"| {r.k} | {len(r.recent)} | {len(r.old)} | {copies} | {in_old} | "
                      f"{r.n_best} | {r.runner_up} | {r.outcome} |")
    print("revisit check outcomes in the detail range:", dict(sorted(outcomes.items())))


def main() -> None:
    """Parse arguments, run and score each log."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--logs", default="victoria")
    ap.add_argument("--poses", type=int, default=0)
    ap.add_argument("--backend", default="isam2")
    ap.add_argument("--windows", default="0,500,2000,3500,4500")
    ap.add_argument("--set", nargs="*", default=[], metavar="SECTION.KEY=VALUE")
    ap.add_argument("--causes", type=int, default=15)
    ap.add_argument("--out", default="/tmp/trace_noids_online")
    ap.add_argument("--held", type=int, default=-1, metavar="N",
                    help="print every held sighting's fate (and the first N unused in full)")
    ap.add_argument("--detail", default="", metavar="FIRST,LAST",
                    help="steps to record per keyframe (and trace the revisit check in)")
    args = ap.parse_args()
    logging.basicConfig(level=logging.WARNING)
    bench = sibling("bench_landmark_logs")
    scale = sibling("bench_noids_scale")
    config = bench.with_overrides(SlamConfig(), args.set)
    print("load average (1, 5, 15 min): " + ", ".join(f"{v:.1f}" for v in os.getloadavg()))
    for name in args.logs.split(","):
        g = scale.load_log(name, Path(args.out))
        if args.poses:
            g = bench.first_poses(g, args.poses)
        ref_res = run_graph_log(g, "isam2", config)
        ref = ref_res.poses
        ref_xy = {lm.id: np.asarray(lm.position[:2]) for lm in ref_res.landmarks + ref_res.provisional}
        c0 = time.process_time()
        decisions, result, be = trace_run(g, config, args.backend)
        cpu = time.process_time() - c0
        windows = [int(x) for x in args.windows.split(",") if int(x) < len(g.pose_ids)]
        print(f"\n## {name}: {len(g.pose_ids)} poses, {args.backend} no ids, {cpu:.1f} s CPU, "
              f"status {result.status}, QR rebuilds {result.extra.get('n_qr_rebuilds')}, "
              f"recoveries {result.extra.get('n_recoveries')}, JCBB keyframes "
              f"{result.extra.get('n_jcbb')} (changed {result.extra.get('n_jcbb_changed')}), "
              f"revisit merges {result.extra.get('n_revisit_merges')}, held sightings resolved "
              f"{result.extra.get('n_revisit_resolved')}, moved {result.extra.get('n_revisit_moved')}; "
              f"held {result.extra.get('n_held')}, given back {result.extra.get('n_held_given_back')}, "
              f"never used {result.extra.get('n_held_unused')}")
        detail = tuple(int(x) for x in args.detail.split(",")) if args.detail else (0, 0)
        owner, first_kf = score(
            g, decisions, be, windows, ref, result.poses, config.association.gate(2),
            config.association.new_threshold(2), args.causes, ref_xy, detail,  # type: ignore[arg-type]
            Path(args.out) / f"{name}_keyframes.csv")
        if args.held >= 0:
            held_report(be, decisions, owner, first_kf, config.association.gate(2), args.held)


if __name__ == "__main__":
    main()
