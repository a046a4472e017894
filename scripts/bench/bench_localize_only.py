"""Localize-only tracking on a saved ceiling map against SLAM from scratch.

Usage::

    lampsam simulate lab --out LAB1 --seed 1
    lampsam slam LAB1 --backend batch --out SLAM1 --save-map MAP
    lampsam simulate lab_day2 --out DAY2 --seed 2
    python scripts/bench/bench_localize_only.py --map MAP DAY2 [DAY3 ...] [--repeats 3] [--cache DIR]

``--cache DIR`` keeps each run's frames (a pickle per run and frame source) so that later
benches skip the frontend. Modes with ``-release`` / ``-norelease`` turn the release of
contradicted map lamps on / off (:data:`RELEASE_KEYS` for its options); the released
landmarks of each run are printed after the tables, with how far the map's value is from the
truth. With several runs or maps a last table lists each method's final RMS per run and how
many runs are at or under the reference.

``--map`` may be given more than once: the maps of separate drives, merged by
:func:`lampsam.backend.map_merge.merge_all` (``--merge seq``: one after the other by
:func:`lampsam.backend.map_merge.merge_maps`, the merge before the fourteenth session), or
with ``--each-map`` each tracked on its own, where a ``--map A+B+...`` is those maps merged
(SLAM from scratch then runs once per run, not once per map). For every run the frames are made once
(the frontend on the images, or ``--frames truth``) and fed to: localize-only on MAP
(:class:`MapLocalizer`, ``localize``: the map fixed; ``localize-priors`` and
``localize-consider``: ``LocalizeConfig.map_mode``; every mode with the map frame's offset
state when the map has a frame model, ``-nooffset`` without it, ``-loose`` with a 2 cm
start; ``-smooth``: the smoother after the filter; :func:`localize_config`), and
SLAM from scratch on the same frames with the backends of ``--backends`` (default
isam2, batch, ekf). Printed per run and method: position and heading RMS against the
run's truth (no alignment, known start pose), and the CPU time (``time.process_time``,
comparable on a loaded machine) per frame: the median of the online steps that had a
frame, and the mean per frame including the final optimisation (batch LM). Timings
are medians over ``--repeats`` runs; ``x ref`` divides by the reference method's
figure (``--reference``, default isam2) measured in the same run. The frontend's
time is not included (it is the same for every method).

The map lives in the mapping run's frame, a few millimetres and hundredths of a
degree off the truth's; localize-only tracks in the map's frame. ``in map frame``
is its error after moving the poses by the SE(2) transform from the map's frame to
the truth's, fitted on the map's landmarks against the true ones
(:func:`lampsam.evaluation.map_alignment.map_to_truth`; never on the trajectory):
what is left is the tracking's own error. SLAM from scratch is read the same two
ways, its ``in map frame`` fitted on the landmarks of its own result. ``online`` is
the error of each step's estimate as the backend returned it (what a robot has at
that moment): localize-only is a causal filter, so its online and final poses are
the same; the smoothers' final poses are hindsight (the batch backend's online pass
is iSAM2's). Figures: docs/ceiling-map.md.
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
import math
import os
import pickle
import time
from pathlib import Path
from typing import Any

import numpy as np

from lampsam.arrays import FloatArray
from lampsam.backend.ceiling import CeilingModel
from lampsam.backend.ceiling_map_io import CeilingMap, read_map
from lampsam.backend.config import SlamConfig
from lampsam.backend.interface import SlamBackend
from lampsam.backend.localize_only import LocalizeConfig, MapLocalizer
from lampsam.backend.map_frame import MapFrame
from lampsam.backend.map_merge import merge_all, merge_maps
from lampsam.backend.map_smoother import MapSmoother, MapSmootherConfig
from lampsam.backend.slam import (
    errors_vs_truth,
    iter_steps,
    make_backend,
    make_frames,
    start_pose_of,
)
from lampsam.datasets.logrun import LoggedRun, read_run
from lampsam.evaluation.map_alignment import (
    MapAlignment,
    map_to_truth,
    transform_points,
    transform_poses,
)


def fit_frame(xy: FloatArray, kinds: list[str], run: LoggedRun) -> MapAlignment | None:
    """The map-to-truth transform of landmarks ``xy`` (L, 2) of ``kinds``, or None
    without truth (or fewer than 3 landmarks paired with it)."""
    if run.landmarks is None or len(xy) == 0:
        return None
    return map_to_truth(xy, kinds, run.landmarks.xyz[:, :2], list(run.landmarks.types))


def map_frame_fit(cmap: CeilingMap, run: LoggedRun) -> MapAlignment | None:
    """The saved map's frame against the truth (its landmarks as saved)."""
    return fit_frame(np.array([lm.position[:2] for lm in cmap.landmarks]).reshape(-1, 2),
                     [lm.kind for lm in cmap.landmarks], run)


