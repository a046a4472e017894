"""Figures of the backend comparison (paper 1, Figs. 9, 10, 12, and more).

Every ``plot_*`` function draws finished results on a given matplotlib axis and
returns the artists; :func:`make_figures` lays them out, writes a one-line caption
under each (what to look for) and saves PNGs. The order of the returned figures is
the order of the report: errors over time and distance first.

Conventions: one colour per backend everywhere (:data:`COLORS`), the truth in black,
bands of chi-square bounds in grey (never a backend's colour); the same axis limits
for every backend of a run, so panels compare by eye.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from lampsam.angles import wrap_angle
from lampsam.arrays import FloatArray
from lampsam.evaluation.metrics import chi2_bounds
from lampsam.safe_io import atomic_path

if TYPE_CHECKING:
    from matplotlib.axes import Axes
    from matplotlib.figure import Figure

    from lampsam.evaluation.compare import JobResult

log = logging.getLogger(__name__)

COLORS = {"ekf": "tab:red", "isam2": "tab:blue", "batch": "tab:green", "truth": "black"}
BAND_COLOR = "0.55"
"""Chi-square bands: grey, so no band takes a backend's colour."""
MAX_ELLIPSE_M = 0.3
"""Largest 3-sigma semi-major axis drawn on a map, m: larger ellipses (badly observed
corners) would cover their neighbours (the lab's tile corners are 0.6 m apart)."""
LANDMARK_STYLE = {  # kind -> (marker, estimate colour)
    "lamp": ("s", "tab:orange"),
    "corner": (".", "tab:purple"),
    "point2": ("o", "tab:cyan"),
}


@dataclass(frozen=True)
class SavedFigure:
    """A written figure and the one line that says what to look for in it."""

    path: Path
    caption: str


def _label(n: int, word: str) -> str:
    """``"1 run"``, ``"3 runs"``."""
    return f"{n} {word}" if n == 1 else f"{n} {word}s"


def distance_travelled(xy: FloatArray) -> FloatArray:
    """Cumulative path length (N,) of positions (N, 2), m, starting at 0."""
    xy = np.asarray(xy, float)
    if len(xy) == 0:
        return np.zeros(0)
    return np.r_[0.0, np.cumsum(np.hypot(*np.diff(xy, axis=0).T))]


def major_sigma(covs: FloatArray) -> FloatArray:
    """Standard deviation along the major axis (N,) of (N, >=2, >=2) position covariances."""
    c = np.asarray(covs, float)[:, :2, :2]
    ok = np.all(np.isfinite(c), axis=(1, 2))
    out = np.full(len(c), np.nan)
    if np.any(ok):
        out[ok] = np.sqrt(np.clip(np.linalg.eigvalsh(c[ok])[:, -1], 0.0, None))
    return out


def covariance_ellipse(cov: FloatArray, n_sigma: float = 3.0, n: int = 40) -> FloatArray:
    """Points (n, 2) of the ``n_sigma`` ellipse of a 2x2 covariance, centred at 0."""
    vals, vecs = np.linalg.eigh(np.asarray(cov, float)[:2, :2])
    vals = np.clip(vals, 0.0, None)
    a = np.linspace(0.0, 2.0 * np.pi, n)
    circle = np.stack([np.cos(a), np.sin(a)])
    return (vecs @ (n_sigma * np.sqrt(vals)[:, None] * circle)).T


def common_limits(*xy: FloatArray | None, margin: float = 0.5) -> tuple[tuple[float, float],
                                                                      tuple[float, float]]:
    """Axis limits ``((x0, x1), (y0, y1))`` in m holding every finite point given, plus a margin."""
    pts = [np.asarray(p, float)[:, :2] for p in xy if p is not None and len(p)]
    allp = np.concatenate(pts) if pts else np.zeros((1, 2))
    allp = allp[np.all(np.isfinite(allp), axis=1)]
    if len(allp) == 0:
        allp = np.zeros((1, 2))
    lo, hi = allp.min(axis=0) - margin, allp.max(axis=0) + margin
    return (float(lo[0]), float(hi[0])), (float(lo[1]), float(hi[1]))


