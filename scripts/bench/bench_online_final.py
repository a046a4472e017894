"""Online runs without ids on graph logs: the online answer against its final solve.

Usage::

    python scripts/bench/bench_online_final.py [--logs vp1k,city,synthetic,mrclam,victoria]
        [--backends isam2,ekf] [--set SECTION.KEY=VALUE ...] [--label NAME]
        [--variants defaults,both,both16,picker] [--candidates defaults,...]

For each log: GTSAM's LM on the file's graph with its ids (the reference, as
``bench_landmark_logs.py``: GTSAM's iSAM2 one update per pose, then LM), lampsam's
known-id batch (its RMS from LM: the "known-id figure" of issue 15), then for each
backend the online run without ids (:func:`lampsam.backend.graph_log.run_graph_log_backend`,
config with the ``--set`` overrides) and the final solve of its association at the
log's stated noise (:func:`lampsam.backend.online_final.final_solve`). Printed per run:
position RMS from GTSAM's LM, landmarks with 2+ sightings against the trees sighted 2+
times (file ids, twins as one: ``bench_noids_scale.twin_map``), duplicated trees, wrong
sightings (``bench_noids_scale.score``), the description length ``C`` (final solve),
failures (iSAM2 recoveries that dropped measurements) and process CPU s of each stage.
The file ids are read only to score. CPU figures are process time on a shared machine.

Logs: those of ``bench_noids_scale.load_log`` (``victoria``, ``synthetic``, ``mrclam``,
``city``, ``vp1k`` and the held-out ``grid``, ``loop``, ``odo2x`` of
:mod:`lampsam.datasets.landmark_log_heldout`, written by its ``write_held_out``) and
``synth2``: a second synthetic log, never used before this bench
(:mod:`lampsam.datasets.landmark_log_sim`, seed 1, 3,000 poses, 800 trees in 200 m,
odometry noise twice the default in sigma). The simulated logs (``synthetic``,
``synth2`` and the held-out three) also print the RMS from their truth in the run's
label.

``--variants`` runs several settings of :data:`VARIANTS` in one invocation (the
reference runs once per log; each variant's overrides are applied after ``--set``):
``defaults``; ``both`` = ``[association] planar_unique`` and ``revisit_check`` on;
``both16`` = ``both`` and ``[pose2_odometry] cov_scale = 16``; ``picker`` = the online
picker (:func:`lampsam.backend.online_final.run_online_picker`) with ``[reassociation]
online_candidates`` = ``--candidates`` (default :data:`PICKER_CANDIDATES`): one row per
candidate (its final solve, or its status when it lost without one), then the chosen one
and whether ``C`` chose the candidate whose final solve is nearest GTSAM's LM; ``mix``,
``both16mix``, ``pickermix`` = ``defaults``, ``both16``, ``picker`` with ``[reassociation]
online_final_held_mixture`` on (the left-out sightings placed by max-mixture factors in
each final solve, :mod:`lampsam.backend.held_placement`). The last column says "yes" when the final solve (or, if it did not run, the online answer) is more
than :data:`DIVERGED_M` from GTSAM's LM.

``corridor``, ``odo3x`` and ``overstated`` (:data:`NEW_HELD_OUT`) are held-out logs of
the picker, fixed before it ran on them; ``carpark`` and ``pillars``
(:data:`ALIASED_HELD_OUT`) aliased held-out logs of its label-entropy cost.
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
import os
import time
from collections import Counter
from pathlib import Path
from types import ModuleType

import gtsam
import numpy as np
from timing import sibling  # scripts/bench/timing.py, a sibling module

from lampsam.backend.config import SlamConfig
from lampsam.backend.graph_log import run_graph_log, run_graph_log_backend
from lampsam.backend.online_final import final_solve, online_association, run_online_picker
from lampsam.backend.reassociate import Sightings
from lampsam.datasets.graph_text import GraphLog, read_graph_text, read_vertices
from lampsam.datasets.landmark_log_heldout import HeldOutSpec, simulate_held_out
from lampsam.datasets.landmark_log_sim import LandmarkLogSpec, write_landmark_log
from lampsam.safe_io import write_text_atomic

#: A run whose RMS from GTSAM's LM exceeds this (m) counts as diverged.
DIVERGED_M = 5.0
#: Named settings for ``--variants`` (``SECTION.KEY=VALUE`` overrides).
VARIANTS: dict[str, list[str]] = {
    "defaults": [],
    "both": ["association.planar_unique=true", "association.revisit_check=true"],
    "both16": ["association.planar_unique=true", "association.revisit_check=true",
               "pose2_odometry.cov_scale=16"],
    "picker": [],  # [reassociation] online_candidates = --candidates (run_picker)
    # the left-out sightings placed by max-mixture factors (backend/held_placement.py)
    "mix": ["reassociation.online_final_held_mixture=true"],
    "both16mix": ["association.planar_unique=true", "association.revisit_check=true",
                  "pose2_odometry.cov_scale=16", "reassociation.online_final_held_mixture=true"],
    "pickermix": ["reassociation.online_final_held_mixture=true"],  # the picker, with it
}
#: ``--candidates`` default: the picker's candidates (``[reassociation] online_candidates``)
PICKER_CANDIDATES = ",".join(SlamConfig().reassociation.online_candidates)



#: Held-out logs of the online picker (session 16, engineer autopick): specs and seeds fixed
#: at 22:55 UTC on 2026-11-24, before any candidate ran on them, and not looked at until the
#: final table (:mod:`lampsam.datasets.landmark_log_heldout`'s simulator, new specs):
#: ``corridor``: a 150 m x 6 m loop driven twice with 120 trees 2-3 m either side (a
#: corridor: few trees in view, the two sides 6 m apart); ``odo3x``: a uniform field whose
#: odometry noise is 3x the stated sigma (understated); ``overstated``: a uniform field
#: whose odometry noise is 1/4 of the stated sigma (stated too large, as
#: victoriaPark_reduced_1k's).
NEW_HELD_OUT: dict[str, tuple[HeldOutSpec, int]] = {
    "corridor": (HeldOutSpec(layout="loop", n_landmarks=120, loop_size=(150.0, 6.0),
                             corridor=3.0, laps=2, max_range=10.0), 201),
    "odo3x": (HeldOutSpec(layout="uniform", n_poses=2000, n_landmarks=250, extent=120.0,
                          true_noise=3.0, max_range=12.0), 202),
    "overstated": (HeldOutSpec(layout="uniform", n_poses=2000, n_landmarks=250,
                               extent=120.0, true_noise=0.25, max_range=12.0), 203),
}


#: Aliased held-out logs of the label-entropy cost (session 17, engineer aliascost): specs
#: and seeds fixed at 01:25 UTC on 2026-11-25, before any run on them. Each is a
#: :data:`NEW_HELD_OUT`-style spec and seed, then ``(every, radius, stated)``: sightings
#: kept at every ``every``-th pose only (sparse, as cityTrees' every 5th), ranges measured
#: to the surface of a pillar of ``radius`` m (short by ``radius``, as MRCLAM's tubes), and
#: the stated range and bearing sigma ``stated`` times the true ones.
#: ``carpark``: lamps on a 5 m grid, 0-4 in view at every 5th pose, noise stated right;
#: ``pillars``: pillars of radius 0.15 m on a 4 m grid, every 2nd pose, ranges to the
#: pillar's surface and measurement noise understated 2x.
ALIASED_HELD_OUT: dict[str, tuple[HeldOutSpec, int, tuple[int, float, float]]] = {
    "carpark": (HeldOutSpec(layout="grid", n_poses=1500, extent=80.0, spacing=5.0, jitter=0.05,
                            sigma_side=0.03, sigma_theta=0.006, max_range=7.0), 301,
                (5, 0.0, 1.0)),
    "pillars": (HeldOutSpec(layout="grid", n_poses=1500, extent=60.0, spacing=4.0, jitter=0.05,
                            max_range=8.0), 302, (2, 0.15, 0.5)),
}


def aliased_lines(lines: list[str], every: int, radius: float, stated: float) -> list[str]:
    """:data:`ALIASED_HELD_OUT`'s changes to a simulated log's records: ``BR`` sightings
    kept at every ``every``-th pose, their range less ``radius`` m, their stated sigmas
    times ``stated``; other records unchanged."""
    out: list[str] = []
    for line in lines:
        f = line.split()
        if f[0] != "BR":
            out.append(line)
            continue
        if int(f[1]) % every:
            continue
        b, r, sb, sr = (float(x) for x in f[3:7])
        out.append(f"BR {f[1]} {f[2]} {b:.9g} {r - radius:.9g} {sb * stated:.9g} "
                   f"{sr * stated:.9g}")
    return out


def write_new_held_out(path: Path, name: str) -> Path:
    """Write :data:`NEW_HELD_OUT` log ``name`` to ``path`` and its truth to
    ``<stem>_truth.txt`` (``VERTEX2``), as ``landmark_log_heldout.write_held_out``."""
    if name in ALIASED_HELD_OUT:
        spec, seed, (every, radius, stated) = ALIASED_HELD_OUT[name]
        lines, truth, _ = simulate_held_out(spec, np.random.default_rng(seed))
        lines = aliased_lines(lines, every, radius, stated)
    else:
        spec, seed = NEW_HELD_OUT[name]
        lines, truth, _ = simulate_held_out(spec, np.random.default_rng(seed))
    write_text_atomic(path, "\n".join(lines) + "\n")
    write_text_atomic(path.with_name(path.stem + "_truth.txt"),
                      "".join(f"VERTEX2 {k} {p[0]:.9g} {p[1]:.9g} {p[2]:.9g}\n"
                              for k, p in enumerate(truth)))
    return path


def load_log(scale: ModuleType, name: str, out: Path) -> GraphLog:
    """A log by name (module doc)."""
    if name in NEW_HELD_OUT or name in ALIASED_HELD_OUT:
        out.mkdir(parents=True, exist_ok=True)
        return read_graph_text(write_new_held_out(out / f"heldout_{name}.txt", name))
    if name == "synth2":
        out.mkdir(parents=True, exist_ok=True)
        spec = LandmarkLogSpec(n_landmarks=800, sigma_fwd=0.02, sigma_side=0.06,
                               sigma_theta=0.008)
        p, _ = write_landmark_log(out / "synth2.txt", spec, np.random.default_rng(1))
        return read_graph_text(p)
    g: GraphLog = scale.load_log(name, out)
    return g


def _rms(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.sum((a[:, :2] - b[:, :2]) ** 2, axis=1))))


def load_truth(g: GraphLog, name: str, out: Path) -> np.ndarray | None:
    """(n, 3) true poses of a simulated log (written beside it), else None."""
    stem = {"synthetic": "synthetic", "synth2": "synth2"}.get(name, f"heldout_{name}")
    tpath = out / f"{stem}_truth.txt"
    if (name not in ("synthetic", "synth2", "grid", "loop", "odo2x", *NEW_HELD_OUT,
                     *ALIASED_HELD_OUT)
            or not tpath.exists()):
        return None
    v = read_vertices(tpath)
    return np.array([v[i] for i in g.pose_ids])


def _vs_truth(poses: np.ndarray, truth: np.ndarray | None) -> str:
    return "" if truth is None else f"; {_rms(poses, truth):.3f} from truth"


def main() -> None:
    """Parse arguments, run every log and backend, print one table."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--logs", default="vp1k,city,synthetic,mrclam")
    ap.add_argument("--backends", default="isam2")
    ap.add_argument("--set", nargs="*", default=[], metavar="SECTION.KEY=VALUE")
    ap.add_argument("--label", default="", help="a name for the setting, printed in each row")
    ap.add_argument("--out", default="/tmp/bench_online_final")
    ap.add_argument("--variants", default="",
                    help=f"comma-separated named settings ({', '.join(VARIANTS)}), each run "
                         "after the --set overrides; empty: --set alone")
    ap.add_argument("--candidates", default=PICKER_CANDIDATES,
                    help="the picker variant's [reassociation] online_candidates, "
                         f"comma-separated (default {PICKER_CANDIDATES})")
    ap.add_argument("--diagnose", action="store_true",
                    help="also the known-id batch on the sightings the online run recorded "
                         "(what the held and dropped sightings cost, apart from the association)")
    args = ap.parse_args()
    logging.basicConfig(level=logging.ERROR)
    bench = sibling("bench_landmark_logs")
    scale = sibling("bench_noids_scale")
    base_label = args.label or (" ".join(args.set) if args.set else "defaults")
    variants = args.variants.split(",") if args.variants else [""]
    for v in variants:
        if v and v not in VARIANTS:
            raise SystemExit(f"--variants: unknown {v!r} (known: {', '.join(VARIANTS)})")
    print("load average (1, 5, 15 min): " + ", ".join(f"{v:.1f}" for v in os.getloadavg()))
    print(f"setting: {base_label}; variants: {args.variants or '-'}")
    print("| log | run | RMS vs LM [m] | landmarks 2+ / trees 2+ | dup | wrong / sightings | C "
          "| failures | CPU [s] | diverged |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for name in args.logs.split(","):
        g = load_log(scale, name, Path(args.out))
        truth = load_truth(g, name, Path(args.out))
        n = len(g.pose_ids)
        graph = bench.gtsam_graph(g, SlamConfig())
        est = bench.gtsam_isam2(g, SlamConfig())[0]
        lm = bench.poses_of(gtsam.LevenbergMarquardtOptimizer(
            graph, est, gtsam.LevenbergMarquardtParams()).optimize(), n)
        c0 = time.process_time()
        known = run_graph_log(g, "batch", SlamConfig())
        c_known = time.process_time() - c0
        twins = scale.twin_map(g, {int(x.id): np.asarray(x.position[:2], float)
                                   for x in list(known.landmarks) + list(known.provisional)})
        trees = Counter(twins.get(x.landmark, x.landmark) for ss in g.sightings for x in ss)
        n_trees2 = sum(1 for v in trees.values() if v >= 2)
        n_sight = sum(len(ss) for ss in g.sightings)
        print(f"| {name} | known-id batch (file noise{_vs_truth(known.poses, truth)}) | "
              f"{_rms(known.poses, lm):.3f} | "
              f"{len(known.landmarks)} / {n_trees2} | | | | | {c_known:.1f} | |", flush=True)
        for v in variants:
            config = bench.with_overrides(SlamConfig(), args.set + VARIANTS.get(v, []))
            label = f"{v}: {base_label}" if v and args.set else (v or base_label)
            if v in ("picker", "pickermix"):
                config = dataclasses.replace(config, reassociation=dataclasses.replace(
                    config.reassociation, online_candidates=tuple(args.candidates.split(","))))
                run_picker(g, name, config, label, args, scale, lm, truth, twins, n_trees2)
                continue
            run_variant(g, name, config, label, args, bench, scale, lm, truth, twins, n_trees2,
                        n_sight)


def run_picker(g: GraphLog, name: str, config: SlamConfig, label: str,  # noqa: PLR0913
               args: argparse.Namespace, scale: ModuleType, lm: np.ndarray,
               truth: np.ndarray | None, twins: dict[int, int], n_trees2: int) -> None:
    """The online picker (:func:`lampsam.backend.online_final.run_online_picker`) per
    backend: one row per candidate (its final solve's RMS, count, ``C``, CPU), then the
    choice, and whether ``C`` chose the candidate whose final solve is nearest GTSAM's LM."""
    for b in args.backends.split(","):
        c0 = time.process_time()
        final, _, cands, chosen = run_online_picker(g, b, config)
        c_all = time.process_time() - c0
        rms: list[float] = []
        for c in cands:
            if c.solve is None:
                rms.append(float("nan"))
                on = c.online
                r_on = (_rms(on.poses, lm[:len(on.poses)]) if on is not None and len(on.poses)
                        else float("nan"))
                print(f"| {name} | {b} candidate {c.name}: {c.status[:70]} | online {r_on:.3f} | "
                      f"| | | | | {c.cpu_s:.1f} | (loses) |", flush=True)
                continue
            run = c.solve
            mapped, dup, wrong = scale.score(run.sightings, scale.tree_ids(g, run.sightings,
                                                                           twins))
            r = _rms(run.poses, lm)
            rms.append(r)
            held = int(c.online.extra.get("n_held_unused", 0)) if c.online is not None else 0
            div = "yes" if not (np.isfinite(r) and r <= DIVERGED_M) else ""
            print(f"| {name} | {b} candidate {c.name} ({held} held unused, "
                  f"{run.n_dropped} not in the association{_vs_truth(run.poses, truth)}) | "
                  f"{r:.3f} | {mapped} / {n_trees2} | {dup} | {wrong} / {len(run.sightings.k)} | "
                  f"{run.cost:.1f}; labels {c.label_cost:.1f}; picker {c.picker_cost:.1f}; sightings "
                  f"chi2/dof {run.chi2_sightings / max(run.dof_sightings, 1):.3f} | | "
                  f"{c.cpu_s:.1f} | {div} |",
                  flush=True)
        ok = [i for i, x in enumerate(rms) if np.isfinite(x)]
        best = min(ok, key=lambda i: rms[i]) if ok else -1
        r_ch = rms[chosen]
        verdict = ("C picked the best by RMS" if chosen == best else
                   f"best by RMS: {cands[best].name} ({rms[best]:.3f})" if best >= 0 else "none")
        div = "yes" if not (np.isfinite(r_ch) and r_ch <= DIVERGED_M) else ""
        print(f"| {name} | **{b} picker ({label}) -> {cands[chosen].name}**; {verdict}"
              f"{_vs_truth(final.poses, truth)} | **{r_ch:.3f}** | "
              f"{len(final.landmarks)} / {n_trees2} | | | {cands[chosen].score():.1f} | | "
              f"{c_all:.1f} (all) | {div} |", flush=True)


def run_variant(g: GraphLog, name: str, config: SlamConfig, label: str,  # noqa: PLR0913
                args: argparse.Namespace, bench: ModuleType, scale: ModuleType,
                lm: np.ndarray, truth: np.ndarray | None, twins: dict[int, int],
                n_trees2: int, n_sight: int) -> None:
    """One setting on one log: the online run and its final solve per backend, printed."""
    for b in args.backends.split(","):
        c0 = time.process_time()
        online, be = run_graph_log_backend(g, b, config, known_ids=False)
        c_on = time.process_time() - c0
        fails = int(online.extra.get("n_recoveries", 0))
        assert be is not None
        if online.status != "ok":  # a run stopped mid-log: no final solve (the CLI's rule)
            n_ok = min(len(online.poses), len(lm))
            r_on = _rms(online.poses[:n_ok], lm[:n_ok]) if n_ok else float("nan")
            print(f"| {name} | {b} online ({label}): {online.status[:80]} | {r_on:.3f} "
                  f"(its {n_ok} poses) | {len(online.landmarks)} / {n_trees2} | | | | "
                  f"{fails} | {c_on:.1f} | yes (failed) |", flush=True)
            continue
        s = online_association(be, online)
        s0 = Sightings(s.k.copy(), s.z, s.r, s.lid.copy())
        fid = scale.tree_ids(g, s0, twins)
        mapped, dup, wrong = scale.score(s0, fid)
        ties = len(getattr(be, "revisit_ties", []))
        r_on = _rms(online.poses, lm)
        print(f"| {name} | {b} online ({label}; {ties} revisit ties, "
              f"{int(online.extra.get('n_held_unused', 0))} held unused"
              f"{_vs_truth(online.poses, truth)}) | {r_on:.3f} | "
              f"{mapped} / {n_trees2} | {dup} | {wrong} / {len(s.k)} of {n_sight} | | "
              f"{fails} | {c_on:.1f} | |", flush=True)
        c1 = time.process_time()
        run = final_solve(g, config, online, s)
        c_fin = time.process_time() - c1
        fid_run = fid if len(run.sightings.k) == len(s0.k) else scale.tree_ids(
            g, run.sightings, twins)  # readmit_dropped took some back
        mapped, dup, wrong = scale.score(run.sightings, fid_run)
        moves = Counter(m.kind for m in run.moves)
        r_fin = _rms(run.poses, lm)
        div = "yes" if not (np.isfinite(r_fin) and r_fin <= DIVERGED_M) else ""
        print(f"| {name} | {b} + final solve ({label}; {len(run.passes)} passes, "
              f"{dict(moves)}{_vs_truth(run.poses, truth)}) | **{r_fin:.3f}** | "
              f"{mapped} / {n_trees2} | "
              f"{dup} | {wrong} / {len(run.sightings.k)} | {run.cost:.1f} | | "
              f"+{c_fin:.1f} | {div} |", flush=True)
        if args.diagnose:
            rec = {(int(k), round(float(z[1]), 9)) for k, z in zip(s0.k, s0.z, strict=True)}
            kept = [[x for x in ss if (kk, round(x.range, 9)) in rec]
                    for kk, ss in enumerate(g.sightings)]
            kr = run_graph_log(dataclasses.replace(g, sightings=kept), "batch", SlamConfig())
            print(f"| {name} | known ids, the {len(s0.k)} recorded sightings only | "
                  f"{_rms(kr.poses, lm):.3f} | {len(kr.landmarks)} / {n_trees2} | | | | | | |",
                  flush=True)
        cfg_known = dataclasses.replace(SlamConfig(), pose2_odometry=config.pose2_odometry)
        if cfg_known.pose2_odometry.cov_scale != 1.0:
            kn = run_graph_log(g, b, cfg_known)
            print(f"| {name} | {b} known ids, cov_scale "
                  f"{cfg_known.pose2_odometry.cov_scale:g} | {_rms(kn.poses, lm):.3f} | "
                  f"{len(kn.landmarks)} / {n_trees2} | | | | | | |", flush=True)


if __name__ == "__main__":
    main()
