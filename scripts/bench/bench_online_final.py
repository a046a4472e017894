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
log's stated noise (:func:`lampsam.backend.online_final.final_solve`). Per log, first
the references (:func:`references`): GTSAM's LM on the file's graph with its ids and with
its twin ids merged (:mod:`lampsam.evaluation.twin_ids`), lampsam's known-id batch on each,
and per twin pair the evidence for one tree. Printed per run: position RMS from GTSAM's
LM on the file's ids / with the twin ids merged, landmarks with 2+ sightings against the trees sighted 2+
times (file ids, twins as one: ``lampsam.evaluation.twin_ids.twin_map``), duplicated trees, wrong
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
each final solve, :mod:`lampsam.backend.held_placement`). ``placements`` = the picker without
the placement, then each rule of :data:`PLACEMENTS` on the chosen candidate, with
:func:`trace_placed` (``--candidates`` the chosen one alone gives the same answer for
a fraction of the CPU). The last column says "yes" when the final solve (or, if it did not run, the online answer) is more
than :data:`DIVERGED_M` from GTSAM's LM.

``corridor``, ``odo3x`` and ``overstated`` (:data:`NEW_HELD_OUT`) are held-out logs of
the picker, fixed before it ran on them; ``carpark`` and ``pillars``
(:data:`ALIASED_HELD_OUT`) aliased held-out logs of its label-entropy cost.
"""

from __future__ import annotations

import argparse
import copy
import dataclasses
import logging
import os
import time
from collections import Counter
from pathlib import Path
from types import ModuleType

import numpy as np
from timing import sibling  # scripts/bench/timing.py, a sibling module

from lampsam.backend.config import SlamConfig
from lampsam.backend.graph_log import run_graph_log, run_graph_log_backend
from lampsam.backend.online_final import (
    final_solve,
    online_association,
    place_chosen,
    run_online_picker,
)
from lampsam.backend.reassociate import Sightings
from lampsam.datasets.graph_text import GraphLog, read_graph_text, read_vertices
from lampsam.datasets.landmark_log_heldout import HeldOutSpec, simulate_held_out
from lampsam.datasets.landmark_log_sim import LandmarkLogSpec, write_landmark_log
from lampsam.evaluation import twin_ids
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
    # the picker without the placement, then each of PLACEMENTS on the chosen candidate
    "placements": [],
}
#: ``placements``: ways of placing the chosen candidate's left-out sightings
#: (``[reassociation]`` fields; :func:`lampsam.backend.online_final.place_chosen`).
PLACEMENTS: dict[str, dict[str, bool]] = {
    "none": {"online_final_held_mixture": False},
    "mixture": {"online_final_held_mixture": True, "online_final_held_new_landmarks": False},
    "new (all left out)": {"online_final_held_mixture": True,
                           "online_final_held_new_landmarks": True,
                           "online_final_held_new_unexplained": False,
                           "online_final_held_new_merge": False},
    "new (all) + merges": {"online_final_held_mixture": True,
                           "online_final_held_new_landmarks": True,
                           "online_final_held_new_unexplained": False,
                           "online_final_held_new_merge": True},
    "new (unexplained)": {"online_final_held_mixture": True,
                          "online_final_held_new_landmarks": True,
                          "online_final_held_new_unexplained": True,
                          "online_final_held_new_merge": False},
    "new (unexplained) + merges": {"online_final_held_mixture": True,
                                   "online_final_held_new_landmarks": True,
                                   "online_final_held_new_unexplained": True,
                                   "online_final_held_new_merge": True},
    "mixture at residual noise": {"online_final_held_mixture": True,
                                  "online_final_held_new_landmarks": False,
                                  "online_final_held_residual_scale": True},
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
    print("| log | run | RMS vs LM: file ids / twins merged [m] | landmarks 2+ / trees 2+ | dup "
          "| wrong / sightings | C | failures | CPU [s] | diverged |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for name in args.logs.split(","):
        g = load_log(scale, name, Path(args.out))
        truth = load_truth(g, name, Path(args.out))
        refs, twins, n_trees2 = references(g, name, bench, truth)
        n_sight = sum(len(ss) for ss in g.sightings)
        for v in variants:
            config = bench.with_overrides(SlamConfig(), args.set + VARIANTS.get(v, []))
            label = f"{v}: {base_label}" if v and args.set else (v or base_label)
            if v in ("picker", "pickermix", "placements"):
                config = dataclasses.replace(config, reassociation=dataclasses.replace(
                    config.reassociation, online_candidates=tuple(args.candidates.split(","))))
                run_picker(g, name, config, label, args, scale, refs, truth, twins, n_trees2,
                           placements=v == "placements")
                continue
            run_variant(g, name, config, label, args, bench, scale, refs, truth, twins,
                        n_trees2, n_sight)


Refs = tuple[np.ndarray, np.ndarray]


def _two(poses: np.ndarray, refs: Refs) -> str:
    """``"a / b"``: position RMS of ``poses`` from GTSAM's LM on the file's ids and on
    the file's graph with its twin ids merged (the same figure twice without twins)."""
    n = min(len(poses), len(refs[0]))
    if not n:
        return "nan / nan"
    return f"{_rms(poses[:n], refs[0][:n]):.3f} / {_rms(poses[:n], refs[1][:n]):.3f}"


