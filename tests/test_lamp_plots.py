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


def test_bench_tilt_curves_bin_the_sightings() -> None:
    """scripts/bench/bench_lamp_model.tilt_curves: per bin the RMS of the sightings in it
    (>= 20 of them, else NaN) and their claimed sigma; an arm with the same sightings as an
    earlier one has no error curve of its own."""
    import importlib.util
    import sys

    path = Path(__file__).resolve().parents[1] / "scripts" / "bench" / "bench_lamp_model.py"
    spec = importlib.util.spec_from_file_location("bench_lamp_model", path)
    assert spec is not None and spec.loader is not None
    bl = importlib.util.module_from_spec(spec)
    sys.modules["bench_lamp_model"] = bl
    spec.loader.exec_module(bl)

    rng = np.random.default_rng(4)
    n = 60  # 40 rect lamps at 0.1 deg tilt, 20 at 30 deg; none of the other types
    theta = np.radians(np.r_[np.full(40, 0.1), np.full(20, 30.0)]) + rng.integers(0, 4, n) * np.pi / 2
    e_px = rng.normal(0.0, 0.05, (n, 2))
    cov = np.tile(np.diag([4e-6, 4e-6]), (n, 1, 1))
    s = {"theta": theta, "type": np.array(["lamp_rect"] * n), "e_px": e_px, "cov_m": cov,
         "focal": np.full(n, 25.0)}
    t2 = dict(s, e_px=2 * e_px)
    mids, panels = bl.tilt_curves({"on": [s], "same": [s], "double": [t2]})
    assert len(mids) == len(bl.TILT_EDGES_DEG) - 1
    on, same, double = panels["lamp_rect"]
    assert on.rms_px is not None and same.rms_px is None and double.rms_px is not None
    lo, hi = 0, int(np.flatnonzero(bl.TILT_EDGES_DEG[1:] > 30.0)[0])  # the bins of 0.1 and 30 deg
    assert on.rms_px[lo] == pytest.approx(np.sqrt(np.mean(e_px[:40] ** 2)))
    assert on.rms_px[hi] == pytest.approx(np.sqrt(np.mean(e_px[40:] ** 2)))
    np.testing.assert_allclose(double.rms_px, 2 * on.rms_px)
    assert np.isnan(np.delete(on.rms_px, [lo, hi])).all()  # empty bins
    assert on.claimed_px[lo] == pytest.approx(0.002 * 25.0)  # sqrt(4e-6) x focal
    assert all(np.isnan(c.rms_px).all() for c in panels["lamp_round"] if c.rms_px is not None)
