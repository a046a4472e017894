"""Contact sheet of a simulated run: frames with the true lamp and corner projections.

A grid of images spread evenly over the run; on each, from ``truth/projections.csv``:
lamps as a circle at the projected centre (filled when ``fully_visible``) with the
projected long axis of rectangular lamps as a line, and visible corners as small
crosses. It is the quickest check that the renderer, the truth and the image
conventions (``docs/conventions.md``: image top = robot forward, image right =
robot left) agree.
"""

from __future__ import annotations

import logging
import math
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from lampsam.datasets.logrun import LoggedRun, ProjectionTable, read_run
from lampsam.datasets.tables import lamp_mask
from lampsam.errors import DatasetError
from lampsam.safe_io import atomic_path

if TYPE_CHECKING:
    from matplotlib.axes import Axes
    from matplotlib.figure import Figure

log = logging.getLogger(__name__)

LAMP_COLOR = "#ff3b30"
CORNER_COLOR = "#00c7ff"


def plot_frame(
    ax: Axes, image: np.ndarray, truth: ProjectionTable, title: str = "", axis_px: float = 18.0
) -> list[Any]:
    """Draw one image with its true projections.

    Args:
        ax: matplotlib axes.
        image: (H, W) uint8 grey image.
        truth: the projection rows of this image.
        title: axes title.
        axis_px: half length of the drawn lamp axis, px.

    Returns:
        The artists drawn.
    """
    h, w = image.shape
    artists: list[Any] = [ax.imshow(image, cmap="gray", vmin=0, vmax=255, interpolation="nearest")]
    is_lamp = lamp_mask(truth.types)
    corners = ~is_lamp & truth.visible
    if corners.any():
        artists.append(
            ax.scatter(
                truth.pixel[corners, 0],
                truth.pixel[corners, 1],
                s=10,
                marker="+",
                c=CORNER_COLOR,
                linewidths=0.7,
            )  # fmt: skip
        )
    for k in np.flatnonzero(is_lamp):
        col, row = truth.pixel[k]
        filled = bool(truth.fully_visible[k])
        artists.append(
            ax.scatter(
                [col],
                [row],
                s=28,
                marker="o",
                facecolors=LAMP_COLOR if filled else "none",
                edgecolors=LAMP_COLOR,
                linewidths=1.0,
            )  # fmt: skip
        )
        a = truth.angle_px[k]
        if math.isfinite(a):
            dc, dr = axis_px * math.cos(a), axis_px * math.sin(a)
            artists += ax.plot([col - dc, col + dc], [row - dr, row + dr], color=LAMP_COLOR, lw=1.2)
        label = str(int(truth.ids[k]))
        artists.append(ax.annotate(label, (col, row), xytext=(4, -4), textcoords="offset points",
                                   color=LAMP_COLOR, fontsize=6))  # fmt: skip
    ax.set_xlim(-0.5, w - 0.5)
    ax.set_ylim(h - 0.5, -0.5)
    ax.set_xticks([])
    ax.set_yticks([])
    if title:
        ax.set_title(title, fontsize=7)
    return artists


def frame_indices(n_images: int, count: int) -> np.ndarray:
    """``count`` image indices spread evenly over ``n_images`` (first and last included)."""
    if n_images <= 0:
        return np.zeros(0, dtype=np.int64)
    return np.unique(np.round(np.linspace(0, n_images - 1, min(count, n_images))).astype(np.int64))


def contact_sheet(run: LoggedRun, rows: int = 4, cols: int = 4) -> Figure:
    """A figure with ``rows x cols`` frames of a run and their true projections.

    Args:
        run: a run with images and ``truth/projections.csv`` (simulated).
        rows: grid rows.
        cols: grid columns.

    Returns:
        The figure (Agg backend; the caller saves it).

    Raises:
        DatasetError: the run has no images or no truth projections.
    """
    if run.images is None or len(run.images) == 0:
        raise DatasetError("run has no images", run.path)
    if run.projections is None:
        raise DatasetError("run has no truth/projections.csv (not simulated?)", run.path)
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    idx = frame_indices(len(run.images), rows * cols)
    fig, axes = plt.subplots(rows, cols, figsize=(3.2 * cols, 2.5 * rows + 0.4), squeeze=False)
    for ax in axes.ravel():
        ax.axis("off")
    for ax, i in zip(axes.ravel(), idx, strict=False):
        ax.axis("on")
        rows_i = run.projections.rows_of_frame(int(i))
        truth = ProjectionTable(
            frame=run.projections.frame[rows_i], t=run.projections.t[rows_i],
            ids=run.projections.ids[rows_i],
            types=tuple(run.projections.types[j] for j in rows_i),
            pixel=run.projections.pixel[rows_i], angle_px=run.projections.angle_px[rows_i],
            visible=run.projections.visible[rows_i],
            fully_visible=run.projections.fully_visible[rows_i],
        )  # fmt: skip
        title = f"#{int(i)}  t={run.images.t[i]:.1f}s"
        if run.groundtruth is not None:
            x, y, th = run.groundtruth.interpolate(np.array([run.images.t[i]]))[0]
            title += f"  ({x:.2f}, {y:.2f}, {math.degrees(th):.0f}°)"
        plot_frame(ax, run.images.load(int(i)), truth, title)
    name = run.meta.get("world", run.path.name)
    fig.suptitle(
        f"{name}: true lamp projections (red; filled = fully visible, line = long axis), "
        "corners (cyan +). Image top = robot forward, image right = robot left.",
        fontsize=9,
    )
    fig.tight_layout(rect=(0, 0, 1, 0.97))
    return fig


def write_contact_sheet(
    run_dir: str | Path, out_png: str | Path, rows: int = 4, cols: int = 4
) -> Path:
    """Read a run and save its contact sheet as a PNG.

    Args:
        run_dir: logged-run directory (simulated).
        out_png: output file.
        rows: grid rows.
        cols: grid columns.

    Returns:
        ``out_png``.
    """
    import matplotlib.pyplot as plt

    run = read_run(run_dir)
    fig = contact_sheet(run, rows, cols)
    out_png = Path(out_png)
    out_png.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(out_png) as tmp:
        fig.savefig(tmp, dpi=110)
    plt.close(fig)
    log.info("contact sheet written to %s", out_png)
    return out_png
