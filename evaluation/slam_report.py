"""SLAM reports: map + path plot against ground truth, and comparison tables.

Plot functions take a matplotlib ``ax`` and finished results
(:class:`lampsam.backend.interface.SlamResult`) and return the artists; they never
estimate. :func:`write_slam_plot` makes the figure file for ``lampsam slam``.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from lampsam.arrays import FloatArray
from lampsam.backend.interface import SlamResult
from lampsam.safe_io import atomic_path

log = logging.getLogger(__name__)


def plot_map_and_path(ax: Any, result: SlamResult, truth: Any = None,
                      true_landmarks_xy: FloatArray | None = None,
                      sigma_scale: float = 2.0) -> list[Any]:
    """Draw the estimated path and map, and the truth when given.

    Args:
        ax: a matplotlib Axes.
        result: the finished SLAM result.
        truth: ground truth with ``t`` (K,) and ``poses`` (K, 3), or None.
        true_landmarks_xy: (L, 2) true landmark positions, m, or None.
        sigma_scale: landmark ellipses are drawn at this many sigmas (default 2).

    Returns:
        The artists drawn.
    """
    from matplotlib.patches import Ellipse

    artists: list[Any] = []
    if truth is not None and len(truth.t):
        artists += ax.plot(truth.poses[:, 0], truth.poses[:, 1], "k-", lw=1.0, label="ground truth")
    if len(result.poses):
        artists += ax.plot(result.poses[:, 0], result.poses[:, 1], "-", color="tab:blue", lw=1.2,
                           label=f"{result.backend} path")
    if true_landmarks_xy is not None and len(true_landmarks_xy):
        artists.append(ax.scatter(true_landmarks_xy[:, 0], true_landmarks_xy[:, 1], marker="x",
                                  c="k", s=25, label="true landmarks"))
    colours = {"lamp": "tab:orange", "corner": "tab:green", "point2": "tab:red"}
    for kind, colour in colours.items():
        lms = [lm for lm in result.landmarks if lm.type == kind]
        if not lms:
            continue
        xy = np.array([lm.position[:2] for lm in lms])
        artists.append(ax.scatter(xy[:, 0], xy[:, 1], s=14, c=colour, label=f"{kind} ({len(lms)})"))
        for lm in lms:
            cov = np.asarray(lm.cov)[:2, :2]
            if not np.all(np.isfinite(cov)):
                continue
            vals, vecs = np.linalg.eigh(0.5 * (cov + cov.T))
            vals = np.clip(vals, 0.0, None)
            angle = float(np.degrees(np.arctan2(vecs[1, 1], vecs[0, 1])))
            e = Ellipse(tuple(lm.position[:2]), 2 * sigma_scale * np.sqrt(vals[1]),
                        2 * sigma_scale * np.sqrt(vals[0]), angle=angle, fill=False,
                        ec=colour, lw=0.6, alpha=0.7)
            ax.add_patch(e)
            artists.append(e)
            if lm.orientation is not None:
                d = 0.25 * np.array([np.cos(lm.orientation), np.sin(lm.orientation)])
                artists += ax.plot([lm.position[0] - d[0], lm.position[0] + d[0]],
                                   [lm.position[1] - d[1], lm.position[1] + d[1]],
                                   "-", color=colour, lw=1.5)
    ax.set_aspect("equal")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.legend(loc="best", fontsize=7)
    ax.set_title(f"{result.backend}: {len(result.landmarks)} landmarks, status {result.status}")
    return artists


def plot_errors(ax: Any, result: SlamResult, truth: Any) -> list[Any]:
    """Position error over time against the truth (no alignment).

    Args:
        ax: a matplotlib Axes.
        result: the finished result.
        truth: ground truth (``interpolate(t) -> (M, 3)``, ``t``).

    Returns:
        The artists drawn.
    """
    inside = (result.times >= truth.t[0]) & (result.times <= truth.t[-1])
    gt = truth.interpolate(result.times[inside])
    err = np.hypot(*(result.poses[inside, :2] - gt[:, :2]).T)
    arts = ax.plot(result.times[inside], err, lw=0.8, label=result.backend)
    ax.set_xlabel("t [s]")
    ax.set_ylabel("position error [m]")
    return arts


def write_slam_plot(path: Path, result: SlamResult, truth: Any = None,
                    true_landmarks_xy: FloatArray | None = None) -> Path:
    """Save the map + path figure (and the error curve when there is truth) as a PNG.

    Args:
        path: output file.
        result: the finished result.
        truth: ground truth or None.
        true_landmarks_xy: (L, 2) or None.

    Returns:
        The file written.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ncols = 2 if truth is not None else 1
    fig, axes = plt.subplots(1, ncols, figsize=(6 * ncols, 5), squeeze=False)
    plot_map_and_path(axes[0, 0], result, truth, true_landmarks_xy)
    if truth is not None:
        plot_errors(axes[0, 1], result, truth)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=120)
    plt.close(fig)
    return Path(path)


def markdown_table(rows: Sequence[dict[str, Any]], columns: Sequence[str]) -> str:
    """A Markdown table of result rows (floats with 4 significant digits).

    Args:
        rows: one mapping per row.
        columns: the keys to show, in order.

    Returns:
        The table text.
    """
    def fmt(v: Any) -> str:
        if isinstance(v, float):
            return f"{v:.4g}"
        return str(v)

    lines = ["| " + " | ".join(columns) + " |", "|" + "---|" * len(columns)]
    for r in rows:
        lines.append("| " + " | ".join(fmt(r.get(c, "")) for c in columns) + " |")
    return "\n".join(lines)
