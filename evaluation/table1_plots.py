"""Figures of the global-localization experiment (paper 2, Table 1).

The experiment (``scripts/table1_experiment.py``) writes one record per trial
and configuration; the functions here draw finished records on a given
matplotlib axis and return the artists, and :func:`save_table1_figure` lays
them out and saves the PNG.

A record is a mapping with at least these keys (the script's ``trials.json``):
``mode`` (str, the configuration), ``success`` (bool: error within 30 cm /
10 deg and localisation time within 60 s), ``error_m`` (final position error,
m), ``error_deg`` (final heading error, deg), ``total_s`` (localisation time:
robot time + compute, s), ``robot_s`` (robot time, s) and ``compute_s``
(compute time, s).
"""

from __future__ import annotations

import logging
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from lampsam.safe_io import atomic_path

if TYPE_CHECKING:
    from matplotlib.axes import Axes

log = logging.getLogger(__name__)

Record = Mapping[str, Any]

#: Colours of the configurations (``lampsam.localization.filter_config.Mode`` values).
COLORS = {
    "grid_only": "tab:grey",
    "no_ceiling": "tab:orange",
    "proposed": "tab:blue",
    "ours": "tab:green",
}

#: The failure bounds of the paper (sec. 5): position (cm), heading (deg), time (s).
FAIL_CM, FAIL_DEG, FAIL_S = 30.0, 10.0, 60.0


def _of_mode(records: Sequence[Record], mode: str) -> list[Record]:
    """The records of one configuration, in the given order."""
    return [r for r in records if r["mode"] == mode]


def success_rate(records: Sequence[Record], mode: str) -> float:
    """Percentage of successful trials of ``mode`` (NaN when it has none)."""
    r = _of_mode(records, mode)
    return 100.0 * sum(bool(x["success"]) for x in r) / len(r) if r else float("nan")


def plot_table1_errors(ax: Axes, records: Sequence[Record], modes: Sequence[str]) -> list[Any]:
    """Final position vs heading error of every trial (log axes), with the failure box.

    Trials over the time limit are drawn as crosses (failures whatever their
    error); errors below 0.3 cm / 0.03 deg are drawn at those values.

    Args:
        ax: target axis.
        records: trial records (module docstring).
        modes: configurations to draw, in legend order.

    Returns:
        The scatter artists.
    """
    artists: list[Any] = []
    for k, mode in enumerate(modes):
        r = _of_mode(records, mode)
        if not r:
            continue
        e = np.array([[float(x["error_m"]) * 100.0, float(x["error_deg"])] for x in r])
        e = np.maximum(e, [0.3, 0.03])
        slow = np.array([float(x["total_s"]) > FAIL_S for x in r])
        spread = 1.0 + 0.04 * (k - 0.5 * (len(modes) - 1))  # side by side, not on top
        c = COLORS.get(mode)
        artists.append(
            ax.scatter(e[~slow, 0] * spread, e[~slow, 1], s=14, alpha=0.7, color=c,
                       label=f"{mode} (n={len(r)})")
        )  # fmt: skip
        if slow.any():
            artists.append(ax.scatter(e[slow, 0] * spread, e[slow, 1], s=30, marker="x", color=c))
    ax.axvline(FAIL_CM, color="red", lw=1, ls="--")
    ax.axhline(FAIL_DEG, color="red", lw=1, ls="--")
    ax.fill_between([0.1, FAIL_CM], 0.01, FAIL_DEG, color="green", alpha=0.06, lw=0)
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlim(0.2, 2000)
    ax.set_ylim(0.02, 300)
    ax.set_xlabel("final position error (cm, log; below 0.3 cm drawn at 0.3)")
    ax.set_ylabel("final heading error (deg, log)")
    ax.set_title("errors; success box 30 cm / 10 deg (x: over 60 s)")
    ax.legend(fontsize=7, loc="upper left")
    return artists