def timed_run(backend: SlamBackend, run: LoggedRun, frames: list[Any],
              frame_fit: MapAlignment | None = None) -> dict[str, float]:
    """Step a backend through the run; errors and CPU times, and the error in the map's
    frame: the poses moved by ``frame_fit`` (a saved map's) or, without it, by the fit
    of the result's own landmarks (SLAM from scratch)."""
    step_cpu, has_frame, online = [], [], []
    for t, wheel, frame in iter_steps(run.odometry, frames):
        c0 = time.process_time()
        est = backend.step(t, wheel, frame)
        step_cpu.append(time.process_time() - c0)
        has_frame.append(frame is not None)
        online.append(est.pose)
    c0 = time.process_time()
    result = backend.finish()
    finish_cpu = time.process_time() - c0
    truth = run.groundtruth
    if truth is None:
        raise SystemExit(f"{run.path}: no groundtruth.tum: nothing to measure the error against")
    pos, head = errors_vs_truth(result, truth)
    as_online = dataclasses.replace(result, poses=np.asarray(online, dtype=np.float64).reshape(-1, 3))
    if len(as_online.poses) != len(result.times):
        raise SystemExit(f"{run.path}: {len(result.times)} result poses for {len(online)} steps")
    pos_on, _ = errors_vs_truth(as_online, truth)
    in_map = in_map_on = float("nan")
    if frame_fit is None:
        own = [lm for lm in result.landmarks if lm.type in ("lamp", "corner")]
        frame_fit = fit_frame(np.array([lm.position[:2] for lm in own]).reshape(-1, 2),
                              [str(lm.type) for lm in own], run)
    if frame_fit is not None:
        moved = dataclasses.replace(result, poses=transform_poses(frame_fit.truth_T_map, result.poses))
        pos_m, _ = errors_vs_truth(moved, truth)
        in_map = 1e3 * float(np.sqrt(np.mean(pos_m**2)))
        moved = dataclasses.replace(result, poses=transform_poses(frame_fit.truth_T_map, as_online.poses))
        pos_m, _ = errors_vs_truth(moved, truth)
        in_map_on = 1e3 * float(np.sqrt(np.mean(pos_m**2)))
    cpu = np.asarray(step_cpu)
    n_frames = max(int(np.sum(has_frame)), 1)
    frame_est = {f"g_{k}": result.extra[f"map_frame_{k}"] for k in ("dx_m", "dy_m", "dtheta_rad")
                 if f"map_frame_{k}" in result.extra}
    return {**frame_est, "pos_rms_mm": 1e3 * float(np.sqrt(np.mean(pos**2))),
            "pos_max_mm": 1e3 * float(pos.max()),
            "pos_rms_map_frame_mm": in_map,
            "online_rms_mm": 1e3 * float(np.sqrt(np.mean(pos_on**2))),
            "online_rms_map_frame_mm": in_map_on,
            "head_rms_deg": float(np.degrees(np.sqrt(np.mean(head**2)))),
            "frame_median_ms": 1e3 * float(np.median(cpu[np.asarray(has_frame)])),
            "per_frame_ms": 1e3 * (float(cpu.sum()) + finish_cpu) / n_frames,
            "finish_s": finish_cpu,
            "landmarks": float(len(result.landmarks)),
            "status_ok": float(result.status == "ok")}