def references(g: GraphLog, name: str, bench: ModuleType, truth: np.ndarray | None
               ) -> tuple[Refs, dict[int, int], int]:
    """The two references of a log, printed: GTSAM's LM on the file's graph with its ids
    (from GTSAM's iSAM2, one update per pose) and with its twin ids merged
    (:mod:`lampsam.evaluation.twin_ids`, from the first's optimum), lampsam's known-id
    batch on each (the "known-id figure" of issue 15, both ways), and per twin pair the
    evidence for one tree (:func:`lampsam.evaluation.twin_ids.twin_tests`).

    Returns:
        ``((LM poses, twin-merged LM poses), twin map, trees seen 2+ (twins as one))``.
    """
    cfg = SlamConfig()
    ref = twin_ids.lm_reference(g, cfg, bench.gtsam_isam2(g, cfg)[0])
    c0 = time.process_time()
    known = run_graph_log(g, "batch", cfg)
    c_known = time.process_time() - c0
    twins = twin_ids.twin_map(g, {int(x.id): np.asarray(x.position[:2], float)
                                  for x in list(known.landmarks) + list(known.provisional)})
    groups = twin_ids.twin_groups(twins)
    gm = twin_ids.merged_log(g, twins)
    ref_m = (twin_ids.lm_reference(gm, cfg, twin_ids.merged_start(ref, twins)) if groups
             else ref)
    refs = (ref.poses, ref_m.poses)
    trees = Counter(twins.get(x.landmark, x.landmark) for ss in g.sightings for x in ss)
    n_trees2 = sum(1 for v in trees.values() if v >= 2)
    print(f"| {name} | LM on the file's graph: chi2/dof {ref.chi2 / max(ref.dof, 1):.3f}, "
          f"sightings' {ref.chi2_sightings / max(ref.dof_sightings, 1):.3f}; twin groups "
          f"{groups or 'none'}; LM with them merged: chi2 +{ref_m.chi2 - ref.chi2:.1f}"
          f"{_vs_truth(ref.poses, truth)} | {_two(ref_m.poses, refs)} (LM merged) | | | | | "
          "| | |", flush=True)
    print(f"| {name} | known-id batch, file ids (file noise{_vs_truth(known.poses, truth)}) | "
          f"{_two(known.poses, refs)} | {len(known.landmarks)} / {n_trees2} | | | | | "
          f"{c_known:.1f} | |", flush=True)
    if groups:
        km = run_graph_log(gm, "batch", cfg)
        print(f"| {name} | known-id batch, twin ids merged | {_two(km.poses, refs)} | "
              f"{len(km.landmarks)} / {n_trees2} | | | | | | |", flush=True)
    for t in twin_ids.twin_tests(g, cfg, ref, twins):
        print(f"| {name} | twins {t.ids[0]}/{t.ids[1]} ({t.n[0]}+{t.n[1]} sightings, "
              f"{t.separation_m:.2f} m apart, viewed {t.view_angle_deg:.0f} deg apart): merge "
              f"chi2 +{t.chi2_merge:.1f} (p {t.p_stated:.2g} stated; residual variance "
              f"x{t.scale:.3f}: p {t.p_scaled:.2g}); poses fixed: two points "
              f"{t.chi2_two:.1f}, one {t.chi2_one:.1f}, one trunk r {t.radius_m:.2f} m "
              f"{t.chi2_trunk:.1f} | | | | | | | | |", flush=True)
    return refs, twins, n_trees2


