"""Stereo two-point relative pose: errors, tables, figures (paper 3, Figs. 3-5), run outputs.

Plot functions take a matplotlib ``ax`` and finished results and return the
artists; nothing here estimates. Figures are built with ``matplotlib.figure.Figure``
(no pyplot, no GUI backend).
"""

from __future__ import annotations

import csv
import logging
import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from lampsam.arrays import BoolArray, FloatArray
from lampsam.backend.stereo import StereoEstimatorConfig, StereoResult
from lampsam.backend.stereo_kitti import KittiTwoPointResult
from lampsam.errors import LampsamError
from lampsam.evaluation.outputs import ensure_dir
from lampsam.safe_io import atomic_path, write_json_atomic

log = logging.getLogger(__name__)

COMPONENTS = ("x", "y", "heading")
UNITS = ("m", "m", "deg")
COLOURS = {"raw": "tab:red", "ekf": "tab:green", "isam2": "tab:orange", "batch": "tab:blue"}


class StereoReportError(LampsamError):
    """Results and truth do not fit together (length, missing truth)."""


def pose_errors(poses: FloatArray, truth: FloatArray) -> FloatArray:
    """(N, 3) errors ``estimate - truth``: x, y (m) and heading (rad, wrapped to (-pi, pi])."""
    poses = np.asarray(poses, dtype=float)
    truth = np.asarray(truth, dtype=float)
    if poses.shape != truth.shape or poses.ndim != 2 or poses.shape[1] != 3:
        raise StereoReportError(f"pose arrays differ: {poses.shape} vs {truth.shape}")
    e = poses - truth
    e[:, 2] = np.pi - np.mod(np.pi - e[:, 2], 2 * np.pi)
    return e


def common_mask(results: Sequence[StereoResult]) -> BoolArray:
    """(N,) frames where every given estimator has an estimate (the fair RMS set)."""
    if not results:
        raise StereoReportError("no results")
    mask = np.ones(len(results[0].t), dtype=bool)
    for r in results:
        if len(r.t) != len(mask):
            raise StereoReportError(f"{r.estimator}: {len(r.t)} frames, expected {len(mask)}")
        mask &= r.valid
    return mask


def rms_errors(result: StereoResult, truth: FloatArray, mask: BoolArray) -> FloatArray:
    """(3,) RMS of the x (m), y (m) and heading (rad) errors over ``mask``."""
    e = pose_errors(result.poses, truth)[mask]
    if len(e) == 0:
        raise StereoReportError(f"{result.estimator}: no frames to score")
    return np.sqrt(np.mean(e**2, axis=0))


def markdown_table(rms: Mapping[str, Mapping[str, Sequence[float]]], caption: str = "") -> str:
    """Markdown table: rows scenario x estimator, columns x (m), y (m), heading (deg).

    Args:
        rms: ``rms[scenario][estimator] = (x, y, heading_rad)``.
        caption: a line put above the table.
    """
    lines = [caption, ""] if caption else []
    lines += ["| scenario | estimator | RMS x (m) | RMS y (m) | RMS heading (deg) |",
              "|---|---|---:|---:|---:|"]
    for scenario, per_est in rms.items():
        for est, v in per_est.items():
            lines.append(f"| {scenario} | {est} | {v[0]:.4f} | {v[1]:.4f} | "
                         f"{math.degrees(v[2]):.3f} |")
    return "\n".join(lines) + "\n"


def summary_table(summary: Mapping[str, Any]) -> str:
    """The ``lampsam stereo`` summary as a Markdown table (as ``compare`` prints).

    One row: estimator, frames, the frames of each status, the RMS errors (x, y in
    m; heading in degrees) over the frames every compared estimator scored, how
    many those are, and the median step time.

    Args:
        summary: what :func:`stereo_job` returns.
    """
    counts: Mapping[str, int] = summary.get("status_counts", {})
    statuses = sorted(counts, key=lambda k: (k != "ok", k))
    rms = summary.get("rms")
    head = ["estimator", "frames", *[f"{s}" for s in statuses], "RMS x [m]", "RMS y [m]",
            "RMS heading [deg]", "scored frames", "median step [ms]"]
    cells = [str(summary.get("estimator", "?")), str(summary.get("frames", "?")),
             *[str(counts[s]) for s in statuses]]
    if rms:
        cells += [f"{rms['x_m']:.4f}", f"{rms['y_m']:.4f}",
                  f"{math.degrees(rms['heading_rad']):.3f}", str(rms["frames"])]
    else:
        cells += ["–", "–", "–", "0"]
    cells.append(f"{summary.get('median_step_ms', float('nan')):.2f}")
    return "\n".join(["| " + " | ".join(head) + " |", "|" + "---|" * len(head),
                      "| " + " | ".join(cells) + " |"])


