"""Power-law fit and figure of the scaling benchmark (lampsam.evaluation.scaling_plots)."""

from __future__ import annotations

import dataclasses
import importlib.util
import sys
from pathlib import Path

import numpy as np
import pytest

from lampsam.backend.config import AssociationConfig, MeasurementNoiseConfig, SlamConfig
from lampsam.backend.slam import frames_from_range_bearing
from lampsam.evaluation.scaling_plots import (
    ScalingFitError,
    fit_power_law,
    fit_series,
    plot_scaling,
    save_scaling_figure,
)

SCRIPT = Path(__file__).resolve().parents[1] / "scripts" / "bench" / "bench_scaling.py"


@pytest.mark.parametrize(("exponent", "coefficient"), [(2.0, 3e-7), (0.0, 1.5e-3), (1.0, 2e-5),
                                                         (-0.5, 4.0), (2.7, 1e-9)])
def test_exact_power_law_recovered(exponent: float, coefficient: float) -> None:
    n = np.array([40.0, 80.0, 160.0, 320.0, 640.0])
    a, c = fit_power_law(n, coefficient * n**exponent)
    assert a == pytest.approx(exponent, abs=1e-9)
    assert c == pytest.approx(coefficient, rel=1e-9)


def test_noisy_power_law_within_tolerance() -> None:
    """Log-normal noise of 10 % on 8 sizes spanning 2**7: the slope's standard error is
    ``0.1 / sqrt(sum (log n - mean)**2) ~ 0.02``; a 0.1 tolerance is 5 sigma."""
    rng = np.random.default_rng(7)
    n = 40.0 * 2.0 ** np.arange(8)
    for exponent in (0.0, 1.0, 2.0):
        t = 1e-6 * n**exponent * np.exp(rng.normal(0.0, 0.1, len(n)))
        a, c = fit_power_law(n, t)
        assert a == pytest.approx(exponent, abs=0.1)
        assert np.log(c) == pytest.approx(np.log(1e-6), abs=0.6)


def test_fit_is_least_squares_in_log_space() -> None:
    """Against numpy.polyfit on the logarithms (an independent implementation)."""
    rng = np.random.default_rng(11)
    n = np.array([42.0, 82.0, 162.0, 322.0, 642.0])
    t = rng.uniform(1e-4, 1e-2, len(n))
    a, c = fit_power_law(n, t)
    slope, intercept = np.polyfit(np.log(n), np.log(t), 1)
    assert a == pytest.approx(slope, abs=1e-9)
    assert np.log(c) == pytest.approx(intercept, abs=1e-9)


@pytest.mark.parametrize(("n", "t", "match"), [
    ([10.0, 20.0], [1.0], "sizes but"),
    ([10.0, 10.0], [1.0, 2.0], "two distinct"),
    ([10.0, 20.0], [1.0, 0.0], "not finite and positive"),
    ([10.0, np.nan], [1.0, 2.0], "not finite and positive"),
    ([-1.0, 20.0], [1.0, 2.0], "point 0"),
    ([], [], "two distinct"),
])
def test_bad_input_raises(n: list[float], t: list[float], match: str) -> None:
    with pytest.raises(ScalingFitError, match=match):
        fit_power_law(n, t)


def test_fit_series_uses_the_larger_sizes() -> None:
    """Flat at small n (overhead), quadratic beyond: the fit over the larger half sees 2."""
    n = np.array([640.0, 40.0, 80.0, 160.0, 320.0])  # unsorted on purpose
    t = np.where(n <= 80, 1e-3, 1e-3 * (n / 80.0) ** 2)
    s = fit_series("ekf", n, t, 1.2 * t)
    assert s.fit_min_landmarks == 160.0
    assert s.exponent == pytest.approx(2.0, abs=1e-9)
    assert np.all(np.diff(s.n_landmarks) > 0)
    np.testing.assert_allclose(s.p95_s, 1.2 * s.median_s)


def test_plot_draws_data_and_fits() -> None:
    matplotlib = pytest.importorskip("matplotlib")
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n = np.array([40.0, 80.0, 160.0, 320.0])
    series = [fit_series("ekf", n, 1e-7 * n**2, 2e-7 * n**2),
              fit_series("isam2", n, np.full(4, 2e-3), np.full(4, 3e-3))]
    fig, ax = plt.subplots()
    artists = plot_scaling(ax, series)
    assert len(artists) == 6  # median, p95, fit per series
    assert ax.get_xscale() == "log" and ax.get_yscale() == "log"
    assert "[ms]" in ax.get_ylabel()
    ekf_median = artists[0]
    np.testing.assert_allclose(ekf_median.get_ydata(), 1e-4 * n**2)  # drawn in ms
    plt.close(fig)