def cached_frames(run: LoggedRun, source: str, cache: Path | None) -> list[Any]:
    """The run's frames (:func:`make_frames`), from ``cache`` (a folder of pickles, keyed by
    the run's resolved path and the frame source) when made there before."""
    if cache is None:
        made, _ = make_frames(run, source)
        return list(made)
    path = cache / f"{run.path.resolve().name}-{source}.pkl"
    key = (str(run.path.resolve()), source)
    if path.exists():
        with path.open("rb") as fh:
            doc = pickle.load(fh)
        if doc.get("key") == key:
            return list(doc["frames"])
    made, _ = make_frames(run, source)
    frames = list(made)
    cache.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp")
    with tmp.open("wb") as fh:
        pickle.dump({"key": key, "frames": frames}, fh, protocol=pickle.HIGHEST_PROTOCOL)
    tmp.replace(path)
    return frames


#: ``-release`` options in a mode name (``-lamps``: lamps only, ``-allkinds``: lamps and
#: corners): ``-p=0.99`` (release_prob), ``-k=8`` (release_evidence_scale), ``-n=10``
#: (release_min_sightings), ``-f=0.5`` (release_max_fraction), ``-s=0.05`` (release_sigma)
RELEASE_KEYS = {"p": "release_prob", "n": "release_min_sightings", "f": "release_max_fraction",
                "s": "release_sigma", "k": "release_evidence_scale"}


def release_lines(filt: MapLocalizer, cmap: CeilingMap, fit: MapAlignment | None,
                  run: LoggedRun) -> list[str]:
    """One line per released landmark: id, time, statistic, the run's offset and (with the
    map's truth fit) how far the map's value is from the nearest true landmark of its kind
    after the fit, mm."""
    out = []
    for r in filt.release_report():
        off = 1e3 * np.asarray(r["offset_m"], float)
        truth_off = ""
        if fit is not None and run.landmarks is not None:
            lm = next(x for x in cmap.landmarks if x.id == r["id"])
            p = transform_points(fit.truth_T_map, np.asarray(lm.position[:2], float).reshape(1, 2))
            kinds = np.asarray(list(run.landmarks.types))
            d = run.landmarks.xyz[kinds == lm.kind, :2] - p
            if len(d):
                k = int(np.argmin(np.hypot(d[:, 0], d[:, 1])))
                truth_off = f"; map value off the truth by {1e3 * d[k, 0]:.2f}, {1e3 * d[k, 1]:.2f} mm"
        out.append(f"{r['kind']} {r['id']} at t={r['t_s']:.1f} s, chi2 {r['chi2']:.1f} after "
                   f"{r['sightings_at_release']} sightings ({r['sightings']} in all): offset "
                   f"{off[0]:.2f}, {off[1]:.2f} mm{truth_off}")
    return out


def localize_config(method: str) -> LocalizeConfig:
    """``localize[-priors|-consider][-nooffset][-loose][-release[-p=P][-n=N][-f=F][-s=S]]
    [-mc=N][-smooth[-turn|-noframe]]`` as the
    filter's settings: the defaults of :class:`LocalizeConfig` (the map frame's offset state
    with a version-2 map, the known start held at 1 mm / 1 mrad as SLAM holds it) with
    ``-nooffset`` without the frame state (``frame_offset`` off), ``-gturn`` with its turn
    estimated too (``frame_turn``), and ``-loose`` with the start at 2 cm / 0.01 rad (the
    settings before the eleventh session); ``-frame`` and ``-tight`` are the defaults now
    (accepted, no effect); ``-smooth`` (:func:`smoother_config`) adds the smoother over the
    filter's poses; ``-mc=N`` keeps at most N corner observations per frame
    (``max_corners``); ``-release`` (``-norelease``) turns the release of contradicted map
    landmarks on (off), with its options as :data:`RELEASE_KEYS`."""
    parts = method.split("-")[1:]
    mode = next((p for p in parts if p in ("priors", "consider")), "fixed")
    extra: dict[str, Any] = ({"sigma_start_xy": 0.02, "sigma_start_theta": 0.01}
                             if "loose" in parts else {})
    if "release" in parts:
        extra["release"] = True
    elif "norelease" in parts:
        extra["release"] = False
    for p in parts:
        key, _, val = p.partition("=")
        if p == "lamps":
            extra["release_kinds"] = ("lamp",)
        elif p == "allkinds":
            extra["release_kinds"] = ("lamp", "corner")
        if val and key == "mc":  # -mc=N: at most N corner observations per frame
            extra["max_corners"] = int(val)
        if val and key in RELEASE_KEYS:
            extra[RELEASE_KEYS[key]] = int(val) if key == "n" else float(val)
    return LocalizeConfig(map_mode=mode, frame_offset="nooffset" not in parts,  # type: ignore[arg-type]
                          frame_turn="gturn" in parts, **extra)