def plot_table1_success(
    ax: Axes, records: Sequence[Record], modes: Sequence[str],
    paper_rates: Mapping[str, float] | None = None,
) -> list[Any]:  # fmt: skip
    """Success rate per configuration (bars), with the paper's rates as black ticks.

    Args:
        ax: target axis.
        records: trial records.
        modes: configurations, left to right (those without records are left out).
        paper_rates: configuration -> the paper's success rate (%), if any.

    Returns:
        The bar rectangles (one per drawn configuration, heights = rates in %).
    """
    names = [m for m in modes if _of_mode(records, m)]
    rates = [success_rate(records, m) for m in names]
    xs = np.arange(len(names))
    bars = ax.bar(xs, rates, color=[COLORS.get(m, "tab:blue") for m in names], alpha=0.7,
                  label="this run")  # fmt: skip
    for x, m, rate in zip(xs, names, rates, strict=True):
        ax.text(float(x), 0.5 * rate, f"{rate:.0f} %\nn={len(_of_mode(records, m))}", ha="center",
                fontsize=7)  # fmt: skip
    paper = paper_rates or {}
    px = [x for x, m in zip(xs, names, strict=True) if m in paper]
    if px:
        ax.scatter(px, [paper[m] for m in names if m in paper], marker="_", s=400,
                   color="black", label="paper 2, Table 1")  # fmt: skip
    ax.set_xticks(xs, names, fontsize=8)
    ax.set_ylim(0, 115)
    ax.set_ylabel("success rate (%)")
    ax.set_xlabel("configuration")
    ax.set_title("success (error < 30 cm / 10 deg, < 60 s)")
    ax.legend(fontsize=7, loc="lower right")
    return list(bars)


def plot_table1_times(ax: Axes, records: Sequence[Record], modes: Sequence[str]) -> list[Any]:
    """Localisation time of every trial (robot time + compute), with the 60 s limit.

    One column of points per configuration (robot-time part as a hollow marker),
    the median as a horizontal bar.

    Args:
        ax: target axis.
        records: trial records.
        modes: configurations, left to right.

    Returns:
        The scatter artists of the total times.
    """
    names = [m for m in modes if _of_mode(records, m)]
    rng = np.random.default_rng(0)  # horizontal jitter only, for legibility
    artists: list[Any] = []
    for k, m in enumerate(names):
        r = _of_mode(records, m)
        total = np.array([float(x["total_s"]) for x in r])
        robot = np.array([float(x["robot_s"]) for x in r])
        dx = k + rng.uniform(-0.18, 0.18, len(r))
        c = COLORS.get(m)
        artists.append(ax.scatter(dx, total, s=10, color=c, alpha=0.7))
        ax.scatter(dx, robot, s=10, facecolors="none", edgecolors=c, alpha=0.5, lw=0.6)
        ax.plot([k - 0.3, k + 0.3], [np.median(total)] * 2, color="black", lw=1.5)
    ax.axhline(FAIL_S, color="red", lw=1, ls="--")
    ax.set_xticks(np.arange(len(names)), names, fontsize=8)
    ax.set_ylabel("localisation time (s)")
    ax.set_title("time (hollow: robot part; bar: median)")
    return artists


def save_table1_figure(
    records: Sequence[Record], modes: Sequence[str], path: str | Path,
    paper_rates: Mapping[str, float] | None = None, dpi: int = 90,
) -> Path:  # fmt: skip
    """Errors, success rates and times side by side; saved as a PNG.

    Args:
        records: trial records.
        modes: configurations.
        path: output file.
        paper_rates: the paper's success rates (%), per configuration.
        dpi: resolution.

    Returns:
        The written path.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(14, 4.2), gridspec_kw={"width_ratios": [1.4, 1, 1]})
    plot_table1_errors(axes[0], records, modes)
    plot_table1_success(axes[1], records, modes, paper_rates)
    plot_table1_times(axes[2], records, modes)
    fig.tight_layout()
    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(out) as tmp:
        fig.savefig(tmp, dpi=dpi)
    plt.close(fig)
    log.info("Table 1 figure: %s", out)
    return out
