"""Lamp measurement models compared on whole-path lab runs: SLAM accuracy and sightings vs truth.

Usage::

    python scripts/bench/bench_lamp_model.py --cache CACHE_DIR [--arms on,off] \
        [--backends isam2,batch] [--csv SIGHTINGS.csv] RUN_DIR [RUN_DIR ...]

``RUN_DIR``: simulated runs (``lampsam simulate lab --seed S --out RUN_DIR``, whole path,
173 s, 2,601 images). Each arm is a frontend setting (:data:`ARMS`): ``on`` the default
(saturated-edge lamp centroids, :mod:`lampsam.frontend.saturated_edges`), ``off`` the
coverage weights as read. Every arm's frames are made once per run from the same images
and cached (``CACHE_DIR/<run>-<arm>.pkl``; delete to remake), then every backend runs on
each arm's frames with the default ``SlamConfig`` (lamps + corners, known start).

Printed:

* per run and backend: position RMS (mm, no alignment) and mean NEES (3-dof pose, 3 ideal)
  of each arm; the means over runs; the paired sign count (runs where the first arm is more
  accurate than the second);
* the lamp sightings against the simulator's truth (``truth/projections.csv``: a detected
  lamp is paired with the fully visible true lamp of the same image within 4 px): error
  ``e = m - m*`` in normalised ceiling coordinates, given in px (``f e``) in the image
  and in mm on the ceiling (``1000 h e`` rotated into the world by the true heading, ``h``
  the lamp's height above the camera); mean (bias) and RMS per arm, and **per-lamp
  means**: for each run and lamp the mean world-frame error of its sightings (what a map
  lamp averaged from them would be off by), its RMS over lamps, and its share of the
  sightings' mean square error;
* the claimed centroid sigma (``sqrt`` of the mean diagonal of ``cov_m``, in px) against
  the sightings' RMS error per arm, and the normalised squared error ``e^T cov^-1 e``
  (2 ideal).

``--csv`` writes every paired sighting (arm, run, frame, lamp id and type, true heading,
pixel, errors, claimed covariance, blob area and elongation). Timings: none (accuracy only).
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import logging
import os
import pickle
import time
from collections.abc import Sequence
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np

from lampsam.arrays import FloatArray
from lampsam.backend.config import SlamConfig
from lampsam.backend.slam import iter_steps, make_backend, start_pose_of
from lampsam.datasets.logrun import LoggedRun, read_run
from lampsam.evaluation import metrics as M
from lampsam.evaluation.lamp_plots import TILT_PANEL_TYPES, TiltCurve, save_tilt_figure
from lampsam.frontend.lamp_config import LampDetectorConfig
from lampsam.frontend.measurements import CeilingFrame
from lampsam.frontend.pipeline import FrontendConfig, iter_run

GATE_PX = 4.0
"""A detected lamp is paired with a true lamp whose projected centre is within this, px."""

ARMS: dict[str, FrontendConfig] = {
    "on": FrontendConfig(),
    "off": FrontendConfig(lamps=LampDetectorConfig(saturated_edges=False)),
    "edges": FrontendConfig(lamps=LampDetectorConfig(edge_phase_noise=True)),
    "off-edges": FrontendConfig(lamps=LampDetectorConfig(saturated_edges=False,
                                                         edge_phase_noise=True)),
}
"""Frontend settings compared, by name."""


def arm_frames(run: LoggedRun, arm: str, cache: Path) -> list[CeilingFrame]:
    """The run's frames under one arm's frontend setting, from the cache when made before."""
    path = cache / f"{run.path.name}-{arm}.pkl"
    if path.exists():
        with path.open("rb") as fh:
            cached = pickle.load(fh)
        if cached["config"] == repr(ARMS[arm]) and cached["run"] == str(run.path.resolve()):
            return list(cached["frames"])
    c0 = time.process_time()
    frames = list(iter_run(run, ARMS[arm]))
    print(f"  {run.path.name} {arm}: {len(frames)} frames in {time.process_time() - c0:.0f} s CPU",
          flush=True)
    tmp = path.with_suffix(".tmp")
    with tmp.open("wb") as fh:
        pickle.dump({"config": repr(ARMS[arm]), "run": str(run.path.resolve()), "frames": frames},
                    fh, protocol=pickle.HIGHEST_PROTOCOL)
    tmp.replace(path)
    return frames


def slam_errors(run: LoggedRun, frames: Sequence[CeilingFrame], backend: str,
                config: SlamConfig) -> dict[str, float]:
    """Run one backend on the frames; position RMS (m) and mean NEES against the truth."""
    be = make_backend(backend, run.rig.odometry, config, start_pose_of(run), run.rig.camera)
    for t, wheel, frame in iter_steps(run.odometry, frames):
        be.step(t, wheel, frame)
    res = be.finish()
    gt = run.groundtruth
    if gt is None:
        raise SystemExit(f"{run.path}: no ground truth")
    inside = (res.times >= gt.t[0]) & (res.times <= gt.t[-1])
    truth = gt.interpolate(res.times[inside])
    pos, _ = M.pose_errors(res.poses[inside], truth)
    nees = M.nees(M.coordinate_errors(res.poses[inside], truth), res.pose_covs[inside])
    return {"pos_rms_m": float(np.sqrt(np.mean(pos**2))), "nees": float(np.mean(nees)),
            "status": res.status}


def sightings(run: LoggedRun, frames: Sequence[CeilingFrame]) -> dict[str, np.ndarray]:
    """Every detected lamp paired with its true lamp, and its error (module docstring).

    Returns:
        Columns of equal length N: ``frame``, ``id``, ``type``, ``theta`` (true heading,
        rad), ``px`` (N, 2) detected pixel, ``e_m`` (N, 2) error in normalised ceiling
        coordinates (body axes), ``e_px`` (N, 2) = ``f e_m``, ``e_world_mm`` (N, 2),
        ``h`` (lamp height above the camera, m), ``cov_m`` (N, 2, 2), ``area_px``, ``ratio``,
        ``axis`` (rad, NaN for point lamps).
    """
    proj, cam, lms = run.projections, run.rig.camera, run.landmarks
    if proj is None or lms is None or run.images is None:
        raise SystemExit(f"{run.path}: needs truth/projections.csv, landmarks.csv and images")
    z_of = {int(i): float(lms.xyz[k, 2]) for k, i in enumerate(lms.ids)}
    is_lamp = np.array([t.startswith("lamp") for t in proj.types]) & proj.fully_visible
    rows_of: dict[int, np.ndarray] = {}
    idx = np.flatnonzero(is_lamp)
    for f in np.unique(proj.frame[idx]):
        rows_of[int(f)] = idx[proj.frame[idx] == f]
    if run.groundtruth is None:
        raise SystemExit(f"{run.path}: no ground truth")
    theta_t = run.groundtruth.interpolate(np.asarray(run.images.t, float))[:, 2]
    focal = float(cam.fx)
    out: dict[str, list[Any]] = {k: [] for k in ("frame", "id", "type", "theta", "px", "e_m",
                                                  "h", "cov_m", "area_px", "ratio", "axis")}
    for fr in frames:
        rows = rows_of.get(int(fr.index))
        if rows is None or not fr.lamps:
            continue
        tpx = proj.pixel[rows]
        for ob in fr.lamps:
            d = np.hypot(*(tpx - ob.pixel).T)
            j = int(np.argmin(d))
            if d[j] > GATE_PX:
                continue
            r = int(rows[j])
            m_true = cam.normalized_from_pixels(proj.pixel[r:r + 1])[0]
            lid = int(proj.ids[r])
            out["frame"].append(fr.index)
            out["id"].append(lid)
            out["type"].append(proj.types[r])
            out["theta"].append(theta_t[fr.index])
            out["px"].append(ob.pixel)
            out["e_m"].append(ob.m - m_true)
            out["h"].append(z_of[lid] - cam.z_cam)
            out["cov_m"].append(ob.cov_m)
            out["area_px"].append(ob.area_px)
            out["ratio"].append(ob.ratio)
            out["axis"].append(np.nan if ob.axis is None else ob.axis)
    cols = {k: np.asarray(v) for k, v in out.items()}
    e = cols["e_m"].reshape(-1, 2)
    c, s = np.cos(cols["theta"]), np.sin(cols["theta"])
    body_mm = 1e3 * e * cols["h"][:, None]
    cols["e_m"] = e
    cols["e_px"] = focal * e
    cols["e_world_mm"] = np.column_stack([c * body_mm[:, 0] - s * body_mm[:, 1],
                                          s * body_mm[:, 0] + c * body_mm[:, 1]])
    cols["cov_m"] = cols["cov_m"].reshape(-1, 2, 2)
    cols["px"] = cols["px"].reshape(-1, 2)
    cols["focal"] = np.full(len(e), focal)
    return cols


def per_lamp_means(s: dict[str, np.ndarray], run_of: np.ndarray) -> tuple[FloatArray, FloatArray]:
    """Mean world-frame error (mm) of each (run, lamp)'s sightings, and their counts."""
    keys = np.stack([run_of, s["id"]], axis=1)
    uniq, inv = np.unique(keys, axis=0, return_inverse=True)
    inv = inv.ravel()
    n = np.bincount(inv, minlength=len(uniq)).astype(float)
    means = np.stack([np.bincount(inv, s["e_world_mm"][:, k], len(uniq)) / n for k in (0, 1)], 1)
    return means, n


