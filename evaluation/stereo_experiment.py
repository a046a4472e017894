"""The stereo two-point experiment of paper 3 (Figs. 3-5): seeds x scenarios x estimators.

For each scenario (``straight``, ``turn``) and seed, a stereo run is simulated and every
estimator (raw triangulation, the paper's EKF, iSAM2, the batch smoother) is run on it.
Errors are pooled over seeds on the frames where every estimator has an estimate, i.e.
where raw triangulation succeeded, so that the estimators are compared on the same
frames. Optionally the two-point model is checked on the shared KITTI sequence
(``lampsam stereo-experiment``; ``docs/stereo.md``).
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure

from lampsam.arrays import FloatArray
from lampsam.backend.stereo import ESTIMATORS, estimate
from lampsam.datasets.stereo_sim import SCENARIOS, simulate_stereo
from lampsam.evaluation.stereo_report import (
    common_mask,
    figure_for_run,
    kitti_summary,
    markdown_table,
    plot_kitti_errors,
    plot_kitti_trajectory,
    pose_errors,
)
from lampsam.safe_io import atomic_path, write_text_atomic

log = logging.getLogger(__name__)


@dataclass
class ScenarioStats:
    """Errors of every estimator on one scenario, collected over seeds.

    Attributes:
        squared: estimator -> per-seed (F_s, 3) squared errors (x, y in m^2; heading in
            rad^2) on the frames every estimator scored.
        per_seed_rms: estimator -> per-seed (3,) RMS (m, m, rad).
        step_ms: estimator -> per-seed per-frame cost, ms.
        statuses: estimator -> status -> frame count.
    """

    squared: dict[str, list[FloatArray]] = field(default_factory=lambda: {e: [] for e in ESTIMATORS})
    per_seed_rms: dict[str, list[FloatArray]] = field(
        default_factory=lambda: {e: [] for e in ESTIMATORS})
    step_ms: dict[str, list[FloatArray]] = field(default_factory=lambda: {e: [] for e in ESTIMATORS})
    statuses: dict[str, dict[str, int]] = field(default_factory=lambda: {e: {} for e in ESTIMATORS})

    def pooled_rms(self, estimator: str) -> FloatArray:
        """(3,) RMS over all seeds' scored frames: x, y (m), heading (rad)."""
        return np.sqrt(np.mean(np.concatenate(self.squared[estimator]), axis=0))

    def summary(self) -> dict[str, object]:
        """JSON-ready figures per estimator, and per-seed win counts."""
        out: dict[str, object] = {}
        for e in ESTIMATORS:
            pooled = self.pooled_rms(e)
            out[e] = {
                "rms_x_m": float(pooled[0]), "rms_y_m": float(pooled[1]),
                "rms_heading_rad": float(pooled[2]),
                "median_seed_rms": np.median(np.array(self.per_seed_rms[e]), axis=0).tolist(),
                "median_step_ms": float(np.median(np.concatenate(self.step_ms[e]))),
                "status_counts": self.statuses[e],
                "frames_scored": int(sum(len(s) for s in self.squared[e])),
            }
        ps = {e: np.array(self.per_seed_rms[e]) for e in ESTIMATORS}
        out["wins"] = {
            "batch_below_ekf_all_components": int(np.sum(np.all(ps["batch"] < ps["ekf"], axis=1))),
            "ekf_below_raw_all_components": int(np.sum(np.all(ps["ekf"] < ps["raw"], axis=1))),
            "seeds": len(ps["batch"]),
        }
        return out


def run_scenario(scenario: str, seeds: int, figure_path: Path | None = None) -> ScenarioStats:
    """Simulate ``seeds`` runs of a scenario and score every estimator on each.

    Args:
        scenario: one of :data:`SCENARIOS`.
        seeds: number of seeds (0 .. seeds-1); each seeds its own ``numpy`` Generator.
        figure_path: where to save seed 0's trajectory/error figure (raw, EKF, batch).
    """
    stats = ScenarioStats()
    for seed in range(seeds):
        run = simulate_stereo(scenario, np.random.default_rng(seed), seed=seed)
        if run.truth is None:
            raise ValueError(f"{scenario} seed {seed}: the simulator gave no truth")
        results = {e: estimate(run, e) for e in ESTIMATORS}
        mask = common_mask(list(results.values()))
        for e, r in results.items():
            err = pose_errors(r.poses, run.truth)[mask]
            stats.squared[e].append(err**2)
            stats.per_seed_rms[e].append(np.sqrt(np.mean(err**2, axis=0)))
            stats.step_ms[e].append(1e3 * r.step_time_s)
            for s, c in r.status_counts().items():
                stats.statuses[e][s] = stats.statuses[e].get(s, 0) + c
        if seed == 0 and figure_path is not None:
            fig = figure_for_run(run.truth, [results["raw"], results["ekf"], results["batch"]],
                                 run.target_t_points,
                                 f"{scenario} (seed 0): raw, EKF, batch smoother")
            with atomic_path(figure_path) as tmp:
                fig.savefig(tmp, dpi=110)
    return stats