def truth_frame_offset(truth_T_map: FloatArray, frame: MapFrame | None) -> FloatArray:
    """The frame offset ``g`` (about the map frame's centre; :mod:`lampsam.backend.map_frame`)
    of the landmark fit ``truth_T_map`` (the inverse of
    :func:`lampsam.backend.map_smoother.frame_to_rigid`); zeros without a frame."""
    if frame is None:
        return np.zeros(3)
    th = float(truth_T_map[2])
    rot = np.array([[math.cos(th), -math.sin(th)], [math.sin(th), math.cos(th)]])
    c = np.asarray(frame.center, float)
    return np.r_[np.asarray(truth_T_map[:2], float) - (c - rot @ c), th]


def smoother_config(method: str) -> MapSmootherConfig | None:
    """``...-smooth``: the localize-only smoother with the map's frame model reduced to its
    shift (the default); ``-turn``: with the turn too; ``-noframe``: with independent
    landmark priors; None without ``-smooth``."""
    parts = method.split("-")[1:]
    if "smooth" not in parts:
        return None
    return MapSmootherConfig(frame="noframe" not in parts, frame_turn="turn" in parts)


def merged(paths: list[str], how: str) -> CeilingMap:
    """The maps at ``paths`` merged: ``joint`` (:func:`merge_all`, the default) or ``seq``
    (:func:`merge_maps` one after the other, the merge before the fourteenth session)."""
    if how == "seq":
        cmap = read_map(paths[0])
        for more in paths[1:]:
            cmap, counts = merge_maps(cmap, read_map(more))
            print(f"merged {more}: {counts}")
        return cmap
    cmap, jc = merge_all([read_map(p) for p in paths])
    print(f"merged {'+'.join(paths)} jointly: {jc['fused']} fused, {jc['alone']} alone; "
          "similarity (dx mm, dy mm, dtheta mdeg, ds ppm) per map: "
          + "; ".join(f"{1e3 * s[0]:.2f}, {1e3 * s[1]:.2f}, {1e3 * s[2]:.1f}, {1e6 * s[3]:.0f}"
                      for s in jc["similarity"]))
    return cmap


