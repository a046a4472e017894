"""MRCLAM adapter: parsing, barcode filtering, (v, w) -> wheel travel, and a short EKF run."""

from __future__ import annotations

import numpy as np
import pytest

from lampsam.backend.slam import errors_vs_truth, run_slam
from lampsam.datasets.logrun import read_run
from lampsam.datasets.mrclam import (
    ROBOT_IDS,
    mrclam_run,
    read_mrclam,
    wheel_travel,
    write_mrclam_run,
)
from lampsam.errors import DatasetError
from lampsam.factors.motion import accumulate_odometry
from tests.conftest import require_shared


def test_wheel_travel_inverts_the_motion_model() -> None:
    """Wheel travel from (v, w) integrates back (eq. 13) to the unicycle's rotation and distance."""
    t = np.arange(0.0, 2.0001, 0.05)
    v = np.full_like(t, 0.3)
    w = np.full_like(t, 0.4)
    t_end, d_left, d_right = wheel_travel(t, v, w, wheel_base=0.26)
    assert len(t_end) == len(t) - 1 and t_end[0] == pytest.approx(0.05)
    delta, _ = accumulate_odometry(d_left, d_right, 0.26, 1e-4, 1e-4)
    assert delta[2] == pytest.approx(0.4 * 2.0, abs=1e-9)
    # exact arc: chord = 2 (v/w) sin(w T / 2)
    chord = 2 * (0.3 / 0.4) * np.sin(0.4)
    assert np.hypot(delta[0], delta[1]) == pytest.approx(chord, rel=1e-3)


def test_malformed_line_names_file_and_line(tmp_path) -> None:
    for name, text in {"Control": "0 0 0\n0.05 0.1 0.2\n", "Groundtruth": "0 1 2 0\n",
                       "Landmark_Groundtruth": "6 1 2 0 0\n", "Barcodes": "6 5\n"}.items():
        (tmp_path / f"ds0_RS_{name}.dat").write_text(text)
    (tmp_path / "ds0_RS_Measurement.dat").write_text("1.0 5 1.0 0.1\n1.1 5 nan 0.2\n")
    with pytest.raises(DatasetError, match=r"Measurement\.dat:2: non-finite"):
        read_mrclam(tmp_path)
    (tmp_path / "ds0_RS_Measurement.dat").write_text("1.0 5 1.0 0.1\n0.5 5 1.0 0.2\n")
    with pytest.raises(DatasetError, match=r"Measurement\.dat:2: time goes backwards"):
        read_mrclam(tmp_path)


@pytest.mark.shared_data
def test_other_robots_are_dropped_and_ids_are_landmarks() -> None:
    data = read_mrclam(require_shared("mrclam_ds0"))
    assert data.n_dropped_robot > 0
    assert not np.isin(data.meas_id, ROBOT_IDS).any()
    assert set(np.unique(data.meas_id)) <= set(data.landmark_ids.tolist())
    assert len(data.landmark_ids) == 15
    # ranges agree with Vicon (README: -0.05 m mean, 0.14 m spread)
    gt = np.column_stack([np.interp(data.meas_t, data.gt_t, data.gt_poses[:, i]) for i in range(2)])
    lm = data.landmark_xy[np.searchsorted(data.landmark_ids, data.meas_id)]
    res = data.meas_range - np.hypot(*(lm - gt).T)
    assert abs(np.median(res)) < 0.1


@pytest.mark.shared_data
def test_mrclam_run_written_and_ekf_beats_dead_reckoning(tmp_path) -> None:
    """The first 150 s as a run folder; EKF with known ids is far better than odometry."""
    root = require_shared("mrclam_ds0")
    run_dir = write_mrclam_run(root, tmp_path / "mrclam", duration=150.0)
    run = read_run(run_dir)
    assert run.range_bearing is not None and len(run.range_bearing) > 100
    ekf = run_slam(run_dir, "ekf")
    from lampsam.backend.config import SlamConfig
    from lampsam.backend.ekf import EkfSlam
    from lampsam.backend.slam import drive, iter_steps, start_pose_of

    dr = drive(EkfSlam(run.rig.odometry, SlamConfig(), start_pose_of(run)),
               iter_steps(run.odometry, []))
    e_ekf, _ = errors_vs_truth(ekf, run.groundtruth)
    e_dr, _ = errors_vs_truth(dr, run.groundtruth)
    rms = lambda e: float(np.sqrt(np.mean(e**2)))  # noqa: E731
    assert rms(e_ekf) < 0.3
    assert rms(e_ekf) < 0.5 * rms(e_dr)
    assert len(ekf.landmarks) >= 10


@pytest.mark.shared_data
def test_gate_only_run_serves_unknown_ids() -> None:
    run = mrclam_run(require_shared("mrclam_ds0"), known_ids=False, duration=30.0)
    assert run.range_bearing is not None
    assert np.all(run.range_bearing.landmark_id == -1)
