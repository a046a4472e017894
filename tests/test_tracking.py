"""Tracking decoupled from mapping (lampsam.backend.tracking): the backend in a worker process."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest

from lampsam.backend.config import SlamConfig
from lampsam.backend.odometry import motion_model
from lampsam.backend.slam import iter_steps, make_backend, start_pose_of
from lampsam.backend.tracking import replay_latency, run_decoupled
from lampsam.datasets.logrun import LoggedRun, read_run
from lampsam.errors import LampsamError
from lampsam.factors.gtsam_factors import pose_array
from lampsam.frontend.pipeline import iter_run
from tests.conftest import SimRun


@pytest.fixture(scope="module")
def lab_run(sim_run: SimRun) -> LoggedRun:
    """3 s of the simulated lab (45 frames)."""
    return read_run(sim_run(seed=3, duration=3.0))


def test_tracked_poses_are_backend_estimates_plus_odometry(lab_run: LoggedRun) -> None:
    """The worker's estimates equal the backend stepped in turn (bit for bit), and every
    tracked pose is its anchor step's estimate composed with the odometry since (1e-9)."""
    frames = list(iter_run(lab_run))
    steps = list(iter_steps(lab_run.odometry, frames))
    start = start_pose_of(lab_run)
    ref = make_backend("isam2", lab_run.rig.odometry, SlamConfig(), start, lab_run.rig.camera)
    ref_poses = np.array([ref.step(t, u, f).pose for t, u, f in steps])
    tm = run_decoupled(iter(steps), "isam2", lab_run.rig.odometry, SlamConfig(), start,
                       lab_run.rig.camera)
    n = len(steps)
    assert len(tm.pose) == len(tm.anchor) == len(tm.back) == n
    np.testing.assert_array_equal(np.array(tm.backend_pose), ref_poses)
    assert sum(tm.keyframe) > 5
    assert all(a < i + 1 for i, a in enumerate(tm.anchor))
    assert all(s <= o for s, o in zip(tm.sent, tm.out, strict=True))
    assert all(b >= s for s, b in zip(tm.sent, tm.back, strict=True))
    assert tm.worker_cpu_s > 0.0
    motion = motion_model(lab_run.rig.odometry)
    for i, j in enumerate(tm.anchor):
        base = gtsam.Pose2(*(ref_poses[j] if j >= 0 else start))
        u = [s[1] for s in steps[j + 1:i + 1] if len(s[1])]
        if u:
            d, _ = motion.relative(np.concatenate(u), 1e-14)
            base = base.compose(gtsam.Pose2(*d))
        np.testing.assert_allclose(tm.pose[i], pose_array(base), atol=1e-9)


def test_worker_error_is_raised(lab_run: LoggedRun) -> None:
    """A backend that cannot be built in the worker stops the run with its message."""
    steps = iter_steps(lab_run.odometry, [])
    with pytest.raises(LampsamError, match="unknown backend"):
        run_decoupled(steps, "nope", lab_run.rig.odometry, SlamConfig(), start_pose_of(lab_run),
                      lab_run.rig.camera)


def test_replay_latency_queues_behind_slow_steps() -> None:
    """Steps at 1 s of data, replayed at 2x (one every 0.5 s): a 1.2 s step delays the
    next two (latencies by hand), a fast queue has latency = service time."""
    t = np.arange(5.0)
    cpu = np.array([0.1, 1.2, 0.1, 0.1, 0.1])
    # arrivals 0, 0.5, 1.0, 1.5, 2.0; finishes 0.1, 1.7, 1.8, 1.9, 2.1
    np.testing.assert_allclose(replay_latency(t, cpu, 2.0), [0.1, 1.2, 0.8, 0.4, 0.1])
    np.testing.assert_allclose(replay_latency(t, np.full(5, 0.2), 1.0), np.full(5, 0.2))


