"""Stereo two-point experiment: 20 seeds x 2 scenarios x 4 estimators (paper 3, Figs. 3-5).

Writes under ``--out``:
  ``stereo_rms.md`` / ``stereo_rms.json``: RMS of the x, y and heading errors per
  scenario and estimator, pooled over all seeds on the frames where every
  estimator has an estimate (i.e. where raw triangulation succeeded), plus per-seed
  win counts and median per-frame cost;
  ``fig_<scenario>.png``: trajectory and x / y / heading errors over time for raw,
  EKF and the batch smoother (seed 0);
  ``stereo_kitti.json``, ``fig_kitti.png``: the two-point model on the shared KITTI
  sequence (when present; ``--no-kitti`` skips it).

Usage: ``python scripts/stereo_experiment.py --out out/stereo [--seeds 20]``
"""

from __future__ import annotations

import argparse
import json
import logging
from pathlib import Path

import numpy as np

from lampsam.backend.stereo import ESTIMATORS, estimate
from lampsam.datasets.stereo_sim import SCENARIOS, simulate_stereo
from lampsam.evaluation.stereo_report import (
    common_mask,
    figure_for_run,
    markdown_table,
    pose_errors,
)


def kitti_part(out: Path) -> str:
    """Two-point relative pose on the shared KITTI sequence; returns a markdown section."""
    from matplotlib.figure import Figure

    from lampsam.backend.stereo_kitti import track_sequence, two_point_on_kitti
    from lampsam.datasets.kitti import read_kitti_sequence
    from lampsam.datasets.paths import shared_dataset
    from lampsam.evaluation.stereo_report import (
        kitti_summary,
        plot_kitti_errors,
        plot_kitti_trajectory,
    )

    path = shared_dataset("kitti_stereo_seq1")
    if path is None:
        return "\nKITTI: shared data not found, skipped.\n"
    seq = read_kitti_sequence(path)
    result = two_point_on_kitti(seq, track_sequence(seq))
    summ = kitti_summary(result)
    (out / "stereo_kitti.json").write_text(json.dumps(summ, indent=2))
    fig = Figure(figsize=(11, 4), layout="constrained")
    ax1, ax2 = fig.subplots(1, 2)
    plot_kitti_trajectory(ax1, result)
    plot_kitti_errors(ax2, result)
    fig.savefig(out / "fig_kitti.png", dpi=110)
    rr, rm, fe, mp = summ["rel_rms"], summ["rel_median_abs"], summ["final_error"], summ["model_px"]
    return (
        f"\nKITTI kitti_stereo_seq1 ({summ['frames']} frames, {summ['path_length_m']:.1f} m, "
        f"{summ['pairs']} point pairs, {summ['scored']} frames scored):\n"
        f"- relative motion anchor->k, RMS: x {rr[0]:.3f} m, y {rr[1]:.3f} m, heading "
        f"{np.degrees(rr[2]):.2f} deg; median |e|: x {rm[0]:.3f} m, y {rm[1]:.3f} m, heading "
        f"{np.degrees(rm[2]):.2f} deg\n"
        f"- chained trajectory, final error: x {fe[0]:.2f} m, y {fe[1]:.2f} m, heading "
        f"{np.degrees(fe[2]):.2f} deg\n"
        f"- eq. 2 check ({mp['count']} coordinates of points moved k-1 -> k by the true "
        f"motion): median {mp['median']:.2f} px, p90 {mp['p90']:.2f} px, RMS {mp['rms']:.2f} px, "
        f"{100 * mp['within_1px']:.0f} % within 1 px\n"
    )


def main() -> int:
    """Run the experiment; returns the exit code."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="out/stereo", help="output directory")
    ap.add_argument("--seeds", type=int, default=20, help="number of seeds (default 20)")
    ap.add_argument("--no-kitti", action="store_true", help="skip the KITTI real-data check")
    args = ap.parse_args()
    logging.basicConfig(level=logging.WARNING)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)

    rms: dict[str, dict[str, list[float]]] = {}
    summary: dict[str, dict] = {}
    for scenario in SCENARIOS:
        sq = {e: [] for e in ESTIMATORS}
        per_seed = {e: [] for e in ESTIMATORS}
        step_ms = {e: [] for e in ESTIMATORS}
        statuses = {e: {} for e in ESTIMATORS}
        for seed in range(args.seeds):
            run = simulate_stereo(scenario, np.random.default_rng(seed), seed=seed)
            assert run.truth is not None
            results = {e: estimate(run, e) for e in ESTIMATORS}
            mask = common_mask(list(results.values()))
            for e, r in results.items():
                err = pose_errors(r.poses, run.truth)[mask]
                sq[e].append(err**2)
                per_seed[e].append(np.sqrt(np.mean(err**2, axis=0)))
                step_ms[e].append(1e3 * r.step_time_s)
                for s, c in r.status_counts().items():
                    statuses[e][s] = statuses[e].get(s, 0) + c
            if seed == 0:
                fig = figure_for_run(
                    run.truth, [results["raw"], results["ekf"], results["batch"]],
                    run.target_t_points, f"{scenario} (seed 0): raw, EKF, batch smoother")
                fig.savefig(out / f"fig_{scenario}.png", dpi=110)
        rms[scenario] = {}
        summary[scenario] = {}
        for e in ESTIMATORS:
            pooled = np.sqrt(np.mean(np.concatenate(sq[e]), axis=0))
            rms[scenario][e] = pooled.tolist()
            seeds_rms = np.array(per_seed[e])
            summary[scenario][e] = {
                "rms_x_m": pooled[0], "rms_y_m": pooled[1], "rms_heading_rad": pooled[2],
                "median_seed_rms": np.median(seeds_rms, axis=0).tolist(),
                "median_step_ms": float(np.median(np.concatenate(step_ms[e]))),
                "status_counts": statuses[e],
                "frames_scored": int(sum(len(s) for s in sq[e])),
            }
        ps = {e: np.array(per_seed[e]) for e in ESTIMATORS}
        summary[scenario]["wins"] = {
            "batch_below_ekf_all_components": int(np.sum(np.all(ps["batch"] < ps["ekf"], axis=1))),
            "ekf_below_raw_all_components": int(np.sum(np.all(ps["ekf"] < ps["raw"], axis=1))),
            "seeds": args.seeds,
        }
    caption = (f"RMS error pooled over {args.seeds} seeds, on frames where raw triangulation "
               "succeeded (all estimators valid).")
    table = markdown_table(rms, caption)
    factors = []
    for scenario in SCENARIOS:
        r = rms[scenario]
        for a, b in (("ekf", "batch"), ("raw", "ekf"), ("raw", "batch")):
            f = np.array(r[a]) / np.array(r[b])
            factors.append(f"- {scenario}: {a} / {b} = x {f[0]:.1f}, y {f[1]:.1f}, "
                           f"heading {f[2]:.1f}")
    text = table + "\nRatios (how many times smaller the second one is):\n" + "\n".join(factors)
    text += "\n\nPer-seed wins (all three components):\n"
    for scenario in SCENARIOS:
        w = summary[scenario]["wins"]
        n = w["seeds"]
        text += (f"- {scenario}: batch < EKF in {w['batch_below_ekf_all_components']}/{n}, "
                 f"EKF < raw in {w['ekf_below_raw_all_components']}/{n}\n")
    if not args.no_kitti:
        text += kitti_part(out)
    (out / "stereo_rms.md").write_text(text)
    (out / "stereo_rms.json").write_text(json.dumps(summary, indent=2, default=float))
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
