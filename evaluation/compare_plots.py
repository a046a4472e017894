"""Figures of the backend comparison (paper 1, Figs. 9, 10, 12, and more).

Every ``plot_*`` function draws finished results on a given matplotlib axis and
returns the artists; :func:`make_figures` lays them out and saves PNGs.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from lampsam.angles import wrap_angle
from lampsam.arrays import FloatArray
from lampsam.evaluation.metrics import chi2_bounds

if TYPE_CHECKING:
    from matplotlib.axes import Axes

    from lampsam.evaluation.compare import JobResult

log = logging.getLogger(__name__)

COLORS = {"ekf": "tab:red", "isam2": "tab:blue", "batch": "tab:green", "truth": "black"}


def plot_paths(ax: Axes, truth_xy: FloatArray | None, paths: dict[str, FloatArray]) -> list[Any]:
    """Estimated paths against the truth (paper Fig. 10).

    Args:
        ax: target axis.
        truth_xy: (K, 2) true positions, m, or None.
        paths: backend name -> (N, 2) estimated positions, m.
    """
    artists = []
    if truth_xy is not None:
        artists += ax.plot(truth_xy[:, 0], truth_xy[:, 1], color="black", lw=2.0, alpha=0.5, label="truth")
    for name, xy in paths.items():
        artists += ax.plot(xy[:, 0], xy[:, 1], color=COLORS.get(name), lw=1.0, label=name)
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.legend(loc="best", fontsize=8)
    return artists


def covariance_ellipse(cov: FloatArray, n_sigma: float = 3.0, n: int = 40) -> FloatArray:
    """Points (n, 2) of the ``n_sigma`` ellipse of a 2x2 covariance, centred at 0."""
    vals, vecs = np.linalg.eigh(np.asarray(cov, float)[:2, :2])
    vals = np.clip(vals, 0.0, None)
    a = np.linspace(0.0, 2.0 * np.pi, n)
    circle = np.stack([np.cos(a), np.sin(a)])
    return (vecs @ (n_sigma * np.sqrt(vals)[:, None] * circle)).T


def plot_map(ax: Axes, lm_xy: FloatArray, lm_cov: FloatArray, lm_type: np.ndarray | None,
             true_xy: FloatArray | None, path_xy: FloatArray | None = None,
             title: str = "") -> list[Any]:
    """The landmark map with 3-sigma covariance ellipses (paper Fig. 9).

    Args:
        lm_xy: (L, 2) estimated landmark positions, m.
        lm_cov: (L, 2, 2) their covariances, m^2.
        lm_type: (L,) type names (lamps drawn as squares, corners as dots).
        true_xy: (T, 2) true landmark positions, or None.
        path_xy: (N, 2) the estimated path, drawn thin, or None.
    """
    artists: list[Any] = []
    if path_xy is not None:
        artists += ax.plot(path_xy[:, 0], path_xy[:, 1], color="0.6", lw=0.6)
    if true_xy is not None and len(true_xy):
        artists.append(ax.scatter(true_xy[:, 0], true_xy[:, 1], marker="+", color="black", s=18,
                                  label="true landmarks"))
    types = lm_type if lm_type is not None else np.array(["?"] * len(lm_xy))
    for kind, marker, color in (("lamp", "s", "tab:orange"), ("corner", ".", "tab:purple"),
                                ("point2", "o", "tab:blue")):
        sel = types == kind
        if np.any(sel):
            artists.append(ax.scatter(lm_xy[sel, 0], lm_xy[sel, 1], marker=marker, s=14,
                                      color=color, label=f"{kind} estimate"))
    for p, c in zip(lm_xy, lm_cov, strict=True):
        if np.all(np.isfinite(c)):
            e = covariance_ellipse(c) + p
            artists += ax.plot(e[:, 0], e[:, 1], color="tab:gray", lw=0.5)
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_title(title or "map (3-sigma ellipses)", fontsize=9)
    ax.legend(loc="best", fontsize=7)
    return artists


def plot_error_with_bounds(ax: Axes, t: FloatArray, err: FloatArray, sigma: FloatArray,
                           label: str, color: str | None = None) -> list[Any]:
    """A signed error over time with the +-3 sigma the estimator reports (paper Fig. 12)."""
    artists = ax.plot(t, err, color=color, lw=0.8, label=f"{label} error")
    artists += ax.plot(t, 3.0 * sigma, color=color, lw=0.6, ls="--", label=f"{label} ±3σ")
    artists += ax.plot(t, -3.0 * sigma, color=color, lw=0.6, ls="--")
    ax.axhline(0.0, color="black", lw=0.4)
    return artists


def plot_nees(ax: Axes, t: FloatArray, nees_avg: FloatArray, n_runs: int, label: str,
              color: str | None = None, dof: int = 3) -> list[Any]:
    """Seed-averaged NEES over time with the chi-square 95 % band of ``n_runs`` runs."""
    lo, hi = chi2_bounds(dof, n_runs)
    artists: list[Any] = list(ax.semilogy(t, np.clip(nees_avg, 1e-3, None), color=color,
                                          lw=0.8, label=label))
    artists.append(ax.axhspan(lo, hi, color="tab:green", alpha=0.08))
    artists.append(ax.axhline(dof, color="black", lw=0.5, ls=":"))
    ax.set_xlabel("time [s]")
    ax.set_ylabel(f"NEES (x, y, θ), mean of {n_runs} runs")
    return artists


def plot_error_distribution(ax: Axes, per_backend: dict[str, list[float]]) -> list[Any]:
    """Position RMS error of every seed, per backend (box + points)."""
    names = list(per_backend)
    data = [per_backend[n] for n in names]
    artists: list[Any] = [ax.boxplot(data, tick_labels=names, showfliers=False)]
    for i, vals in enumerate(data, start=1):
        artists.append(ax.scatter(np.full(len(vals), i), vals, s=10, color=COLORS.get(names[i - 1])))
    ax.set_ylabel("position RMS error [m]")
    ax.set_title("error across seeds", fontsize=9)
    return artists


def _load(results: list[JobResult]) -> dict[tuple[str, int, str], dict[str, np.ndarray]]:
    """Saved arrays of each finished job, keyed by (group, seed, backend)."""
    data: dict[tuple[str, int, str], dict[str, np.ndarray]] = {}
    for r in results:
        if r.arrays and Path(r.arrays).exists() and not r.status.startswith("failed"):
            with np.load(r.arrays, allow_pickle=False) as z:
                data[(r.job.group, r.job.seed, r.job.backend)] = {k: z[k] for k in z.files}
    return data


def make_figures(fig_dir: Path, results: list[JobResult]) -> list[Path]:
    """Draw and save every comparison figure; returns the PNG paths."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig_dir.mkdir(parents=True, exist_ok=True)
    data = _load(results)
    paths: list[Path] = []
    groups = sorted({k[0] for k in data})
    for g in groups:
        backends = [b for b in ("ekf", "isam2", "batch") if (g, 0, b) in data] or sorted(
            {k[2] for k in data if k[0] == g})
        seed0 = {b: data[(g, 0, b)] for b in backends if (g, 0, b) in data}
        if not seed0:
            continue
        any_d = next(iter(seed0.values()))
        # Paths (Fig. 10)
        fig, ax = plt.subplots(figsize=(7, 6))
        plot_paths(ax, any_d.get("gt_xy"), {b: d["poses"][:, :2] for b, d in seed0.items()})
        ax.set_title(f"{g}, seed 0: estimated paths against truth")
        paths.append(_save(fig, fig_dir / f"{g}_paths.png"))
        # Maps with ellipses (Fig. 9)
        with_map = {b: d for b, d in seed0.items() if "lm_xy" in d}
        if with_map:
            fig, axes = plt.subplots(1, len(with_map), figsize=(5.5 * len(with_map), 5), squeeze=False)
            for ax, (b, d) in zip(axes[0], with_map.items(), strict=True):
                plot_map(ax, d["lm_xy"], d["lm_cov"], d.get("lm_type"), d.get("true_lm_xy"),
                         d["poses"][:, :2], title=f"{g} / {b}: map, 3σ ellipses")
            paths.append(_save(fig, fig_dir / f"{g}_maps.png"))
        # Errors over time with 3-sigma (Fig. 12)
        with_err = {b: d for b, d in seed0.items() if "pos_err" in d}
        if with_err:
            fig, axes = plt.subplots(3, len(with_err), figsize=(5 * len(with_err), 7.5),
                                     squeeze=False, sharex="col")
            for j, (b, d) in enumerate(with_err.items()):
                t = d["t_err"]
                inside = np.isin(d["t"], t)
                covs = d["covs"][inside]
                e = d["truth"] - d["poses"][inside]
                e[:, 2] = np.degrees(wrap_angle(e[:, 2]))
                sig = np.sqrt(np.clip(np.diagonal(covs, axis1=1, axis2=2), 0, None))
                sig[:, 2] = np.degrees(sig[:, 2])
                for i, (name, unit) in enumerate((("x", "m"), ("y", "m"), ("heading", "deg"))):
                    plot_error_with_bounds(axes[i, j], t, e[:, i], sig[:, i], b, COLORS.get(b))
                    axes[i, j].set_ylabel(f"{name} error [{unit}]")
                axes[0, j].set_title(f"{g} / {b}, seed 0", fontsize=9)
                axes[-1, j].set_xlabel("time [s]")
                axes[0, j].legend(fontsize=7, loc="upper left")
            paths.append(_save(fig, fig_dir / f"{g}_errors.png"))
        # NEES over time, seed-averaged
        fig, ax = plt.subplots(figsize=(8, 4))
        drawn = False
        for b in backends:
            runs = [d for (gg, _, bb), d in data.items() if gg == g and bb == b and "nees" in d]
            if not runs:
                continue
            n = min(len(d["nees"]) for d in runs)
            avg = np.nanmean(np.array([d["nees"][:n] for d in runs]), axis=0)
            plot_nees(ax, runs[0]["t_err"][:n], avg, len(runs), b, COLORS.get(b))
            drawn = True
        if drawn:
            ax.set_title(f"{g}: pose NEES (band: 95 % chi-square bounds)")
            ax.legend(fontsize=8)
            paths.append(_save(fig, fig_dir / f"{g}_nees.png"))
        else:
            plt.close(fig)
        # Error distribution across seeds
        per_b: dict[str, list[float]] = {}
        for r in results:
            if r.job.group == g and "pos_rms_m" in r.metrics:
                per_b.setdefault(r.job.backend, []).append(r.metrics["pos_rms_m"])
        if per_b and max(len(v) for v in per_b.values()) > 1:
            fig, ax = plt.subplots(figsize=(5, 4))
            plot_error_distribution(ax, {b: per_b[b] for b in backends if b in per_b})
            paths.append(_save(fig, fig_dir / f"{g}_error_distribution.png"))
    return paths


def _save(fig: Any, path: Path) -> Path:
    """Lay out, save at 110 dpi and close a figure; returns ``path``."""
    import matplotlib.pyplot as plt

    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
