"""Figures of the Table-1 experiment (lampsam.evaluation.table1_plots) on synthetic records."""

from __future__ import annotations

import matplotlib

matplotlib.use("Agg")

import matplotlib.pyplot as plt
import numpy as np

from lampsam.evaluation.table1_plots import (
    plot_table1_errors,
    plot_table1_success,
    plot_table1_times,
    save_table1_figure,
    success_rate,
)


def _records(rng: np.random.Generator) -> list[dict[str, object]]:
    out: list[dict[str, object]] = []
    for mode, n_ok, n in (("grid_only", 3, 5), ("proposed", 4, 4)):
        for i in range(n):
            robot = 12.0 + float(rng.uniform(0, 5))
            out.append({
                "mode": mode, "success": i < n_ok, "error_m": float(rng.uniform(0.0, 0.2)),
                "error_deg": float(rng.uniform(0.0, 5.0)), "robot_s": robot,
                "compute_s": 1.0, "total_s": robot + (70.0 if i >= n_ok else 1.0),
            })  # fmt: skip
    return out


def test_success_bars_equal_the_rates() -> None:
    recs = _records(np.random.default_rng(3))
    assert success_rate(recs, "grid_only") == 60.0
    assert np.isnan(success_rate(recs, "ours"))
    fig, ax = plt.subplots()
    bars = plot_table1_success(ax, recs, ["grid_only", "ours", "proposed"], {"proposed": 98.0})
    assert [b.get_height() for b in bars] == [60.0, 100.0]  # "ours" has no records: left out
    plt.close(fig)


def test_error_and_time_panels_draw_every_trial(tmp_path) -> None:
    recs = _records(np.random.default_rng(4))
    fig, (a, b) = plt.subplots(1, 2)
    pts = plot_table1_errors(a, recs, ["grid_only", "proposed"])
    # grid_only: 3 in time + 2 over 60 s (crosses); proposed: 4
    assert sorted(len(p.get_offsets()) for p in pts) == [2, 3, 4]
    times = plot_table1_times(b, recs, ["grid_only", "proposed"])
    drawn = np.concatenate([np.asarray(p.get_offsets())[:, 1] for p in times])
    np.testing.assert_allclose(np.sort(drawn), np.sort([float(r["total_s"]) for r in recs]))
    plt.close(fig)
    path = save_table1_figure(recs, ["grid_only", "proposed"], tmp_path / "t1.png")
    assert path.stat().st_size > 1000