PASS_GAP_FRAMES = 3
"""Sightings of a lamp more than this many images apart belong to different passes."""


def pass_means(run_of: np.ndarray, ids: np.ndarray, frames: np.ndarray, e: FloatArray
               ) -> tuple[FloatArray, np.ndarray, np.ndarray]:
    """Mean error of each pass (a lamp's sightings in consecutive images of one run).

    Returns:
        ``(means (K, 2), counts (K,), pass index of each sighting (N,))``.
    """
    order = np.lexsort((frames, ids, run_of))
    new = np.ones(len(order), dtype=bool)
    new[1:] = ((run_of[order][1:] != run_of[order][:-1]) | (ids[order][1:] != ids[order][:-1])
               | (np.diff(frames[order]) > PASS_GAP_FRAMES))
    label = np.empty(len(order), dtype=np.intp)
    label[order] = np.cumsum(new) - 1
    k = int(label.max()) + 1 if len(label) else 0
    n = np.bincount(label, minlength=k).astype(float)
    means = np.stack([np.bincount(label, e[:, j], k) / np.maximum(n, 1) for j in (0, 1)], 1)
    return means, n, label


def _pooled(runs: list[dict[str, np.ndarray]]) -> dict[str, np.ndarray]:
    """One arm's sightings of every run, concatenated per field."""
    return {k: np.concatenate([r[k] for r in runs]) for k in runs[0]}