# --------------------------------------------------------------------------- errors
def plot_error_norms(ax: Axes, x: FloatArray, err: FloatArray, bound: FloatArray, label: str,
                     color: str | None) -> list[Any]:
    """An error magnitude against time or distance, with the estimator's 3-sigma bound (dashed).

    Args:
        x: (N,) abscissa (time, s, or distance travelled, m).
        err: (N,) error magnitude (position, m, or |heading|, deg).
        bound: (N,) the 3-sigma bound the estimator reports, same unit.
    """
    z = 3 if label == "ekf" else 2  # the filter over the two smoothers, which coincide
    artists = ax.plot(x, err, color=color, lw=0.9, label=f"{label}", zorder=z)
    artists += ax.plot(x, bound, color=color, lw=0.7, ls="--", alpha=0.8, zorder=z)
    return artists


def plot_error_with_bounds(ax: Axes, t: FloatArray, err: FloatArray, sigma: FloatArray,
                           label: str, color: str | None = None) -> list[Any]:
    """A signed error over time inside the shaded +-3 sigma band the estimator reports (paper Fig. 12)."""
    artists: list[Any] = [ax.fill_between(t, -3.0 * sigma, 3.0 * sigma, color=color, alpha=0.18,
                                          lw=0, label=f"{label} ±3σ")]
    artists += ax.plot(t, err, color=color, lw=0.8, label=f"{label} error")
    artists.append(ax.axhline(0.0, color="black", lw=0.4))
    return artists


def plot_nees(ax: Axes, t: FloatArray, nees_avg: FloatArray, n_runs: int, label: str,
              color: str | None = None, dof: int = 3, band: bool = True) -> list[Any]:
    """Seed-averaged NEES over time (log scale), with the grey chi-square 95 % band of ``n_runs`` runs."""
    artists: list[Any] = []
    if band:
        lo, hi = chi2_bounds(dof, n_runs)
        artists.append(ax.axhspan(lo, hi, color=BAND_COLOR, alpha=0.2, lw=0,
                                  label=f"95 % χ² band, {_label(n_runs, 'run')}"))
        artists.append(ax.axhline(dof, color="black", lw=0.6, ls=":", label=f"ideal ({dof})"))
    artists += ax.semilogy(t, np.clip(nees_avg, 1e-2, None), color=color, lw=0.9, label=label)
    ax.set_xlabel("time [s]")
    ax.set_ylabel("NEES over (x, y, θ) [–]" if n_runs == 1
                  else f"NEES over (x, y, θ), mean of {n_runs} runs [–]")
    return artists


def plot_error_distribution(ax: Axes, per_backend: dict[str, list[float]]) -> list[Any]:
    """Position RMS error of every seed, per backend (box + points)."""
    names = list(per_backend)
    data = [per_backend[n] for n in names]
    artists: list[Any] = [ax.boxplot(data, tick_labels=names, showfliers=False)]
    for i, vals in enumerate(data, start=1):
        artists.append(ax.scatter(np.full(len(vals), i), vals, s=10, color=COLORS.get(names[i - 1])))
    ax.set_ylabel("position RMS error [m]")
    ax.set_title("position RMS error across seeds", fontsize=9)
    return artists


# --------------------------------------------------------------------------- paths
def plot_error_path(ax: Axes, xy: FloatArray, err: FloatArray, norm: Any, cmap: str = "viridis",
                    lw: float = 2.0) -> Any:
    """A path (N, 2), m, drawn as segments coloured by its position error (N,) under ``norm``."""
    from matplotlib.collections import LineCollection

    seg = np.stack([xy[:-1], xy[1:]], axis=1)
    lc = LineCollection(list(seg), cmap=cmap, norm=norm, linewidths=lw, zorder=3)
    lc.set_array(0.5 * (err[:-1] + err[1:]))
    ax.add_collection(lc)
    return lc