def test_saved_figure_names_the_clock(tmp_path: Path) -> None:
    """The PNG has the figure's size (7 x 5 in at 120 dpi) and the y axis names the clock."""
    matplotlib = pytest.importorskip("matplotlib")
    matplotlib.use("Agg")
    import matplotlib.image as mpimg
    import matplotlib.pyplot as plt

    n = np.array([40.0, 80.0, 160.0])
    series = [fit_series("ekf", n, 1e-7 * n**2, 2e-7 * n**2)]
    labels = []
    real_close = plt.close
    with pytest.MonkeyPatch.context() as mp:  # read the axis before the figure is closed
        mp.setattr(plt, "close", lambda fig: (labels.append(fig.axes[0].get_ylabel()),
                                              real_close(fig)))
        for clock in ("cpu", "wall"):
            out = save_scaling_figure(tmp_path / f"{clock}.png", series, clock)
            assert mpimg.imread(out).shape[:2] == (600, 840)
    assert labels == ["CPU (process) time per update [ms]", "wall-clock time per update [ms]"]


def _load_script() -> object:
    if str(SCRIPT.parent) not in sys.path:  # its sibling modules (corridor_world, ...)
        sys.path.insert(0, str(SCRIPT.parent))
    spec = importlib.util.spec_from_file_location("bench_scaling", SCRIPT)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules["bench_scaling"] = module
    spec.loader.exec_module(module)
    return module


def test_corridor_world_counts_and_observations_match_truth() -> None:
    """The benchmark's world: landmark count, and observations that invert to the landmarks."""
    bs = _load_script()
    cfg = bs.CorridorConfig()  # type: ignore[attr-defined]
    lms = sys.modules["corridor_world"].corridor_landmarks(10.0, cfg)
    assert lms.shape == (42, 2)
    exact = bs.CorridorConfig(sigma_range=0.0, sigma_bearing=0.0)  # type: ignore[attr-defined]
    run, lms = bs.simulate_corridor(10.0, exact, np.random.default_rng(3))  # type: ignore[attr-defined]
    rb, gt = run.range_bearing, run.groundtruth
    assert len(rb) > 0 and np.all(rb.landmark_id >= 0)
    pose = gt.interpolate(rb.t)
    x = pose[:, 0] + rb.range * np.cos(pose[:, 2] + rb.bearing)
    y = pose[:, 1] + rb.range * np.sin(pose[:, 2] + rb.bearing)
    np.testing.assert_allclose(np.column_stack([x, y]), lms[rb.landmark_id], atol=1e-9)
    assert rb.range.max() <= exact.max_range + 1e-12
    assert gt.poses[-1, 0] == pytest.approx(10.0, abs=0.05)  # drove the whole corridor


@pytest.mark.parametrize("variant", ["ekf", "isam2", "isam2-gtsam"])
def test_timed_run_on_short_corridor(variant: str) -> None:
    """One timed run over 10 m: every landmark enters the state, the end pose is close to
    the truth (0.3 m; dead reckoning on this seed is off by ~0.1 m, SLAM by ~0.05 m)."""
    bs = _load_script()
    cfg = bs.CorridorConfig()  # type: ignore[attr-defined]
    run, lms = bs.simulate_corridor(10.0, cfg, np.random.default_rng(0))  # type: ignore[attr-defined]
    config = SlamConfig(noise=MeasurementNoiseConfig(sigma_range=cfg.sigma_range,
                                                     sigma_bearing=cfg.sigma_bearing),
                        association=AssociationConfig(prune_after_steps=10**9))
    name, overrides = bs.VARIANTS[variant]  # type: ignore[attr-defined]
    config = dataclasses.replace(config, isam2=dataclasses.replace(config.isam2, **overrides))
    r = bs.time_one_run(name, run, config, 0.2)  # type: ignore[attr-defined]
    assert r["status"] == "ok"
    assert r["n_landmarks"] >= len(lms) - 4  # the last few are seen near the very end
    assert r["final_pos_err_m"] < 0.3
    assert 0 < r["cpu_median_s"] <= r["cpu_p95_s"]
    n_frames = len(frames_from_range_bearing(run.range_bearing))
    assert r["n_updates"] == pytest.approx(0.2 * n_frames, abs=1)


def test_dense_reference_is_used_and_agrees_with_the_ekf() -> None:
    """``ekf-dense`` swaps the EKF's covariance storage for the full-matrix reference (the
    patch names the module that builds the storage: it once named ``backend.ekf`` after the
    storage had moved, and the variant failed) and gives the EKF's estimate to round-off
    (end error equal to 1e-9 m on 10 m)."""
    import lampsam.backend.ekf_state as ekf_state

    bs = _load_script()
    dense = sys.modules["dense_covariance"]
    with dense.covariance_storage(True):
        assert ekf_state.LowerCovariance is dense.DenseCovariance
    assert ekf_state.LowerCovariance is not dense.DenseCovariance
    cfg = bs.CorridorConfig()  # type: ignore[attr-defined]
    run, _ = bs.simulate_corridor(10.0, cfg, np.random.default_rng(1))  # type: ignore[attr-defined]
    config = SlamConfig(association=AssociationConfig(prune_after_steps=10**9))
    r = {d: bs.time_one_run("ekf", run, config, 0.2, dense_reference=d)  # type: ignore[attr-defined]
         for d in (False, True)}
    assert r[True]["status"] == r[False]["status"] == "ok"
    assert r[True]["n_map"] == r[False]["n_map"]
    assert r[True]["final_pos_err_m"] == pytest.approx(r[False]["final_pos_err_m"], abs=1e-9)