def _tilt_deg(theta: np.ndarray) -> np.ndarray:
    """Angle (deg, 0-45) of each true heading ``theta`` (rad) from the nearest axis."""
    return np.degrees(np.abs((theta + np.pi / 4) % (np.pi / 2) - np.pi / 4))


def _claimed_px(s: dict[str, np.ndarray], sel: np.ndarray | slice = slice(None)) -> float:
    """The sightings' claimed centroid sigma per axis, px (RMS over ``sel``)."""
    return float(np.sqrt(np.mean(s["cov_m"][sel, 0, 0] + s["cov_m"][sel, 1, 1]) / 2)
                 * s["focal"][0])


def sighting_table(all_s: dict[str, list[dict[str, np.ndarray]]]) -> None:
    """Print the sightings' bias, RMS, per-lamp means and claimed sigma per arm."""
    print("\nlamp sightings against truth (all runs):")
    print("| arm | sightings | bias px (u, v) | RMS px | RMS mm (ceiling) | per-lamp mean: RMS mm "
          "| share of MSE | lamps | per-pass mean: RMS px | share of MSE | passes "
          "| claimed sigma px | NSE (2 ideal) |")
    print("|---|---:|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    for arm, runs in all_s.items():
        s = _pooled(runs)
        run_of = np.concatenate([np.full(len(r["id"]), i) for i, r in enumerate(runs)])
        bias = s["e_px"].mean(axis=0)
        rms_px = float(np.sqrt(np.mean(np.sum(s["e_px"] ** 2, 1) / 2)))
        rms_mm = float(np.sqrt(np.mean(np.sum(s["e_world_mm"] ** 2, 1) / 2)))
        means, n = per_lamp_means(s, run_of)
        lamp_rms = float(np.sqrt(np.mean(np.sum(means**2, 1) / 2)))
        share = float(np.sum(n * np.sum(means**2, 1)) / np.sum(s["e_world_mm"] ** 2))
        pm, pn, _ = pass_means(run_of, s["id"], s["frame"], s["e_px"])
        pass_rms = float(np.sqrt(np.mean(np.sum(pm**2, 1) / 2)))
        pass_share = float(np.sum(pn * np.sum(pm**2, 1)) / np.sum(s["e_px"] ** 2))
        claimed = _claimed_px(s)
        nse = np.einsum("ni,nij,nj->n", s["e_m"], np.linalg.inv(s["cov_m"]), s["e_m"])
        print(f"| {arm} | {len(s['id'])} | {bias[0]:+.3f}, {bias[1]:+.3f} | {rms_px:.3f} | "
              f"{rms_mm:.2f} | {lamp_rms:.2f} | {share:.0%} | {len(n)} | {pass_rms:.3f} | "
              f"{pass_share:.0%} | {len(pn)} | {claimed:.3f} | "
              f"{np.mean(nse):.2f} |")


TILT_BINS_DEG = (0.0, 0.5, 1.0, 2.0, 5.0, 45.0)
"""Bins of the true heading's angle from the nearest axis (the lab's lamps lie along the
axes: this is their edges' angle from the pixel grid)."""


def tilt_table(all_s: dict[str, list[dict[str, np.ndarray]]]) -> None:
    """Print RMS error against claimed sigma (px, per axis) by lamp type and grid tilt."""
    print("\nRMS error / claimed sigma, px per axis, by lamp type and the heading's tilt from "
          "the grid (deg):")
    arms = list(all_s)
    print("| type | tilt | sightings | " + " | ".join(arms) + " |")
    print("|---|---|---:|" + "---|" * len(arms))
    cat = {a: _pooled(runs) for a, runs in all_s.items()}
    for typ in sorted(set(cat[arms[0]]["type"].tolist())):
        for lo, hi in zip(TILT_BINS_DEG[:-1], TILT_BINS_DEG[1:], strict=True):
            cells = []
            n = 0
            for a in arms:
                s = cat[a]
                t = _tilt_deg(s["theta"])
                sel = (s["type"] == typ) & (t >= lo) & (t < hi)
                n = int(sel.sum())
                if not n:
                    cells.append("-")
                    continue
                rms = np.sqrt(np.mean(s["e_px"][sel] ** 2))
                cells.append(f"{rms:.3f} / {_claimed_px(s, sel):.3f}")
            print(f"| {typ} | {lo:g}-{hi:g} | {n} | " + " | ".join(cells) + " |")


TILT_EDGES_DEG = np.array([0.0, 0.25, 0.5, 0.75, 1.0, 1.5, 2.0, 3.0, 5.0, 10.0, 20.0, 45.0])
"""The figure's tilt bins, deg (finer than :data:`TILT_BINS_DEG`); a bin needs 20 sightings."""


def tilt_curves(all_s: dict[str, list[dict[str, np.ndarray]]]
                ) -> tuple[FloatArray, dict[str, list[TiltCurve]]]:
    """RMS error and claimed sigma (px per axis) per fine tilt bin, lamp type and arm.

    Returns:
        The bins' geometric centres (deg) and per lamp type of ``TILT_PANEL_TYPES`` one
        curve per arm (an arm's error curve equal to an earlier arm's, i.e. the same
        sightings, is given as None: drawn once).
    """
    edges = TILT_EDGES_DEG
    mids = np.sqrt(np.maximum(edges[:-1], 0.1) * edges[1:])
    cat = {a: _pooled(runs) for a, runs in all_s.items()}
    panels: dict[str, list[TiltCurve]] = {}
    for typ in TILT_PANEL_TYPES:
        drawn: list[FloatArray] = []
        curves = []
        for arm, s in cat.items():
            t = _tilt_deg(s["theta"])
            rms, claim = np.full(mids.size, np.nan), np.full(mids.size, np.nan)
            for i in range(mids.size):
                sel = (s["type"] == typ) & (t >= edges[i]) & (t < edges[i + 1])
                if sel.sum() >= 20:
                    rms[i] = np.sqrt(np.mean(s["e_px"][sel] ** 2))
                    claim[i] = _claimed_px(s, sel)
            new = not any(np.allclose(rms, r, equal_nan=True) for r in drawn)
            if new:
                drawn.append(rms)
            curves.append(TiltCurve(arm, rms if new else None, claim))
        panels[typ] = curves
    return mids, panels


def write_csv(path: Path, all_s: dict[str, list[dict[str, np.ndarray]]], names: list[str]) -> None:
    """Every paired sighting as one CSV row."""
    with path.open("w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["arm", "run", "frame", "id", "type", "theta", "col", "row", "h", "e_u_px",
                    "e_v_px", "e_x_mm", "e_y_mm", "cov_uu", "cov_uv", "cov_vv", "focal",
                    "area_px", "ratio", "axis"])
        for arm, runs in all_s.items():
            for name, s in zip(names, runs, strict=True):
                for i in range(len(s["id"])):
                    w.writerow([arm, name, int(s["frame"][i]), int(s["id"][i]), s["type"][i],
                                f"{s['theta'][i]:.5f}", f"{s['px'][i, 0]:.3f}",
                                f"{s['px'][i, 1]:.3f}", f"{s['h'][i]:.4f}",
                                f"{s['e_px'][i, 0]:.5f}", f"{s['e_px'][i, 1]:.5f}",
                                f"{s['e_world_mm'][i, 0]:.4f}", f"{s['e_world_mm'][i, 1]:.4f}",
                                f"{s['cov_m'][i, 0, 0]:.4e}", f"{s['cov_m'][i, 0, 1]:.4e}",
                                f"{s['cov_m'][i, 1, 1]:.4e}", f"{s['focal'][i]:.4f}",
                                f"{s['area_px'][i]:.2f}", f"{s['ratio'][i]:.3f}",
                                f"{s['axis'][i]:.5f}"])