def plot_paths(ax: Axes, truth_xy: FloatArray | None, xy: FloatArray, err: FloatArray, norm: Any,
               zoom_at: FloatArray | None = None, zoom_half_m: float = 0.1,
               truth_at_err: FloatArray | None = None,
               limits: tuple[tuple[float, float], tuple[float, float]] | None = None) -> Any:
    """One backend's path coloured by position error, the truth in black, and a zoomed inset.

    In the inset, thin grey segments join each estimate to the true position at the
    same time: the error vector, so an error along the path shows as well as across.

    Args:
        truth_xy: (K, 2) true positions, m, or None.
        xy: (N, 2) estimated positions, m, at the error samples.
        err: (N,) position errors (any unit ``norm`` maps).
        norm: the matplotlib colour normalisation (shared by the backends compared).
        zoom_at: (2,) centre of the inset, m (None: no inset).
        zoom_half_m: half width of the inset's square window, m.
        truth_at_err: (N, 2) true positions at the error samples, m (error vectors), or None.
        limits: ``((x0, x1), (y0, y1))`` of the main axis, m.

    Returns:
        The coloured line collection (for a colour bar).
    """
    if truth_xy is not None:
        ax.plot(truth_xy[:, 0], truth_xy[:, 1], color="black", lw=0.8, label="truth", zorder=2)
    lc = plot_error_path(ax, xy, err, norm)
    if limits is not None:
        ax.set_xlim(*limits[0])
        ax.set_ylim(*limits[1])
    ax.set_aspect("equal", adjustable="box")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    if zoom_at is not None:
        from matplotlib.collections import LineCollection

        ins = ax.inset_axes(_inset_bounds(ax, xy, limits))
        if truth_xy is not None:
            ins.plot(truth_xy[:, 0], truth_xy[:, 1], color="black", lw=1.0, zorder=2)
        if truth_at_err is not None:
            ins.add_collection(LineCollection(list(np.stack([truth_at_err, xy], axis=1)),
                                              colors="0.6", linewidths=0.5, zorder=1))
        plot_error_path(ins, xy, err, norm, lw=2.5)
        ins.set_xlim(zoom_at[0] - zoom_half_m, zoom_at[0] + zoom_half_m)
        ins.set_ylim(zoom_at[1] - zoom_half_m, zoom_at[1] + zoom_half_m)
        ins.set_aspect("equal", adjustable="box")
        ins.tick_params(labelsize=6)
        ax.indicate_inset_zoom(ins, edgecolor="0.3")
    return lc


def _inset_bounds(ax: Axes, xy: FloatArray,
                  limits: tuple[tuple[float, float], tuple[float, float]] | None
                  ) -> tuple[float, float, float, float]:
    """Inset rectangle (axes fraction) in the corner that covers the fewest path points."""
    if limits is None:
        (x0, x1), (y0, y1) = ax.get_xlim(), ax.get_ylim()
    else:
        (x0, x1), (y0, y1) = limits
    u = (xy[:, 0] - x0) / max(x1 - x0, 1e-9)
    v = (xy[:, 1] - y0) / max(y1 - y0, 1e-9)
    size = 0.42
    best, best_n = (0.56, 0.56, size, size), len(xy) + 1
    for cx in (0.02, 1.0 - size - 0.02):
        for cy in (0.02, 1.0 - size - 0.02):
            n = int(np.sum((u > cx - 0.05) & (u < cx + size + 0.05)
                           & (v > cy - 0.05) & (v < cy + size + 0.05)))
            if n < best_n:
                best, best_n = (cx, cy, size, size), n
    return best