def run_picker(g: GraphLog, name: str, config: SlamConfig, label: str,  # noqa: PLR0913
               args: argparse.Namespace, scale: ModuleType, refs: Refs,
               truth: np.ndarray | None, twins: dict[int, int], n_trees2: int,
               placements: bool = False) -> None:
    """The online picker (:func:`lampsam.backend.online_final.run_online_picker`) per
    backend: one row per candidate (its final solve's RMS, count, ``C``, CPU), then the
    choice, and whether ``C`` chose the candidate whose final solve is nearest GTSAM's LM.
    With ``placements``: the picker without the placement, then each of
    :data:`PLACEMENTS` on the chosen candidate (:func:`run_placements`)."""
    lm = refs[0]
    if placements:
        config = dataclasses.replace(config, reassociation=dataclasses.replace(
            config.reassociation, online_final_held_mixture=False))
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
                  f"{_two(run.poses, refs)} | {mapped} / {n_trees2} | {dup} | {wrong} / {len(run.sightings.k)} | "
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
              f"{_vs_truth(final.poses, truth)} | **{_two(final.poses, refs)}** | "
              f"{len(final.landmarks)} / {n_trees2} | | | {cands[chosen].score():.1f} | | "
              f"{c_all:.1f} (all) | {div} |", flush=True)
        if placements and cands[chosen].solve is not None:
            run_placements(g, name, config, cands[chosen], scale, refs, truth, twins, n_trees2)


def _key(k: np.ndarray, z: np.ndarray) -> list[tuple[int, float]]:
    return [(int(a), round(float(b[1]), 9)) for a, b in zip(k, z, strict=True)]


def trace_placed(g: GraphLog, scale: ModuleType, before: Sightings, after: Sightings,
                 twins: dict[int, int]) -> str:
    """What a placement did with the sightings ``before`` left out, by their file tree
    (twins as one): placed / left-out; placed on the landmark of another tree while
    their own tree has one ("neighbour"), while their own tree had none before
    ("unmapped -> neighbour"), on a landmark new since ``before`` ("new")."""
    f0, f1 = scale.tree_ids(g, before, twins), scale.tree_ids(g, after, twins)

    def majority(s: Sightings, f: np.ndarray) -> dict[int, int]:
        return {int(i): Counter(f[s.lid == i].tolist()).most_common(1)[0][0]
                for i in np.unique(s.lid).tolist()}

    m0, m1 = majority(before, f0), majority(after, f1)
    mapped0 = set(m0.values())
    old = set(_key(before.k, before.z))
    n_left = sum(len(ss) for ss in g.sightings) - len(before.k)
    placed = own = nb = un_nb = new = new_wrong = 0
    for j, key in enumerate(_key(after.k, after.z)):
        if key in old:
            continue
        placed += 1
        lid, tree = int(after.lid[j]), int(f1[j])
        if lid not in m0:
            new += 1
            new_wrong += m1[lid] != tree
        elif m1[lid] == tree:
            own += 1
        elif tree in mapped0:
            nb += 1
        else:
            un_nb += 1
    return (f"{placed} of {n_left} placed: {own} own tree, {nb} neighbour, {un_nb} unmapped "
            f"-> neighbour, {new} on new landmarks ({new_wrong} not their majority)")