def first_seconds(run: LoggedRun, frames: list[CeilingFrame], duration: float | None
                  ) -> tuple[LoggedRun, list[CeilingFrame]]:
    """The run's odometry and frames cut at ``duration`` s from the start (None: all)."""
    if duration is None:
        return run, frames
    odo = run.odometry
    keep = odo.t <= odo.t[0] + duration
    run = dataclasses.replace(run, odometry=dataclasses.replace(
        odo, t=odo.t[keep], d_left=odo.d_left[keep], d_right=odo.d_right[keep]))
    return run, [f for f in frames if f.t <= odo.t[keep][-1]]


def one_run(job: tuple[Path, list[str], list[str], Path, float | None]
            ) -> tuple[list[dict[str, Any]], dict[str, dict[str, np.ndarray]]]:
    """One run: each arm's frames (cached), sightings and backend errors."""
    run_dir, arms, backends, cache, duration = job
    full = read_run(run_dir)
    rows = []
    out = {}
    for arm in arms:
        run, frames = first_seconds(full, arm_frames(full, arm, cache), duration)
        out[arm] = sightings(run, frames)
        for be in backends:
            r = slam_errors(run, frames, be, SlamConfig())
            rows.append({"run": run_dir.name, "arm": arm, "backend": be, **r})
            print(f"  {run_dir.name} {arm:4s} {be:6s} pos RMS {1e3 * r['pos_rms_m']:.2f} mm "
                  f"NEES {r['nees']:.2f} ({r['status']})", flush=True)
    return rows, out


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("runs", nargs="+", type=Path, help="simulated lab run directories")
    p.add_argument("--cache", type=Path, required=True, help="directory of cached frames")
    p.add_argument("--arms", default="on,off", help="comma-separated, of " + ", ".join(ARMS))
    p.add_argument("--backends", default="isam2,batch")
    p.add_argument("--csv", type=Path, default=None, help="write the paired sightings here")
    p.add_argument("--duration", type=float, default=None,
                   help="use the first S seconds of each run only")
    p.add_argument("--jobs", type=int, default=1, help="runs measured in parallel processes")
    p.add_argument("--figure", type=Path, default=None,
                   help="write the error / claimed sigma against grid tilt figure here")
    p.add_argument("--no-slam", action="store_true", help="sightings only")
    args = p.parse_args()
    logging.basicConfig(level=logging.ERROR)
    arms = args.arms.split(",")
    for a in arms:
        if a not in ARMS:
            raise SystemExit(f"--arms: unknown arm {a!r}; choose from {', '.join(ARMS)}")
    backends = [] if args.no_slam else args.backends.split(",")
    args.cache.mkdir(parents=True, exist_ok=True)
    load0 = os.getloadavg()[0]
    rows: list[dict[str, Any]] = []
    all_s: dict[str, list[dict[str, np.ndarray]]] = {a: [] for a in arms}
    names = [d.name for d in args.runs]
    jobs = [(d, arms, backends, args.cache, args.duration) for d in args.runs]
    if args.jobs > 1:
        with ProcessPoolExecutor(args.jobs) as pool:
            done = list(pool.map(one_run, jobs))
    else:
        done = [one_run(j) for j in jobs]
    for run_rows, run_s in done:
        rows += run_rows
        for a in arms:
            all_s[a].append(run_s[a])
    for be in backends:
        print(f"\n{be}: position RMS mm / mean NEES per run")
        print("| run | " + " | ".join(arms) + " |")
        print("|---|" + "---|" * len(arms))
        table = {(r["run"], r["arm"]): r for r in rows if r["backend"] == be}
        for name in names:
            print(f"| {name} | " + " | ".join(
                f"{1e3 * table[name, a]['pos_rms_m']:.2f} / {table[name, a]['nees']:.2f}"
                for a in arms) + " |")
        pos = np.array([[table[n, a]["pos_rms_m"] for a in arms] for n in names]) * 1e3
        nees = np.array([[table[n, a]["nees"] for a in arms] for n in names])
        print("| mean | " + " | ".join(f"**{pos[:, k].mean():.2f}** / {nees[:, k].mean():.2f}"
                                      for k in range(len(arms))) + " |")
        print("| sd of runs (se) | " + " | ".join(
            f"{pos[:, k].std(ddof=1):.2f} ({pos[:, k].std(ddof=1) / np.sqrt(len(names)):.2f})"
            for k in range(len(arms))) + " |")
        for k in range(1, len(arms)):
            d = pos[:, 0] - pos[:, k]
            print(f"{arms[0]} better than {arms[k]} on {int(np.sum(d < 0))} of {len(names)} runs; "
                  f"mean difference {d.mean():+.2f} mm (se of the paired difference "
                  f"{d.std(ddof=1) / np.sqrt(len(names)):.2f})")
    sighting_table(all_s)
    tilt_table(all_s)
    if args.csv is not None:
        write_csv(args.csv, all_s, names)
    if args.figure is not None:
        save_tilt_figure(args.figure, *tilt_curves(all_s))
    print(f"\nload average {load0:.1f} at the start, {os.getloadavg()[0]:.1f} now, "
          f"on {os.cpu_count()} cores")


if __name__ == "__main__":
    main()