# --------------------------------------------------------------------------- maps
def plot_map(ax: Axes, lm_xy: FloatArray, lm_cov: FloatArray, lm_type: np.ndarray | None,
             true_xy: FloatArray | None, true_type: np.ndarray | None = None,
             path_xy: FloatArray | None = None, title: str = "",
             limits: tuple[tuple[float, float], tuple[float, float]] | None = None,
             max_ellipse_m: float = MAX_ELLIPSE_M) -> dict[str, int]:
    """The landmark map with 3-sigma ellipses where they are readable (paper Fig. 9).

    True lamps are open black squares, true corners small grey crosses; estimated
    lamps orange squares, estimated corners purple dots. An ellipse is drawn only
    if its 3-sigma semi-major axis is at most ``max_ellipse_m``; the numbers not
    drawn and outside the limits are written in the corner of the panel.

    Args:
        lm_xy: (L, 2) estimated landmark positions, m.
        lm_cov: (L, 2, 2) their covariances, m^2.
        lm_type: (L,) type names (``lamp``, ``corner``, ``point2``).
        true_xy: (T, 2) true landmark positions, m, or None.
        true_type: (T,) their types, or None (all drawn as crosses).
        path_xy: (N, 2) the estimated path, drawn thin, or None.
        limits: ``((x0, x1), (y0, y1))`` in m (the same for every backend).
        max_ellipse_m: largest 3-sigma semi-major axis drawn, m.

    Returns:
        ``{"drawn": ellipses drawn, "too_large": not drawn, "outside": estimates outside the limits}``.
    """
    if path_xy is not None:
        ax.plot(path_xy[:, 0], path_xy[:, 1], color="0.6", lw=0.8, label="estimated path")
    if true_xy is not None and len(true_xy):
        ttype = true_type if true_type is not None else np.array(["?"] * len(true_xy))
        lamp = ttype == "lamp"
        if np.any(lamp):
            ax.scatter(true_xy[lamp, 0], true_xy[lamp, 1], marker="s", s=60, facecolors="none",
                       edgecolors="black", lw=1.0, label="true lamp")
        if np.any(~lamp):
            ax.scatter(true_xy[~lamp, 0], true_xy[~lamp, 1], marker="+", s=16, color="0.45",
                       lw=0.8, label="true corner" if true_type is not None else "true landmark")
    types = lm_type if lm_type is not None else np.array(["point2"] * len(lm_xy))
    for kind, (marker, color) in LANDMARK_STYLE.items():
        sel = types == kind
        if np.any(sel):
            ax.scatter(lm_xy[sel, 0], lm_xy[sel, 1], marker=marker, s=22 if kind == "lamp" else 18,
                       color=color, label=f"estimated {kind}", zorder=4)
    semi = 3.0 * major_sigma(lm_cov) if len(lm_cov) else np.zeros(0)
    readable = np.isfinite(semi) & (semi <= max_ellipse_m)
    for p, c, kind in zip(lm_xy[readable], lm_cov[readable], types[readable], strict=True):
        e = covariance_ellipse(c) + p
        ax.plot(e[:, 0], e[:, 1], color=LANDMARK_STYLE.get(kind, ("", "0.4"))[1], lw=0.6, alpha=0.8)
    outside = 0
    if limits is not None:
        ax.set_xlim(*limits[0])
        ax.set_ylim(*limits[1])
        (x0, x1), (y0, y1) = limits
        outside = int(np.sum((lm_xy[:, 0] < x0) | (lm_xy[:, 0] > x1)
                             | (lm_xy[:, 1] < y0) | (lm_xy[:, 1] > y1)))
    ax.set_aspect("equal", adjustable="box")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    counts = {"drawn": int(readable.sum()), "too_large": int(len(semi) - readable.sum()),
              "outside": outside}
    note = (f"{len(lm_xy)} landmarks; ellipses drawn: {counts['drawn']}, "
            f"not drawn (3σ > {100 * max_ellipse_m:.0f} cm): {counts['too_large']}")
    if outside:
        note += f"; {outside} outside the frame"
    ax.set_title(f"{title or 'map, 3σ ellipses'}\n{note}", fontsize=8)
    return counts


# --------------------------------------------------------------------------- layout
def _load(results: list[JobResult]) -> dict[tuple[str, int, str], dict[str, np.ndarray]]:
    """Saved arrays of each finished job, keyed by (group, seed, backend)."""
    data: dict[tuple[str, int, str], dict[str, np.ndarray]] = {}
    for r in results:
        if r.arrays and Path(r.arrays).exists() and not r.status.startswith("failed"):
            with np.load(r.arrays, allow_pickle=False) as z:
                data[(r.job.group, r.job.seed, r.job.backend)] = {k: z[k] for k in z.files}
    return data