def run_placements(g: GraphLog, name: str, config: SlamConfig, c: object,  # noqa: PLR0913
                   scale: ModuleType, refs: Refs, truth: np.ndarray | None,
                   twins: dict[int, int], n_trees2: int) -> None:
    """Each of :data:`PLACEMENTS` on the chosen candidate ``c`` (a
    :class:`lampsam.backend.online_final.Candidate` whose final solve was not placed):
    RMS from both references, landmarks 2+, dup, wrong, ``C``, the placement's CPU, and
    :func:`trace_placed`."""
    base = c.solve  # type: ignore[attr-defined]
    for label, fields in PLACEMENTS.items():
        cc = copy.copy(c)
        cfg = dataclasses.replace(config, reassociation=dataclasses.replace(
            config.reassociation, **fields))
        c0 = time.process_time()
        place_chosen(g, cfg, cc)  # type: ignore[arg-type]
        cpu = time.process_time() - c0
        run = cc.solve  # type: ignore[attr-defined]
        mapped, dup, wrong = scale.score(run.sightings, scale.tree_ids(g, run.sightings, twins))
        moves = Counter(m.kind for m in run.moves[len(base.moves):])
        print(f"| {name} | placement {label} ({trace_placed(g, scale, base.sightings, run.sightings, twins)}; "
              f"moves {dict(moves)}{_vs_truth(run.poses, truth)}) | {_two(run.poses, refs)} | "
              f"{mapped} / {n_trees2} | {dup} | {wrong} / {len(run.sightings.k)} | "
              f"{run.cost:.1f} | | +{cpu:.1f} | |", flush=True)


def run_variant(g: GraphLog, name: str, config: SlamConfig, label: str,  # noqa: PLR0913
                args: argparse.Namespace, bench: ModuleType, scale: ModuleType,
                refs: Refs, truth: np.ndarray | None, twins: dict[int, int],
                n_trees2: int, n_sight: int) -> None:
    """One setting on one log: the online run and its final solve per backend, printed."""
    lm = refs[0]
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
        print(f"| {name} | {b} online ({label}; {ties} revisit ties, "
              f"{int(online.extra.get('n_held_unused', 0))} held unused"
              f"{_vs_truth(online.poses, truth)}) | {_two(online.poses, refs)} | "
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
              f"{dict(moves)}{_vs_truth(run.poses, truth)}) | **{_two(run.poses, refs)}** | "
              f"{mapped} / {n_trees2} | "
              f"{dup} | {wrong} / {len(run.sightings.k)} | {run.cost:.1f} | | "
              f"+{c_fin:.1f} | {div} |", flush=True)
        if args.diagnose:
            rec = {(int(k), round(float(z[1]), 9)) for k, z in zip(s0.k, s0.z, strict=True)}
            kept = [[x for x in ss if (kk, round(x.range, 9)) in rec]
                    for kk, ss in enumerate(g.sightings)]
            kr = run_graph_log(dataclasses.replace(g, sightings=kept), "batch", SlamConfig())
            print(f"| {name} | known ids, the {len(s0.k)} recorded sightings only | "
                  f"{_two(kr.poses, refs)} | {len(kr.landmarks)} / {n_trees2} | | | | | | |",
                  flush=True)
        cfg_known = dataclasses.replace(SlamConfig(), pose2_odometry=config.pose2_odometry)
        if cfg_known.pose2_odometry.cov_scale != 1.0:
            kn = run_graph_log(g, b, cfg_known)
            print(f"| {name} | {b} known ids, cov_scale "
                  f"{cfg_known.pose2_odometry.cov_scale:g} | {_two(kn.poses, refs)} | "
                  f"{len(kn.landmarks)} / {n_trees2} | | | | | | |", flush=True)


if __name__ == "__main__":
    main()
