"""Figures of the lamp measurement studies: centroid error by grid tilt and by cause.

Two scripts measure lamp sightings against the simulator's truth and hand their
finished figures here (this module never measures, bins or fits anything):

- ``scripts/bench/bench_lamp_model.py --figure``: RMS centroid error and the claimed
  sigma (px per axis) against the true heading's tilt from the pixel grid, one panel
  per lamp type (:func:`plot_tilt_curves`, :func:`save_tilt_figure`);
- ``scripts/lamp_bias.py --out``: the lamp centre error RMS per simulator variant and
  detector setting (:func:`plot_error_by_cause`), and the across-axis error of
  aligned rect lamps against the clipped-edge model's prediction
  (:func:`plot_phase_model`); both in :func:`save_lamp_bias_figure`.

The plot functions draw on a given matplotlib axis and return the artists; the
``save_*`` functions lay the panels out and write the PNG atomically.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from lampsam.arrays import FloatArray
from lampsam.evaluation.outputs import save_figure

if TYPE_CHECKING:
    from matplotlib.axes import Axes

#: Lamp types in the tilt figure's panels, left to right.
TILT_PANEL_TYPES = ("lamp_rect", "lamp_square", "lamp_round")


@dataclass(frozen=True)
class TiltCurve:
    """One arm's centroid error and claimed sigma per tilt bin, for one lamp type.

    Attributes:
        arm: the frontend setting's name (legend label).
        rms_px: (B,) RMS centroid error per axis, px, per tilt bin (NaN: too few
            sightings), or None when it equals an earlier arm's curve (the same
            sightings: drawn once).
        claimed_px: (B,) the sightings' claimed centroid sigma per axis, px (NaN: too
            few sightings).
    """

    arm: str
    rms_px: FloatArray | None
    claimed_px: FloatArray


def plot_tilt_curves(ax: Axes, tilt_deg: FloatArray, curves: Sequence[TiltCurve],
                     title: str) -> list[Any]:
    """Error (solid, circles) and claimed sigma (dashed) against grid tilt, log x.

    Args:
        ax: target axis.
        tilt_deg: (B,) the tilt bins' centres, deg (heading's angle from the nearest
            pixel axis).
        curves: finished results, one per arm; arm ``k`` is drawn in colour ``C{k}``.
        title: the panel's title.

    Returns:
        The lines drawn.
    """
    artists: list[Any] = []
    for k, c in enumerate(curves):
        color = f"C{k}"
        if c.rms_px is not None:
            artists += ax.semilogx(tilt_deg, c.rms_px, "o-", color=color,
                                   label=f"{c.arm}: RMS error")
        artists += ax.semilogx(tilt_deg, c.claimed_px, "--", color=color,
                               label=f"{c.arm}: claimed sigma")
    ax.set_title(title)
    ax.set_xlabel("heading's tilt from the pixel grid, deg")
    ax.grid(True, which="both", alpha=0.3)
    return artists


def save_tilt_figure(path: str | Path, tilt_deg: FloatArray,
                     panels: Mapping[str, Sequence[TiltCurve]]) -> Path:
    """The three lamp types' :func:`plot_tilt_curves` side by side (shared y), as a PNG.

    Args:
        path: output file.
        tilt_deg: (B,) tilt bin centres, deg.
        panels: per lamp type of :data:`TILT_PANEL_TYPES` the curves of every arm.

    Returns:
        The written path.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(12, 3.6), sharey=True)
    for ax, typ in zip(axes, TILT_PANEL_TYPES, strict=True):
        plot_tilt_curves(ax, tilt_deg, panels[typ], typ.replace("lamp_", "") + " lamps")
    axes[0].set_ylabel("centroid error per axis, px")
    axes[0].legend(fontsize=7)
    fig.tight_layout()
    return save_figure(fig, path, dpi=110)


@dataclass(frozen=True)
class PhasePoints:
    """Aligned rect lamps' across-axis error, measured against predicted.

    Attributes:
        label: legend label (``variant/setting``).
        marker: matplotlib marker.
        predicted_px: (N,) the clipped-edge model's prediction, px.
        measured_px: (N,) the measured across-axis error, px.
    """

    label: str
    marker: str
    predicted_px: FloatArray
    measured_px: FloatArray


def plot_error_by_cause(ax: Axes, variants: Sequence[str], settings: Sequence[str],
                        rms_px: FloatArray) -> list[Any]:
    """Grouped bars: lamp centre error RMS per simulator variant and detector setting.

    Args:
        ax: target axis.
        variants: (V,) the simulator variants (x groups).
        settings: (C,) the detector settings (bars in a group).
        rms_px: (C, V) error RMS, px (NaN: not measured).

    Returns:
        The bar containers.
    """
    width = 0.8 / max(len(settings), 1)
    artists: list[Any] = []
    for j, c in enumerate(settings):
        artists.append(ax.bar(np.arange(len(variants)) + (j - (len(settings) - 1) / 2) * width,
                              list(rms_px[j]), width, label=f"weights: {c}"))
    ax.set_xticks(np.arange(len(variants)), variants, rotation=20)
    ax.set_ylabel("lamp centre error RMS, px")
    ax.set_title("lamp observation error on the simulated lab, by cause")
    ax.legend(fontsize=8)
    return artists


def plot_phase_model(ax: Axes, points: Sequence[PhasePoints], lim_px: float = 0.3
                     ) -> list[Any]:
    """Measured against predicted across-axis error, with the identity line.

    Args:
        ax: target axis.
        points: finished results, one marker set each.
        lim_px: both axes span ``[-lim_px, lim_px]``, px (default 0.3).

    Returns:
        The marker lines drawn (not the identity line).
    """
    artists: list[Any] = []
    for p in points:
        artists += ax.plot(p.predicted_px, p.measured_px, p.marker, ms=4, alpha=0.6,
                           label=p.label)
    ax.plot([-lim_px, lim_px], [-lim_px, lim_px], "k-", lw=0.5)
    ax.set_xlim(-lim_px, lim_px)
    ax.set_ylim(-lim_px, lim_px)
    ax.set_aspect("equal")
    ax.set_xlabel("clipped-edge model, weights as read: (e(phi_r) - e(phi_l)) / 2, px")
    ax.set_ylabel("measured across-axis error, px")
    ax.set_title("rect lamps with edges along image columns")
    ax.legend(fontsize=8)
    return artists


def save_lamp_bias_figure(path: str | Path, variants: Sequence[str], settings: Sequence[str],
                          rms_px: FloatArray, points: Sequence[PhasePoints]) -> Path:
    """:func:`plot_error_by_cause` and :func:`plot_phase_model` side by side, as a PNG.

    Args:
        path: output file.
        variants, settings, rms_px: as :func:`plot_error_by_cause`.
        points: as :func:`plot_phase_model`.

    Returns:
        The written path.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(12, 4.8))
    plot_error_by_cause(ax1, variants, settings, rms_px)
    plot_phase_model(ax2, points)
    fig.tight_layout()
    return save_figure(fig, path, dpi=110)