def _errors_of(d: dict[str, np.ndarray]) -> dict[str, FloatArray]:
    """Signed errors, sigmas, magnitudes and distance travelled at one job's error samples.

    Returns ``t`` (s), ``dist`` (m), ``e`` (N, 3) truth - estimate (m, m, deg),
    ``sig`` (N, 3) standard deviations (m, m, deg), ``pos`` (m), ``pos3s`` (3-sigma
    along the major axis, m), ``head`` (|heading error|, deg), ``head3s`` (deg), ``xy``
    (estimate) and ``truth_xy`` (truth), (N, 2) m.
    """
    t = d["t_err"]
    inside = np.isin(d["t"], t)
    covs = d["covs"][inside]
    e = d["truth"] - d["poses"][inside]
    e[:, 2] = np.degrees(wrap_angle(e[:, 2]))
    sig = np.sqrt(np.clip(np.diagonal(covs, axis1=1, axis2=2), 0, None))
    sig[:, 2] = np.degrees(sig[:, 2])
    return {"t": t, "dist": distance_travelled(d["truth"][:, :2]), "e": e, "sig": sig,
            "pos": np.hypot(e[:, 0], e[:, 1]), "pos3s": 3.0 * major_sigma(covs),
            "head": np.abs(e[:, 2]), "head3s": 3.0 * sig[:, 2], "xy": d["poses"][inside][:, :2],
            "truth_xy": d["truth"][:, :2]}


def make_figures(fig_dir: Path, results: list[JobResult]) -> list[SavedFigure]:
    """Draw and save every comparison figure; returns them in report order, with captions."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig_dir.mkdir(parents=True, exist_ok=True)
    data = _load(results)
    saved: list[SavedFigure] = []
    for g in sorted({k[0] for k in data}):
        backends = [b for b in ("ekf", "isam2", "batch") if (g, 0, b) in data] or sorted(
            {k[2] for k in data if k[0] == g})
        seed0 = {b: data[(g, 0, b)] for b in backends if (g, 0, b) in data}
        if not seed0:
            continue
        errs = {b: _errors_of(d) for b, d in seed0.items() if "pos_err" in d}
        if errs:
            saved.append(_fig_error_norms(plt, fig_dir, g, errs))
            saved.append(_fig_signed_errors(plt, fig_dir, g, errs))
            saved.append(_fig_paths(plt, fig_dir, g, seed0, errs))
        with_map = {b: d for b, d in seed0.items() if "lm_xy" in d}
        if with_map:
            saved.append(_fig_maps(plt, fig_dir, g, with_map))
        nees = _fig_nees(plt, fig_dir, g, backends, data)
        if nees is not None:
            saved.append(nees)
        per_b: dict[str, list[float]] = {}
        for r in results:
            if r.job.group == g and "pos_rms_m" in r.metrics:
                per_b.setdefault(r.job.backend, []).append(r.metrics["pos_rms_m"])
        if per_b and max(len(v) for v in per_b.values()) > 1:
            fig, ax = plt.subplots(figsize=(5, 4))
            plot_error_distribution(ax, {b: per_b[b] for b in backends if b in per_b})
            saved.append(_save(fig, fig_dir / f"{g}_error_distribution.png",
                               "Spread of the position RMS error over Monte Carlo seeds: a lower, "
                               "tighter box is a more accurate and more repeatable backend."))
    return saved


def _fig_error_norms(plt: Any, fig_dir: Path, g: str, errs: dict[str, dict[str, FloatArray]]
                     ) -> SavedFigure:
    """Position and heading error magnitudes against time and distance, all backends."""
    fig, axes = plt.subplots(2, 2, figsize=(11, 6.5), sharey="row")
    for b, e in errs.items():
        for j, x in enumerate((e["t"], e["dist"])):
            plot_error_norms(axes[0, j], x, e["pos"] * 100, e["pos3s"] * 100, b, COLORS.get(b))
            plot_error_norms(axes[1, j], x, e["head"], e["head3s"], b, COLORS.get(b))
    for j, xl in enumerate(("time [s]", "distance travelled [m]")):
        axes[1, j].set_xlabel(xl)
        for i in range(2):
            axes[i, j].set_ylim(bottom=0)
            axes[i, j].grid(alpha=0.3)
    axes[0, 0].set_ylabel("position error [cm]")
    axes[1, 0].set_ylabel("|heading error| [deg]")
    axes[0, 0].plot([], [], color="0.3", ls="--", lw=0.7, label="3σ it reports (dashed)")
    axes[0, 0].legend(fontsize=8, loc="upper left")
    fig.suptitle(f"{g}, seed 0: error of each backend, without alignment (known start pose)",
                 fontsize=10)
    return _save(fig, fig_dir / f"{g}_errors_time_distance.png",
                 "Solid: error against truth; dashed: the 3σ the backend reports (position: along "
                 "its major axis). Look for the lowest solid line, and for solid lines that cross "
                 "their own dashed line (overconfidence).")


def _fig_signed_errors(plt: Any, fig_dir: Path, g: str, errs: dict[str, dict[str, FloatArray]]
                       ) -> SavedFigure:
    """x, y, heading errors over time inside each backend's +-3 sigma band (paper Fig. 12)."""
    fig, axes = plt.subplots(3, len(errs), figsize=(4.6 * len(errs), 7.5), squeeze=False,
                             sharex=True, sharey="row")
    for j, (b, e) in enumerate(errs.items()):
        scale = np.array([100.0, 100.0, 1.0])
        for i, (name, unit) in enumerate((("x", "cm"), ("y", "cm"), ("heading", "deg"))):
            plot_error_with_bounds(axes[i, j], e["t"], e["e"][:, i] * scale[i],
                                   e["sig"][:, i] * scale[i], b, COLORS.get(b))
            axes[i, 0].set_ylabel(f"{name} error [{unit}]")
        axes[0, j].set_title(f"{b}", fontsize=10, color=COLORS.get(b))
        axes[-1, j].set_xlabel("time [s]")
        axes[0, j].legend(fontsize=7, loc="upper left")
    fig.suptitle(f"{g}, seed 0: signed error (truth − estimate) and ±3σ per axis", fontsize=10)
    return _save(fig, fig_dir / f"{g}_errors_xyh.png",
                 "Each error should stay inside its shaded ±3σ band; a band much wider than the "
                 "error is underconfident. Smoother bands saw-tooth: narrow at keyframes, "
                 "widening with odometry between them.")