# --------------------------------------------------------------------------- plots
def plot_trajectory(
    ax: Any,
    truth: FloatArray,
    results: Sequence[StereoResult],
    target_t_points: FloatArray,
    heading_every: int = 0,
) -> list[Any]:
    """Top view in the target frame (paper Figs. 3 and 5a): truth, estimates, target.

    Args:
        ax: a matplotlib Axes.
        truth: (N, 3) true rig poses.
        results: estimators to draw (only their valid frames).
        target_t_points: (2, 2) target points, m.
        heading_every: draw a heading arrow every this many frames of the truth
            (0: none).

    Returns:
        The artists drawn.
    """
    artists: list[Any] = []
    for r in results:
        m = r.valid
        style = "." if r.estimator == "raw" else "-"
        artists += ax.plot(r.poses[m, 0], r.poses[m, 1], style, ms=3, lw=1.2,
                           color=COLOURS.get(r.estimator), label=r.estimator)
    artists += ax.plot(truth[:, 0], truth[:, 1], "k--", lw=1.0, label="truth")
    if heading_every > 0:
        sel = truth[::heading_every]
        artists.append(ax.quiver(sel[:, 0], sel[:, 1], np.cos(sel[:, 2]), np.sin(sel[:, 2]),
                                 angles="xy", scale=12, width=0.004, color="k"))
    pts = np.asarray(target_t_points)
    artists += ax.plot(pts[:, 0], pts[:, 1], "ks", ms=6, label="target points")
    ax.set_xlabel("x in target frame (m)")
    ax.set_ylabel("y in target frame (m)")
    ax.set_aspect("equal", adjustable="datalim")
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=8)
    return artists


def plot_error(
    ax: Any, truth: FloatArray, results: Sequence[StereoResult], component: int
) -> list[Any]:
    """Error of one component over time (paper Figs. 4 and 5b).

    Args:
        ax: a matplotlib Axes.
        truth: (N, 3) true poses.
        results: the estimators to draw (valid frames only).
        component: 0 = x (m), 1 = y (m), 2 = heading (deg).

    Returns:
        The artists drawn.
    """
    artists: list[Any] = []
    for r in results:
        e = pose_errors(r.poses, truth)[:, component]
        if component == 2:
            e = np.degrees(e)
        m = r.valid
        style = "." if r.estimator == "raw" else "-"
        artists += ax.plot(r.t[m], e[m], style, ms=3, lw=1.2, color=COLOURS.get(r.estimator),
                           label=r.estimator)
    ax.axhline(0.0, color="k", lw=0.5)
    ax.set_xlabel("time (s)")
    ax.set_ylabel(f"{COMPONENTS[component]} error ({UNITS[component]})")
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=8)
    return artists