def load_maps(paths: list[str], each: bool, how: str = "joint") -> list[tuple[str, CeilingMap]]:
    """``(label, map)`` per map with ``each`` (a path ``A+B+...`` is those maps merged),
    else one map merged from all; ``how``: :func:`merged`."""
    def label(ps: list[str]) -> str:
        return "+".join(os.path.basename(os.path.normpath(p)) for p in ps) + (
            "" if len(ps) == 1 or how == "joint" else f" ({how})")
    if each:
        out = []
        for p in paths:
            ps = p.split("+")
            out.append((label(ps), read_map(ps[0]) if len(ps) == 1 else merged(ps, how)))
        return out
    return [(label(paths), read_map(paths[0]) if len(paths) == 1 else merged(paths, how))]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("runs", nargs="+", help="run directories (e.g. lab_day2 simulations)")
    ap.add_argument("--map", required=True, action="append",
                    help="ceiling map folder (slam --save-map); repeat to merge maps")
    ap.add_argument("--each-map", action="store_true",
                    help="track every --map on its own instead of merging them (a --map "
                         "A+B+... is then those maps merged)")
    ap.add_argument("--merge", default="joint", choices=("joint", "seq"),
                    help="how maps are merged: joint (merge_all, default) or seq (merge_maps "
                         "one after the other)")
    ap.add_argument("--modes", default="fixed,priors,consider,priors-smooth,priors-smooth-turn",
                    help="localize-only variants: fixed, priors, consider (the defaults: the "
                         "map frame's offset state with a version-2 map, the known start at 1 mm "
                         "/ 1 mrad), -nooffset (without the frame state), -gturn (the frame state's turn "
                         "estimated too), -loose (2 cm / 0.01 rad "
                         "start), priors-smooth (the smoother with the map frame's shift), "
                         "priors-smooth-turn (shift and turn), priors-smooth-noframe "
                         "(independent landmark priors)")
    ap.add_argument("--frames", default="images", choices=("images", "truth"))
    ap.add_argument("--backends", default="isam2,batch,ekf", help="SLAM from scratch backends")
    ap.add_argument("--reference", default="isam2", help="method the ratios divide by")
    ap.add_argument("--repeats", type=int, default=3, help="runs per method (timing median)")
    ap.add_argument("--cache", type=Path, default=None,
                    help="folder for the runs' frames (made once, read back in later runs)")
    args = ap.parse_args()
    logging.basicConfig(level=logging.ERROR)
    maps = load_maps(args.map, args.each_map, args.merge)
    config = SlamConfig()
    config = dataclasses.replace(config, isam2=dataclasses.replace(config.isam2,
                                                                   final_covariances=False))
    load = os.getloadavg()
    for label, cmap in maps:
        print(f"map {label}: {len(cmap.by_kind('lamp'))} lamps, {len(cmap.by_kind('corner'))} "
              f"corners, frame model {'yes' if cmap.frame is not None else 'no'}")
    print(f"frames {args.frames}; repeats {args.repeats}; load average "
          f"{load[0]:.1f} {load[1]:.1f} {load[2]:.1f} (2 cores)")
    modes = [m for m in args.modes.split(",") if m]
    methods: list[tuple[str, CeilingMap | None, str]] = []
    for label, cmap in maps:
        prefix = f"{label}: " if len(maps) > 1 else ""
        for mode in modes:
            if ("smooth" in mode.split("-") and "noframe" not in mode.split("-")
                    and cmap.frame is None):
                continue
            name = "localize" if mode == "fixed" else f"localize-{mode}"
            methods.append((prefix + name, cmap, name))
    methods += [(b, None, b) for b in args.backends.split(",") if b]
    rows: dict[str, list[dict[str, float]]] = {m: [] for m, _, _ in methods}
    refs: list[float] = []
    released: dict[tuple[str, str], list[str]] = {}
    for run_dir in args.runs:
        run = read_run(run_dir)
        frames = cached_frames(run, args.frames, args.cache)
        start = start_pose_of(run)
        fits = {label: map_frame_fit(cmap, run) for label, cmap in maps}
        figures: dict[str, dict[str, float]] = {}
        for m, on_map, kind in methods:
            fit = next((fits[label] for label, c in maps if c is on_map), None)
            reps = []
            for _ in range(args.repeats):
                smooth = smoother_config(kind)
                if on_map is not None and smooth is not None:
                    be: SlamBackend = MapSmoother(
                        run.rig.odometry, config, start, on_map,
                        CeilingModel.from_camera(run.rig.camera), localize_config(kind),
                        smooth=smooth)
                elif on_map is not None:
                    be = MapLocalizer(
                        run.rig.odometry, config, start, on_map,
                        CeilingModel.from_camera(run.rig.camera), localize_config(kind))
                else:
                    be = make_backend(kind, run.rig.odometry, config, start, run.rig.camera)
                reps.append(timed_run(be, run, frames, fit))
            fig = {k: float(np.median([r[k] for r in reps])) for k in reps[0]}
            filt = be.filter if isinstance(be, MapSmoother) else be
            if isinstance(filt, MapLocalizer) and filt.loc.release and on_map is not None:
                released[(run_dir, m)] = release_lines(filt, on_map, fit, run)
            figures[m] = fig
            rows[m].append(fig)
        ref = figures.get(args.reference)
        refs.append(ref["pos_rms_mm"] if ref else float("nan"))
        print(f"\n{run_dir} ({len(frames)} frames)")
        for label, fit in fits.items():
            if fit is not None:
                x, y, th = fit.truth_T_map
                print(f"map {label} frame vs truth (fit on {fit.n_pairs} landmarks, {fit.n_lamps} "
                      f"lamps): dx {1e3 * x:.2f} mm, dy {1e3 * y:.2f} mm, dtheta "
                      f"{1e3 * math.degrees(th):.1f} mdeg; landmark residual "
                      f"{1e3 * fit.residual_rms_m:.1f} mm RMS")
        for m, on_map, _ in methods:
            f = figures[m]
            label = next((lb for lb, c in maps if c is on_map), None)
            fit = None if label is None else fits[label]
            if "g_dx_m" in f and on_map is not None and fit is not None:
                true_g = truth_frame_offset(fit.truth_T_map, on_map.frame)
                print(f"{m}: map frame offset g estimated {1e3 * f['g_dx_m']:.2f}, "
                      f"{1e3 * f['g_dy_m']:.2f} mm, {1e3 * math.degrees(f['g_dtheta_rad']):.1f} "
                      f"mdeg; from the truth fit {1e3 * true_g[0]:.2f}, {1e3 * true_g[1]:.2f} mm, "
                      f"{1e3 * math.degrees(true_g[2]):.1f} mdeg")
        print("| method | pos RMS mm | in map frame mm | online RMS mm | online in map frame mm "
              "| pos max mm | head RMS deg | CPU/frame median ms | x ref | CPU/frame mean incl. "
              "final ms | x ref |")
        print("|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
        for m, f in figures.items():
            r1 = f["frame_median_ms"] / ref["frame_median_ms"] if ref else float("nan")
            r2 = f["per_frame_ms"] / ref["per_frame_ms"] if ref else float("nan")
            print(f"| {m} | {f['pos_rms_mm']:.2f} | {f['pos_rms_map_frame_mm']:.2f} | {f['online_rms_mm']:.2f} "
                  f"| {f['online_rms_map_frame_mm']:.2f} | {f['pos_max_mm']:.1f} "
                  f"| {f['head_rms_deg']:.3f} | {f['frame_median_ms']:.2f} | {r1:.3f} "
                  f"| {f['per_frame_ms']:.2f} | {r2:.3f} |")
    for (run_dir, m), lines in released.items():
        print(f"{run_dir} {m}: released {len(lines)}" + "".join(f"\n    {ln}" for ln in lines))
    if len(args.runs) > 1 or len(maps) > 1:
        print(f"\nfinal position RMS mm per run, at or under {args.reference} (final) counted; "
              f"{args.reference}: " + " / ".join(f"{r:.2f}" for r in refs)
              + f" (mean {np.mean(refs):.2f})")
        for m, fs in rows.items():
            vals = [f["pos_rms_mm"] for f in fs]
            n_ok = sum(v <= r for v, r in zip(vals, refs, strict=True))
            print(f"| {m} | " + " / ".join(f"{v:.2f}" for v in vals)
                  + f" | mean {np.mean(vals):.2f} | {n_ok} of {len(vals)} | CPU/frame mean "
                  f"{np.mean([f['per_frame_ms'] for f in fs]):.2f} ms, x ref "
                  + " / ".join(f"{f['per_frame_ms'] / ff['per_frame_ms']:.2f}"
                               for f, ff in zip(fs, rows.get(args.reference, fs), strict=True))
                  + " |")
    if len(args.runs) > 1:
        for key, what in (("", "final"), ("online_", "online")):
            print(f"\n{what} position RMS mm, world frame / map frame, per run ("
                  + ", ".join(args.runs) + ")")
            k_w = f"{key}rms_mm" if key else "pos_rms_mm"
            k_m = f"{key}rms_map_frame_mm" if key else "pos_rms_map_frame_mm"
            for m, fs in rows.items():
                cells = " | ".join(f"{f[k_w]:.2f} / {f[k_m]:.2f}" for f in fs)
                print(f"| {m} | {cells} | mean {np.mean([f[k_w] for f in fs]):.2f} / "
                      f"{np.mean([f[k_m] for f in fs]):.2f} | CPU/frame mean "
                      f"{np.mean([f['per_frame_ms'] for f in fs]):.2f} ms |")


if __name__ == "__main__":
    main()