def _fig_paths(plt: Any, fig_dir: Path, g: str, seed0: dict[str, dict[str, np.ndarray]],
               errs: dict[str, dict[str, FloatArray]]) -> SavedFigure:
    """One panel per backend: path coloured by position error, same limits, zoom on the worst point."""
    from matplotlib.colors import Normalize

    any_d = next(iter(seed0.values()))
    truth = any_d.get("gt_xy")
    # the room (true landmarks) when known: a straight path alone gives a sliver of a plot
    limits = common_limits(any_d.get("true_lm_xy"), truth, *[e["xy"] for e in errs.values()],
                           margin=0.3)
    vmax = max(float(np.nanmax(e["pos"])) for e in errs.values()) * 100
    norm = Normalize(0.0, max(vmax, 1e-3))
    worst_b = max(errs, key=lambda b: float(np.nanmax(errs[b]["pos"])))
    k = int(np.nanargmax(errs[worst_b]["pos"]))
    centre = errs[worst_b]["xy"][k]
    half = float(np.clip(2.0 * np.nanmax(errs[worst_b]["pos"]), 0.02, 1.0))
    fig, axes = plt.subplots(1, len(errs), figsize=(5.2 * len(errs), 4.6), squeeze=False)
    lc = None
    for ax, (b, e) in zip(axes[0], errs.items(), strict=True):
        lc = plot_paths(ax, truth, e["xy"], e["pos"] * 100, norm, zoom_at=centre, zoom_half_m=half,
                        truth_at_err=e["truth_xy"], limits=limits)
        ax.set_title(f"{b}: RMS {100 * np.sqrt(np.mean(e['pos'] ** 2)):.1f} cm, "
                     f"max {100 * np.nanmax(e['pos']):.1f} cm", fontsize=9, color=COLORS.get(b))
    fig.tight_layout(rect=(0, 0.06, 0.93, 0.95))
    if lc is not None:
        cax = fig.add_axes((0.94, 0.15, 0.012, 0.7))
        fig.colorbar(lc, cax=cax, label="position error [cm]")
    fig.suptitle(f"{g}, seed 0: estimated path coloured by position error; truth in black",
                 fontsize=10)
    return _save(fig, fig_dir / f"{g}_paths.png",
                 f"Same colour scale and limits for every backend; insets: the {200 * half:.0f} cm "
                 f"square around the worst point ({worst_b}, t = {errs[worst_b]['t'][k]:.1f} s), "
                 "grey ticks join estimate and truth at equal times. Look for where the colour "
                 "turns yellow.",
                 tight=False)