def test_reply_due_releases_a_waiting_tracker_at_once() -> None:
    """The worker replies after the step a tracker waiting on back-pressure needs (the
    tracker has sent up to 40 and holds estimates to 20: with max_lag 15 it waits for
    step 25), not before it, not again until it could wait again; every 16 steps anyway;
    never for back-pressure when there is none."""
    from lampsam.backend.mapping_worker import reply_due

    assert not reply_due(3, 24, 40, 20, 15)
    assert reply_due(4, 25, 40, 20, 15)
    assert not reply_due(1, 26, 40, 25, 15)  # 40 - 25 = 15: the tracker is not waiting
    assert reply_due(1, 26, 41, 25, 15)
    assert reply_due(16, 5, 6, -1, None) and not reply_due(15, 5, 60, -1, None)
    assert reply_due(1, 7, 7, 6, 0) and not reply_due(1, 7, 8, 6, 0)


def test_inbox_flushes_at_the_stop_mark() -> None:
    """The worker's step source sends the pending estimates when it reaches the stop mark,
    before the backend's final optimisation runs (not after it), and when the inbox is
    empty; its clocks count the steps taken."""
    import queue
    import threading

    from lampsam.backend.mapping_worker import STOP, WorkerClocks, _Backlog, _inbox_steps

    inbox: queue.Queue[object] = queue.Queue()
    for i in range(3):
        inbox.put((i, 0.1 * i, np.zeros((1, 2)), ("raw", None), None))
    inbox.put(STOP)
    flushes: list[int] = []
    taken: list[int] = []
    clocks = WorkerClocks()
    index, at = [-1], [0.0]
    steps = _inbox_steps(_Backlog(inbox), threading.Event(), at, index,
                         lambda: flushes.append(index[0]), clocks)
    for _t, _u, frame in steps:
        assert frame is None and not flushes  # everything queued: no flush while steps wait
        taken.append(index[0])
    assert taken == [0, 1, 2] and flushes == [2]  # the flush at the stop mark
    assert clocks.inbox_cpu_s >= 0.0 and clocks.idle_s == 0.0


def test_backend_takes_the_mirrors_odometry_bit_for_bit(lab_run: LoggedRun,
                                                       monkeypatch: pytest.MonkeyPatch) -> None:
    """A graph backend given each step's odometry as the tracker's KeyframeMirror advanced
    it (packed for the queue and unpacked, as the worker gets it) composes none itself
    and ends bit for bit where the backend composing its own samples ends: every step's
    pose and covariance, the final trajectory and map. The mirror's step motion is bit for
    bit the tracker's own composition (its odometry chain)."""
    import lampsam.backend.graph as graph_module
    from lampsam.backend.keyframes import KeyframeMirror
    from lampsam.backend.mapping_worker import pack_odometry, unpack_odometry

    frames = list(iter_run(lab_run))
    steps = list(iter_steps(lab_run.odometry, frames))
    start, cfg = start_pose_of(lab_run), SlamConfig()
    ref = make_backend("isam2", lab_run.rig.odometry, cfg, start, lab_run.rig.camera)
    ref_est = [ref.step(t, u, f) for t, u, f in steps]
    ref_res = ref.finish()

    be = make_backend("isam2", lab_run.rig.odometry, cfg, start, lab_run.rig.camera)
    motion = motion_model(lab_run.rig.odometry)
    mirror = KeyframeMirror(motion, cfg)

    def never(*args: object, **kwargs: object) -> None:
        raise AssertionError("the backend composed a step's odometry itself")

    monkeypatch.setattr(graph_module, "advance_odometry", never)
    given = 0
    for (t, u, f), want in zip(steps, ref_est, strict=True):
        checked = motion.check(t, u)
        mirror.reads(checked, f)
        given += mirror.advanced is not None
        if len(checked):  # the tracker's chain increment: what it composed itself before
            np.testing.assert_array_equal(mirror.step_motion, motion.relative(checked, 1e-14)[0])
        be.give_odometry(unpack_odometry(pack_odometry(mirror.advanced)))
        got = be.step(t, u, f)
        np.testing.assert_array_equal(got.pose, want.pose)
        np.testing.assert_array_equal(got.cov, want.cov)
    res = be.finish()
    assert given > 40
    np.testing.assert_array_equal(res.poses, ref_res.poses)
    np.testing.assert_array_equal(res.pose_covs, ref_res.pose_covs)
    assert [lm.position.tolist() for lm in res.landmarks] == [
        lm.position.tolist() for lm in ref_res.landmarks]
