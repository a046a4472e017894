"""Per-pose error along a drive against a reference trajectory, with where the sightings
an online run left out were made (issue 15, docs/noids-offline.md "Placing the held
sightings"). Plot only: the estimates come finished."""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

import numpy as np

from lampsam.arrays import FloatArray, IntArray
from lampsam.safe_io import atomic_path


def position_errors(poses: FloatArray, reference: FloatArray) -> FloatArray:
    """(N,) position error of each pose from the reference's, m (both (N, 3))."""
    return np.asarray(np.hypot(*(poses[:, :2] - reference[:, :2]).T), float)


def write_pose_error_plot(path: Path, reference: FloatArray, runs: Mapping[str, FloatArray],
                          left_out: IntArray, title: str, ref_label: str) -> Path:
    """Two panels: each run's per-pose position error from ``reference`` along the drive
    (pose index; legend with its RMS), and a histogram of the poses of the left-out
    sightings on the same axis.

    Args:
        path: the PNG to write; reference: (N, 3) reference poses; runs: label -> (N, 3)
            poses; left_out: (D,) pose index of each left-out sighting; title: figure
            title; ref_label: what the reference is (y-axis label).

    Returns:
        The file written.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax, ax2) = plt.subplots(2, 1, figsize=(10, 6), sharex=True,
                                  gridspec_kw={"height_ratios": [3, 1]})
    k = np.arange(len(reference))
    for label, poses in runs.items():
        e = position_errors(poses, reference)
        ax.plot(k, e, lw=0.8, label=f"{label} (RMS {np.sqrt(np.mean(e**2)):.3f} m)")
    ax.set_ylabel(f"position error from\n{ref_label} [m]")
    ax.set_title(title)
    ax.legend(fontsize=8, loc="upper left")
    ax.grid(alpha=0.3)
    ax2.hist(left_out, bins=100, range=(0, len(reference)), color="0.4")
    ax2.set_ylabel("left-out\nsightings")
    ax2.set_xlabel("pose index along the drive")
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110)
    plt.close(fig)
    return Path(path)