def kitti_section(kitti_dir: Path, out: Path) -> str:
    """The two-point model on a KITTI stereo sequence; writes its JSON and figure.

    Returns:
        A Markdown section with the relative-motion errors and the eq. 2 check.
    """
    from lampsam.backend.stereo_kitti import track_sequence, two_point_on_kitti
    from lampsam.datasets.kitti import read_kitti_sequence

    seq = read_kitti_sequence(kitti_dir)
    result = two_point_on_kitti(seq, track_sequence(seq))
    summ = kitti_summary(result)
    write_text_atomic(out / "stereo_kitti.json", json.dumps(summ, indent=2))
    fig = Figure(figsize=(11, 4), layout="constrained")
    ax1, ax2 = fig.subplots(1, 2)
    plot_kitti_trajectory(ax1, result)
    plot_kitti_errors(ax2, result)
    with atomic_path(out / "fig_kitti.png") as tmp:
        fig.savefig(tmp, dpi=110)
    rr, rm, fe, mp = summ["rel_rms"], summ["rel_median_abs"], summ["final_error"], summ["model_px"]
    return (
        f"\nKITTI {kitti_dir.name} ({summ['frames']} frames, {summ['path_length_m']:.1f} m, "
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


def report_text(stats: dict[str, ScenarioStats]) -> str:
    """Markdown: the pooled RMS table, the ratios between estimators and per-seed wins."""
    seeds = len(next(iter(stats.values())).per_seed_rms["raw"])
    rms = {s: {e: st.pooled_rms(e).tolist() for e in ESTIMATORS} for s, st in stats.items()}
    caption = (f"RMS error pooled over {seeds} seeds, on frames where raw triangulation "
               "succeeded (all estimators valid).")
    lines = [markdown_table(rms, caption), "\nRatios (how many times smaller the second one is):"]
    for scenario, r in rms.items():
        for a, b in (("ekf", "batch"), ("raw", "ekf"), ("raw", "batch")):
            f = np.array(r[a]) / np.array(r[b])
            lines.append(f"- {scenario}: {a} / {b} = x {f[0]:.1f}, y {f[1]:.1f}, heading {f[2]:.1f}")
    lines.append("\nPer-seed wins (all three components):")
    for scenario, st in stats.items():
        w = st.summary()["wins"]
        assert isinstance(w, dict)
        lines.append(f"- {scenario}: batch < EKF in {w['batch_below_ekf_all_components']}/{seeds}, "
                     f"EKF < raw in {w['ekf_below_raw_all_components']}/{seeds}")
    return "\n".join(lines) + "\n"


def stereo_experiment(out: Path, seeds: int = 20, kitti_dir: Path | None = None,
                      scenarios: tuple[str, ...] = SCENARIOS) -> str:
    """Run the whole experiment and write ``stereo_rms.md``/``.json`` and figures to ``out``.

    Args:
        out: output directory (created).
        seeds: seeds per scenario.
        kitti_dir: a KITTI stereo sequence for the real-data check, or None to skip it.
        scenarios: which of :data:`SCENARIOS` to run.

    Returns:
        The Markdown report.
    """
    if seeds < 1:
        raise ValueError(f"seeds must be at least 1, got {seeds}")
    out.mkdir(parents=True, exist_ok=True)
    unknown = set(scenarios) - set(SCENARIOS)
    if unknown:
        raise ValueError(f"unknown scenarios {sorted(unknown)}; choose from {SCENARIOS}")
    stats = {s: run_scenario(s, seeds, out / f"fig_{s}.png") for s in scenarios}
    text = report_text(stats)
    if kitti_dir is not None:
        text += kitti_section(kitti_dir, out)
    write_text_atomic(out / "stereo_rms.md", text)
    write_text_atomic(out / "stereo_rms.json",
                      json.dumps({s: st.summary() for s, st in stats.items()}, indent=2))
    return text