def _fig_maps(plt: Any, fig_dir: Path, g: str, with_map: dict[str, dict[str, np.ndarray]]
              ) -> SavedFigure:
    """One map per backend at common limits (true landmarks and the true path)."""
    any_d = next(iter(with_map.values()))
    limits = common_limits(any_d.get("true_lm_xy"), any_d.get("gt_xy"), margin=0.6)
    fig, axes = plt.subplots(1, len(with_map), figsize=(5.4 * len(with_map), 4.9), squeeze=False)
    hidden = []
    for ax, (b, d) in zip(axes[0], with_map.items(), strict=True):
        c = plot_map(ax, d["lm_xy"], d["lm_cov"], d.get("lm_type"), d.get("true_lm_xy"),
                     d.get("true_lm_type"), d["poses"][:, :2], title=f"{b}", limits=limits)
        hidden.append(f"{b} {c['too_large']}")
    handles, labels = axes[0, 0].get_legend_handles_labels()
    for ax in axes[0, 1:]:
        for h, lab in zip(*ax.get_legend_handles_labels(), strict=True):
            if lab not in labels:
                handles.append(h)
                labels.append(lab)
    fig.legend(handles, labels, loc="lower center", ncol=len(labels), fontsize=8, frameon=False,
               bbox_to_anchor=(0.5, 0.04))
    fig.suptitle(f"{g}, seed 0: landmark maps with 3σ ellipses (only those ≤ "
                 f"{100 * MAX_ELLIPSE_M:.0f} cm)", fontsize=10)
    fig.tight_layout(rect=(0, 0.1, 1, 0.95))
    return _save(fig, fig_dir / f"{g}_maps.png",
                 "Estimates should sit on their true markers, inside their ellipses; ellipses "
                 f"larger than {100 * MAX_ELLIPSE_M:.0f} cm (badly observed corners) are not drawn "
                 f"({', '.join(hidden)}).", tight=False)


def _fig_nees(plt: Any, fig_dir: Path, g: str, backends: list[str],
              data: dict[tuple[str, int, str], dict[str, np.ndarray]]) -> SavedFigure | None:
    """Seed-averaged NEES of every backend against the chi-square band."""
    fig, ax = plt.subplots(figsize=(9, 4))
    n_runs = 0
    for b in backends:
        runs = [d for (gg, _, bb), d in data.items() if gg == g and bb == b and "nees" in d]
        if not runs:
            continue
        n = min(len(d["nees"]) for d in runs)
        avg = np.nanmean(np.array([d["nees"][:n] for d in runs]), axis=0)
        plot_nees(ax, runs[0]["t_err"][:n], avg, len(runs), b, COLORS.get(b), band=n_runs == 0)
        n_runs = len(runs)
    if n_runs == 0:
        plt.close(fig)
        return None
    ax.legend(fontsize=8, loc="lower right", ncol=2)
    ax.grid(alpha=0.3, which="major")
    ax.set_title(f"{g}: pose NEES{'' if n_runs == 1 else f', mean of {n_runs} seeds'}",
                 fontsize=10)
    return _save(fig, fig_dir / f"{g}_nees.png",
                 "A consistent backend stays inside the grey 95 % band around the ideal 3; above it "
                 "the backend is overconfident (reports less uncertainty than its error), below it "
                 "underconfident.")


def _save(fig: Figure, path: Path, caption: str, tight: bool = True) -> SavedFigure:
    """Write the caption under the figure, save it at 110 dpi and close it."""
    import matplotlib.pyplot as plt

    if tight:
        fig.tight_layout(rect=(0, 0.05, 1, 1))
    fig.text(0.5, 0.005, caption, ha="center", va="bottom", fontsize=8, wrap=True,
             style="italic")
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110)
    plt.close(fig)
    return SavedFigure(path, caption)
