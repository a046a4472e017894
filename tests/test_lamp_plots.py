"""The lamp studies' figures (lampsam.evaluation.lamp_plots): what is drawn is what is passed.

The plot functions are given hand-made results; the drawn lines' and bars' data must equal
them (NaN where a bin had too few sightings), an arm whose error curve is None has only
its claimed-sigma line, and the saved PNGs have the figure's pixel size.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from lampsam.evaluation.lamp_plots import (
    TILT_PANEL_TYPES,
    PhasePoints,
    TiltCurve,
    plot_error_by_cause,
    plot_phase_model,
    plot_tilt_curves,
    save_lamp_bias_figure,
    save_tilt_figure,
)

matplotlib = pytest.importorskip("matplotlib")
matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402


def _curves(rng: np.random.Generator) -> tuple[np.ndarray, list[TiltCurve]]:
    mids = np.array([0.16, 0.35, 0.61, 0.87, 1.2])
    rms = rng.uniform(0.01, 0.1, mids.size)
    rms[2] = np.nan
    return mids, [TiltCurve("on", rms, rng.uniform(0.01, 0.1, mids.size)),
                  TiltCurve("edges", None, rng.uniform(0.01, 0.1, mids.size))]


def test_tilt_curves_draw_the_results() -> None:
    mids, curves = _curves(np.random.default_rng(1))
    fig, ax = plt.subplots()
    lines = plot_tilt_curves(ax, mids, curves, "rect lamps")
    # on: error + claimed; edges (error None: same sightings as on): claimed only
    assert [ln.get_label() for ln in lines] == ["on: RMS error", "on: claimed sigma",
                                                "edges: claimed sigma"]
    assert curves[0].rms_px is not None
    for ln, y in zip(lines, [curves[0].rms_px, curves[0].claimed_px, curves[1].claimed_px],
                     strict=True):
        np.testing.assert_array_equal(ln.get_xdata(), mids)
        np.testing.assert_array_equal(ln.get_ydata(), y)  # NaN kept (a gap, not a zero)
    assert lines[0].get_color() == lines[1].get_color() == "C0"
    assert lines[2].get_color() == "C1"  # colour follows the arm's place, drawn or not
    assert ax.get_xscale() == "log" and ax.get_title() == "rect lamps"
    plt.close(fig)


def test_error_by_cause_bars_equal_the_rms() -> None:
    rms = np.array([[0.05, 0.07, np.nan], [0.03, 0.04, 0.02]])
    fig, ax = plt.subplots()
    bars = plot_error_by_cause(ax, ["as-is", "unsat", "ideal"], ["read", "model"], rms)
    assert [b.get_label() for b in bars] == ["weights: read", "weights: model"]
    for j, container in enumerate(bars):
        np.testing.assert_array_equal([p.get_height() for p in container], rms[j])
        xs = [p.get_x() + p.get_width() / 2 for p in container]  # centres: group -/+ width/2
        np.testing.assert_allclose(xs, np.arange(3) + (j - 0.5) * 0.4)
    assert [t.get_text() for t in ax.get_xticklabels()] == ["as-is", "unsat", "ideal"]
    plt.close(fig)


def test_phase_model_points_equal_the_results() -> None:
    rng = np.random.default_rng(2)
    pts = [PhasePoints("as-is/read", "o", rng.normal(0, 0.1, 7), rng.normal(0, 0.1, 7)),
           PhasePoints("as-is/model", "x", rng.normal(0, 0.1, 5), rng.normal(0, 0.1, 5))]
    fig, ax = plt.subplots()
    lines = plot_phase_model(ax, pts)
    assert len(lines) == 2 and len(ax.get_lines()) == 3  # + the identity line
    for ln, p in zip(lines, pts, strict=True):
        np.testing.assert_array_equal(ln.get_xdata(), p.predicted_px)
        np.testing.assert_array_equal(ln.get_ydata(), p.measured_px)
        assert ln.get_marker() == p.marker and ln.get_label() == p.label
    assert ax.get_xlim() == (-0.3, 0.3) and ax.get_ylim() == (-0.3, 0.3)
    plt.close(fig)


def test_saved_figures_have_their_size(tmp_path: Path) -> None:
    import matplotlib.image as mpimg

    mids, curves = _curves(np.random.default_rng(3))
    tilt = save_tilt_figure(tmp_path / "tilt.png", mids, dict.fromkeys(TILT_PANEL_TYPES, curves))
    assert mpimg.imread(tilt).shape[:2] == (396, 1320)  # 3.6 x 12 in at 110 dpi
    pts = [PhasePoints("a/read", "o", np.zeros(3), np.ones(3) * 0.1)]
    bias = save_lamp_bias_figure(tmp_path / "bias.png", ["a", "b"], ["read"],
                                 np.array([[0.1, 0.2]]), pts)
    assert mpimg.imread(bias).shape[:2] == (528, 1320)  # 4.8 x 12 in at 110 dpi
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bias.png", "tilt.png"]  # no temp left