def figure_for_run(
    truth: FloatArray, results: Sequence[StereoResult], target_t_points: FloatArray, title: str
) -> Any:
    """A 2x2 figure: trajectory and x, y, heading errors. Returns a ``Figure``."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=(11, 8), layout="constrained")
    axes = fig.subplots(2, 2)
    plot_trajectory(axes[0, 0], truth, results, target_t_points, heading_every=10)
    for comp, ax in zip((0, 1, 2), (axes[0, 1], axes[1, 0], axes[1, 1]), strict=True):
        plot_error(ax, truth, results, comp)
    fig.suptitle(title)
    return fig


# --------------------------------------------------------------------------- outputs
def write_stereo_result(result: StereoResult, out: Path) -> list[Path]:
    """Write ``estimate.tum`` (valid frames) and ``status.csv`` (every frame) to ``out``.

    ``status.csv`` header: ``t,valid,status,x,y,theta,var_x,var_y,var_theta,step_ms``.

    Raises:
        StereoReportError: ``out`` cannot be created (e.g. it is a file).
    """
    out = ensure_dir(out, StereoReportError)
    tum = out / "estimate.tum"
    with atomic_path(tum) as tmp, open(tmp, "w") as fh:
        fh.write(f"# t x y z qx qy qz qw ({result.estimator}, rig pose in the target frame)\n")
        for i in np.nonzero(result.valid)[0]:
            x, y, th = result.poses[i]
            fh.write(f"{result.t[i]:.6f} {x:.9f} {y:.9f} 0 0 0 {math.sin(th / 2):.12f} "
                     f"{math.cos(th / 2):.12f}\n")
    status = out / "status.csv"
    with atomic_path(status) as tmp, open(tmp, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["t", "valid", "status", "x", "y", "theta", "var_x", "var_y", "var_theta",
                    "step_ms"])
        for k in range(len(result.t)):
            c = np.diag(result.covariances[k])
            w.writerow([f"{result.t[k]:.6f}", int(result.valid[k]), result.status[k]]
                       + [f"{v:.9g}" for v in result.poses[k]] + [f"{v:.6g}" for v in c]
                       + [f"{1e3 * result.step_time_s[k]:.4f}"])
    return [tum, status]


def stereo_job(
    run_dir: Path, estimator: str, out: Path, config: StereoEstimatorConfig | None = None
) -> dict[str, Any]:
    """``lampsam stereo RUN --estimator E --out OUT``: estimate, write, score, plot.

    Writes ``estimate.tum``, ``status.csv``, ``summary.json`` and, when the run has
    ground truth, ``errors.png`` (trajectory and errors against the truth, with
    the raw triangulation beside the estimator).

    Args:
        run_dir: the stereo run directory.
        estimator: ``raw``, ``ekf``, ``isam2`` or ``batch``.
        out: the output directory.
        config: estimator settings (defaults when None).

    Returns:
        The summary (status counts, median step time, RMS when truth exists).
    """
    from lampsam.backend.stereo import estimate
    from lampsam.datasets.stereo_sim import read_stereo_run

    run = read_stereo_run(Path(run_dir))
    ensure_dir(out, StereoReportError)  # before the work, after the input is known good
    result = estimate(run, estimator, config)
    out = Path(out)
    write_stereo_result(result, out)
    summary: dict[str, Any] = {
        "run": str(run_dir), "estimator": estimator, "frames": len(run),
        "status_counts": result.status_counts(),
        "median_step_ms": float(1e3 * np.median(result.step_time_s)),
    }
    if run.truth is not None and result.valid.any():
        results = [result] if estimator == "raw" else [estimate(run, "raw", config), result]
        mask = common_mask(results)
        if mask.any():
            rms = rms_errors(result, run.truth, mask)
            summary["rms"] = {"x_m": float(rms[0]), "y_m": float(rms[1]),
                              "heading_rad": float(rms[2]),
                              "heading_deg": float(np.degrees(rms[2])), "frames": int(mask.sum())}
        fig = figure_for_run(run.truth, results, run.target_t_points,
                             f"{run.scenario or run_dir}: {estimator}")
        with atomic_path(out / "errors.png") as tmp:
            fig.savefig(tmp, dpi=110)
    write_json_atomic(out / "summary.json", summary)
    log.info("stereo %s on %s: %s", estimator, run_dir, summary.get("rms"))
    return summary


# --------------------------------------------------------------------------- KITTI
def kitti_summary(result: KittiTwoPointResult) -> dict[str, Any]:
    """Numbers of the KITTI two-point check (see :mod:`lampsam.backend.stereo_kitti`).

    Returns:
        ``frames``, ``scored``, ``pairs``; relative motion anchor -> k errors
        (``rel_rms``, ``rel_median_abs``: x m, y m, heading rad); the chained
        trajectory's final error (``final_error``: x, y m, heading rad) and path
        length; the eq. 2 check on moved points (``model_px``: median, RMS, p90,
        fraction within 1 px, count).
    """
    e = result.rel_error[result.scored]
    steps = np.linalg.norm(np.diff(result.truth[:, :2], axis=0), axis=1)
    final = pose_errors(result.estimate[-1:], result.truth[-1:])[0]
    res = np.abs(result.model_residual_px)
    return {
        "frames": len(result.truth), "scored": int(result.scored.sum()),
        "pairs": int(result.n_pairs),
        "rel_rms": np.sqrt(np.mean(e**2, axis=0)).tolist(),
        "rel_median_abs": np.median(np.abs(e), axis=0).tolist(),
        "final_error": final.tolist(), "path_length_m": float(steps.sum()),
        "model_px": {"median": float(np.median(res)), "rms": float(np.sqrt(np.mean(res**2))),
                     "p90": float(np.percentile(res, 90)),
                     "within_1px": float(np.mean(res < 1.0)), "count": int(len(res))},
    }


def plot_kitti_trajectory(ax: Any, result: KittiTwoPointResult) -> list[Any]:
    """Top view (paper axes: x forward, y left of the frame-0 rig): truth and chain."""
    artists = ax.plot(result.truth[:, 0], result.truth[:, 1], "k--", label="KITTI ground truth")
    artists += ax.plot(result.estimate[:, 0], result.estimate[:, 1], ".-", color="tab:red",
                       ms=3, label="two-point raw, chained")
    ax.set_xlabel("x forward of frame 0 (m)")
    ax.set_ylabel("y left of frame 0 (m)")
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=8)
    return artists


def plot_kitti_errors(ax: Any, result: KittiTwoPointResult) -> list[Any]:
    """Relative-motion errors (anchor -> k) per frame: x, y (m) and heading (deg, right axis)."""
    k = np.nonzero(result.scored)[0]
    e = result.rel_error[k]
    artists = ax.plot(k, e[:, 0], ".-", label="x error (m)")
    artists += ax.plot(k, e[:, 1], ".-", label="y error (m)")
    ax.set_xlabel("frame")
    ax.set_ylabel("relative motion error (m)")
    ax.grid(True, alpha=0.3)
    ax2 = ax.twinx()
    artists += ax2.plot(k, np.degrees(e[:, 2]), ".-", color="tab:green",
                        label="heading error (deg)")
    ax2.set_ylabel("heading error (deg)")
    ax.legend(loc="upper left", fontsize=8)
    ax2.legend(loc="lower right", fontsize=8)
    return artists
