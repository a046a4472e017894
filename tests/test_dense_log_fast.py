"""The known-id fast path over graph logs (:mod:`lampsam.backend.dense_log`) gives the
general path's numbers (issue 15).

Each case runs the general path (:class:`~lampsam.backend.graph.Isam2Slam` /
:class:`~lampsam.backend.graph.BatchSlam` stepped by :func:`drive`) and
:func:`run_graph_log` (the fast path) on the same log and compares poses, landmarks
and their covariances exactly: the fast path is a pure speed-up.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from lampsam.backend.config import SlamConfig
from lampsam.backend.dense_log import plan_log, run_known_ids, single_sample_relative
from lampsam.backend.graph_log import graph_log_steps, run_graph_log
from lampsam.backend.interface import SlamResult
from lampsam.backend.odometry import Pose2Motion
from lampsam.backend.slam import drive, make_backend
from lampsam.datasets.graph_text import GraphLog, Sighting, read_graph_text
from lampsam.datasets.landmark_log_sim import LandmarkLogSpec, write_landmark_log
from lampsam.datasets.odometry import Pose2OdometryLog, Pose2OdometryModel

SPEC = LandmarkLogSpec(n_poses=160, n_landmarks=40, extent=40.0, stop_every=60, stop_length=10)


@pytest.fixture(scope="module")
def small_log(tmp_path_factory: pytest.TempPathFactory) -> GraphLog:
    """A synthetic log; every 7th pose loses its sightings (steps between keyframes),
    every 11th carries one sighting seen once more (a re-sight from the same pose)."""
    path, _ = write_landmark_log(tmp_path_factory.mktemp("fast") / "log.txt", SPEC,
                                 np.random.default_rng(5))
    g = read_graph_text(Path(path))
    sightings = [[] if k % 7 == 3 else list(ss) for k, ss in enumerate(g.sightings)]
    for k in range(30, len(sightings), 11):
        if sightings[k] and any(sightings[k][0].landmark in {s.landmark for s in ss}
                                for ss in sightings[:k]):
            sightings[k].append(sightings[k][0])
    return dataclasses.replace(g, sightings=sightings)


def _general(g: GraphLog, backend: str, config: SlamConfig) -> SlamResult:
    cfg = dataclasses.replace(config, isam2=dataclasses.replace(
        config.isam2, every_frame=True, pose_cov_every_step=False, final_covariances=False))
    be = make_backend(backend, cfg.pose2_odometry, cfg, g.start_pose())
    return drive(be, graph_log_steps(g, True))


def _assert_same(a: SlamResult, b: SlamResult) -> None:
    assert a.status == b.status and a.backend == b.backend
    np.testing.assert_array_equal(a.times, b.times)
    np.testing.assert_array_equal(a.poses, b.poses)
    np.testing.assert_array_equal(a.keyframes, b.keyframes)
    assert a.n_pruned == b.n_pruned and a.pruned == b.pruned
    for la, lb in ((a.landmarks, b.landmarks), (a.provisional, b.provisional)):
        assert [x.id for x in la] == [x.id for x in lb]
        for x, y in zip(la, lb, strict=True):
            np.testing.assert_array_equal(x.position, y.position)
            np.testing.assert_array_equal(x.cov, y.cov)
            assert x.n_obs == y.n_obs
    assert a.graph is not None and b.graph is not None
    assert a.graph.factors.size() == b.graph.factors.size()


@pytest.mark.parametrize("backend,init", [("isam2", "isam2"), ("batch", "isam2"), ("batch", "odometry")])
def test_fast_path_equals_general_path(small_log: GraphLog, backend: str, init: str) -> None:
    cfg = SlamConfig()
    cfg = dataclasses.replace(cfg, batch=dataclasses.replace(cfg.batch, init=init))
    ref = _general(small_log, backend, cfg)
    fast = run_known_ids(small_log, backend, cfg, Pose2Motion(cfg.pose2_odometry),
                         small_log.start_pose())
    assert fast is not None and ref.status == "ok"
    assert 0 < int(fast.keyframes.sum()) < len(fast.poses)  # steps between keyframes exist
    assert len(fast.landmarks) > 20
    _assert_same(fast, ref)
    np.testing.assert_array_equal(run_graph_log(small_log, backend, cfg).poses, ref.poses)


def test_fast_path_counts_once_seen_landmarks(small_log: GraphLog) -> None:
    counts: dict[int, int] = {}
    for ss in small_log.sightings:
        for s in ss:
            counts[s.landmark] = counts.get(s.landmark, 0) + 1
    least = int(np.percentile(list(counts.values()), 30)) + 1  # about a third seen fewer times
    cfg = SlamConfig()
    cfg = dataclasses.replace(cfg, association=dataclasses.replace(cfg.association,
                                                                   min_observations=least))
    for prune in (False, True):
        c = dataclasses.replace(cfg, association=dataclasses.replace(cfg.association,
                                                                     prune_once_seen=prune))
        fast = run_known_ids(small_log, "isam2", c, Pose2Motion(c.pose2_odometry), small_log.start_pose())
        assert fast is not None and 0 < fast.n_pruned < len(counts)
        assert (len(fast.provisional) == 0) == prune
        _assert_same(fast, _general(small_log, "isam2", c))


def test_single_sample_relative_equals_the_motion_model() -> None:
    motion = Pose2Motion(Pose2OdometryModel())
    rng = np.random.default_rng(11)
    a = rng.normal(size=(200, 3, 3)) * 1e-2
    rows = np.hstack([rng.normal(size=(200, 3)) * [1.0, 1.0, 4.0],
                      np.einsum("nij,nkj->nik", a, a).reshape(-1, 9)])
    rows[::9, 3:] = np.nan  # the model's default: left to the model
    for floor in (1e-9, 1e-14, 0.0):
        d, c, ok = single_sample_relative(rows, motion.sample_floor, floor)
        assert ok.sum() == 200 - len(rows[::9])
        for i in np.flatnonzero(ok):
            d_ref, c_ref = motion.relative(rows[i : i + 1], floor)
            np.testing.assert_array_equal(d[i], d_ref)
            np.testing.assert_array_equal(c[i], c_ref)


def test_inputs_the_fast_path_leaves_to_the_general_path(small_log: GraphLog) -> None:
    cfg = SlamConfig()
    motion = Pose2Motion(cfg.pose2_odometry)
    assert plan_log(small_log, motion, cfg) is not None
    od = small_log.odometry
    bad_delta = od.delta.copy()
    bad_delta[50, 0] = np.nan
    nan_log = dataclasses.replace(small_log, odometry=Pose2OdometryLog(od.t, bad_delta, od.cov))
    assert plan_log(nan_log, motion, cfg) is None
    res = run_graph_log(nan_log, "isam2", cfg)  # the general path's message and partial result
    assert res.status.startswith("failed") and "NaN" in res.status and len(res.poses) == 50
    back = od.t.copy()
    back[80] = back[78]
    assert plan_log(dataclasses.replace(small_log, odometry=Pose2OdometryLog(back, od.delta, od.cov)),
                    motion, cfg) is None
    twice = [list(ss) for ss in small_log.sightings]
    k = next(i for i, ss in enumerate(twice) if ss)
    twice[k].append(Sighting(10_000, 0.1, 5.0, np.diag([1e-4, 1e-2])))
    twice[k].append(Sighting(10_000, 0.1, 5.0, np.diag([1e-4, 1e-2])))
    assert plan_log(dataclasses.replace(small_log, sightings=twice), motion, cfg) is None
    bad_cov = [list(ss) for ss in small_log.sightings]
    bad_cov[k][0] = dataclasses.replace(bad_cov[k][0], cov=np.diag([1e-4, -1e-2]))
    bad_log = dataclasses.replace(small_log, sightings=bad_cov)
    assert plan_log(bad_log, motion, cfg) is None
    res = run_graph_log(bad_log, "isam2", cfg)  # the general path names the covariance
    assert res.status.startswith("failed") and "positive definite" in res.status
    huber = dataclasses.replace(cfg, batch=dataclasses.replace(cfg.batch, huber_k=1.345))
    assert run_known_ids(small_log, "batch", huber, motion, small_log.start_pose()) is None
    assert run_known_ids(small_log, "ekf", cfg, motion, small_log.start_pose()) is None


def test_fast_path_stops_on_request(small_log: GraphLog, monkeypatch: pytest.MonkeyPatch) -> None:
    """A stop request between keyframes keeps what is finished: the general path's
    result on the log cut there (the same graph)."""
    calls = []

    def stop_after_40() -> None:
        calls.append(1)
        if len(calls) > 40:
            raise KeyboardInterrupt("stopped by test")

    monkeypatch.setattr("lampsam.backend.dense_log.raise_if_stopped", stop_after_40)
    res = run_graph_log(small_log, "isam2", SlamConfig())
    n = len(res.poses)
    assert res.status == "interrupted" and int(res.keyframes.sum()) == 40 and 40 < n < 160
    od = small_log.odometry
    head = dataclasses.replace(small_log, pose_ids=small_log.pose_ids[:n],
                               sightings=small_log.sightings[:n],
                               odometry=Pose2OdometryLog(od.t[:n], od.delta[:n], od.cov[:n]))
    ref = _general(head, "isam2", SlamConfig())
    np.testing.assert_array_equal(res.poses, ref.poses)
    assert [x.id for x in res.landmarks] == [x.id for x in ref.landmarks]
