"""The comparison's aggregation and failure handling (no backend needed)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from lampsam.evaluation import compare as C
from lampsam.evaluation.compare_report import consistency_sentences


def _job(backend: str, seed: int, tmp: Path) -> C.Job:
    return C.Job("lab", seed, str(tmp / f"run{seed}"), backend, str(tmp / f"job{seed}{backend}"))


def _ok(job: C.Job, pos_rms: float, tmp: Path, nees: np.ndarray) -> C.JobResult:
    path = tmp / f"{job.backend}{job.seed}.npz"
    np.savez(path, nees=nees)
    return C.JobResult(job, "ok", {"pos_rms_m": pos_rms, "pos_max_m": 2 * pos_rms}, str(path))


def test_failed_jobs_are_counted_not_dropped(tmp_path: Path, rng: np.random.Generator) -> None:
    nees = np.sum(rng.normal(size=(2, 300, 3)) ** 2, axis=2)
    results = [
        _ok(_job("ekf", 0, tmp_path), 0.10, tmp_path, nees[0]),
        _ok(_job("ekf", 1, tmp_path), 0.20, tmp_path, nees[1]),
        C.JobResult(_job("batch", 0, tmp_path), "failed: indeterminate system"),
        _ok(_job("batch", 1, tmp_path), 0.04, tmp_path, nees[0]),
    ]
    rows = {r["backend"]: r for r in C.aggregate(results)}
    assert rows["ekf"]["failed"] == 0 and rows["ekf"]["pos_rms_m"] == pytest.approx(0.15)
    assert rows["ekf"]["pos_max_m"] == pytest.approx(0.40)  # max over seeds, not mean
    assert rows["batch"]["failed"] == 1 and rows["batch"]["failures"] == ["failed: indeterminate system"]
    assert rows["batch"]["pos_rms_m"] == pytest.approx(0.04)
    # consistent NEES from 2 runs: mean near 3 and not flagged
    assert abs(rows["ekf"]["nees_mean"] - 3.0) < 0.3 and not rows["ekf"]["nees_overconfident"]
    table = C.markdown_table(C.aggregate(results))
    assert "| lab | batch | 1/2 |" in table and "| lab | ekf | 2/2 |" in table
    text = "\n".join(consistency_sentences(C.aggregate(results)))
    assert "batch position RMS is 0.27x the EKF's" in text


def test_job_on_missing_run_is_a_failed_result(tmp_path: Path) -> None:
    res = C.run_job(C.Job("x", 0, str(tmp_path / "absent"), "ekf", str(tmp_path / "out")))
    assert res.status.startswith("failed") and "absent" in res.status


def test_unknown_run_and_backend_raise(tmp_path: Path) -> None:
    with pytest.raises(C.CompareError):
        C.compare(["no-such-thing"], out=tmp_path)
    with pytest.raises(C.CompareError):
        C.compare(["lab"], backends=("kalman",), out=tmp_path)


def test_map_error_associates_by_position_when_ids_are_the_backends() -> None:
    from types import SimpleNamespace

    lm = lambda i, x, y: SimpleNamespace(id=i, type="lamp", position=np.array([x, y, 2.5]))  # noqa: E731
    # Backend ids 0, 1 collide with true ids 0, 1 but name other landmarks.
    result = SimpleNamespace(landmarks=[lm(0, 5.02, 0.0), lm(1, 0.0, 0.03)])
    truth = (np.array([0, 1]), np.array(["lamp", "lamp"]), np.array([[0.0, 0.0, 2.5], [5.0, 0.0, 2.5]]))
    by_position = C._map_error(result, truth, ids_are_true=False)
    assert by_position["map_associated"] == 2
    assert by_position["map_rms_m"] == pytest.approx(np.sqrt((0.02**2 + 0.03**2) / 2))
    by_id = C._map_error(result, truth, ids_are_true=True)
    assert by_id["map_rms_m"] > 4.9  # the same ids taken at face value pair the wrong landmarks


def test_map_error_is_per_type_with_lamps_as_headline() -> None:
    from types import SimpleNamespace

    result = SimpleNamespace(landmarks=[
        SimpleNamespace(id=0, type="lamp", position=np.array([0.01, 0.0, 2.5])),
        SimpleNamespace(id=1, type="corner", position=np.array([0.0, 0.3, 2.7])),  # near the lamp only
        SimpleNamespace(id=2, type="corner", position=np.array([2.0, 0.04, 2.7])),
    ])
    truth = (np.array([0, 1000]), np.array(["lamp", "corner"]),
             np.array([[0.0, 0.0, 2.5], [2.0, 0.0, 2.7]]))
    out = C._map_error(result, truth, ids_are_true=False)
    assert out["map_type"] == "lamp" and out["map_rms_m"] == pytest.approx(0.01)
    # the corner at (0, 0.3) must not be paired with the lamp; only the true corner counts
    assert out["map_corner_associated"] == 1 and out["map_corner_rms_m"] == pytest.approx(0.04)


def test_job_passes_its_config_to_the_backend(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """``compare(config=...)`` reaches ``run_slam`` in the worker (here: a stub that fails)."""
    import lampsam.backend.slam as slam
    import lampsam.datasets.logrun as logrun
    from lampsam.backend.config import EkfConfig, SlamConfig
    from lampsam.errors import EstimationError

    seen: list[SlamConfig | None] = []

    def fake_run_slam(*args: object, config: SlamConfig | None = None, **kw: object) -> None:
        seen.append(config)
        raise EstimationError("stub")

    monkeypatch.setattr(logrun, "read_run", lambda path: object())
    monkeypatch.setattr(slam, "run_slam", fake_run_slam)
    cfg = SlamConfig(ekf=EkfConfig(corner_budget=True))
    job = C.Job("x", 0, str(tmp_path), "ekf", str(tmp_path / "out"), config=cfg)
    res = C.run_job(job)
    assert res.status == "failed: stub"
    assert seen == [cfg] and seen[0] is not None and seen[0].ekf.corner_budget
